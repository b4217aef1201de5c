//! The region of interest: an axis-aligned box in the capture's world frame.
use glam::DVec3;

/// An axis-aligned box given by its centre and half extents (metres).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RoiBox {
    /// Centre of the box.
    pub centre: DVec3,
    /// Half extent along x, y and z (all positive).
    pub half: DVec3,
}

/// Why a box was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("invalid region of interest {min:?}..{max:?}: every axis needs min < max, finite")]
pub struct RoiError {
    min: DVec3,
    max: DVec3,
}

impl RoiBox {
    /// The box spanning `min` to `max`.
    pub fn from_bounds(min: DVec3, max: DVec3) -> Result<Self, RoiError> {
        if !(min.is_finite() && max.is_finite() && min.cmplt(max).all()) {
            return Err(RoiError { min, max });
        }
        Ok(Self {
            centre: (min + max) * 0.5,
            half: (max - min) * 0.5,
        })
    }

    /// Lower corner.
    pub fn min(&self) -> DVec3 {
        self.centre - self.half
    }

    /// Upper corner.
    pub fn max(&self) -> DVec3 {
        self.centre + self.half
    }

    /// Whether `p` lies inside (inclusive).
    pub fn contains(&self, p: DVec3) -> bool {
        (p - self.centre).abs().cmple(self.half).all()
    }

    /// Volume, m³.
    pub fn volume(&self) -> f64 {
        8.0 * self.half.x * self.half.y * self.half.z
    }
}

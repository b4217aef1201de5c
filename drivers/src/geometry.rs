//! The galvo-pair calibration model: optical angles ↔ ray direction.
//!
//! A galvo pair sits at `origin` with a local frame whose +z axis is the boresight (the
//! ray at zero optical angles), +x the direction the first mirror deflects towards and
//! +y the second. The model is the ideal two-axis scanner with a common pivot:
//!
//! ```text
//! d_local = normalize(tan θx, tan θy, 1)      d_world = R · d_local
//! θx = atan2(q.x, q.z),  θy = atan2(q.y, q.z)  with q = Rᵀ (p − origin)
//! ```
//!
//! so the two directions are exact inverses of each other. Angles are optical angles
//! (twice the mechanical mirror angle), in radians. The residual distortion of a real
//! pair (mirror separation, axis skew) is absorbed by calibrating `R` and `origin`.
use glam::{DMat3, DVec3};
use serde::{Deserialize, Serialize};

/// Optical scan angles of a galvo pair, in radians.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OpticalAngles {
    /// Deflection about the local y axis (towards +x).
    pub x: f64,
    /// Deflection about the local x axis (towards +y).
    pub y: f64,
}

/// Pose of a galvo pair: its pivot and its local frame in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GalvoPose {
    /// The common pivot of the scanned rays, metres, world frame.
    pub origin: DVec3,
    /// Columns are the local x, y and z (boresight) axes in the world frame.
    pub rotation: DMat3,
}

impl GalvoPose {
    /// A pose whose boresight points along `boresight` with `up` giving the local +y
    /// direction (projected to be orthogonal to the boresight). Returns `None` when
    /// either vector is zero or they are parallel.
    pub fn looking(origin: DVec3, boresight: DVec3, up: DVec3) -> Option<Self> {
        let z = boresight.try_normalize()?;
        let x = up.cross(z).try_normalize()?;
        let y = z.cross(x);
        Some(Self {
            origin,
            rotation: DMat3::from_cols(x, y, z),
        })
    }

    /// The unit direction, world frame, of the ray leaving the pivot at `angles`.
    pub fn direction(&self, angles: OpticalAngles) -> DVec3 {
        let local = DVec3::new(angles.x.tan(), angles.y.tan(), 1.0).normalize();
        self.rotation * local
    }

    /// The optical angles that aim the pair at `target`; `None` when the target lies
    /// on or behind the pivot's plane (the pair cannot point there).
    pub fn angles_for(&self, target: DVec3) -> Option<OpticalAngles> {
        let q = self.rotation.transpose() * (target - self.origin);
        if q.z <= f64::EPSILON * q.length().max(1.0) {
            return None;
        }
        Some(OpticalAngles {
            x: q.x.atan2(q.z),
            y: q.y.atan2(q.z),
        })
    }
}

/// The optical angle range a galvo pair may be commanded to, radians, inclusive.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AngleLimits {
    /// Allowed range of θx, `[min, max]`.
    pub x: [f64; 2],
    /// Allowed range of θy, `[min, max]`.
    pub y: [f64; 2],
}

impl AngleLimits {
    /// Whether `angles` lies within the limits (inclusive); NaN is never within.
    pub fn contains(&self, angles: OpticalAngles) -> bool {
        (self.x[0]..=self.x[1]).contains(&angles.x) && (self.y[0]..=self.y[1]).contains(&angles.y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tilted_pose() -> GalvoPose {
        GalvoPose::looking(DVec3::new(0.3, -0.2, 1.5), DVec3::new(-0.2, 0.1, -1.0), DVec3::Y).unwrap()
    }

    #[test]
    fn angles_and_direction_are_inverse() {
        let pose = tilted_pose();
        for (x, y) in [(0.0, 0.0), (0.2, -0.1), (-0.3, 0.25), (0.01, 0.4)] {
            let angles = OpticalAngles { x, y };
            let target = pose.origin + 2.0 * pose.direction(angles);
            let back = pose.angles_for(target).unwrap();
            assert!(
                (back.x - x).abs() < 1e-12 && (back.y - y).abs() < 1e-12,
                "{angles:?} -> {back:?}"
            );
        }
    }

    #[test]
    fn zero_angles_follow_the_boresight() {
        let pose = tilted_pose();
        let d = pose.direction(OpticalAngles { x: 0.0, y: 0.0 });
        let expected = DVec3::new(-0.2, 0.1, -1.0).normalize();
        assert!((d - expected).length() < 1e-12);
    }

    #[test]
    fn targets_behind_the_pivot_are_unreachable() {
        let pose = tilted_pose();
        let behind = pose.origin - pose.rotation.z_axis;
        assert!(pose.angles_for(behind).is_none());
        assert!(pose.angles_for(pose.origin).is_none());
    }

    #[test]
    fn degenerate_frames_are_rejected() {
        assert!(GalvoPose::looking(DVec3::ZERO, DVec3::ZERO, DVec3::Y).is_none());
        assert!(GalvoPose::looking(DVec3::ZERO, DVec3::Y, DVec3::Y).is_none());
    }

    #[test]
    fn limits_are_inclusive_and_reject_nan() {
        let limits = AngleLimits {
            x: [-0.1, 0.1],
            y: [-0.2, 0.2],
        };
        assert!(limits.contains(OpticalAngles { x: 0.1, y: -0.2 }));
        assert!(!limits.contains(OpticalAngles { x: 0.11, y: 0.0 }));
        assert!(!limits.contains(OpticalAngles { x: f64::NAN, y: 0.0 }));
    }
}

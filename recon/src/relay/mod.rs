//! Relay geometry: from the first-bounce point cloud to relay points with normals, and
//! the virtual relay plane on which virtual confocal scans are synthesised.
//!
//! The measured relay may be any shape (a wall, a curved panel, two people's backs), so
//! nothing here assumes a plane except [`VirtualRelay`], which is a plane by design.
mod albedo;
mod cloud;
mod normals;
mod region;
mod virtual_relay;

pub use albedo::RelayAlbedo;
pub use cloud::{Thresholds, reject_isolated};
pub use normals::{SurfaceNormal, estimate_normals};
pub use region::Region;
pub use virtual_relay::VirtualRelay;

/// Why a geometry operation could not run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// Too few points for the requested neighbourhood size.
    #[error(
        "{points} relay points are too few for {needed} neighbours: lower the neighbour count or scan more points"
    )]
    TooFewPoints {
        /// Points available.
        points: usize,
        /// Points needed.
        needed: usize,
    },
    /// A parameter outside its valid range.
    #[error("{name} = {value} is out of range: {expected}")]
    OutOfRange {
        /// The parameter.
        name: &'static str,
        /// Its value, formatted.
        value: String,
        /// What would be valid.
        expected: &'static str,
    },
    /// A point or vector is NaN or infinite.
    #[error("relay point {index} is not finite: {what}")]
    NotFinite {
        /// Index of the offending point.
        index: usize,
        /// What was wrong.
        what: &'static str,
    },
    /// No plane could be fitted (fewer than three points, or all on a line).
    #[error(
        "no plane fits the {points} relay points: they are fewer than three or collinear (a line scan?); 3D-GTR renders its virtual confocal scan on that plane, so reconstruct such a capture with method = \"fbp\", which takes relay points of any shape"
    )]
    NoPlane {
        /// Points given.
        points: usize,
    },
}

pub(crate) fn check_finite(points: &[glam::DVec3]) -> Result<(), GeometryError> {
    match points.iter().position(|p| !p.is_finite()) {
        Some(index) => Err(GeometryError::NotFinite {
            index,
            what: "position",
        }),
        None => Ok(()),
    }
}

//! The galvo-pair calibration model: optical angles ↔ ray direction.
//!
//! A galvo pair sits at `origin` with a local frame whose +z axis is the boresight (the
//! ray at zero optical angles), +x the direction the first mirror deflects towards and
//! +y the second. Two kinematics ([`Scanner`]), each with its exact inverse
//! (q = Rᵀ (p − origin), d_world = R · d_local):
//!
//! ```text
//! two-mirror  d_local = (sin θx, cos θx sin θy, cos θx cos θy)
//!             θy = atan2(q.y, q.z),  θx = atan2(q.x, hypot(q.y, q.z))
//! pivot       d_local = normalize(tan θx, tan θy, 1)
//!             θx = atan2(q.x, q.z),  θy = atan2(q.y, q.z)
//! ```
//!
//! Angles are optical angles (twice the mechanical mirror angle), in radians. A galvo
//! pair is two mirrors, the second turning the first's fan of rays about an axis along
//! local x: on a plane D away its spot lies at x = D·tan θx / cos θy, the pincushion
//! that a pose cannot absorb (19 mm at 15° on both axes, 2 m away; a review's model of
//! calibrating such a pair with the pivot kinematics left 2.4 mm of range RMS and
//! relay points up to 21 mm off). The
//! mirrors' separation (a few millimetres of spot, under a millimetre of path) is not
//! modelled: the pair's origin is the second mirror's axis.
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

/// How a pair's two optical angles turn its ray (the module's table).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Scanner {
    /// Two mirrors one after the other, the first deflecting towards local x, the
    /// second, turning about local x, towards y: what a galvo pair is.
    TwoMirror,
    /// The ideal scanner with one pivot for both angles, `(tan θx, tan θy, 1)`: the
    /// default where a config names none (Periscope's simulated instruments, and every
    /// config written before the choice existed). No galvo pair turns its ray so.
    #[default]
    Pivot,
}

/// Pose of a galvo pair: its pivot and its local frame in world coordinates, and how
/// its angles turn the ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GalvoPose {
    /// The pivot of the scanned rays (for two mirrors, on the second's axis), metres,
    /// world frame.
    pub origin: DVec3,
    /// Columns are the local x, y and z (boresight) axes in the world frame.
    pub rotation: DMat3,
    /// The kinematics of the angles.
    pub scanner: Scanner,
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
            scanner: Scanner::default(),
        })
    }

    /// The same pose with `scanner`'s kinematics.
    pub fn with_scanner(self, scanner: Scanner) -> Self {
        Self { scanner, ..self }
    }

    /// The unit direction, world frame, of the ray leaving the pivot at `angles`.
    pub fn direction(&self, angles: OpticalAngles) -> DVec3 {
        let local = match self.scanner {
            Scanner::TwoMirror => {
                let (sx, cx) = angles.x.sin_cos();
                let (sy, cy) = angles.y.sin_cos();
                DVec3::new(sx, cx * sy, cx * cy)
            }
            Scanner::Pivot => DVec3::new(angles.x.tan(), angles.y.tan(), 1.0).normalize(),
        };
        self.rotation * local
    }

    /// The optical angles that aim the pair at `target`; `None` when the target lies
    /// on or behind the pivot's plane (the pair cannot point there).
    pub fn angles_for(&self, target: DVec3) -> Option<OpticalAngles> {
        let q = self.rotation.transpose() * (target - self.origin);
        if q.z <= f64::EPSILON * q.length().max(1.0) {
            return None;
        }
        Some(match self.scanner {
            Scanner::TwoMirror => OpticalAngles {
                x: q.x.atan2(q.y.hypot(q.z)),
                y: q.y.atan2(q.z),
            },
            Scanner::Pivot => OpticalAngles {
                x: q.x.atan2(q.z),
                y: q.y.atan2(q.z),
            },
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
        for scanner in [Scanner::Pivot, Scanner::TwoMirror] {
            let pose = tilted_pose().with_scanner(scanner);
            for (x, y) in [(0.0, 0.0), (0.2, -0.1), (-0.3, 0.25), (0.01, 0.4)] {
                let angles = OpticalAngles { x, y };
                let target = pose.origin + 2.0 * pose.direction(angles);
                let back = pose.angles_for(target).unwrap();
                assert!(
                    (back.x - x).abs() < 1e-12 && (back.y - y).abs() < 1e-12,
                    "{scanner:?}: {angles:?} -> {back:?}"
                );
                assert!((pose.direction(angles).length() - 1.0).abs() < 1e-12);
            }
        }
    }

    /// Two mirrors, traced as reflections: the beam comes in along local −x, hits the
    /// first mirror (its normal turned about local z by half θx from 45°), then the
    /// second (about local x, half θy from 45°), and leaves where the model says, with
    /// the pincushion the pivot model lacks: on a plane 2 m away at (0.3, 0.3) rad, the
    /// two models' spots are 29 mm apart.
    #[test]
    fn two_mirrors_turn_the_ray_as_reflections_do() {
        let reflect = |d: DVec3, n: DVec3| d - 2.0 * d.dot(n) * n;
        let pose = GalvoPose::looking(DVec3::ZERO, DVec3::Z, DVec3::Y).unwrap();
        for (x, y) in [(0.0, 0.0), (0.3, 0.0), (0.0, -0.25), (0.3, 0.3), (-0.2, 0.35)] {
            // First mirror: sends +x light into +y at rest, then (second mirror) +y
            // into +z. Each mirror turns its ray by twice its own angle.
            let m1 = |a: f64| {
                let t = std::f64::consts::FRAC_PI_4 + 0.5 * a;
                DVec3::new(-t.cos(), t.sin(), 0.0)
            };
            let m2 = |a: f64| {
                let t = std::f64::consts::FRAC_PI_4 + 0.5 * a;
                DVec3::new(0.0, -t.cos(), t.sin())
            };
            let d = reflect(reflect(DVec3::X, m1(x)), m2(y));
            let model = pose
                .with_scanner(Scanner::TwoMirror)
                .direction(OpticalAngles { x, y });
            assert!(
                (d - model).length() < 1e-12,
                "({x}, {y}): traced {d:?}, model {model:?}"
            );
        }
        let spot = |s: Scanner| {
            let d = pose.with_scanner(s).direction(OpticalAngles { x: 0.3, y: 0.3 });
            d * (2.0 / d.z)
        };
        let apart = spot(Scanner::TwoMirror).distance(spot(Scanner::Pivot));
        assert!((0.028..0.030).contains(&apart), "{apart}");
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

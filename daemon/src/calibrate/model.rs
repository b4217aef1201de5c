//! The calibration's forward model and its parameters: what a range or a spot
//! measurement should read for given arm poses and target plane, the nine parameters
//! the fit moves (the gauge fixed as `mod.rs` explains), and the gauge transform that
//! expresses any true geometry in the frame the fit reports.
use glam::{DMat3, DQuat, DVec3};
use periscope_drivers::{GalvoPose, OpticalAngles};

/// A flat target (the relay wall or a calibration board).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// A point on it, metres, world frame.
    pub point: DVec3,
    /// Its unit normal, facing the instrument.
    pub normal: DVec3,
}

impl Plane {
    /// Where the ray from `origin` along unit `dir` meets the plane's front; `None` when
    /// it runs parallel to the plane, away from it or starts behind it.
    pub fn hit(&self, origin: DVec3, dir: DVec3) -> Option<DVec3> {
        let facing = self.normal.dot(dir);
        if !(facing < -1e-9) {
            return None;
        }
        let t = self.normal.dot(self.point - origin) / facing;
        (t.is_finite() && t > 0.0).then(|| origin + dir * t)
    }
}

/// Both arms' poses and the target: everything a calibration scan depends on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Geometry {
    /// The laser arm.
    pub laser: GalvoPose,
    /// The SPAD arm.
    pub spad: GalvoPose,
    /// The flat target.
    pub target: Plane,
}

impl Geometry {
    /// The first-bounce path laser → p → SPAD, metres, for the point p the SPAD sees
    /// at `spad` angles (the diffuser lights the whole target): |p − L| + |p − S|.
    pub fn path(&self, spad: OpticalAngles) -> Option<f64> {
        let s = self.spad.origin;
        let p = self.target.hit(s, self.spad.direction(spad))?;
        Some(p.distance(s) + p.distance(self.laser.origin))
    }

    /// The SPAD angles that look at the laser's spot when the laser arm points at
    /// `laser` angles (diffuser out).
    pub fn spot(&self, laser: OpticalAngles) -> Option<OpticalAngles> {
        let q = self.target.hit(self.laser.origin, self.laser.direction(laser))?;
        self.spad.angles_for(q)
    }
}

/// A rotation vector (axis × angle, radians) as a matrix.
fn rotation(w: DVec3) -> DMat3 {
    DMat3::from_quat(DQuat::from_scaled_axis(w))
}

/// Two unit vectors completing `n` to a right-handed orthonormal frame.
pub(crate) fn plane_basis(n: DVec3) -> (DVec3, DVec3) {
    let hint = if n.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
    let u = n.cross(hint).normalize();
    (u, n.cross(u))
}

/// Number of fitted parameters in either gauge.
pub(crate) const PARAMETERS: usize = 9;

/// The nine parameters around a nominal geometry. With the target known (`known`):
/// the SPAD origin's offset along the target normal, the SPAD frame's tilt about the
/// two in-plane axes, the laser origin's offset and the laser frame's rotation. With
/// the target fitted: the target's offset along its nominal normal and its tilt about
/// the two in-plane axes, then the laser's six; the SPAD arm stays as configured.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Parameters {
    pub nominal: Geometry,
    pub known_target: bool,
    u: DVec3,
    v: DVec3,
}

impl Parameters {
    pub(crate) fn new(nominal: Geometry, known_target: bool) -> Parameters {
        let (u, v) = plane_basis(nominal.target.normal);
        Parameters {
            nominal,
            known_target,
            u,
            v,
        }
    }

    /// What each parameter is, for messages.
    pub(crate) fn names(&self) -> [&'static str; PARAMETERS] {
        let first = if self.known_target {
            [
                "the SPAD origin's distance from the target",
                "the SPAD arm's tilt (first axis)",
                "the SPAD arm's tilt (second axis)",
            ]
        } else {
            [
                "the target's distance",
                "the target's tilt (first axis)",
                "the target's tilt (second axis)",
            ]
        };
        [
            first[0],
            first[1],
            first[2],
            "the laser origin's x",
            "the laser origin's y",
            "the laser origin's z",
            "the laser arm's rotation about x",
            "the laser arm's rotation about y",
            "the laser arm's rotation about z",
        ]
    }

    /// The geometry at parameters `p` (all zero: the nominal geometry).
    pub(crate) fn geometry(&self, p: &[f64]) -> Geometry {
        let n0 = &self.nominal;
        let (mut spad, mut target) = (n0.spad, n0.target);
        if self.known_target {
            spad.origin += target.normal * p[0];
            spad.rotation = rotation(self.u * p[1] + self.v * p[2]) * spad.rotation;
        } else {
            target.point += target.normal * p[0];
            target.normal = (target.normal + self.u * p[1] + self.v * p[2]).normalize();
        }
        let laser = GalvoPose {
            origin: n0.laser.origin + DVec3::new(p[3], p[4], p[5]),
            rotation: rotation(DVec3::new(p[6], p[7], p[8])) * n0.laser.rotation,
            ..n0.laser
        };
        Geometry { laser, spad, target }
    }
}

/// `truth` moved into the calibration's gauge around `nominal`: by the rigid motion
/// that leaves what the scans cannot see where the fit fixes it. With the target known
/// that motion keeps the target plane (a turn about its normal and a shift along it)
/// and brings the SPAD origin over its configured point and the SPAD frame's twist
/// about the normal to the configured one; with the target fitted it brings the whole
/// SPAD pose onto the configured pose. The fit's result is to be compared with this.
pub fn in_gauge(truth: &Geometry, nominal: &Geometry, known_target: bool) -> Geometry {
    let (turn, shift) = if known_target {
        let n = nominal.target.normal;
        // The twist about n that, applied first, leaves the SPAD frame a pure swing
        // (rotation about an in-plane axis) away from the configured frame:
        // p = Q⁻¹ = swing·twist, so twist·Q = swing⁻¹.
        let q = DQuat::from_mat3(&(truth.spad.rotation * nominal.spad.rotation.transpose()));
        let p = q.conjugate();
        let along = p.xyz().dot(n) * n;
        let twist = DQuat::from_xyzw(along.x, along.y, along.z, p.w).normalize();
        let turn = DMat3::from_quat(twist);
        let pivot = nominal.target.point;
        let moved = turn * (truth.spad.origin - pivot) + pivot;
        let gap = nominal.spad.origin - moved;
        let shift = gap - gap.dot(n) * n;
        (turn, pivot + shift - turn * pivot)
    } else {
        let turn = nominal.spad.rotation * truth.spad.rotation.transpose();
        (turn, nominal.spad.origin - turn * truth.spad.origin)
    };
    let pose = |g: &GalvoPose| GalvoPose {
        origin: turn * g.origin + shift,
        rotation: turn * g.rotation,
        ..*g
    };
    Geometry {
        laser: pose(&truth.laser),
        spad: pose(&truth.spad),
        target: Plane {
            point: turn * truth.target.point + shift,
            normal: turn * truth.target.normal,
        },
    }
}

/// The angle of the rotation between two frames, radians.
pub fn rotation_between(a: DMat3, b: DMat3) -> f64 {
    let m = a * b.transpose();
    let c = (m.x_axis.x + m.y_axis.y + m.z_axis.z - 1.0) / 2.0;
    // acos loses precision near 1: the sine from the antisymmetric part keeps small
    // angles exact.
    let s = 0.5
        * DVec3::new(
            m.y_axis.z - m.z_axis.y,
            m.z_axis.x - m.x_axis.z,
            m.x_axis.y - m.y_axis.x,
        )
        .length();
    s.atan2(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn nominal() -> Geometry {
        Geometry {
            laser: GalvoPose::looking(DVec3::new(-0.1, 0.0, 2.0), -DVec3::Z, DVec3::Y).unwrap(),
            spad: GalvoPose::looking(DVec3::new(0.1, 0.0, 2.0), -DVec3::Z, DVec3::Y).unwrap(),
            target: Plane {
                point: DVec3::ZERO,
                normal: DVec3::Z,
            },
        }
    }

    #[test]
    fn the_path_matches_the_pipelines_first_bounce_range() {
        let g = nominal();
        let a = OpticalAngles { x: 0.2, y: -0.1 };
        let ell = g.path(a).unwrap();
        let d = g.spad.direction(a);
        let r = crate::pipeline::first_bounce_range(ell, g.laser.origin, g.spad.origin, d).unwrap();
        let p = g.spad.origin + d * r;
        assert!(p.z.abs() < 1e-12, "{p}");
    }

    #[test]
    fn a_confocal_spot_is_seen_where_the_arms_cross() {
        let g = nominal();
        let a = g.spot(OpticalAngles { x: 0.0, y: 0.0 }).unwrap();
        // Laser spot at (-0.1, 0, 0); the SPAD at x = 0.1 looks back by atan(0.2/2).
        // The SPAD's local x is world −x (up × boresight), so it turns by +atan(0.2/2).
        assert!((a.x - 0.2f64.atan2(2.0)).abs() < 1e-12, "{a:?}");
        assert!(a.y.abs() < 1e-12);
    }

    #[test]
    fn zero_parameters_give_the_nominal_geometry() {
        for known in [true, false] {
            let p = Parameters::new(nominal(), known);
            assert_eq!(p.geometry(&[0.0; PARAMETERS]), nominal());
        }
    }

    #[test]
    fn the_gauge_keeps_what_the_scans_see() {
        let n = nominal();
        let mut truth = n;
        let turn = rotation(DVec3::new(0.003, -0.002, 0.004));
        truth.spad.rotation = turn * truth.spad.rotation;
        truth.spad.origin += DVec3::new(0.004, -0.003, 0.002);
        truth.laser.rotation = rotation(DVec3::new(-0.001, 0.002, 0.003)) * truth.laser.rotation;
        truth.laser.origin += DVec3::new(-0.002, 0.001, 0.003);
        for known in [true, false] {
            let g = in_gauge(&truth, &n, known);
            // What the scans measure is the same in either frame.
            for a in [(0.0, 0.0), (0.2, -0.1), (-0.15, 0.2)] {
                let a = OpticalAngles { x: a.0, y: a.1 };
                assert!((g.path(a).unwrap() - truth.path(a).unwrap()).abs() < 1e-12);
                let (s, t) = (g.spot(a).unwrap(), truth.spot(a).unwrap());
                assert!((s.x - t.x).abs() < 1e-12 && (s.y - t.y).abs() < 1e-12);
            }
            if known {
                assert!((g.target.normal - n.target.normal).length() < 1e-12);
                assert!(g.target.normal.dot(g.target.point - n.target.point).abs() < 1e-12);
                let gap = g.spad.origin - n.spad.origin;
                assert!((gap - gap.dot(DVec3::Z) * DVec3::Z).length() < 1e-12, "{gap}");
                // No twist left about the normal: a pure swing.
                let q = DQuat::from_mat3(&(g.spad.rotation * n.spad.rotation.transpose()));
                assert!(q.xyz().dot(DVec3::Z).abs() < 1e-12, "{q}");
            } else {
                assert!((g.spad.origin - n.spad.origin).length() < 1e-12);
                assert!(rotation_between(g.spad.rotation, n.spad.rotation) < 1e-12);
            }
        }
    }

    #[test]
    fn rotation_angles_are_exact_when_small() {
        let a = rotation(DVec3::new(0.0, 1e-7, 0.0));
        assert!((rotation_between(a, DMat3::IDENTITY) - 1e-7).abs() < 1e-15);
        let b = rotation(DVec3::new(0.0, 0.0, 1.0));
        assert!((rotation_between(b, DMat3::IDENTITY) - 1.0).abs() < 1e-12);
    }
}

//! The virtual relay: a plane on which the optimised Gaussians are rendered as a dense
//! confocal scan, for solvers that need a planar grid (LCT, RSD).
use glam::DVec3;

use super::{GeometryError, check_finite};
use crate::linalg::fit_plane;

/// A rectangular grid of points on a plane, with a normal facing the hidden scene.
///
/// Grid point `(ix, iy)` sits at `centre + u·x[ix] + v·y[iy]`, with cell-centred
/// coordinates `x[i] = −size[0]/2 + (i + ½)·size[0]/resolution[0]` (likewise y).
/// Points are listed row by row: index `iy·resolution[0] + ix`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VirtualRelay {
    /// Centre of the grid, metres.
    pub centre: DVec3,
    /// Unit normal toward the hidden scene.
    pub normal: DVec3,
    /// Unit in-plane axis of the grid's columns.
    pub u: DVec3,
    /// Unit in-plane axis of the grid's rows (`normal × u`).
    pub v: DVec3,
    /// Extent along u and v, metres.
    pub size: [f64; 2],
    /// Points along u and v.
    pub resolution: [usize; 2],
}

impl VirtualRelay {
    /// A plane through `centre` with `normal`; `u_hint` is projected into the plane to
    /// give the column axis (any vector not parallel to the normal).
    pub fn new(
        centre: DVec3,
        normal: DVec3,
        u_hint: DVec3,
        size: [f64; 2],
        resolution: [usize; 2],
    ) -> Result<Self, GeometryError> {
        let bad = |name: &'static str, value: String, expected: &'static str| GeometryError::OutOfRange {
            name,
            value,
            expected,
        };
        if !centre.is_finite() {
            return Err(bad("centre", format!("{centre:?}"), "a finite position"));
        }
        let normal = normal
            .try_normalize()
            .ok_or_else(|| bad("normal", format!("{normal:?}"), "a finite, non-zero direction"))?;
        let u = (u_hint - normal * u_hint.dot(normal))
            .try_normalize()
            .ok_or_else(|| {
                bad(
                    "u",
                    format!("{u_hint:?}"),
                    "a direction not parallel to the normal",
                )
            })?;
        if !size.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(bad("size", format!("{size:?}"), "two positive lengths in metres"));
        }
        if resolution.iter().any(|&r| r < 2) {
            return Err(bad(
                "resolution",
                format!("{resolution:?}"),
                "at least 2 points per axis",
            ));
        }
        Ok(Self {
            centre,
            normal,
            u,
            v: normal.cross(u),
            size,
            resolution,
        })
    }

    /// The plane fitted to measured relay points, its normal facing `viewpoint`, its
    /// columns along the world x axis projected into the plane (world y if the plane
    /// is normal to x). With no `size`, the grid spans the points' projected extent.
    pub fn fitted(
        points: &[DVec3],
        viewpoint: DVec3,
        size: Option<[f64; 2]>,
        resolution: [usize; 2],
    ) -> Result<Self, GeometryError> {
        check_finite(points)?;
        let plane = fit_plane(points).ok_or(GeometryError::NoPlane { points: points.len() })?;
        let plane = plane.world_oriented(viewpoint - plane.centre);
        let normal = plane.normal;
        let provisional = Self::new(plane.centre, normal, plane.u, [1.0, 1.0], [2, 2])?;
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in points {
            let d = *p - plane.centre;
            for (a, axis) in [provisional.u, provisional.v].iter().enumerate() {
                let t = d.dot(*axis);
                lo[a] = lo[a].min(t);
                hi[a] = hi[a].max(t);
            }
        }
        let centre =
            plane.centre + provisional.u * 0.5 * (lo[0] + hi[0]) + provisional.v * 0.5 * (lo[1] + hi[1]);
        let size = size.unwrap_or([hi[0] - lo[0], hi[1] - lo[1]]);
        Self::new(centre, normal, provisional.u, size, resolution)
    }

    /// The same plane, centre and orientation with its points `pitch` apart along both
    /// axes: the extent grows about the centre to a whole number of pitches (at least
    /// 2 points per axis); where that would take more than `max_resolution` points, the
    /// extent stays and the pitch coarsens instead.
    pub fn with_pitch(&self, pitch: f64, max_resolution: usize) -> Result<Self, GeometryError> {
        if !(pitch.is_finite() && pitch > 0.0) {
            return Err(GeometryError::OutOfRange {
                name: "pitch",
                value: pitch.to_string(),
                expected: "a positive length in metres",
            });
        }
        let most = max_resolution.max(2);
        let resolution = self
            .size
            .map(|s| ((s / pitch - 1e-9).ceil() as usize).clamp(2, most));
        let size = [0, 1].map(|a| (resolution[a] as f64 * pitch).max(self.size[a]));
        Self::new(self.centre, self.normal, self.u, size, resolution)
    }

    /// The same plane, orientation and grid pitch, its extent grown where needed to
    /// cover the projections of `points` too (the reconstruction volume's corners: a
    /// virtual scan narrower than the volume sees nothing of what lies beyond its
    /// edge, while the fitted primitives do). The resolution grows with the extent,
    /// up to `max_resolution` points per axis (then the pitch coarsens instead).
    pub fn covering(&self, points: &[DVec3], max_resolution: usize) -> Result<Self, GeometryError> {
        check_finite(points)?;
        let mut lo = [-0.5 * self.size[0], -0.5 * self.size[1]];
        let mut hi = [0.5 * self.size[0], 0.5 * self.size[1]];
        for p in points {
            let d = *p - self.centre;
            for (a, axis) in [self.u, self.v].iter().enumerate() {
                let t = d.dot(*axis);
                lo[a] = lo[a].min(t);
                hi[a] = hi[a].max(t);
            }
        }
        let centre = self.centre + self.u * 0.5 * (lo[0] + hi[0]) + self.v * 0.5 * (lo[1] + hi[1]);
        let size = [hi[0] - lo[0], hi[1] - lo[1]];
        let pitch = self.spacing();
        let resolution = [0, 1].map(|a| {
            let n = (size[a] / pitch[a] - 1e-9).ceil() as usize;
            n.clamp(self.resolution[a], max_resolution.max(self.resolution[a]))
        });
        Self::new(centre, self.normal, self.u, size, resolution)
    }

    /// The same plane and centre, its column pitch snapped to a whole fraction of
    /// `voxel` (the volume's voxel pitch along world x) when its columns run along
    /// world x and the plane is level (normal along world z), to within 10⁻¹⁰ per
    /// component. Then every voxel–point pair of the confocal scan on it shares its
    /// path length with every other pair at the same lateral offset, and FBP takes its
    /// grid path. The fraction is the one nearest the current pitch whose columns
    /// still cover the current extent within `max_resolution` (at least the current
    /// count); the extent grows about the centre to a whole number of the new pitch.
    /// Any other relay, or none that fits, comes back unchanged.
    pub fn columns_fitting(&self, voxel: f64, max_resolution: usize) -> Self {
        let level = |d: DVec3, along: usize| (0..3).all(|a| a == along || d[a].abs() <= 1e-10);
        if !(level(self.u, 0) && level(self.v, 1) && voxel.is_finite() && voxel > 0.0) {
            return *self;
        }
        let most = max_resolution.max(self.resolution[0]);
        let mut ratio = (voxel / self.spacing()[0]).round().max(1.0);
        while ratio >= 1.0 {
            let pitch = voxel / ratio;
            let n = ((self.size[0] / pitch - 1e-9).ceil() as usize).max(2);
            if n <= most {
                let mut snapped = *self;
                snapped.size[0] = n as f64 * pitch;
                snapped.resolution[0] = n;
                return snapped;
            }
            ratio -= 1.0;
        }
        *self
    }

    /// Grid spacing along u and v, metres.
    pub fn spacing(&self) -> [f64; 2] {
        [
            self.size[0] / self.resolution[0] as f64,
            self.size[1] / self.resolution[1] as f64,
        ]
    }

    /// In-plane coordinate of column `ix` (along u) and row `iy` (along v).
    pub fn coords(&self, ix: usize, iy: usize) -> (f64, f64) {
        let s = self.spacing();
        (
            -0.5 * self.size[0] + (ix as f64 + 0.5) * s[0],
            -0.5 * self.size[1] + (iy as f64 + 0.5) * s[1],
        )
    }

    /// Grid point `(ix, iy)`.
    pub fn point(&self, ix: usize, iy: usize) -> DVec3 {
        let (x, y) = self.coords(ix, iy);
        self.centre + self.u * x + self.v * y
    }

    /// All grid points, row by row.
    pub fn points(&self) -> Vec<DVec3> {
        (0..self.resolution[1])
            .flat_map(|iy| (0..self.resolution[0]).map(move |ix| (ix, iy)))
            .map(|(ix, iy)| self.point(ix, iy))
            .collect()
    }

    /// Number of grid points.
    pub fn len(&self) -> usize {
        self.resolution[0] * self.resolution[1]
    }

    /// Always false (a relay has at least 2×2 points); for clippy's `len` rule.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

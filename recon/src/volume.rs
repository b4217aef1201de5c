//! Reconstructed volumes on a world-frame voxel grid, and the images derived from them.
//!
//! Layout: `data[(iz·ny + iy)·nx + ix]`, i.e. numpy shape `[nz, ny, nx]` in C order.
//! Voxels are cell-centred: the box's outer bounds are the ranges given by the user.
use glam::DVec3;

/// A world-frame axis-aligned voxel grid.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VolumeGrid {
    /// Outer bounds along x, metres.
    pub x: [f64; 2],
    /// Outer bounds along y, metres.
    pub y: [f64; 2],
    /// Outer bounds along z, metres.
    pub z: [f64; 2],
    /// Voxels along x, y, z.
    pub shape: [usize; 3],
}

/// Why a grid or volume was rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum VolumeError {
    /// A range is not increasing and finite.
    #[error("volume range `{axis}` = {range:?} must be two finite numbers, the first smaller")]
    Range {
        /// Axis name.
        axis: &'static str,
        /// The range.
        range: [f64; 2],
    },
    /// A voxel count is zero or absurdly large.
    #[error(
        "volume shape {shape:?} is out of range: each count must be 1..=4096 and the total at most 2^30 voxels"
    )]
    Shape {
        /// The shape.
        shape: [usize; 3],
    },
    /// Data of the wrong length.
    #[error("volume data has {got} values, the grid {shape:?} needs {want}")]
    Length {
        /// Values given.
        got: usize,
        /// Values needed.
        want: usize,
        /// The grid's shape.
        shape: [usize; 3],
    },
}

impl VolumeGrid {
    /// A validated grid.
    pub fn new(x: [f64; 2], y: [f64; 2], z: [f64; 2], shape: [usize; 3]) -> Result<Self, VolumeError> {
        for (axis, range) in [("x", x), ("y", y), ("z", z)] {
            if !(range[0].is_finite() && range[1].is_finite() && range[0] < range[1]) {
                return Err(VolumeError::Range { axis, range });
            }
        }
        let total = shape.iter().try_fold(1usize, |acc, &n| acc.checked_mul(n));
        if shape.iter().any(|&n| n == 0 || n > 4096) || total.is_none_or(|t| t > 1 << 30) {
            return Err(VolumeError::Shape { shape });
        }
        Ok(Self { x, y, z, shape })
    }

    /// Number of voxels.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }

    /// Always false for a validated grid; for clippy's `len` rule.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Voxel size along x, y, z.
    pub fn voxel(&self) -> DVec3 {
        DVec3::new(
            (self.x[1] - self.x[0]) / self.shape[0] as f64,
            (self.y[1] - self.y[0]) / self.shape[1] as f64,
            (self.z[1] - self.z[0]) / self.shape[2] as f64,
        )
    }

    /// Lower corner.
    pub fn min(&self) -> DVec3 {
        DVec3::new(self.x[0], self.y[0], self.z[0])
    }

    /// Upper corner.
    pub fn max(&self) -> DVec3 {
        DVec3::new(self.x[1], self.y[1], self.z[1])
    }

    /// Centre of voxel `(ix, iy, iz)`.
    pub fn centre(&self, ix: usize, iy: usize, iz: usize) -> DVec3 {
        self.min() + self.voxel() * (DVec3::new(ix as f64, iy as f64, iz as f64) + 0.5)
    }

    /// Linear index of voxel `(ix, iy, iz)`.
    pub fn index(&self, ix: usize, iy: usize, iz: usize) -> usize {
        (iz * self.shape[1] + iy) * self.shape[0] + ix
    }

    /// The voxel containing `p`, if inside.
    pub fn voxel_of(&self, p: DVec3) -> Option<[usize; 3]> {
        let f = (p - self.min()) / self.voxel();
        let i = [f.x.floor(), f.y.floor(), f.z.floor()];
        (0..3)
            .all(|a| i[a] >= 0.0 && (i[a] as usize) < self.shape[a])
            .then(|| i.map(|v| v as usize))
    }
}

/// A scalar volume on a grid.
#[derive(Clone, Debug, PartialEq)]
pub struct Volume {
    /// The grid.
    pub grid: VolumeGrid,
    /// Values, `[nz, ny, nx]` C order.
    pub data: Vec<f32>,
}

/// A depth map and its mask: for each (x, y) column, the z of the volume's maximum.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    /// Voxels along x and y.
    pub shape: [usize; 2],
    /// z of the maximum (metres), NaN where masked; `[ny, nx]` C order.
    pub depth: Vec<f32>,
    /// The maximum along z (the albedo image), `[ny, nx]`.
    pub peak: Vec<f32>,
    /// The z range the depths lie in.
    pub z: [f64; 2],
}

impl Volume {
    /// Wraps `data` laid out on `grid`.
    pub fn new(grid: VolumeGrid, data: Vec<f32>) -> Result<Self, VolumeError> {
        if data.len() != grid.len() {
            return Err(VolumeError::Length {
                got: data.len(),
                want: grid.len(),
                shape: grid.shape,
            });
        }
        Ok(Self { grid, data })
    }

    /// The value at voxel `(ix, iy, iz)`.
    pub fn at(&self, ix: usize, iy: usize, iz: usize) -> f32 {
        self.data[self.grid.index(ix, iy, iz)]
    }

    /// Position and value of the largest voxel (first one on ties).
    pub fn argmax(&self) -> (DVec3, f32) {
        let (mut best, mut at) = (f32::NEG_INFINITY, 0);
        for (i, &v) in self.data.iter().enumerate() {
            if v > best {
                best = v;
                at = i;
            }
        }
        let [nx, ny, _] = self.grid.shape;
        (self.grid.centre(at % nx, (at / nx) % ny, at / (nx * ny)), best)
    }

    /// Largest value (0 for an all-negative or empty volume).
    pub fn max_value(&self) -> f32 {
        self.data.iter().copied().fold(0.0, f32::max)
    }

    /// Depth map: for each column the z of the maximum, refined to sub-voxel precision
    /// by a parabola through the peak and its neighbours; columns whose peak is below
    /// `threshold` × the volume's maximum are masked (NaN).
    pub fn depth_map(&self, threshold: f32) -> DepthMap {
        let [nx, ny, nz] = self.grid.shape;
        let global = self.max_value();
        let dz = self.grid.voxel().z;
        let mut depth = vec![f32::NAN; nx * ny];
        let mut peak = vec![0.0f32; nx * ny];
        for iy in 0..ny {
            for ix in 0..nx {
                let column = |iz: usize| self.at(ix, iy, iz);
                let (mut best, mut at) = (f32::NEG_INFINITY, 0);
                for iz in 0..nz {
                    if column(iz) > best {
                        best = column(iz);
                        at = iz;
                    }
                }
                peak[iy * nx + ix] = best.max(0.0);
                if !(best > 0.0 && best >= threshold * global) {
                    continue;
                }
                let mut offset = 0.0;
                if at > 0 && at + 1 < nz {
                    let (a, b, c) = (column(at - 1) as f64, best as f64, column(at + 1) as f64);
                    let curvature = a - 2.0 * b + c;
                    if curvature < 0.0 {
                        offset = (0.5 * (a - c) / curvature).clamp(-0.5, 0.5);
                    }
                }
                depth[iy * nx + ix] = (self.grid.z[0] + (at as f64 + 0.5 + offset) * dz) as f32;
            }
        }
        DepthMap {
            shape: [nx, ny],
            depth,
            peak,
            z: self.grid.z,
        }
    }
}

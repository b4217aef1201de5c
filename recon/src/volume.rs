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

/// The axis a depth map looks along: the volume's axis nearest the relay's normal, and
/// which way along it leads away from the relay into the hidden scene. A wall in the
/// x–y plane facing +z (our instrument's frame) gives [`DepthAxis::Z`]; a Zaragoza
/// (ZNLOS) wall in the x–z plane with its scene at −y gives `y`, away towards −y.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct DepthAxis {
    /// 0, 1 or 2: x, y or z.
    pub axis: usize,
    /// Whether the depth away from the relay grows with the coordinate.
    pub positive: bool,
}

impl DepthAxis {
    /// Along +z, away from a relay that faces +z.
    pub const Z: DepthAxis = DepthAxis {
        axis: 2,
        positive: true,
    };

    /// The axis nearest `direction` (from the relay into the scene), and its sign;
    /// `None` for a zero or non-finite direction.
    pub fn nearest(direction: DVec3) -> Option<Self> {
        if !(direction.is_finite() && direction != DVec3::ZERO) {
            return None;
        }
        let a = direction.abs();
        // Ties go to z, then y: the instrument's own frame first.
        let axis = if a.z >= a.x && a.z >= a.y {
            2
        } else if a.y >= a.x {
            1
        } else {
            0
        };
        Some(Self {
            axis,
            positive: direction[axis] > 0.0,
        })
    }

    /// The two other axes, in increasing order: a depth image's columns, then its rows.
    pub fn lateral(self) -> [usize; 2] {
        match self.axis {
            0 => [1, 2],
            1 => [0, 2],
            _ => [0, 1],
        }
    }

    /// The axis's name, `x`, `y` or `z`.
    pub fn name(self) -> &'static str {
        ["x", "y", "z"][self.axis.min(2)]
    }

    /// `+z`, `-y`, …: the axis and the way away from the relay.
    pub fn label(self) -> String {
        format!("{}{}", if self.positive { "+" } else { "-" }, self.name())
    }
}

impl Default for DepthAxis {
    fn default() -> Self {
        Self::Z
    }
}

/// A depth map and its mask: for each column of the volume along its depth axis
/// ([`DepthAxis`]; z for a relay facing +z), the coordinate of the volume's maximum.
#[derive(Clone, Debug, PartialEq)]
pub struct DepthMap {
    /// The axis the columns run along.
    pub axis: DepthAxis,
    /// Voxels along the two other axes ([`DepthAxis::lateral`]; x and y for z).
    pub shape: [usize; 2],
    /// The coordinate of the maximum along the axis (metres), NaN where masked;
    /// `[rows, columns]` C order (`[ny, nx]` for z).
    pub depth: Vec<f32>,
    /// The maximum along the axis (the albedo image), `[rows, columns]`.
    pub peak: Vec<f32>,
    /// The volume's range along the axis, metres.
    pub range: [f64; 2],
}

impl DepthMap {
    /// How far `depth` lies from the relay's side of the range, as a fraction of the
    /// range: 0 nearest the relay, 1 farthest.
    pub fn distance_fraction(&self, depth: f64) -> f64 {
        let span = (self.range[1] - self.range[0]).max(f64::MIN_POSITIVE);
        let t = (depth - self.range[0]) / span;
        if self.axis.positive { t } else { 1.0 - t }
    }
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

    /// Depth map along +z ([`Volume::depth_map_along`] with [`DepthAxis::Z`]).
    pub fn depth_map(&self, threshold: f32) -> DepthMap {
        self.depth_map_along(DepthAxis::Z, threshold)
    }

    /// Depth map: for each column along `axis` the coordinate of the maximum, refined
    /// to sub-voxel precision by a parabola through the peak and its neighbours;
    /// columns whose peak is below `threshold` × the volume's maximum are masked (NaN).
    /// The maximum is the first along the way away from the relay on ties.
    pub fn depth_map_along(&self, axis: DepthAxis, threshold: f32) -> DepthMap {
        let d = axis.axis.min(2);
        let [ca, ra] = axis.lateral();
        let shape = self.grid.shape;
        let (cols, rows, n) = (shape[ca], shape[ra], shape[d]);
        let global = self.max_value();
        let range = [self.grid.x, self.grid.y, self.grid.z][d];
        let step = self.grid.voxel()[d];
        let mut depth = vec![f32::NAN; cols * rows];
        let mut peak = vec![0.0f32; cols * rows];
        for r in 0..rows {
            for c in 0..cols {
                let column = |k: usize| {
                    let mut i = [0usize; 3];
                    i[ca] = c;
                    i[ra] = r;
                    i[d] = k;
                    self.at(i[0], i[1], i[2])
                };
                let (mut best, mut at) = (f32::NEG_INFINITY, 0);
                for j in 0..n {
                    let k = if axis.positive { j } else { n - 1 - j };
                    if column(k) > best {
                        best = column(k);
                        at = k;
                    }
                }
                peak[r * cols + c] = best.max(0.0);
                if !(best > 0.0 && best >= threshold * global) {
                    continue;
                }
                let mut offset = 0.0;
                if at > 0 && at + 1 < n {
                    let (a, b, c) = (column(at - 1) as f64, best as f64, column(at + 1) as f64);
                    let curvature = a - 2.0 * b + c;
                    if curvature < 0.0 {
                        offset = (0.5 * (a - c) / curvature).clamp(-0.5, 0.5);
                    }
                }
                depth[r * cols + c] = (range[0] + (at as f64 + 0.5 + offset) * step) as f32;
            }
        }
        DepthMap {
            axis,
            shape: [cols, rows],
            depth,
            peak,
            range,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 6 × 5 × 8 volume holding a bright plane at `index` along `axis` (one voxel
    /// thick) and a dimmer one at `dim`, both across the two other axes.
    fn planes(axis: usize, index: usize, dim: usize) -> Volume {
        let grid = VolumeGrid::new([-0.3, 0.3], [-0.5, 0.0], [0.2, 1.0], [6, 5, 8]).unwrap();
        let mut data = vec![0.0f32; grid.len()];
        for iz in 0..8 {
            for iy in 0..5 {
                for ix in 0..6 {
                    let at = [ix, iy, iz][axis];
                    data[grid.index(ix, iy, iz)] = if at == index {
                        1.0
                    } else if at == dim {
                        0.5
                    } else {
                        0.0
                    };
                }
            }
        }
        Volume::new(grid, data).unwrap()
    }

    #[test]
    fn the_nearest_axis_follows_the_relays_normal() {
        let axis = |x, y, z| DepthAxis::nearest(DVec3::new(x, y, z)).map(DepthAxis::label);
        assert_eq!(axis(0.1, 0.2, 1.0).as_deref(), Some("+z"));
        assert_eq!(axis(0.1, -1.0, 0.2).as_deref(), Some("-y"));
        assert_eq!(axis(-0.9, 0.3, -0.2).as_deref(), Some("-x"));
        // Ties go to z, then y.
        assert_eq!(axis(1.0, 1.0, -1.0).as_deref(), Some("-z"));
        assert_eq!(axis(1.0, 1.0, 0.0).as_deref(), Some("+y"));
        assert_eq!(axis(0.0, 0.0, 0.0), None);
        assert_eq!(axis(f64::NAN, 0.0, 1.0), None);
        assert_eq!(
            DepthAxis {
                axis: 0,
                positive: true
            }
            .lateral(),
            [1, 2]
        );
        assert_eq!(
            DepthAxis {
                axis: 1,
                positive: false
            }
            .lateral(),
            [0, 2]
        );
        assert_eq!(DepthAxis::Z.lateral(), [0, 1]);
    }

    /// Along −y (a Zaragoza wall at y = 0 facing its scene at −y) the map is over x and
    /// z, holds the plane's y, and calls the side nearest the relay near.
    #[test]
    fn a_depth_map_along_minus_y_looks_from_the_relay() {
        let v = planes(1, 1, 3);
        let axis = DepthAxis {
            axis: 1,
            positive: false,
        };
        let map = v.depth_map_along(axis, 0.2);
        assert_eq!(map.shape, [6, 8], "columns along x, rows along z");
        assert_eq!(map.range, [-0.5, 0.0]);
        let want = -0.5 + 1.5 * 0.1;
        assert!(
            map.depth.iter().all(|&d| (d as f64 - want).abs() < 1e-6),
            "{:?}",
            map.depth
        );
        assert!(map.peak.iter().all(|&p| p == 1.0));
        // Near the relay (y = 0) is the start of the colour scale, far (y = −0.5) its end.
        assert!((map.distance_fraction(0.0) - 0.0).abs() < 1e-12);
        assert!((map.distance_fraction(-0.5) - 1.0).abs() < 1e-12);
        // Along +z the same volume is a column of equal values: no depth to read there
        // but the first maximum's (every voxel of a column along z is as bright).
        let along_z = v.depth_map(0.2);
        assert_eq!(along_z.shape, [6, 5]);
    }

    /// Two equally bright planes: the one nearer the relay is the surface, whichever
    /// way the axis runs.
    #[test]
    fn on_a_tie_the_surface_nearer_the_relay_wins() {
        let mut v = planes(0, 1, 4);
        for x in v.data.iter_mut() {
            if *x == 0.5 {
                *x = 1.0;
            }
        }
        let centre = |i: usize| -0.3 + (i as f64 + 0.5) * 0.1;
        let towards_plus = v.depth_map_along(
            DepthAxis {
                axis: 0,
                positive: true,
            },
            0.5,
        );
        let towards_minus = v.depth_map_along(
            DepthAxis {
                axis: 0,
                positive: false,
            },
            0.5,
        );
        assert_eq!(towards_plus.shape, [5, 8], "columns along y, rows along z");
        assert!(
            towards_plus
                .depth
                .iter()
                .all(|&d| (d as f64 - centre(1)).abs() < 1e-6)
        );
        assert!(
            towards_minus
                .depth
                .iter()
                .all(|&d| (d as f64 - centre(4)).abs() < 1e-6)
        );
    }
}

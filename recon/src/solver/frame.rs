//! A volume sampled in a relay plane's frame, and its resampling onto world voxels.
use glam::DVec3;
use rayon::prelude::*;

use crate::relay::VirtualRelay;
use crate::volume::{Volume, VolumeGrid};

/// Values on the relay grid's columns and rows, at depths `depth_start + k·depth_step`
/// along its normal. Layout `[depth][row][column]`.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameVolume {
    /// The plane and its grid.
    pub relay: VirtualRelay,
    /// Depth of slice 0, metres along the normal.
    pub depth_start: f64,
    /// Depth between slices, metres.
    pub depth_step: f64,
    /// Number of slices.
    pub depths: usize,
    /// Values.
    pub data: Vec<f32>,
}

impl FrameVolume {
    /// Trilinear sample at world point `p`; 0 outside the sampled box.
    pub fn sample(&self, p: DVec3) -> f32 {
        let [nx, ny] = self.relay.resolution;
        let s = self.relay.spacing();
        let d = p - self.relay.centre;
        // Continuous indices: grid point i sits at coordinate −size/2 + (i + ½)·spacing.
        let fx = (d.dot(self.relay.u) + 0.5 * self.relay.size[0]) / s[0] - 0.5;
        let fy = (d.dot(self.relay.v) + 0.5 * self.relay.size[1]) / s[1] - 0.5;
        let fz = (d.dot(self.relay.normal) - self.depth_start) / self.depth_step;
        let dims = [nx, ny, self.depths];
        let f = [fx, fy, fz];
        if !f.iter().all(|v| v.is_finite()) {
            return 0.0;
        }
        let mut lo = [0usize; 3];
        let mut w = [0.0f64; 3];
        for a in 0..3 {
            if f[a] < -0.5 || f[a] > dims[a] as f64 - 0.5 {
                return 0.0;
            }
            // Clamp into the interior so the box edges (within half a cell) extrapolate flat.
            let c = f[a].clamp(0.0, (dims[a] - 1) as f64);
            lo[a] = (c.floor() as usize).min(dims[a].saturating_sub(2));
            w[a] = if dims[a] > 1 { c - lo[a] as f64 } else { 0.0 };
        }
        let at = |x: usize, y: usize, z: usize| self.data[(z * ny + y) * nx + x] as f64;
        let mut v = 0.0;
        for (dz, wz) in [(0, 1.0 - w[2]), (1, w[2])] {
            for (dy, wy) in [(0, 1.0 - w[1]), (1, w[1])] {
                for (dx, wx) in [(0, 1.0 - w[0]), (1, w[0])] {
                    let weight = wx * wy * wz;
                    if weight > 0.0 {
                        let (x, y, z) = (
                            (lo[0] + dx).min(nx - 1),
                            (lo[1] + dy).min(ny - 1),
                            (lo[2] + dz).min(self.depths - 1),
                        );
                        v += weight * at(x, y, z);
                    }
                }
            }
        }
        v as f32
    }

    /// Resamples onto the world grid, in parallel over z slices.
    pub fn to_world(&self, grid: &VolumeGrid) -> Volume {
        let [nx, ny, _] = grid.shape;
        let mut data = vec![0.0f32; grid.len()];
        data.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
            for iy in 0..ny {
                for ix in 0..nx {
                    slice[iy * nx + ix] = self.sample(grid.centre(ix, iy, iz));
                }
            }
        });
        Volume { grid: *grid, data }
    }
}

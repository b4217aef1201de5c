//! A volume sampled in a relay plane's frame, and its resampling onto world voxels.
use glam::DVec3;
use rayon::prelude::*;

use crate::relay::VirtualRelay;
use crate::volume::{Volume, VolumeGrid};

/// Most sub-samples per world-voxel axis when resampling (a voxel 16 frame cells deep
/// is averaged from 16 samples along that axis; a deeper one from 16 spread over it).
const MAX_SUBSAMPLES: usize = 16;

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

    /// Sub-samples per world-voxel axis needed to see every frame cell the voxel spans:
    /// the voxel's extent along each world axis, in frame cells (L1 over the frame's
    /// three axes), rounded up (less a rounding allowance, so an exact fit is one
    /// sample); at most [`MAX_SUBSAMPLES`].
    fn subsamples(&self, voxel: DVec3) -> [usize; 3] {
        let s = self.relay.spacing();
        let axes = [DVec3::X, DVec3::Y, DVec3::Z];
        let mut n = [1usize; 3];
        for a in 0..3 {
            let e = axes[a];
            let cells = voxel[a]
                * (e.dot(self.relay.u).abs() / s[0]
                    + e.dot(self.relay.v).abs() / s[1]
                    + e.dot(self.relay.normal).abs() / self.depth_step.abs());
            if cells.is_finite() {
                n[a] = ((cells - 1e-6).ceil() as usize).clamp(1, MAX_SUBSAMPLES);
            }
        }
        n
    }

    /// Resamples onto the world grid, in parallel over z slices. Each voxel is the mean
    /// of the frame over the voxel (a box filter, sampled at least once per frame cell
    /// along each axis), so a thin surface resolved finer than the voxels keeps its
    /// integrated intensity wherever it falls inside a voxel, instead of being point
    /// sampled (and missed) between voxel centres.
    pub fn to_world(&self, grid: &VolumeGrid) -> Volume {
        let [nx, ny, _] = grid.shape;
        let voxel = grid.voxel();
        let n = self.subsamples(voxel);
        let offsets: Vec<DVec3> = (0..n[2])
            .flat_map(|k| {
                (0..n[1]).flat_map(move |j| {
                    (0..n[0]).map(move |i| {
                        let f = |c: usize, m: usize| (c as f64 + 0.5) / m as f64 - 0.5;
                        DVec3::new(f(i, n[0]), f(j, n[1]), f(k, n[2]))
                    })
                })
            })
            .map(|f| f * voxel)
            .collect();
        let inv = 1.0 / offsets.len() as f64;
        let mut data = vec![0.0f32; grid.len()];
        data.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
            for iy in 0..ny {
                for ix in 0..nx {
                    let c = grid.centre(ix, iy, iz);
                    let sum: f64 = offsets.iter().map(|o| self.sample(c + *o) as f64).sum();
                    slice[iy * nx + ix] = (sum * inv) as f32;
                }
            }
        });
        Volume { grid: *grid, data }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A frame 8 × 8 cells of 0.1 m laterally and 200 slices 2 mm deep, normal +z, with
    /// one bright slice at `depth` (a thin surface resolved finer than world voxels).
    fn sheet(depth_slice: usize) -> FrameVolume {
        let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [0.8, 0.8], [8, 8]).unwrap();
        let mut data = vec![0.0f32; 200 * 64];
        data[depth_slice * 64..(depth_slice + 1) * 64].fill(1.0);
        FrameVolume {
            relay,
            depth_start: 0.001,
            depth_step: 0.002,
            depths: 200,
            data,
        }
    }

    fn column(v: &Volume) -> Vec<f32> {
        let [nx, ny, nz] = v.grid.shape;
        (0..nz)
            .map(|iz| v.data[v.grid.index(nx / 2, ny / 2, iz)])
            .collect()
    }

    #[test]
    fn coarse_voxels_keep_a_thin_surface_wherever_it_falls() {
        // World voxels 2 cm deep (10 frame slices): the surface's integral over the
        // column is the same whether it sits at a voxel centre or between two, and the
        // voxel holding it gets the mean over its depth (1/10).
        let grid = VolumeGrid {
            x: [-0.4, 0.4],
            y: [-0.4, 0.4],
            z: [0.0, 0.4],
            shape: [8, 8, 20],
        };
        for slice in [54, 55, 59, 60, 64] {
            let v = sheet(slice).to_world(&grid);
            let col = column(&v);
            let total: f32 = col.iter().sum();
            assert!(
                (total - 0.1).abs() < 1e-4,
                "slice {slice}: column sum {total}, {col:?}"
            );
            let peak = col.iter().copied().fold(0.0f32, f32::max);
            assert!(
                peak >= 0.05 - 1e-6,
                "slice {slice}: peak {peak} lost between voxels"
            );
        }
    }

    #[test]
    fn voxels_as_fine_as_the_frame_are_sampled_once() {
        let frame = sheet(100);
        let grid = VolumeGrid {
            x: [-0.4, 0.4],
            y: [-0.4, 0.4],
            z: [0.0, 0.4],
            shape: [8, 8, 200],
        };
        assert_eq!(frame.subsamples(grid.voxel()), [1, 1, 1]);
        let col = column(&frame.to_world(&grid));
        assert_eq!(col[100], 1.0);
        assert_eq!(col.iter().filter(|v| **v != 0.0).count(), 1);
    }
}

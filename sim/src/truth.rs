//! Ground truth for judging reconstructions: the depth map and mask of the hidden
//! objects on a grid, and the relay's true points and normals.
use glam::DVec3;

use crate::transport::World;

/// Depth and mask of the hidden objects on an x/y grid, seen along +z from `z_start`
/// (the planar-relay convention: the relay near z = 0, the hidden scene at z > 0).
#[derive(Clone, Debug, PartialEq)]
pub struct DepthTruth {
    /// Pixels along x and y.
    pub shape: [usize; 2],
    /// Outer bounds along x and y, metres (pixels are cell-centred).
    pub x: [f64; 2],
    /// Outer bounds along y.
    pub y: [f64; 2],
    /// z of the first hidden surface per pixel, NaN where none; `[ny, nx]` C order.
    pub depth: Vec<f64>,
}

impl DepthTruth {
    /// Whether pixel (ix, iy) sees a hidden object.
    pub fn mask(&self, ix: usize, iy: usize) -> bool {
        self.depth[iy * self.shape[0] + ix].is_finite()
    }
}

/// The hidden objects' depth map on the grid, casting one ray per pixel centre.
pub fn depth_truth(world: &World, x: [f64; 2], y: [f64; 2], shape: [usize; 2], z_start: f64) -> DepthTruth {
    let [nx, ny] = shape;
    let mut depth = Vec::with_capacity(nx * ny);
    for iy in 0..ny {
        for ix in 0..nx {
            let px = x[0] + (ix as f64 + 0.5) * (x[1] - x[0]) / nx as f64;
            let py = y[0] + (iy as f64 + 0.5) * (y[1] - y[0]) / ny as f64;
            let hit = world.cast_hidden(DVec3::new(px, py, z_start), DVec3::Z);
            depth.push(hit.map_or(f64::NAN, |(p, _)| p.z));
        }
    }
    DepthTruth { shape, x, y, depth }
}

/// True relay points and normals (facing `viewpoint`) where rays from `viewpoint`
/// through a grid of directions hit the relay.
pub fn relay_truth(world: &World, viewpoint: DVec3, directions: &[DVec3]) -> Vec<(DVec3, DVec3)> {
    directions
        .iter()
        .filter_map(|d| world.cast(viewpoint, *d))
        .filter(|h| h.on_relay)
        .map(|h| (h.point, h.normal))
        .collect()
}

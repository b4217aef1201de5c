//! Filtered backprojection (Velten et al. 2012) for arbitrary pairs on any relay.
//!
//! Every voxel x collects, from every pair, the histogram value at its path length
//! |x − x_i| + |x − x_d| (linearly interpolated between bin centres), optionally times
//! d_i²·d_d² to undo the radiometric falloff. The backprojection is then sharpened
//! with the negative 3-D Laplacian and its negative lobes are clipped.
//!
//! Work is split by z slices (each thread owns whole slices and loops over all pairs,
//! so a slice stays in cache); the inner loop runs in f32 along x.
use rayon::prelude::*;

use super::SolverError;
use crate::transient::TransientSet;
use crate::volume::{Volume, VolumeGrid};

/// Pairs whose histograms are swept together over a slice (64 × 2 KiB fits in L2).
const PAIR_TILE: usize = 64;

/// The filter applied after backprojection.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FbpFilter {
    /// Plain backprojection.
    None,
    /// Negative Laplacian, negatives clipped to zero.
    Laplacian,
}

/// FBP settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct FbpSettings {
    /// Filter after backprojection.
    pub filter: FbpFilter,
    /// Weight each contribution by d_i²·d_d² (undoes the 1/r² falloff of both legs).
    pub compensate_falloff: bool,
}

impl Default for FbpSettings {
    fn default() -> Self {
        Self {
            filter: FbpFilter::Laplacian,
            compensate_falloff: true,
        }
    }
}

/// Filtered backprojection of `set` onto `grid`.
pub fn fbp(set: &TransientSet, grid: &VolumeGrid, settings: &FbpSettings) -> Result<Volume, SolverError> {
    if set.is_empty() {
        return Err(SolverError::Empty);
    }
    let axis = *set.axis();
    let [nx, ny, _] = grid.shape;
    let voxel = grid.voxel();
    let min = grid.min();
    let xs: Vec<f32> = (0..nx)
        .map(|i| (min.x + (i as f64 + 0.5) * voxel.x) as f32)
        .collect();
    let inv_w = (1.0 / axis.width) as f32;
    let offset = (axis.start / axis.width + 0.5) as f32;
    let bins = axis.bins;
    // Histograms padded with one zero before and two after, so the interpolation below
    // needs no bounds checks: indices are clamped into the padding instead.
    let padded: Vec<Vec<f32>> = (0..set.len())
        .map(|p| {
            let w = set.weight(p);
            let mut h = Vec::with_capacity(bins + 3);
            h.push(0.0);
            h.extend(set.histogram(p).iter().map(|v| v * w));
            h.extend([0.0, 0.0]);
            h
        })
        .collect();
    let top = (bins + 1) as f32;
    let mut data = vec![0.0f32; grid.len()];
    data.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
        let z = (min.z + (iz as f64 + 0.5) * voxel.z) as f32;
        let mut index = vec![0.0f32; nx];
        let mut gain = vec![1.0f32; nx];
        // Pairs in tiles whose histograms stay in L2 while every row of the slice
        // visits them; the row being summed stays in L1.
        for (pairs, hists) in set.pairs().chunks(PAIR_TILE).zip(padded.chunks(PAIR_TILE)) {
            for iy in 0..ny {
                let y = (min.y + (iy as f64 + 0.5) * voxel.y) as f32;
                let row = &mut slice[iy * nx..(iy + 1) * nx];
                for (pair, h) in pairs.iter().zip(hists) {
                    let (xi, xd) = (pair.xi.as_vec3(), pair.xd.as_vec3());
                    let byi = (z - xi.z) * (z - xi.z) + (y - xi.y) * (y - xi.y);
                    let byd = (z - xd.z) * (z - xd.z) + (y - xd.y) * (y - xd.y);
                    // Vectorisable pass: fractional bin index (shifted by the leading pad).
                    for ((f, g), &x) in index.iter_mut().zip(gain.iter_mut()).zip(&xs) {
                        let ri2 = byi + (x - xi.x) * (x - xi.x);
                        let rd2 = byd + (x - xd.x) * (x - xd.x);
                        *f = ((ri2.sqrt() + rd2.sqrt()) * inv_w - offset + 1.0)
                            .max(0.0)
                            .min(top);
                        *g = ri2 * rd2;
                    }
                    if !settings.compensate_falloff {
                        gain.fill(1.0);
                    }
                    // Gather pass.
                    for ((out, &f), &g) in row.iter_mut().zip(&index).zip(&gain) {
                        let b = f as usize;
                        let t = f - b as f32;
                        *out += g * ((1.0 - t) * h[b] + t * h[b + 1]);
                    }
                }
            }
        }
    });
    let mut volume = Volume { grid: *grid, data };
    if settings.filter == FbpFilter::Laplacian {
        volume = negative_laplacian(&volume);
    }
    Ok(volume)
}

/// −∇² with edge replication, negatives clipped.
fn negative_laplacian(v: &Volume) -> Volume {
    let [nx, ny, nz] = v.grid.shape;
    let h = v.grid.voxel();
    let inv = [1.0 / (h.x * h.x), 1.0 / (h.y * h.y), 1.0 / (h.z * h.z)].map(|x| x as f32);
    let mut out = vec![0.0f32; v.data.len()];
    out.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
        for iy in 0..ny {
            for ix in 0..nx {
                let c = v.at(ix, iy, iz);
                let pair = |a: f32, b: f32, w: f32| (2.0 * c - a - b) * w;
                let lap = pair(
                    v.at(ix.saturating_sub(1), iy, iz),
                    v.at((ix + 1).min(nx - 1), iy, iz),
                    inv[0],
                ) + pair(
                    v.at(ix, iy.saturating_sub(1), iz),
                    v.at(ix, (iy + 1).min(ny - 1), iz),
                    inv[1],
                ) + pair(
                    v.at(ix, iy, iz.saturating_sub(1)),
                    v.at(ix, iy, (iz + 1).min(nz - 1)),
                    inv[2],
                );
                slice[iy * nx + ix] = lap.max(0.0);
            }
        }
    });
    Volume {
        grid: v.grid,
        data: out,
    }
}

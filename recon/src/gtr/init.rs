//! Initial primitive placement: uniform in the ROI (the paper's default), or seeded
//! from a coarse backprojection of the data so primitives start where the measured
//! transients put energy (the paper notes good initialisation speeds convergence).
use glam::{DQuat, DVec3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{GaussianCloud, ModelError, Primitive, ScaleBounds};
use crate::roi::RoiBox;
use crate::transient::TransientSet;

/// How primitives are placed before optimisation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum Init {
    /// Centres uniform in the ROI.
    Uniform,
    /// Centres drawn from a coarse backprojection of the data on a `grid` of voxels,
    /// with `uniform_fraction` of them still uniform, to keep exploring.
    Backprojection {
        /// Voxels along x, y, z.
        grid: [usize; 3],
        /// Fraction of primitives placed uniformly instead.
        uniform_fraction: f64,
    },
}

/// Primitives used for the backprojection at most (evenly spread over the set).
const BACKPROJECTION_PAIRS: usize = 2000;

/// Places `count` primitives with a shared isotropic `scale` and `albedo`.
pub fn initial_cloud(
    roi: RoiBox,
    bounds: ScaleBounds,
    count: usize,
    scale: f64,
    albedo: f64,
    init: &Init,
    data: &TransientSet,
    seed: u64,
) -> Result<GaussianCloud, ModelError> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5EED_1417);
    let mut cloud = GaussianCloud::new(roi, bounds)?;
    let uniform = |rng: &mut ChaCha8Rng| {
        let r = DVec3::new(
            rng.random_range(-0.95..0.95),
            rng.random_range(-0.95..0.95),
            rng.random_range(-0.95..0.95),
        );
        roi.centre + roi.half * r
    };
    let centres: Vec<DVec3> = match init {
        Init::Backprojection {
            grid,
            uniform_fraction,
        } if !data.is_empty() => {
            let density = backprojection(roi, *grid, data);
            let total: f64 = density.iter().sum();
            let seeded = ((1.0 - uniform_fraction.clamp(0.0, 1.0)) * count as f64).round() as usize;
            if total > 0.0 {
                let cumulative: Vec<f64> = density
                    .iter()
                    .scan(0.0, |acc, d| {
                        *acc += d / total;
                        Some(*acc)
                    })
                    .collect();
                let voxel = roi.half * 2.0 / DVec3::new(grid[0] as f64, grid[1] as f64, grid[2] as f64);
                let mut out: Vec<DVec3> = (0..seeded)
                    .map(|_| {
                        let u: f64 = rng.random();
                        let idx = cumulative.partition_point(|&c| c < u).min(density.len() - 1);
                        let (ix, iy, iz) = (
                            idx % grid[0],
                            (idx / grid[0]) % grid[1],
                            idx / (grid[0] * grid[1]),
                        );
                        let jitter = DVec3::new(rng.random(), rng.random(), rng.random());
                        let p = roi.min() + voxel * (DVec3::new(ix as f64, iy as f64, iz as f64) + jitter);
                        // Keep strictly inside for the tanh map.
                        roi.centre
                            + ((p - roi.centre) / roi.half).clamp(DVec3::splat(-0.95), DVec3::splat(0.95))
                                * roi.half
                    })
                    .collect();
                out.extend((seeded..count).map(|_| uniform(&mut rng)));
                out
            } else {
                (0..count).map(|_| uniform(&mut rng)).collect()
            }
        }
        _ => (0..count).map(|_| uniform(&mut rng)).collect(),
    };
    for centre in centres {
        cloud.push(Primitive {
            centre,
            scale: DVec3::splat(scale),
            rotation: DQuat::IDENTITY,
            albedo,
        })?;
    }
    Ok(cloud)
}

/// A non-negative density on the voxel grid (x fastest): each pair's counts spread on
/// the ellipsoids `|x − xi| + |x − xd| = ℓ`, compensated for 1/(di² dd²) falloff,
/// with the grid mean removed and negatives clipped.
pub fn backprojection(roi: RoiBox, grid: [usize; 3], data: &TransientSet) -> Vec<f64> {
    let step = (data.len() / BACKPROJECTION_PAIRS).max(1);
    let pairs: Vec<usize> = (0..data.len()).step_by(step).collect();
    let n = grid[0] * grid[1] * grid[2];
    // Voxels in chunks, each summed inside `simd::dispatch`: built for AVX2 the root
    // and `floor` are instructions (`floor` is a libm call in the baseline build); the
    // arithmetic, and so every bit, is the same.
    const VOXELS_PER_TASK: usize = 64;
    let mut density = vec![0.0f64; n];
    density
        .par_chunks_mut(VOXELS_PER_TASK)
        .enumerate()
        .for_each(|(task, out)| {
            crate::simd::dispatch(DensityChunk {
                first: task * VOXELS_PER_TASK,
                out,
                roi,
                grid,
                data,
                pairs: &pairs,
            })
        });
    let mean = density.iter().sum::<f64>() / n.max(1) as f64;
    density.iter_mut().for_each(|d| *d = (*d - mean).max(0.0).powi(2));
    density
}

/// Voxels `first..first + out.len()` of [`backprojection`]'s density, before the mean
/// is removed.
struct DensityChunk<'a> {
    first: usize,
    out: &'a mut [f64],
    roi: RoiBox,
    grid: [usize; 3],
    data: &'a TransientSet,
    pairs: &'a [usize],
}

impl crate::simd::Work for DensityChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) {
        let Self {
            first,
            out,
            roi,
            grid,
            data,
            pairs,
        } = self;
        let axis = *data.axis();
        let voxel = roi.half * 2.0 / DVec3::new(grid[0] as f64, grid[1] as f64, grid[2] as f64);
        for (i, d) in out.iter_mut().enumerate() {
            let idx = first + i;
            let (ix, iy, iz) = (
                idx % grid[0],
                (idx / grid[0]) % grid[1],
                idx / (grid[0] * grid[1]),
            );
            let x = roi.min() + voxel * (DVec3::new(ix as f64, iy as f64, iz as f64) + 0.5);
            let mut sum = 0.0;
            for &p in pairs {
                let pair = data.pairs()[p];
                let (di, dd) = (x.distance(pair.xi), x.distance(pair.xd));
                let b = ((di + dd - axis.start) / axis.width).floor();
                if b >= 0.0 && (b as usize) < axis.bins {
                    sum += (data.histogram(p)[b as usize] / data.gain(p)) as f64
                        * data.weight(p) as f64
                        * di
                        * di
                        * dd
                        * dd;
                }
            }
            *d = sum;
        }
    }
}

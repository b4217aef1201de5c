//! Virtual confocal synthesis: the optimised Gaussians rendered, with the same forward
//! model they were fitted with, as a dense confocal scan of a virtual planar relay, so a
//! conventional solver (LCT, RSD) can turn them into a volume.
use rayon::prelude::*;

use crate::gpu::Compute;
use crate::gtr::{Kernel, RenderOptions, render_pairs};
use crate::relay::VirtualRelay;
use crate::solver::PlanarScan;
use crate::transient::{Pair, TimeAxis, TransientError, TransientSet};
use crate::volume::VolumeGrid;

/// A synthesised confocal scan and the grid it lies on.
#[derive(Clone, Debug)]
pub struct VirtualScan {
    /// One confocal transient per grid point, row by row.
    pub set: TransientSet,
    /// The grid (cells in pair order).
    pub scan: PlanarScan,
}

/// A time axis for synthesis on `relay` that starts at path length 0 and reaches twice
/// the distance from the relay to the farthest corner of `volume` (plus 5 %), in `bins`
/// bins.
pub fn default_axis(relay: &VirtualRelay, volume: &VolumeGrid, bins: usize) -> TimeAxis {
    let mut far: f64 = 0.0;
    for corner in 0..8 {
        let c = glam::DVec3::new(
            volume.x[corner & 1],
            volume.y[(corner >> 1) & 1],
            volume.z[(corner >> 2) & 1],
        );
        for (ix, iy) in [(0, 0), (relay.resolution[0] - 1, 0), (0, relay.resolution[1] - 1)] {
            far = far.max(c.distance(relay.point(ix, iy)));
        }
        far = far.max(c.distance(relay.point(relay.resolution[0] - 1, relay.resolution[1] - 1)));
    }
    TimeAxis {
        start: 0.0,
        width: 2.0 * far * 1.05 / bins.max(1) as f64,
        bins: bins.max(1),
    }
}

/// Renders confocal transients at every point of `relay` from `kernels`, in parallel
/// over groups of four grid points (one vector lane each).
pub fn synthesise(
    kernels: &[Kernel],
    relay: &VirtualRelay,
    axis: TimeAxis,
    opt: &RenderOptions,
) -> Result<VirtualScan, TransientError> {
    match synthesise_on(&Compute::Cpu, kernels, relay, axis, opt) {
        Ok(scan) => Ok(scan),
        Err(SynthError::Transient(e)) => Err(e),
        Err(SynthError::Gpu(e)) => unreachable!("the CPU path has no GPU to fail: {e}"),
    }
}

/// Why [`synthesise_on`] failed.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// The rendered transients do not make a set.
    #[error(transparent)]
    Transient(#[from] TransientError),
    /// The GPU failed.
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
}

/// [`synthesise`] on `compute`: on a GPU, [`crate::gpu::render_pairs`] in f32.
pub fn synthesise_on(
    compute: &Compute,
    kernels: &[Kernel],
    relay: &VirtualRelay,
    axis: TimeAxis,
    opt: &RenderOptions,
) -> Result<VirtualScan, SynthError> {
    let pairs: Vec<Pair> = relay
        .points()
        .into_iter()
        .map(|x| Pair::confocal(x, relay.normal))
        .collect();
    let bins = axis.bins;
    if let Some(gpu) = compute.gpu() {
        let histograms = crate::gpu::render_pairs(gpu, kernels, &pairs, &axis, opt)?;
        return scan(relay, axis, &pairs, &histograms);
    }
    let mut histograms = vec![0.0f32; pairs.len() * bins];
    const GROUP: usize = 4;
    histograms
        .par_chunks_mut(GROUP * bins)
        .zip(pairs.par_chunks(GROUP))
        .for_each_init(
            || vec![0.0f64; GROUP * bins],
            |buf, (out, pairs)| {
                let buf = &mut buf[..pairs.len() * bins];
                render_pairs(kernels, pairs, &axis, opt, buf);
                for (o, v) in out.iter_mut().zip(buf.iter()) {
                    *o = *v as f32;
                }
            },
        );
    scan(relay, axis, &pairs, &histograms)
}

/// The scan of `relay` whose transients, `axis.bins` a pair, are `histograms`.
fn scan(
    relay: &VirtualRelay,
    axis: TimeAxis,
    pairs: &[Pair],
    histograms: &[f32],
) -> Result<VirtualScan, SynthError> {
    let mut set = TransientSet::new(axis)?;
    for (pair, h) in pairs.iter().zip(histograms.chunks(axis.bins)) {
        set.push(*pair, h)?;
    }
    Ok(VirtualScan {
        set,
        scan: PlanarScan::full(*relay),
    })
}

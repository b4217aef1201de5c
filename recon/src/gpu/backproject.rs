//! Backprojection on the GPU (`backproject.wgsl`): the hot loop of
//! [`crate::solver::fbp`], every voxel against every pair, after the CPU has filtered
//! the histograms.
use super::{Gpu, GpuError, MAX_GROUPS};
use crate::transient::TimeAxis;
use crate::volume::VolumeGrid;

/// Threads of a workgroup (voxels along a slice).
const WORKGROUP: usize = 64;
/// The most pairs one dispatch takes, so no dispatch runs long enough for a desktop
/// driver's watchdog (8,000 pairs × 128² × 64 voxels is 16 dispatches at this size).
const PAIRS_PER_DISPATCH: usize = 512;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    nx: u32,
    ny: u32,
    channels: u32,
    pairs: u32,
    min_x: f32,
    min_y: f32,
    min_z: f32,
    inv_w: f32,
    vx: f32,
    vy: f32,
    vz: f32,
    offset: f32,
    top: f32,
    falloff: f32,
    stride: u32,
    z0: u32,
}

/// Backprojects `hists` (one per pair of `points`, `channels` interleaved values a bin,
/// on `axis` extended by `lead` bins each side) onto `grid` on `gpu`, each voxel's
/// contribution weighted by `(4·d_i·d_d/ℓ²)^falloff`; returns `channels` sums a voxel
/// in the grid's order. The same arithmetic as the CPU's general path, in f32 and in
/// the same order of pairs.
#[allow(clippy::too_many_arguments)]
pub fn backproject(
    gpu: &Gpu,
    points: &[([f32; 3], [f32; 3])],
    hists: &[Vec<f32>],
    channels: usize,
    grid: &VolumeGrid,
    axis: &TimeAxis,
    lead: usize,
    falloff: f64,
) -> Result<Vec<f32>, GpuError> {
    assert!(channels == 1 || channels == 2, "one or two channels");
    assert_eq!(points.len(), hists.len(), "one histogram a pair");
    let [nx, ny, nz] = grid.shape;
    let plane = nx * ny;
    if points.is_empty() {
        return Ok(vec![0.0; grid.len() * channels]);
    }
    let bins = hists[0].len() / channels;
    assert!(
        hists.iter().all(|h| h.len() == bins * channels),
        "every histogram as long"
    );
    gpu.scoped("backprojecting", || {
        let pipeline = gpu
            .backproject
            .get_or_init(|| gpu.pipeline("backproject", include_str!("backproject.wgsl")));
        // Padded as the CPU pads them: one zero bin before, two after.
        let stride = bins + 3;
        let pair_bytes = (stride * channels * 4) as u64;
        let per_chunk = ((gpu.max_binding() / pair_bytes) as usize).clamp(1, PAIRS_PER_DISPATCH);
        let chunks: Vec<(wgpu::Buffer, wgpu::Buffer, usize)> = (0..points.len())
            .step_by(per_chunk)
            .map(|first| {
                let n = per_chunk.min(points.len() - first);
                let mut padded = vec![0.0f32; n * stride * channels];
                for (dst, h) in padded
                    .chunks_exact_mut(stride * channels)
                    .zip(&hists[first..first + n])
                {
                    dst[channels..channels + h.len()].copy_from_slice(h);
                }
                let pts: Vec<[f32; 4]> = points[first..first + n]
                    .iter()
                    .flat_map(|(i, d)| [[i[0], i[1], i[2], 0.0], [d[0], d[1], d[2], 0.0]])
                    .collect();
                (
                    gpu.upload("pair points", &pts),
                    gpu.upload("histograms", &padded),
                    n,
                )
            })
            .collect();
        let min = grid.min();
        let voxel = grid.voxel();
        let base = Params {
            nx: nx as u32,
            ny: ny as u32,
            channels: channels as u32,
            pairs: 0,
            min_x: min.x as f32,
            min_y: min.y as f32,
            min_z: min.z as f32,
            inv_w: (1.0 / axis.width) as f32,
            vx: voxel.x as f32,
            vy: voxel.y as f32,
            vz: voxel.z as f32,
            offset: (axis.start / axis.width + 0.5) as f32 - lead as f32 - 1.0,
            top: (bins + 1) as f32,
            falloff: falloff as f32,
            stride: stride as u32,
            z0: 0,
        };
        // Slabs of z slices whose sums fit one binding and one dispatch.
        let slice_bytes = (plane * channels * 4) as u64;
        let per_slab = ((gpu.max_binding() / slice_bytes) as usize).clamp(1, MAX_GROUPS);
        let mut out = Vec::with_capacity(grid.len() * channels);
        for z0 in (0..nz).step_by(per_slab) {
            let slices = per_slab.min(nz - z0);
            let sums = gpu.output("sums", slices * plane * channels);
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            for (points, hist, n) in &chunks {
                let uniform = gpu.uniform(
                    "backprojection parameters",
                    &Params {
                        pairs: *n as u32,
                        z0: z0 as u32,
                        ..base
                    },
                );
                gpu.dispatch(
                    &mut encoder,
                    pipeline,
                    &[&uniform, points, hist, &sums],
                    [plane.div_ceil(WORKGROUP) as u32, slices as u32, 1],
                );
            }
            out.extend(gpu.finish("backprojecting", encoder, &sums, slices * plane * channels)?);
        }
        Ok(out)
    })
}

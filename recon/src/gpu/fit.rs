//! One step of the 3D-GTR fit on the GPU: the mini-batch's forward render
//! (`render.wgsl`, the primitives split across workgroups so a batch of a few pairs
//! still fills the GPU, and `reduce.wgsl`), its residuals and loss (`residual.wgsl`)
//! and the analytic backward pass (`backward.wgsl`), recorded in one submission with
//! one readback: each primitive's gradient with respect to its physical parameters,
//! and each pair's loss.
//!
//! The parameter maps' chain rule and AdamW stay on the CPU
//! ([`crate::gtr::Trainer`]): they are linear in the primitives and a small share of a
//! step (docs/gpu.md).
use super::render::{Model, Render, TILE, pair, prim, source, spread};
use super::{BatchGradient, Gpu, GpuError, MAX_GROUPS};
use crate::gtr::{Kernel, Loss, PhysicalGrad, RenderOptions};
use crate::transient::{Pair, TimeAxis};

/// Threads of a backward workgroup (one primitive each).
const BACKWARD_THREADS: usize = 64;
/// Workgroups a forward render should have at least, so a mini-batch of a few pairs
/// still spreads over a GPU's multiprocessors: the primitives are split into this
/// many groups over the batch's pairs.
const MIN_WORKGROUPS: usize = 256;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ResidualParams {
    bins: u32,
    loss: u32,
    loss_at: u32,
    pad0: u32,
    background: f32,
    pad: [f32; 3],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct BackwardParams {
    model: Model,
    prims: u32,
    pairs: u32,
    pad: [u32; 2],
}

/// The loss and gradient of one mini-batch on `gpu`: `kernels` rendered for `pairs`
/// on `axis`, compared with `data` (the pairs' measured histograms, one after the
/// other), each pair weighted by `weights[p][0]` and its model scaled by the gain
/// `weights[p][1]`, under `opt`'s loss. The values [`crate::gtr::batch_loss_grad`]
/// computes in f64 before the chain rule, to the f32 tolerance its tests state.
pub fn batch_gradient(
    gpu: &Gpu,
    kernels: &[Kernel],
    pairs: &[Pair],
    data: &[f32],
    weights: &[[f32; 2]],
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Result<BatchGradient, GpuError> {
    let (b, bins, k) = (pairs.len(), axis.bins, kernels.len());
    assert_eq!(data.len(), b * bins, "one histogram a pair");
    assert_eq!(weights.len(), b, "one weight a pair");
    if b == 0 || bins == 0 {
        return Ok(BatchGradient {
            losses: vec![0.0; b],
            grads: vec![PhysicalGrad::default(); k],
        });
    }
    let what = "fitting the primitives";
    let too_large = |reason: String| GpuError::Run {
        adapter: gpu.info.name.clone(),
        what,
        reason,
    };
    let batch_bytes = (4 * b * bins) as u64;
    if b > MAX_GROUPS || batch_bytes > gpu.max_binding() {
        return Err(too_large(format!(
            "a mini-batch of {b} pairs × {bins} bins is more than one dispatch holds; lower [gtr] batch-size"
        )));
    }
    // Groups of primitives for the forward render: enough workgroups in all, each
    // group at least one tile, and the partial transients within one binding.
    let tiles = k.div_ceil(TILE).max(1);
    let fit = (gpu.max_binding() / batch_bytes).max(1) as usize;
    let groups = MIN_WORKGROUPS
        .div_ceil(b)
        .clamp(1, tiles)
        .min(fit)
        .min(MAX_GROUPS);
    gpu.scoped(what, || {
        let prims: Vec<[[f32; 4]; 5]> = kernels.iter().map(prim).collect();
        let geometry: Vec<[[f32; 4]; 4]> = pairs.iter().map(pair).collect();
        let prims = gpu.upload("primitives", &prims);
        let geometry = gpu.upload("pairs", &geometry);
        let data = gpu.upload("measured transients", data);
        let weights = gpu.upload("pair weights", weights);
        let model = Model::new(axis, opt);
        let rendered = gpu.output("rendered transients", groups * b * bins);
        let dl = gpu.output("residuals", b * bins);
        let result = gpu.output("gradients and losses", 16 * k + b);
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        Render {
            prims: &prims,
            count: k,
            pairs: &geometry,
            target: &rendered,
            model,
        }
        .record(gpu, &mut encoder, 0, b, groups);

        let residual = gpu
            .residual
            .get_or_init(|| gpu.pipeline("residual", include_str!("residual.wgsl")));
        let (loss, background) = match opt.loss {
            Loss::L2 => (0, 0.0),
            Loss::Poisson { background } => (1, background as f32),
        };
        let params = ResidualParams {
            bins: bins as u32,
            loss,
            loss_at: (16 * k) as u32,
            pad0: 0,
            background,
            pad: [0.0; 3],
        };
        let uniform = gpu.uniform("residual parameters", &params);
        gpu.dispatch(
            &mut encoder,
            residual,
            &[&uniform, &rendered, &data, &weights, &dl, &result],
            [b as u32, 1, 1],
        );

        if k > 0 {
            let backward = gpu
                .backward
                .get_or_init(|| gpu.pipeline("backward", &source(include_str!("backward.wgsl"))));
            let params = BackwardParams {
                model,
                prims: k as u32,
                pairs: b as u32,
                pad: [0; 2],
            };
            let uniform = gpu.uniform("backward parameters", &params);
            gpu.dispatch(
                &mut encoder,
                backward,
                &[&uniform, &prims, &geometry, &dl, &result],
                spread(k.div_ceil(BACKWARD_THREADS)),
            );
        }
        let out = gpu.finish(what, encoder, &result, 16 * k + b)?;
        let grads = out[..16 * k].chunks_exact(16).map(physical).collect();
        Ok(BatchGradient {
            losses: out[16 * k..].to_vec(),
            grads,
        })
    })
}

/// A primitive's 16 gradient values as `backward.wgsl` writes them.
fn physical(v: &[f32]) -> PhysicalGrad {
    let d = |i: usize| f64::from(v[i]);
    let v3 = |i: usize| glam::DVec3::new(d(i), d(i + 1), d(i + 2));
    PhysicalGrad {
        x: v3(0),
        r: glam::DMat3::from_cols(v3(3), v3(6), v3(9)),
        s: v3(12),
        rho: d(15),
    }
}

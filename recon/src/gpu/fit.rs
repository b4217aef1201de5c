//! One step of the 3D-GTR fit on the GPU: the mini-batch's forward render
//! (`render.wgsl`, the primitives split across workgroups so a batch of a few pairs
//! still fills the GPU, and `reduce.wgsl`), its residuals and loss (`residual.wgsl`)
//! and the analytic backward pass (`backward.wgsl`), recorded in one submission with
//! one readback: each primitive's gradient with respect to its physical parameters,
//! and each pair's loss ([`batch_gradient`]).
//!
//! The fit itself ([`fit_steps`], what [`crate::gtr::Trainer`] runs on a GPU) keeps
//! the parameters there from step to step: after each step's backward pass,
//! `update.wgsl` chains the gradient through the parameter maps, takes the AdamW step
//! and writes the primitives the next step renders, so a run of steps needs no
//! transfer but the mini-batches in and their losses out.
use super::render::{Model, Render, TILE, pair, prim, source, spread};
use super::{BatchGradient, Gpu, GpuError, MAX_GROUPS, Optimiser, RAW, Resident, Step, Steps};
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
/// `weights[p][1]`, its data term over bins `weights[p][2]` to `weights[p][3]` (the
/// bins it recorded, [`crate::transient::TransientSet::recorded`]), under `opt`'s
/// loss. The values [`crate::gtr::batch_loss_grad`] computes in f64 before the chain
/// rule, to the f32 tolerance its tests state.
pub fn batch_gradient(
    gpu: &Gpu,
    kernels: &[Kernel],
    pairs: &[Pair],
    data: &[f32],
    weights: &[[f32; 4]],
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
    check_batch(gpu, b, bins)?;
    gpu.scoped(WHAT, || {
        let prims: Vec<[[f32; 4]; 5]> = kernels.iter().map(prim).collect();
        let prims = gpu.upload("primitives", &prims);
        let batch = Batch::upload(gpu, pairs, data, weights, k, bins);
        let mut encoder = gpu.device.create_command_encoder(&Default::default());
        batch.record(gpu, &mut encoder, &prims, k, Model::new(axis, opt), opt.loss);
        let out = gpu.finish(WHAT, encoder, &batch.result, 16 * k + b)?;
        let grads = out[..16 * k].chunks_exact(16).map(physical).collect();
        Ok(BatchGradient {
            losses: out[16 * k..].to_vec(),
            grads,
        })
    })
}

/// What a fit's GPU work is called in its errors.
const WHAT: &str = "fitting the primitives";

/// A mini-batch of `b` pairs × `bins` bins fits one dispatch and one binding, or the
/// error says to lower `[gtr] batch-size`.
fn check_batch(gpu: &Gpu, b: usize, bins: usize) -> Result<(), GpuError> {
    if b > MAX_GROUPS || (4 * b * bins) as u64 > gpu.max_binding() {
        return Err(GpuError::Run {
            adapter: gpu.info.name.clone(),
            what: WHAT,
            reason: format!(
                "a mini-batch of {b} pairs × {bins} bins is more than one dispatch holds; lower [gtr] batch-size"
            ),
        });
    }
    Ok(())
}

/// One mini-batch on the GPU: its pairs, measured histograms and weights, and the
/// buffers its step writes (the groups' partial transients, the residuals, and each
/// primitive's 16 gradient values followed by each pair's loss).
struct Batch {
    pairs: usize,
    /// Groups the primitives are split into for the forward render.
    groups: usize,
    geometry: wgpu::Buffer,
    data: wgpu::Buffer,
    weights: wgpu::Buffer,
    rendered: wgpu::Buffer,
    dl: wgpu::Buffer,
    result: wgpu::Buffer,
}

impl Batch {
    /// The batch of `pairs` ([`batch_gradient`]'s arguments) for `k` primitives.
    fn upload(gpu: &Gpu, pairs: &[Pair], data: &[f32], weights: &[[f32; 4]], k: usize, bins: usize) -> Self {
        let b = pairs.len();
        // Groups of primitives for the forward render: enough workgroups in all, each
        // group at least one tile, and the partial transients within one binding.
        let tiles = k.div_ceil(TILE).max(1);
        let fit = (gpu.max_binding() / (4 * b * bins) as u64).max(1) as usize;
        let groups = MIN_WORKGROUPS
            .div_ceil(b)
            .clamp(1, tiles)
            .min(fit)
            .min(MAX_GROUPS);
        let geometry: Vec<[[f32; 4]; 4]> = pairs.iter().map(pair).collect();
        Batch {
            pairs: b,
            groups,
            geometry: gpu.upload("pairs", &geometry),
            data: gpu.upload("measured transients", data),
            weights: gpu.upload("pair weights", weights),
            rendered: gpu.output("rendered transients", groups * b * bins),
            dl: gpu.output("residuals", b * bins),
            result: gpu.output("gradients and losses", 16 * k + b),
        }
    }

    /// Records the batch's forward render of the `k` primitives `prims`, its residuals
    /// and loss under `loss`, and the analytic backward pass into `result`.
    fn record(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        prims: &wgpu::Buffer,
        k: usize,
        model: Model,
        loss: Loss,
    ) {
        let b = self.pairs;
        Render {
            prims,
            count: k,
            pairs: &self.geometry,
            target: &self.rendered,
            model,
        }
        .record(gpu, encoder, 0, b, self.groups);

        let residual = gpu
            .residual
            .get_or_init(|| gpu.pipeline("residual", include_str!("residual.wgsl")));
        let (loss, background) = match loss {
            Loss::L2 => (0, 0.0),
            Loss::Poisson { background } => (1, background as f32),
        };
        let params = ResidualParams {
            bins: model.bins(),
            loss,
            loss_at: (16 * k) as u32,
            pad0: 0,
            background,
            pad: [0.0; 3],
        };
        let uniform = gpu.uniform("residual parameters", &params);
        gpu.dispatch(
            encoder,
            residual,
            &[
                &uniform,
                &self.rendered,
                &self.data,
                &self.weights,
                &self.dl,
                &self.result,
            ],
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
                encoder,
                backward,
                &[&uniform, prims, &self.geometry, &self.dl, &self.result],
                spread(k.div_ceil(BACKWARD_THREADS)),
            );
        }
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct UpdateParams {
    centre: [f32; 4],
    half: [f32; 4],
    lr: [f32; 4],
    decay: [f32; 4],
    beta1: f32,
    beta2: f32,
    bias1: f32,
    bias2: f32,
    eps: f32,
    mean_weight: f32,
    prims: u32,
    /// The step's pairs, whose losses scale the surface prior's gradient; 0: no prior.
    prior_pairs: u32,
    /// The centre's coordinate the prior pulls (its depth axis): 0, 1 or 2.
    prior_axis: u32,
    /// WGSL rounds the struct's size up to its 16-byte alignment.
    _pad: [u32; 3],
}

/// Steps a submission records: the fit checks `stop` and reads the losses back
/// between submissions.
const STEPS_PER_SUBMISSION: usize = 32;

/// Runs `count` optimiser steps of the fit on `gpu` with the parameters resident
/// there: each step's mini-batch forward render, residuals and backward pass (as
/// [`batch_gradient`]), then `update.wgsl`'s chain rule through the parameter maps,
/// AdamW update, rotation renormalisation and running mean, which also writes the
/// primitives the next step renders. `kernels` are the primitives of `state.raw`
/// (what the first step renders); `step(i)` gives step i's batch. Nothing comes back
/// between steps but each batch's loss, 32 steps to a submission; `state` is read
/// back at the end. When `stop()` turns true between submissions, the steps end
/// there: the losses say how many were taken, and `state` holds the parameters after
/// them. `prior`, the depth axis (0, 1, 2: x, y, z) and one `[z̄, c]` a primitive
/// ([`crate::gtr::SurfacePrior`]'s terms), adds the surface prior's gradient
/// c · L · (z − z̄) to each step's, z the centre's coordinate along that axis and L the
/// step's loss, as the CPU's steps do with the terms of their own step.
#[allow(clippy::too_many_arguments)]
pub fn fit_steps(
    gpu: &Gpu,
    kernels: &[Kernel],
    state: &mut Resident,
    optimiser: &Optimiser,
    count: usize,
    step: &mut dyn FnMut(usize) -> Step,
    axis: &TimeAxis,
    opt: &RenderOptions,
    prior: Option<(usize, &[[f64; 2]])>,
    stop: &dyn Fn() -> bool,
) -> Result<Steps, GpuError> {
    let (k, bins) = (kernels.len(), axis.bins);
    if let Some((a, prior)) = prior {
        assert!(a < 3, "the prior's axis is x, y or z");
        assert_eq!(prior.len(), k, "the prior's terms, one a primitive");
    }
    assert_eq!(state.raw.len(), RAW * k, "{RAW} raw parameters a primitive");
    assert_eq!(state.m1.len(), RAW * k, "a first moment a parameter");
    assert_eq!(state.m2.len(), RAW * k, "a second moment a parameter");
    if let Some(mean) = &state.mean {
        assert_eq!(mean.len(), RAW * k, "a mean a parameter");
    }
    gpu.scoped(WHAT, || {
        let prims: Vec<[[f32; 4]; 5]> = kernels.iter().map(prim).collect();
        let prims = gpu.upload("primitives", &prims);
        let raw = gpu.upload("raw parameters", &state.raw);
        let m1 = gpu.upload("first moments", &state.m1);
        let m2 = gpu.upload("second moments", &state.m2);
        let mean = gpu.upload("running mean", state.mean.as_deref().unwrap_or(&[]));
        let skipped = gpu.upload("skipped entries", &[0u32; 4]);
        let prior_terms: Vec<[f32; 2]> = match prior {
            Some((_, terms)) => terms.iter().map(|&[m, c]| [m as f32, c as f32]).collect(),
            None => vec![[0.0; 2]],
        };
        let prior_terms = gpu.upload("surface prior", &prior_terms);
        let update = gpu
            .update
            .get_or_init(|| gpu.pipeline("update", &source(include_str!("update.wgsl"))));
        let model = Model::new(axis, opt);
        let o = optimiser;
        let v4 = |v: glam::DVec3, w: f64| [v.x as f32, v.y as f32, v.z as f32, w as f32];
        let mut losses = Vec::with_capacity(count);
        while losses.len() < count && !stop() {
            let first = losses.len();
            let n = STEPS_PER_SUBMISSION.min(count - first);
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            let mut batches = Vec::with_capacity(n);
            for i in first..first + n {
                let s = step(i);
                let b = s.pairs.len();
                assert!(b > 0, "a step has pairs");
                assert_eq!(s.data.len(), b * bins, "one histogram a pair");
                assert_eq!(s.weights.len(), b, "one weight a pair");
                check_batch(gpu, b, bins)?;
                let batch = Batch::upload(gpu, &s.pairs, &s.data, &s.weights, k, bins);
                batch.record(gpu, &mut encoder, &prims, k, model, opt.loss);
                if k > 0 {
                    let t = s.t.min(i32::MAX as u64) as i32;
                    let params = UpdateParams {
                        centre: v4(o.centre, o.log_min),
                        half: v4(o.half, o.log_span),
                        lr: o.lr.map(|lr| (lr * s.factor) as f32),
                        decay: o.decay.map(|d| d as f32),
                        beta1: o.beta1 as f32,
                        beta2: o.beta2 as f32,
                        bias1: (1.0 - o.beta1.powi(t)) as f32,
                        bias2: (1.0 - o.beta2.powi(t)) as f32,
                        eps: o.eps as f32,
                        mean_weight: s.mean_of.map_or(0.0, |n| 1.0 / n.max(1) as f32),
                        prims: k as u32,
                        prior_pairs: if prior.is_some() { b as u32 } else { 0 },
                        prior_axis: prior.map_or(2, |(a, _)| a as u32),
                        _pad: [0; 3],
                    };
                    let uniform = gpu.uniform("update parameters", &params);
                    gpu.dispatch(
                        &mut encoder,
                        update,
                        &[
                            &uniform,
                            &batch.result,
                            &raw,
                            &m1,
                            &m2,
                            &mean,
                            &prims,
                            &skipped,
                            &prior_terms,
                        ],
                        spread(k.div_ceil(UPDATE_THREADS)),
                    );
                }
                batches.push(batch);
            }
            // Each step's losses, gathered for one readback.
            let total: usize = batches.iter().map(|b| b.pairs).sum();
            let gathered = gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("step losses"),
                size: (total.max(4) * 4) as u64,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::COPY_SRC
                    | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            let mut at = 0;
            for batch in &batches {
                let b = batch.pairs as u64;
                encoder.copy_buffer_to_buffer(&batch.result, (64 * k) as u64, &gathered, at, 4 * b);
                at += 4 * b;
            }
            let out = gpu.finish(WHAT, encoder, &gathered, total)?;
            let mut at = 0;
            for batch in &batches {
                let b = batch.pairs;
                losses.push(out[at..at + b].iter().map(|&l| f64::from(l)).sum());
                at += b;
            }
        }
        let read = |buffer: &wgpu::Buffer, len: usize| {
            gpu.finish(
                WHAT,
                gpu.device.create_command_encoder(&Default::default()),
                buffer,
                len,
            )
        };
        state.raw = read(&raw, RAW * k)?;
        state.m1 = read(&m1, RAW * k)?;
        state.m2 = read(&m2, RAW * k)?;
        if state.mean.is_some() {
            state.mean = Some(read(&mean, RAW * k)?);
        }
        let skipped = u64::from(read(&skipped, 1)?[0].to_bits());
        Ok(Steps { losses, skipped })
    })
}

/// Threads of an update workgroup (one primitive each).
const UPDATE_THREADS: usize = 64;

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

#[cfg(test)]
mod tests {
    use glam::{DQuat, DVec3};
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::gpu::testing;
    use crate::gtr::{
        AdamW, AdamWSettings, GaussianCloud, GroupSettings, Primitive, RawGrads, ScaleBounds, SurfacePrior,
        batch_loss_grad, render_set,
    };
    use crate::roi::RoiBox;
    use crate::transient::TransientSet;
    use crate::volume::DepthAxis;

    /// 200 primitives of every size and orientation, 12 non-confocal and confocal
    /// pairs, and "measurements" that are a distorted copy of their render (peak about
    /// 1), so every parameter has a gradient.
    fn scene() -> (GaussianCloud, TransientSet, RenderOptions) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let roi = RoiBox::from_bounds(DVec3::new(-0.4, -0.4, 0.3), DVec3::new(0.4, 0.4, 0.9)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 2e-3, max: 0.2 }).unwrap();
        for _ in 0..200 {
            let axis = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(0.1..1.0),
            )
            .normalize();
            cloud
                .push(Primitive {
                    centre: DVec3::new(
                        rng.random_range(-0.35..0.35),
                        rng.random_range(-0.35..0.35),
                        rng.random_range(0.35..0.85),
                    ),
                    scale: DVec3::new(
                        rng.random_range(0.004..0.06),
                        rng.random_range(0.004..0.06),
                        rng.random_range(0.004..0.06),
                    ),
                    rotation: DQuat::from_axis_angle(axis, rng.random_range(0.0..3.0)),
                    albedo: rng.random_range(0.2..2.0),
                })
                .unwrap();
        }
        let axis = TimeAxis {
            start: 0.4,
            width: 0.01,
            bins: 260,
        };
        let mut geometry = TransientSet::new(axis).unwrap();
        for i in 0..12 {
            let mut point = || DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
            let (xi, xd) = (point(), point());
            let pair = if i % 3 == 0 {
                Pair::confocal(xi, DVec3::Z)
            } else {
                Pair {
                    xi,
                    ni: DVec3::Z,
                    xd,
                    nd: DVec3::Z,
                }
            };
            geometry.push(pair, &vec![0.0; axis.bins]).unwrap();
        }
        let opt = RenderOptions {
            sigma_sys: 0.004,
            ..RenderOptions::default()
        };
        let rendered = render_set(&cloud.kernels(), &geometry, &opt);
        let gain = 1.0 / rendered.iter().fold(0.0f64, |m, &v| m.max(v));
        let mut set = TransientSet::new(axis).unwrap();
        for (i, pair) in geometry.pairs().iter().enumerate() {
            let hist: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
                .iter()
                .map(|&v| (gain * v * rng.random_range(0.3..1.5) + rng.random_range(0.0..0.05)) as f32)
                .collect();
            set.push(*pair, &hist).unwrap();
        }
        (cloud, set, RenderOptions { gain, ..opt })
    }

    /// Relative L2 distance of `got` from `want`.
    fn relative_l2(got: &[f64], want: &[f64]) -> f64 {
        let num: f64 = got.iter().zip(want).map(|(a, b)| (a - b) * (a - b)).sum();
        let den: f64 = want.iter().map(|b| b * b).sum();
        (num / den).sqrt()
    }

    /// Steps with the parameters resident on the GPU (`update.wgsl`: the maps' chain
    /// rule, AdamW with weight decay, the rotations' renormalisation, the running mean
    /// and the next step's primitives) take the CPU's steps (f64): from an optimiser
    /// state three CPU steps old, three more steps on each with the running mean kept,
    /// the losses within 1e-4 (the later steps render the primitives the GPU wrote), and
    /// each group's parameter change, both moments and the mean's change within 1e-3
    /// relative L2.
    #[test]
    fn steps_resident_on_the_gpu_are_the_cpus_steps() {
        let Some(gpu) = testing::gpu("steps_resident_on_the_gpu_are_the_cpus_steps") else {
            return;
        };
        resident_steps_against_the_cpus(&gpu, None);
    }

    /// The same with the surface prior, its terms those of the first step's
    /// primitives on both: 3 cm columns and a 5 mm spread, so the prior's share of the
    /// depths' gradient is large (leaving it out of `update.wgsl` fails this).
    #[test]
    fn steps_resident_on_the_gpu_take_the_surface_priors_gradient() {
        resident_steps_with_a_prior_along(
            "steps_resident_on_the_gpu_take_the_surface_priors_gradient",
            DepthAxis::Z,
        );
    }

    /// The same with the prior's columns along y, as for a relay facing −y (a
    /// Zaragoza wall): the shader pulls the coordinate the prior names, not z
    /// (`update.wgsl` pulling z whatever the axis fails this).
    #[test]
    fn steps_resident_on_the_gpu_take_the_surface_priors_gradient_along_y() {
        resident_steps_with_a_prior_along(
            "steps_resident_on_the_gpu_take_the_surface_priors_gradient_along_y",
            DepthAxis {
                axis: 1,
                positive: false,
            },
        );
    }

    /// [`resident_steps_against_the_cpus`] with a prior of 5 mm spread on 3 cm columns
    /// along `axis`, where a GPU opens for `test`.
    fn resident_steps_with_a_prior_along(test: &str, axis: DepthAxis) {
        let Some(gpu) = testing::gpu(test) else {
            return;
        };
        let prior = SurfacePrior {
            spread: 0.005,
            cell: 0.03,
            axis,
        };
        resident_steps_against_the_cpus(&gpu, Some(prior));
    }

    /// The surface prior's gradient at fixed `terms` ([`SurfacePrior::terms`]) on the
    /// CPU, in f64: what `SurfacePrior::add_gradient` adds with the terms of its own step.
    fn add_prior(cloud: &GaussianCloud, (a, terms): (usize, &[[f64; 2]]), loss: f64, grads: &mut RawGrads) {
        for (i, k) in cloud.kernels().iter().enumerate() {
            let [mean, c] = terms[i];
            grads.centres[3 * i + a] += c * loss * (k.x[a] - mean) * cloud.slopes(i).centre[a];
        }
    }

    /// Three steps from an optimiser state three CPU steps old on each side (with
    /// `prior`'s gradient, at the terms of the state they start from), compared as
    /// the test above says.
    fn resident_steps_against_the_cpus(gpu: &Gpu, prior: Option<SurfacePrior>) {
        let (cloud, set, opt) = scene();
        let settings = AdamWSettings {
            centres: GroupSettings {
                lr: 0.01,
                weight_decay: 0.05,
            },
            rotations: GroupSettings {
                lr: 0.02,
                weight_decay: 0.1,
            },
            ..AdamWSettings::default()
        };
        let batches: Vec<Vec<usize>> = vec![
            (0..6).collect(),
            (6..12).collect(),
            (0..12).rev().collect(),
            vec![1, 4, 7, 10],
            vec![0, 3, 6, 9],
            vec![2, 5, 8, 11],
        ];
        let factors = [0.25, 0.5, 1.0, 1.0, 0.5, 0.5];
        // The CPU's steps, the last three averaged.
        let cpu_step = |cloud: &mut GaussianCloud,
                        adam: &mut AdamW,
                        i: usize,
                        mean: Option<(&mut GaussianCloud, usize)>,
                        terms: Option<(usize, &[[f64; 2]])>| {
            let mut grads = RawGrads::default();
            let kernels = cloud.kernels();
            let loss = batch_loss_grad(cloud, &kernels, &set, &batches[i], &opt, &mut grads);
            if let Some(terms) = terms {
                add_prior(cloud, terms, loss, &mut grads);
            }
            assert_eq!(adam.step_averaged(cloud, &grads, factors[i], mean), 0);
            loss
        };
        let mut warm = cloud.clone();
        let mut adam = AdamW::new(settings);
        for i in 0..3 {
            cpu_step(&mut warm, &mut adam, i, None, None);
        }
        let (start, adam_start) = (warm.clone(), adam.clone());
        let terms = prior.map(|p| {
            let terms = p.terms(&start.kernels(), start.roi()).expect("the prior's terms");
            (p.axis.axis, terms)
        });
        let terms = terms.as_ref().map(|(a, t)| (*a, t.as_slice()));
        if let Some(terms) = terms {
            // The prior's gradient is a large share of the depths' on this scene.
            let mut data = RawGrads::default();
            let loss = batch_loss_grad(&start, &start.kernels(), &set, &batches[3], &opt, &mut data);
            let mut with = data.clone();
            add_prior(&start, terms, loss, &mut with);
            let z = |g: &RawGrads| {
                g.centres
                    .iter()
                    .skip(terms.0)
                    .step_by(3)
                    .copied()
                    .collect::<Vec<_>>()
            };
            let share = relative_l2(&z(&with), &z(&data));
            eprintln!("the prior changes the depths' gradient by {share:.2} relative L2");
            assert!(share > 0.3, "{share}");
        }
        let mut cpu_mean = warm.clone();
        let cpu_losses: Vec<f64> = (3..6)
            .map(|i| cpu_step(&mut warm, &mut adam, i, Some((&mut cpu_mean, i - 2)), terms))
            .collect();

        let mut state = Resident::of(&start, &adam_start, Some(&start));
        let optimiser = Optimiser::of(&start, &settings);
        let mut step = |i: usize| {
            let (pairs, data, weights) = crate::gtr::render::gpu_batch(&set, &batches[3 + i], None);
            Step {
                pairs,
                data,
                weights,
                factor: factors[3 + i],
                t: 4 + i as u64,
                mean_of: Some(i + 1),
            }
        };
        let done = fit_steps(
            gpu,
            &start.kernels(),
            &mut state,
            &optimiser,
            3,
            &mut step,
            set.axis(),
            &opt,
            terms,
            &|| false,
        )
        .unwrap();
        assert_eq!(done.skipped, 0);
        for (got, want) in done.losses.iter().zip(&cpu_losses) {
            eprintln!("loss {got} against {want}");
            assert!((got - want).abs() <= 1e-4 * want, "loss {got} against {want}");
        }
        assert_eq!(done.losses.len(), 3);
        let (mut gpu_cloud, mut gpu_adam, mut gpu_mean) = (start.clone(), adam_start.clone(), start.clone());
        state.write_back(&mut gpu_cloud, &mut gpu_adam, 3, Some(&mut gpu_mean));
        assert_eq!(gpu_adam.steps_taken(), adam.steps_taken());
        let change = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x - y).collect::<Vec<_>>();
        for (g, name) in ["centres", "scales", "rotations", "albedo"]
            .into_iter()
            .enumerate()
        {
            let pick = |c: &GaussianCloud| [&c.centres, &c.scales, &c.rotations, &c.albedo][g].clone();
            let width = [3, 3, 4, 1][g] * start.len();
            let moved = relative_l2(
                &change(&pick(&gpu_cloud), &pick(&start)),
                &change(&pick(&warm), &pick(&start)),
            );
            let mean = relative_l2(
                &change(&pick(&gpu_mean), &pick(&start)),
                &change(&pick(&cpu_mean), &pick(&start)),
            );
            let (m, v) = gpu_adam.moments(g, width);
            let (m_cpu, v_cpu) = adam.moments(g, width);
            let (m, v) = (relative_l2(m, m_cpu), relative_l2(v, v_cpu));
            eprintln!("{name}: change {moved:.2e}, mean {mean:.2e}, moments {m:.2e} and {v:.2e}");
            assert!(pick(&warm) != pick(&start), "{name} moved");
            for (what, e) in [
                ("change", moved),
                ("mean", mean),
                ("first moment", m),
                ("second moment", v),
            ] {
                assert!(e <= 1e-3, "{name}: {what} relative L2 {e:e}");
            }
        }
    }

    /// A stop between submissions ends the steps there: asked after the first
    /// submission, a run of 40 steps takes 32, and hands back the state after them,
    /// the state a run of exactly 32 steps gives.
    #[test]
    fn a_stop_ends_the_steps_between_submissions() {
        let Some(gpu) = testing::gpu("a_stop_ends_the_steps_between_submissions") else {
            return;
        };
        let (cloud, set, opt) = scene();
        let settings = AdamWSettings::default();
        let run = |count: usize, stop_after: usize| {
            let mut state = Resident::of(&cloud, &AdamW::new(settings), None);
            let asked = std::cell::Cell::new(0);
            let mut step = |i: usize| {
                let batch: Vec<usize> = (0..4).map(|j| (i + 3 * j) % set.len()).collect();
                let (pairs, data, weights) = crate::gtr::render::gpu_batch(&set, &batch, None);
                Step {
                    pairs,
                    data,
                    weights,
                    factor: 1.0,
                    t: i as u64 + 1,
                    mean_of: None,
                }
            };
            let done = fit_steps(
                &gpu,
                &cloud.kernels(),
                &mut state,
                &Optimiser::of(&cloud, &settings),
                count,
                &mut step,
                set.axis(),
                &opt,
                None,
                &|| {
                    asked.set(asked.get() + 1);
                    asked.get() > stop_after
                },
            )
            .unwrap();
            (done.losses.len(), state)
        };
        let (taken, stopped) = run(40, 1);
        assert_eq!(taken, STEPS_PER_SUBMISSION);
        let (whole, state) = run(STEPS_PER_SUBMISSION, usize::MAX);
        assert_eq!(whole, STEPS_PER_SUBMISSION);
        let start = Resident::of(&cloud, &AdamW::new(settings), None);
        assert!(stopped.raw != start.raw, "the steps taken moved the primitives");
        let worst = stopped
            .raw
            .iter()
            .zip(&state.raw)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 1e-6, "{worst}");
        let (none, untouched) = run(5, 0);
        assert_eq!((none, untouched), (0, start));
    }
}

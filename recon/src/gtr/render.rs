//! Batched rendering and the fused loss/gradient of a mini-batch.
//!
//! Full renders parallelise over pairs (each thread owns whole histograms). A training
//! step parallelises over fixed-size chunks of primitives instead: each chunk renders
//! the batch into its own small buffer, the buffers are summed in chunk order, and the
//! backward pass writes each primitive's gradient in place. Chunk boundaries do not
//! depend on the thread count, so results are bit-identical however many threads run.
use rayon::prelude::*;

use super::kernel::{Kernel, Loss, PhysicalGrad, RenderOptions};
use super::lanes::{LANES, PairGroup, Pulses, backward_group, backward_two, evaluate_chunk_into, groups};
use super::model::{GaussianCloud, MapSlopes, RawGrads};
use crate::transient::{Pair, TimeAxis, TransientSet};

/// Primitives per parallel work item in a training step. Small enough that two
/// threads share a step evenly (512 left K = 2,000 in four items, and a thread idle
/// for up to one of them: `periscope recon` fitted 7 % slower), large enough that
/// summing the items' batch buffers costs nothing measurable.
const CHUNK: usize = 128;

/// Renders every pair of `set` (its histograms are ignored) from `kernels`, each times
/// its known gain ([`TransientSet::gain`]); returns the histograms concatenated,
/// `set.axis().bins` per pair.
pub fn render_set(kernels: &[Kernel], set: &TransientSet, opt: &RenderOptions) -> Vec<f64> {
    let bins = set.axis().bins;
    let mut out = vec![0.0; bins * set.len()];
    out.par_chunks_mut(LANES * bins)
        .zip(set.pairs().par_chunks(LANES))
        .for_each(|(hists, pairs)| render_pairs(kernels, pairs, set.axis(), opt, hists));
    apply_known_gains(set, &mut out);
    out
}

/// Multiplies each transient of `rendered` ([`render_set`]'s layout, at gain 1) by its
/// known gain in `set` ([`TransientSet::gain`]).
pub(crate) fn apply_known_gains(set: &TransientSet, rendered: &mut [f64]) {
    if set.has_gains() {
        for (i, h) in rendered.chunks_mut(set.axis().bins).enumerate() {
            let g = f64::from(set.gain(i));
            h.iter_mut().for_each(|v| *v *= g);
        }
    }
}

/// Renders `pairs` from `kernels` into `out` (overwritten), `axis.bins` per pair: the
/// same bits as [`render_pair`](super::render_pair) on each, four pairs at a time in vector lanes.
pub fn render_pairs(
    kernels: &[Kernel],
    pairs: &[Pair],
    axis: &TimeAxis,
    opt: &RenderOptions,
    out: &mut [f64],
) {
    assert_eq!(
        out.len(),
        pairs.len() * axis.bins,
        "one histogram of axis.bins a pair"
    );
    for (pairs, out) in pairs.chunks(LANES).zip(out.chunks_mut(LANES * axis.bins)) {
        crate::simd::dispatch(RenderGroup {
            kernels,
            group: PairGroup::new(&pairs.iter().collect::<Vec<_>>()),
            axis,
            opt,
            out,
        });
    }
}

/// [`render_pairs`]'s loop for one group, compiled for the machine's SIMD level.
struct RenderGroup<'a> {
    kernels: &'a [Kernel],
    group: PairGroup,
    axis: &'a TimeAxis,
    opt: &'a RenderOptions,
    out: &'a mut [f64],
}

impl crate::simd::Work for RenderGroup<'_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, quad: Q) {
        let Self {
            kernels,
            group,
            axis,
            opt,
            out,
        } = self;
        out.fill(0.0);
        // Two primitives at a time in eight lanes; each one's pulses added in the
        // primitives' order, as one at a time.
        let mut slots = [None, None];
        for ks in kernels.chunks(2) {
            evaluate_chunk_into(quad, ks, &group, axis, opt, slots.each_mut());
            for pulses in slots.iter().flatten() {
                for (w, hist) in pulses.iter().zip(out.chunks_exact_mut(axis.bins)) {
                    if let Some(w) = w {
                        w.accumulate_with(quad, axis, hist);
                    }
                }
            }
        }
    }
}

/// Loss of a mini-batch: `(1/B) Σ_p w_p ‖τ̂_p − τ_p‖²` over the pairs `batch` of `set`.
/// Also returns the rendered histograms (B × bins).
pub fn batch_loss(
    kernels: &[Kernel],
    set: &TransientSet,
    batch: &[usize],
    opt: &RenderOptions,
) -> (f64, Vec<f64>) {
    let rendered = forward_batch(kernels, set, batch, opt);
    let (loss, _) = residuals(&rendered, set, batch, opt.loss, None);
    (loss, rendered)
}

fn forward_batch(kernels: &[Kernel], set: &TransientSet, batch: &[usize], opt: &RenderOptions) -> Vec<f64> {
    forward_chunks(kernels, set, &groups(set, batch), batch.len(), opt, false).0
}

/// What a chunk keeps of its forward pass: the evaluations of its primitives against
/// the batch's pair groups, primitive-major.
type Kept = Vec<Option<Pulses>>;

/// Renders the batch (`batch_len` pairs in `groups`) chunk by chunk (see the module
/// comment) and sums the chunks. With `keep`, also returns each chunk's evaluations,
/// one per group and primitive (primitive-major), for the backward pass to reuse
/// instead of recomputing them.
fn forward_chunks(
    kernels: &[Kernel],
    set: &TransientSet,
    groups: &[PairGroup],
    batch_len: usize,
    opt: &RenderOptions,
    keep: bool,
) -> (Vec<f64>, Vec<Kept>) {
    let bins = set.axis().bins;
    let partial: Vec<(Vec<f64>, Kept)> = kernels
        .par_chunks(CHUNK)
        .map(|chunk| {
            crate::simd::dispatch(ForwardChunk {
                chunk,
                set,
                groups,
                batch_len,
                opt,
                keep,
            })
        })
        .collect();
    let mut total = vec![0.0; bins * batch_len];
    let mut kept = Vec::with_capacity(partial.len());
    for (part, evals) in partial {
        total.iter_mut().zip(&part).for_each(|(t, p)| *t += p);
        kept.push(evals);
    }
    (total, kept)
}

/// One chunk of primitives rendered into a batch-sized buffer.
struct ForwardChunk<'a> {
    chunk: &'a [Kernel],
    set: &'a TransientSet,
    groups: &'a [PairGroup],
    batch_len: usize,
    opt: &'a RenderOptions,
    keep: bool,
}

impl crate::simd::Work for ForwardChunk<'_> {
    type Output = (Vec<f64>, Kept);

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, quad: Q) -> Self::Output {
        let Self {
            chunk,
            set,
            groups,
            batch_len,
            opt,
            keep,
        } = self;
        let axis = set.axis();
        let bins = axis.bins;
        let n = groups.len();
        let mut local = vec![0.0; bins * batch_len];
        let mut kept: Kept = if keep {
            vec![None; chunk.len() * n]
        } else {
            Vec::new()
        };
        // Primitive-major: the batch's histograms (a few KiB) stay in L1, and the
        // evaluations are kept in the order the backward pass reads them. Two
        // primitives at a time in eight lanes; each one's pulses are added in the
        // primitives' order, so every histogram gets the bits of one at a time.
        let mut fresh = [None, None];
        for (c, ks) in chunk.chunks(2).enumerate() {
            let i = 2 * c;
            for (g, (out, group)) in local.chunks_mut(LANES * bins).zip(groups).enumerate() {
                // The pulses are built in their slots (the kept ones, or two reused)
                // and read from there: built aside and moved, they were copied (3 % of
                // a fit).
                let [sa, sb] = match (keep, ks) {
                    (true, [_, _]) => kept
                        .get_disjoint_mut([i * n + g, (i + 1) * n + g])
                        .expect("two primitives' slots"),
                    (true, _) => [&mut kept[i * n + g], &mut fresh[1]],
                    (false, _) => fresh.each_mut(),
                };
                evaluate_chunk_into(quad, ks, group, axis, opt, [&mut *sa, &mut *sb]);
                for e in [&mut *sa, &mut *sb].into_iter().flatten() {
                    for (w, hist) in e.iter_mut().zip(out.chunks_exact_mut(bins)) {
                        match w {
                            Some(w) if keep => w.accumulate_keeping(quad, axis, hist),
                            Some(w) => w.accumulate_with(quad, axis, hist),
                            None => {}
                        }
                    }
                }
            }
        }
        (local, kept)
    }
}

/// The loss and ∂L/∂τ̂ for a rendered batch. The pairs' bins are computed in
/// parallel (the Poisson deviance's logarithms had been a serial stretch of every
/// step) and the loss is summed afterwards in the batch's order, bin by bin, so it
/// does not depend on the split.
///
/// Each pair's rendering is multiplied in the model by its known gain in `set`
/// ([`TransientSet::gain`]) and by `gains` (one per pair of `set`, or `None` for all 1:
/// the per-transient gains of the relay and the instrument that
/// [`crate::gtr::Trainer`] estimates), so ∂L/∂τ̂ is the gain times ∂L/∂model.
fn residuals(
    rendered: &[f64],
    set: &TransientSet,
    batch: &[usize],
    loss_kind: Loss,
    gains: Option<&[f64]>,
) -> (f64, Vec<f64>) {
    let bins = set.axis().bins;
    let scale = 1.0 / batch.len().max(1) as f64;
    let mut dl = vec![0.0; rendered.len()];
    let mut terms = vec![0.0; rendered.len()];
    dl.par_chunks_mut(bins)
        .zip(terms.par_chunks_mut(bins))
        .zip(rendered.par_chunks(bins))
        .zip(batch.par_iter())
        .for_each(|(((dl, terms), rendered), &p)| {
            let w = set.weight(p) as f64 * scale;
            let gain = f64::from(set.gain(p)) * gains.map_or(1.0, |g| g[p]);
            let measured = set.histogram(p);
            // Bins the recording did not cover hold zeros nobody measured: no term.
            for b in set.recorded(p) {
                let (model, data) = (gain * rendered[b], measured[b] as f64);
                let (l, d) = match loss_kind {
                    Loss::L2 => {
                        let r = model - data;
                        (r * r, 2.0 * r)
                    }
                    Loss::Poisson { background } => {
                        // The model is a sum of non-negative contributions; the floor
                        // only guards the logarithm against round-off below zero.
                        let rate = (model + background).max(f64::MIN_POSITIVE);
                        let log_term = if data > 0.0 {
                            data * (data / rate).ln()
                        } else {
                            0.0
                        };
                        (2.0 * (log_term - data + rate), 2.0 * (1.0 - data / rate))
                    }
                };
                terms[b] = w * l;
                dl[b] = w * d * gain;
            }
        });
    let loss = terms.iter().fold(0.0, |sum, &t| sum + t);
    (loss, dl)
}

/// Loss of a mini-batch and its gradient with respect to every raw parameter of
/// `cloud` (written into `grads`, which is resized). `kernels` must be
/// `cloud.kernels()`.
pub fn batch_loss_grad(
    cloud: &GaussianCloud,
    kernels: &[Kernel],
    set: &TransientSet,
    batch: &[usize],
    opt: &RenderOptions,
    grads: &mut RawGrads,
) -> f64 {
    batch_loss_grad_with(cloud, kernels, None, set, batch, opt, None, grads)
}

/// [`batch_loss_grad`], with the map slopes of every primitive already known
/// (`slopes[k]` from [`GaussianCloud::kernel_and_slopes`], as `kernels[k]`) or, with
/// `None`, computed here, and with per-pair gains in the model (`None`: all 1).
#[allow(clippy::too_many_arguments)]
pub(crate) fn batch_loss_grad_with(
    cloud: &GaussianCloud,
    kernels: &[Kernel],
    slopes: Option<&[MapSlopes]>,
    set: &TransientSet,
    batch: &[usize],
    opt: &RenderOptions,
    gains: Option<&[f64]>,
    grads: &mut RawGrads,
) -> f64 {
    let n = cloud.len();
    if grads.albedo.len() != n {
        *grads = RawGrads::zeros(n);
    }
    if batch.is_empty() {
        grads.centres.fill(0.0);
        grads.scales.fill(0.0);
        grads.rotations.fill(0.0);
        grads.albedo.fill(0.0);
        return 0.0;
    }
    let groups = groups(set, batch);
    let (rendered, evals) = forward_chunks(kernels, set, &groups, batch.len(), opt, true);
    let (loss, dl) = residuals(&rendered, set, batch, opt.loss, gains);
    grads
        .centres
        .par_chunks_mut(3 * CHUNK)
        .zip(grads.scales.par_chunks_mut(3 * CHUNK))
        .zip(grads.rotations.par_chunks_mut(4 * CHUNK))
        .zip(grads.albedo.par_chunks_mut(CHUNK))
        .zip(evals.par_iter())
        .enumerate()
        .for_each(|(c, ((((gc, gs), gr), ga), evals))| {
            crate::simd::dispatch(BackwardChunk {
                first: c * CHUNK,
                cloud,
                kernels,
                slopes,
                set,
                groups: &groups,
                opt,
                dl: &dl,
                evals,
                out: (gc, gs, gr, ga),
            });
        });
    loss
}

/// [`batch_loss_grad`] with the render, the residuals and the backward pass on `gpu`
/// ([`crate::gpu::batch_gradient`], in f32) and the parameter maps' chain rule here.
pub fn batch_loss_grad_gpu(
    gpu: &crate::gpu::Gpu,
    cloud: &GaussianCloud,
    kernels: &[Kernel],
    set: &TransientSet,
    batch: &[usize],
    opt: &RenderOptions,
    grads: &mut RawGrads,
) -> Result<f64, crate::gpu::GpuError> {
    let slopes: Vec<MapSlopes> = (0..cloud.len()).map(|k| cloud.slopes(k)).collect();
    batch_loss_grad_gpu_with(gpu, cloud, kernels, &slopes, set, batch, opt, None, grads)
}

/// [`batch_loss_grad_gpu`] with the map slopes of every primitive already known
/// (`slopes[k]` as `kernels[k]`) and per-pair gains in the model (`None`: all 1).
#[allow(clippy::too_many_arguments)]
pub(crate) fn batch_loss_grad_gpu_with(
    gpu: &crate::gpu::Gpu,
    cloud: &GaussianCloud,
    kernels: &[Kernel],
    slopes: &[MapSlopes],
    set: &TransientSet,
    batch: &[usize],
    opt: &RenderOptions,
    gains: Option<&[f64]>,
    grads: &mut RawGrads,
) -> Result<f64, crate::gpu::GpuError> {
    let n = cloud.len();
    if grads.albedo.len() != n {
        *grads = RawGrads::zeros(n);
    }
    let (pairs, data, weights) = gpu_batch(set, batch, gains);
    let out = crate::gpu::batch_gradient(gpu, kernels, &pairs, &data, &weights, set.axis(), opt)?;
    grads
        .centres
        .par_chunks_mut(3 * CHUNK)
        .zip(grads.scales.par_chunks_mut(3 * CHUNK))
        .zip(grads.rotations.par_chunks_mut(4 * CHUNK))
        .zip(grads.albedo.par_chunks_mut(CHUNK))
        .enumerate()
        .for_each(|(c, (((gc, gs), gr), ga))| {
            for (i, a) in ga.iter_mut().enumerate() {
                let k = c * CHUNK + i;
                *a = cloud.chain_with(
                    k,
                    &slopes[k],
                    &out.grads[k],
                    &mut gc[3 * i..3 * i + 3],
                    &mut gs[3 * i..3 * i + 3],
                    &mut gr[4 * i..4 * i + 4],
                );
            }
        });
    Ok(out.losses.iter().map(|&l| f64::from(l)).sum())
}

/// Mini-batch `batch` of `set` as the GPU takes one: its pairs, their histograms one
/// after the other, and each pair's weight over the batch size with its gain in the
/// model (the set's, times `gains[p]` where given) and its recorded bins (first, end;
/// exact in f32 to 2²⁴ bins).
#[allow(clippy::type_complexity)]
pub(crate) fn gpu_batch(
    set: &TransientSet,
    batch: &[usize],
    gains: Option<&[f64]>,
) -> (Vec<Pair>, Vec<f32>, Vec<[f32; 4]>) {
    let pairs: Vec<Pair> = batch.iter().map(|&p| set.pairs()[p]).collect();
    let data: Vec<f32> = batch
        .iter()
        .flat_map(|&p| set.histogram(p).iter().copied())
        .collect();
    let scale = 1.0 / batch.len().max(1) as f64;
    let weights: Vec<[f32; 4]> = batch
        .iter()
        .map(|&p| {
            let gain = f64::from(set.gain(p)) * gains.map_or(1.0, |g| g[p]);
            let recorded = set.recorded(p);
            [
                (set.weight(p) as f64 * scale) as f32,
                gain as f32,
                recorded.start as f32,
                recorded.end as f32,
            ]
        })
        .collect();
    (pairs, data, weights)
}

/// The backward pass of one chunk of primitives: each primitive's gradient over the
/// batch, chained to its raw parameters and written in place.
struct BackwardChunk<'a, 'g> {
    first: usize,
    cloud: &'a GaussianCloud,
    kernels: &'a [Kernel],
    slopes: Option<&'a [MapSlopes]>,
    set: &'a TransientSet,
    groups: &'a [PairGroup],
    opt: &'a RenderOptions,
    dl: &'a [f64],
    /// The chunk's evaluations from the forward pass, one per group and primitive.
    evals: &'a [Option<Pulses>],
    /// Raw gradients of the chunk: centres, scales, rotations, albedo.
    out: (&'g mut [f64], &'g mut [f64], &'g mut [f64], &'g mut [f64]),
}

impl crate::simd::Work for BackwardChunk<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, quad: Q) {
        let Self {
            first,
            cloud,
            kernels,
            slopes,
            set,
            groups,
            opt,
            dl,
            evals,
            out: (gc, gs, gr, ga),
        } = self;
        let axis = set.axis();
        let bins = axis.bins;
        let (n, len) = (groups.len(), ga.len());
        let mut chain = |i: usize, g: &PhysicalGrad| {
            let k = first + i;
            let slope = match slopes {
                Some(all) => all[k],
                None => cloud.slopes(k),
            };
            ga[i] = cloud.chain_with(
                k,
                &slope,
                g,
                &mut gc[3 * i..3 * i + 3],
                &mut gs[3 * i..3 * i + 3],
                &mut gr[4 * i..4 * i + 4],
            );
        };
        // Two primitives at a time in eight lanes where both reach a group's pairs,
        // one alone where only one does; each one's gradient gets its lanes in the
        // batch's order, the bits of one primitive at a time.
        let mut i = 0;
        while i < len {
            let (a, b) = (
                &kernels[first + i],
                kernels.get(first + i + 1).filter(|_| i + 1 < len),
            );
            let (mut g_a, mut g_b) = (PhysicalGrad::default(), PhysicalGrad::default());
            for (g, (group, dl)) in groups.iter().zip(dl.chunks(LANES * bins)).enumerate() {
                let e_a = &evals[i * n + g];
                let e_b = b.and(evals.get((i + 1) * n + g)).and_then(Option::as_ref);
                match (e_a, b.zip(e_b)) {
                    (Some(p_a), Some((b, p_b))) => backward_two(
                        quad,
                        [a, b],
                        group,
                        [p_a, p_b],
                        axis,
                        opt,
                        dl,
                        [&mut g_a, &mut g_b],
                    ),
                    (Some(p_a), None) => backward_group(quad, a, group, p_a, axis, opt, dl, &mut g_a),
                    (None, Some((b, p_b))) => backward_group(quad, b, group, p_b, axis, opt, dl, &mut g_b),
                    (None, None) => {}
                }
            }
            chain(i, &g_a);
            if b.is_some() {
                chain(i + 1, &g_b);
            }
            i += if b.is_some() { 2 } else { 1 };
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::{DQuat, DVec3};

    use super::*;
    use crate::gtr::{Primitive, ScaleBounds};
    use crate::roi::RoiBox;
    use crate::transient::{Pair, TimeAxis};

    /// Per-pair gains in the model: a batch's loss and gradient with gains g_p are the
    /// mean of each pair's own, rendered at the gain times g_p (Poisson deviance, the
    /// default data term).
    #[test]
    fn pair_gains_scale_each_pairs_model_and_gradient() {
        let roi = RoiBox::from_bounds(DVec3::new(-0.3, -0.3, 0.3), DVec3::new(0.3, 0.3, 0.9)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
        for (k, c) in [DVec3::new(0.05, -0.04, 0.55), DVec3::new(-0.1, 0.08, 0.7)]
            .into_iter()
            .enumerate()
        {
            cloud
                .push(Primitive {
                    centre: c,
                    scale: DVec3::new(0.02, 0.03, 0.015),
                    rotation: DQuat::from_rotation_z(0.3 * k as f64),
                    albedo: 0.5 + k as f64,
                })
                .unwrap();
        }
        let axis = TimeAxis::from_seconds(0.6, 32e-12, 160);
        let mut set = TransientSet::new(axis).unwrap();
        for i in 0..6 {
            let x = DVec3::new(-0.3 + 0.12 * i as f64, 0.05 * i as f64 - 0.1, 0.0);
            let h: Vec<f32> = (0..axis.bins).map(|b| ((b * 7 + i * 3) % 5) as f32).collect();
            set.push(Pair::confocal(x, DVec3::Z), &h).unwrap();
        }
        let gains = [0.5, 1.0, 1.7, 0.8, 2.5, 1.2];
        let opt = RenderOptions {
            gain: 3e3,
            loss: Loss::Poisson { background: 0.01 },
            ..RenderOptions::default()
        };
        let kernels = cloud.kernels();
        let batch: Vec<usize> = (0..set.len()).collect();
        let mut with = RawGrads::default();
        let loss = batch_loss_grad_with(
            &cloud,
            &kernels,
            None,
            &set,
            &batch,
            &opt,
            Some(&gains),
            &mut with,
        );
        let (mut sum, mut grads) = (0.0, RawGrads::zeros(cloud.len()));
        for p in 0..set.len() {
            let own = RenderOptions {
                gain: opt.gain * gains[p],
                ..opt
            };
            let mut g = RawGrads::default();
            sum += batch_loss_grad_with(&cloud, &kernels, None, &set, &[p], &own, None, &mut g) / 6.0;
            for (a, b) in [
                (&mut grads.centres, &g.centres),
                (&mut grads.scales, &g.scales),
                (&mut grads.rotations, &g.rotations),
                (&mut grads.albedo, &g.albedo),
            ] {
                a.iter_mut().zip(b).for_each(|(a, b)| *a += b / 6.0);
            }
        }
        assert!(
            loss > 0.0 && (loss - sum).abs() <= 1e-9 * sum,
            "{loss} against {sum}"
        );
        for (name, a, b) in [
            ("centres", &with.centres, &grads.centres),
            ("scales", &with.scales, &grads.scales),
            ("rotations", &with.rotations, &grads.rotations),
            ("albedo", &with.albedo, &grads.albedo),
        ] {
            let top = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(top > 0.0, "{name}");
            for (x, y) in a.iter().zip(b) {
                assert!((x - y).abs() <= 1e-9 * top, "{name}: {x} against {y}");
            }
        }
        // A point-source laser's falloff held as the set's own gains (the counts as
        // counted) is the same model: the same loss, gradient and rendering as those
        // gains given explicitly.
        let mut lit = set.clone();
        lit.compensate_laser_falloff(DVec3::new(0.0, -2.0, 1.2)).unwrap();
        assert!(lit.has_gains());
        let known: Vec<f64> = (0..lit.len()).map(|i| f64::from(lit.gain(i))).collect();
        let (mut a, mut b) = (RawGrads::default(), RawGrads::default());
        let la = batch_loss_grad_with(&cloud, &kernels, None, &lit, &batch, &opt, None, &mut a);
        let lb = batch_loss_grad_with(&cloud, &kernels, None, &set, &batch, &opt, Some(&known), &mut b);
        assert!((la - lb).abs() <= 1e-12 * lb, "{la} against {lb}");
        assert_eq!(a.centres, b.centres);
        assert_eq!(a.albedo, b.albedo);
        let (ra, rb) = (render_set(&kernels, &lit, &opt), render_set(&kernels, &set, &opt));
        for (p, (x, y)) in ra.chunks(axis.bins).zip(rb.chunks(axis.bins)).enumerate() {
            for (x, y) in x.iter().zip(y) {
                assert!(
                    (x - known[p] * y).abs() <= 1e-12 * y.abs().max(1e-300),
                    "pair {p}: {x} against {y}"
                );
            }
        }
    }
}

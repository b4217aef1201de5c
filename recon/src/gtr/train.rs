//! Fitting primitives to transients: gain matching, shuffled mini-batches, AdamW, a
//! cancel token, typed progress events, streaming input and pruning.
//!
//! Streaming: [`Trainer::run`] takes an optional channel of new transients. While the
//! channel is open (the capture is still running) the fit runs [`LIVE_EPOCHS_PER_BATCH`]
//! "live" epochs on the data so far, then waits for the next batch; live epochs do not
//! count towards `epochs`. Once the sender hangs up, the counted epochs
//! ([`TrainConfig::counted_epochs`]) run on the complete data. The schedule follows the
//! data received, never the clock: the same batches in the same order give the same fit
//! bit for bit, however fast they came (a fit that falls behind the capture works
//! through its backlog after it).
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender};

use glam::{DMat3, DVec3};

use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::init::{Init, initial_cloud};
use super::kernel::{Kernel, Loss, RenderOptions};
use super::model::{GaussianCloud, MapSlopes, ModelError, Primitive, RawGrads, ScaleBounds};
use super::optim::{AdamW, AdamWSettings, Schedule};
use super::render::{batch_loss_grad_with, render_set};
use crate::gpu::{Gpu, GpuError};
use crate::roi::RoiBox;
use crate::transient::{TransientError, TransientSet};
use crate::volume::DepthAxis;

/// Primitives a parallel work item of the kernels' refresh maps (four at a time).
const REFRESH_CHUNK: usize = 256;

/// Live epochs run on the data so far after each batch streamed in (and on the data
/// the fit starts with) while the capture goes on.
pub const LIVE_EPOCHS_PER_BATCH: usize = 1;

/// Which primitives pruning removes.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PruneSettings {
    /// Remove primitives whose centre lies within this fraction of the ROI half extent
    /// of a face (the tanh map pins escaping primitives there).
    pub boundary_margin: f64,
    /// Remove primitives whose weight ([`Primitive::weight`]: what they add to a
    /// transient) is below this fraction of the mean weight.
    pub min_weight_fraction: f64,
    /// Remove primitives whose centre moved less than this (metres) from where it
    /// started: the data never touched them.
    pub min_motion: f64,
}

impl Default for PruneSettings {
    fn default() -> Self {
        Self {
            boundary_margin: 0.02,
            min_weight_fraction: 0.02,
            min_motion: 1e-5,
        }
    }
}

/// Rounds of densification in a fit by default ([`DensifySettings::rounds`]). On an
/// independent render of 2 cm bars 2 cm apart seen from a 4 cm relay pitch, 8 rounds
/// left the bars one blob however many steps followed them, and 16 through the first
/// half of an 8,192-step fit resolved them; the validation captures and the two-torso
/// renders held or gained (docs/recon.md, "More steps and more rounds of
/// densification").
pub const DENSIFY_ROUNDS: usize = 16;

/// Adaptive density control: large primitives that carry signal are split in two,
/// and the second half takes the place of a primitive that carries none (3DGS's split
/// with relocation, as in 3DGS-MCMC). A fit may also start with fewer primitives than
/// K and grow towards K in its rounds (`grow_from`), where the splits outnumber the
/// primitives that carry nothing: a scene that needs fewer than K never gets them,
/// and every step costs less until it does.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DensifySettings {
    /// Densify within the first `until` fraction of the counted epochs (0: never).
    pub until: f64,
    /// Rounds in that span, evenly spread over its epochs and at most one an epoch: a
    /// small capture (many short epochs) is split a few times with many steps between,
    /// never after every few dozen steps (3DGS densifies every 100 iterations for the
    /// same reason: a split needs steps to settle before the next is judged).
    pub rounds: usize,
    /// A primitive is dead when its weight ([`Primitive::weight`]) is below this fraction of the mean weight.
    pub dead_fraction: f64,
    /// Primitives whose largest scale exceeds this (metres) are split; `None`:
    /// [`default_target_scale`].
    pub target_scale: Option<f64>,
    /// The fraction of [`TrainConfig::primitives`] placed at initialisation (0 < f ≤ 1).
    /// Below 1 each round may add primitives ([`densify`]'s `grow`) up to K: the
    /// heavy ones left over once every dead slot has taken a split. While some carry
    /// nothing, the cloud does not grow, so a simple scene keeps fewer than K. 1: all
    /// K from the start, the relocation alone. A coarse capture starts with
    /// [`CoarseFit::grow_from`].
    #[serde(default = "full_start")]
    pub grow_from: f64,
}

fn full_start() -> f64 {
    1.0
}

/// What the daemon's fits start with ([`DensifySettings::grow_from`]) where the plan
/// leaves `epochs` to the step floor: half of K. On the validation captures it took
/// a fifth to two fifths off the run with the scores held, and the simulator's two
/// torsos (which grow to K) held theirs; starting with a quarter cost them 0.06 IoU
/// (docs/recon.md, "Growing to K").
pub const GROW_FROM: f64 = 0.5;

impl Default for DensifySettings {
    fn default() -> Self {
        Self {
            until: 0.5,
            rounds: DENSIFY_ROUNDS,
            dead_fraction: 0.05,
            target_scale: None,
            grow_from: full_start(),
        }
    }
}

/// One round of adaptive density control on `cloud`: the heaviest primitives (by
/// [`Primitive::weight`], at least the mean) wider than `target_scale` are split along
/// their widest axis into two children, one in the parent's slot and one in the slot
/// of the lightest dead primitive (weight below `dead_fraction` × the mean). Each child
/// has half the parent's scale along that axis and sits √3/2 of it from the parent's
/// centre, so the pair keeps the parent's mean and spread (variance) along the axis;
/// with twice the parent's albedo it keeps the parent's weight, each child's
/// projected area being half the parent's. (Children at 1/√2 of the scale, a
/// single-peaked pair, shrink the cloud more slowly and scored 0.03–0.10 lower on
/// every validation capture: docs/recon.md.) As many splits as there are
/// dead slots; deterministic, ties broken by index. Returns the (parent, slot) pairs.
///
/// With `grow` > 0 the cloud may also grow by up to `grow` primitives: the parents left
/// over when the dead slots run out get new slots at the end, and when the splittable
/// parents run out, the other heavy ones (at or under `target_scale`) are cloned: two
/// children of the parent's scale, half its albedo each, half its scale either side
/// of its centre along its widest axis, so no child is finer than the split floor
/// allows. A slot index of `cloud.len()` or more in the result is a new primitive.
pub fn densify(
    cloud: &mut GaussianCloud,
    dead_fraction: f64,
    target_scale: f64,
    grow: usize,
) -> Vec<(usize, usize)> {
    let n = cloud.len();
    let prims: Vec<Primitive> = (0..n).map(|k| cloud.primitive(k)).collect();
    let w: Vec<f64> = prims.iter().map(Primitive::weight).collect();
    let mean = w.iter().sum::<f64>() / n.max(1) as f64;
    if !(mean.is_finite() && mean > 0.0) {
        return Vec::new();
    }
    let mut dead: Vec<usize> = (0..n).filter(|&k| w[k] < dead_fraction * mean).collect();
    dead.sort_by(|&a, &b| w[a].total_cmp(&w[b]).then(a.cmp(&b)));
    let by_weight = |mut ks: Vec<usize>| {
        ks.sort_by(|&a, &b| w[b].total_cmp(&w[a]).then(a.cmp(&b)));
        ks
    };
    let splittable = |k: usize| prims[k].scale.max_element() > target_scale;
    let mut parents = by_weight((0..n).filter(|&k| w[k] >= mean && splittable(k)).collect());
    let split = parents.len();
    if grow > 0 {
        parents.extend(by_weight(
            (0..n).filter(|&k| w[k] >= mean && !splittable(k)).collect(),
        ));
        let added = parents.len().saturating_sub(dead.len()).min(grow);
        dead.extend(n..n + added);
    }
    let min_scale = cloud.scale_bounds().min * 1.01;
    let roi = *cloud.roi();
    let inside = |c: DVec3| {
        let rel = ((c - roi.centre) / roi.half).clamp(DVec3::splat(-0.999), DVec3::splat(0.999));
        roi.centre + rel * roi.half
    };
    let mut moved = Vec::new();
    for (j, (&parent, &slot)) in parents.iter().zip(&dead).enumerate() {
        let p = prims[parent];
        let widest = p.scale.max_position();
        let axis = DMat3::from_quat(p.rotation).col(widest);
        let mut scale = p.scale;
        let (offset, albedo) = if j < split {
            scale[widest] = (0.5 * scale[widest]).max(min_scale);
            (0.75f64.sqrt() * p.scale[widest], 2.0 * p.albedo)
        } else {
            (0.5 * p.scale[widest], 0.5 * p.albedo)
        };
        let offset = axis * offset;
        let child = |c| Primitive {
            centre: inside(c),
            scale,
            rotation: p.rotation,
            albedo,
        };
        if slot > cloud.len() {
            // An earlier new slot was not filled: the rest cannot be appended in order.
            break;
        }
        if cloud.set(parent, child(p.centre + offset)).is_err() {
            continue;
        }
        let placed = if slot == cloud.len() {
            cloud.push(child(p.centre - offset))
        } else {
            cloud.set(slot, child(p.centre - offset))
        };
        if placed.is_err() {
            // Put the parent back: it was valid a moment ago.
            cloud.set(parent, p).expect("the parent as it was");
            continue;
        }
        moved.push((parent, slot));
    }
    moved
}

/// Everything that controls a fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Number of primitives K at initialisation.
    pub primitives: usize,
    /// Placement of the initial primitives.
    pub init: Init,
    /// Shared initial isotropic scale, metres; `None`: [`default_initial_scale`].
    pub initial_scale: Option<f64>,
    /// Shared initial albedo (the gain absorbs the absolute scale).
    pub initial_albedo: f64,
    /// Scale bounds; `None`: 0.5 mm to half the smallest ROI half extent.
    pub scale_bounds: Option<ScaleBounds>,
    /// Counted epochs (after the input is complete), at least.
    pub epochs: usize,
    /// Optimiser steps the counted epochs take, at least: a capture with few pairs gets
    /// more epochs, so that every fit takes about the same number of steps
    /// ([`TrainConfig::counted_epochs`]). 0: exactly `epochs`.
    pub min_steps: usize,
    /// Pairs per mini-batch.
    pub batch_size: usize,
    /// Pairs an epoch trains on, at most (0: all of them). A capture with more takes
    /// each epoch's pairs from a shuffled pass over it, so the steps a fit takes stop
    /// growing with the capture ([`TrainConfig::pairs_per_epoch`]).
    #[serde(default)]
    pub epoch_pairs: usize,
    /// Optimiser settings per group.
    pub adam: AdamWSettings,
    /// Learning-rate schedule (milestones at fractions of the counted epochs).
    pub schedule: Schedule,
    /// Forward-model switches; its `gain` is replaced by the matched gain and its
    /// `loss` by the one `loss` chooses.
    pub render: RenderOptions,
    /// The data term: L2, Poisson, or chosen from the data ([`LossChoice`]).
    pub loss: LossChoice,
    /// Pruning after the last epoch.
    pub prune: PruneSettings,
    /// Splitting and relocation during the first counted epochs.
    pub densify: DensifySettings,
    /// The fit's result is the mean of its iterates over the counted epochs after this
    /// fraction of them (and after the last densification), instead of the last
    /// iterate: mini-batches of a few transients leave the last iterate jittering
    /// about the optimum by more than a pixel. 1 (or more): the last iterate, as
    /// the paper.
    #[serde(default = "default_average_from")]
    pub average_from: f64,
    /// Pairs a step takes in the averaged epochs ([`AverageBatch`]): each of those
    /// epochs takes as many steps as the others, so with fewer pairs a step it trains on
    /// fewer pairs, in turn from a shuffled pass over the capture.
    #[serde(default)]
    pub average_batch: AverageBatch,
    /// Pairs used to match the gain at initialisation, at most.
    pub gain_pairs: usize,
    /// Whether each transient's own gain is estimated from the data during the fit
    /// ([`PairGains`]).
    #[serde(default)]
    pub pair_gains: PairGains,
    /// Seed of initialisation and shuffling.
    pub seed: u64,
    /// When the last stage (the averaged epochs) ends before the counted epochs are
    /// spent: once its loss has stopped falling ([`Convergence`]). `None`: every
    /// counted epoch runs.
    #[serde(default)]
    pub converge: Option<Convergence>,
    /// The surface prior: each column of the scene, seen along the ROI's depth axis,
    /// held to one surface ([`SurfacePrior`]). `None`: off, the paper's fit.
    #[serde(default)]
    pub surface: Option<SurfacePrior>,
    /// What the fit takes instead of `batch_size` and `surface` where its capture
    /// places points coarsely ([`CoarseFit`]). `None`: the same fit on every capture.
    #[serde(default)]
    pub coarse: Option<CoarseFit>,
}

/// A fit's settings for a capture that places points coarsely: where the separation
/// it resolves at the ROI's centre ([`resolvable_separation`]) raises the split floor
/// to [`CoarseFit::FROM_RATIO`] times the ROI's capacity ([`default_target_scale`]) or
/// more, as one laser spot on one back and a few hundred detection points on another
/// do (3.0–3.4 times on independent renders) and no validation capture does
/// (0.41–0.83; 2 cm bars scanned confocally at a 4 cm pitch, 1.18). There the pairs
/// place light across their mean path gradient so loosely that an unconstrained fit
/// strings a surface's light along its columns in depth; twice the pairs a step and
/// the surface prior hold it to the surface (docs/recon.md, "A fit for coarse
/// captures").
///
/// The choice is made once, when the fit first has data (a streamed fit: its first
/// batch), and logged.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseFit {
    /// Pairs per mini-batch there.
    pub batch_size: usize,
    /// The surface prior there (`None`: off).
    pub surface: Option<SurfacePrior>,
    /// [`DensifySettings::grow_from`] there. Started with half its primitives, the
    /// coarse fit lost 0.07 IoU on the mean of the mannequin fixture's seeds and was no
    /// faster, its cloud filling at once (docs/recon.md, "Growing to K"), so the
    /// daemon starts it with all of them.
    #[serde(default = "full_start")]
    pub grow_from: f64,
    /// [`TrainConfig::average_batch`] there. Half the batch in the averaged epochs cost
    /// the noisy near mannequin fixture 0.011 IoU on the mean of three seeds (0.526
    /// against 0.537) and the other 0.003, where twice the pairs a step is what lifted
    /// these captures (docs/recon.md, "Fewer pairs a step where the iterates are
    /// averaged"), so the daemon keeps the whole batch there.
    #[serde(default)]
    pub average_batch: AverageBatch,
}

impl CoarseFit {
    /// The split floor over the ROI's capacity from which a capture counts as coarse.
    pub const FROM_RATIO: f64 = 2.0;

    /// The batch size a coarse capture takes when the plan sets none.
    pub const DEFAULT_BATCH: usize = 8;
}

/// A prior that holds each column of the scene to one surface.
///
/// Light the pairs cannot place laterally (one laser spot and a small patch of
/// detection points resolve little across their mean path gradient) can be explained
/// as well by primitives spread in depth along a column as by primitives spread
/// across the surface at one depth: the former is what an unconstrained fit finds on
/// a mannequin beside two backs, its torso's light in a column of lumps at the
/// centre. The prior pulls each primitive's depth (its coordinate along `axis`, z for a
/// relay facing +z) towards the weight-weighted mean depth of its column (cells of
/// `cell` metres across the two other axes),
/// as the gradient of
///
/// P = L̄ / spread² · Σ_cells Σ_{i ∈ cell} w_i (z_i − z̄_cell)² / Σ_i w_i,
///
/// with the primitives' weights w ([`Primitive::weight`](super::model::Primitive::weight))
/// held fixed and L̄ the mini-batch's loss, so the prior is the data term's size when a
/// column's light spreads `spread` metres in depth. A scene seen from the relay as one
/// surface per column (a wall, a letter, a person) loses nothing by it. On the GPU,
/// whose steps run resident, the same gradient is taken with the column means and
/// weights of the epoch's start instead of each step's.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SurfacePrior {
    /// The depth spread within a column that the prior weighs as much as the data,
    /// metres; smaller pulls harder.
    pub spread: f64,
    /// The columns' width across the two other axes, metres (the daemon takes the
    /// volume's lateral voxel pitch: one surface per pixel of its image).
    pub cell: f64,
    /// The depth axis the columns run along: the volume's axis nearest the relay's
    /// normal (the daemon sets it from the relay; z when left out).
    #[serde(default)]
    pub axis: DepthAxis,
}

impl SurfacePrior {
    /// The daemon's default spread, metres: chosen on the mannequin fixtures
    /// (docs/recon.md, "A surface prior").
    pub const DEFAULT_SPREAD: f64 = 0.018;

    /// Each primitive's column mean depth (by weight), or `None` where the prior's
    /// sizes are not usable; primitives of weight zero sit in their column but pull
    /// nothing.
    fn column_means(&self, kernels: &[Kernel], roi: &RoiBox) -> Option<(Vec<f64>, Vec<f64>, f64)> {
        if !(self.cell.is_finite() && self.cell > 0.0 && self.spread.is_finite() && self.spread > 0.0) {
            return None;
        }
        let lo = roi.centre - roi.half;
        let (d, [ca, ra]) = (self.depth_index(), self.axis.lateral());
        // Columns numbered row by row; sorted by column (and index within one), so a
        // column's sums add its primitives in their order, whatever the grid's size:
        // no array of columns, which a fine wide volume would make large.
        let cols =
            |a: usize| ((2.0 * roi.half[a] / self.cell).ceil()).clamp(1.0, f64::from(1u32 << 30)) as u64;
        let nx = cols(ca);
        let column = |k: &Kernel| {
            let at = |a: usize, n: u64| (((k.x[a] - lo[a]) / self.cell).floor().max(0.0) as u64).min(n - 1);
            at(ra, cols(ra)) * nx + at(ca, nx)
        };
        let weights: Vec<f64> = kernels.iter().map(Kernel::weight).collect();
        let total: f64 = weights.iter().sum();
        if !(total.is_finite() && total > 0.0) {
            return None;
        }
        let mut order: Vec<(u64, u32)> = kernels
            .iter()
            .enumerate()
            .map(|(i, k)| (column(k), i as u32))
            .collect();
        order.sort_unstable();
        let mut means = vec![0.0; kernels.len()];
        for members in order.chunk_by(|a, b| a.0 == b.0) {
            let (mut w, mut wz) = (0.0, 0.0);
            for &(_, i) in members {
                w += weights[i as usize];
                wz += weights[i as usize] * kernels[i as usize].x[d];
            }
            for &(_, i) in members {
                let z = kernels[i as usize].x[d];
                means[i as usize] = if w > 0.0 { wz / w } else { z };
            }
        }
        Some((means, weights, total))
    }

    /// The index of the depth axis among a centre's coordinates: 0, 1 or 2.
    pub(crate) fn depth_index(&self) -> usize {
        self.axis.axis.min(2)
    }

    /// Each primitive's term of the prior's gradient, `[z̄, c]`: its column's mean
    /// depth z̄ and c = 2 w / (spread² Σ w), so that a mini-batch of loss L adds
    /// c · L · (z − z̄) to ∂/∂z of its centre (z its coordinate along the depth axis) (what [`SurfacePrior::add_gradient`] adds
    /// with each step's terms); `None` where the prior's sizes are not usable. What the
    /// GPU's steps take, once an epoch ([`crate::gpu::fit_steps`]).
    pub(crate) fn terms(&self, kernels: &[Kernel], roi: &RoiBox) -> Option<Vec<[f64; 2]>> {
        let (means, weights, total) = self.column_means(kernels, roi)?;
        let scale = 2.0 / (self.spread * self.spread * total);
        Some(
            means
                .into_iter()
                .zip(weights)
                .map(|(m, w)| [m, scale * w])
                .collect(),
        )
    }

    /// Adds the prior's gradient for a mini-batch of loss `loss` to `grads` (the
    /// centres' entries along the depth axis, through the maps' slopes); returns P.
    pub(crate) fn add_gradient(
        &self,
        kernels: &[Kernel],
        slopes: &[MapSlopes],
        roi: &RoiBox,
        loss: f64,
        grads: &mut RawGrads,
    ) -> f64 {
        let Some((means, weights, total)) = self.column_means(kernels, roi) else {
            return 0.0;
        };
        if !(loss.is_finite() && loss > 0.0) {
            return 0.0;
        }
        let lambda = loss / (self.spread * self.spread * total);
        let a = self.depth_index();
        let mut p = 0.0;
        for (i, k) in kernels.iter().enumerate() {
            let d = k.x[a] - means[i];
            p += lambda * weights[i] * d * d;
            grads.centres[3 * i + a] += 2.0 * lambda * weights[i] * d * slopes[i].centre[a];
        }
        p
    }
}

/// The test that ends a fit's last stage early: after at least `min_steps` averaged
/// steps, the mean mini-batch loss over the latest `window` steps (whole epochs, at
/// least that many) has fallen by less than `tolerance` (a fraction) from the mean
/// over the `window` steps before them. Opt-in: on the validation captures the loss
/// levels off a fifth to a third of the way into the averaged epochs, but the mean of
/// the iterates still sharpens after that (stopping there cost up to 0.024 IoU;
/// docs/recon.md, "Stopping when the loss levels off").
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Convergence {
    /// Averaged steps before the first test, at least.
    pub min_steps: usize,
    /// Steps in each of the two windows compared, at least.
    pub window: usize,
    /// The relative fall below which the fit has converged.
    pub tolerance: f64,
}

/// The pairs a step takes in a fit's averaged epochs ([`TrainConfig::average_from`]),
/// against the batch in force before them ([`TrainConfig::batch_size`], or
/// [`TrainConfig::coarse`]'s).
///
/// The fit's result is the mean of those epochs' iterates, which averages the
/// gradients' noise over a thousand steps and more, so they need fewer pairs a step
/// than the steps before them, where each step's direction decides where the
/// primitives go. Half the pairs there, at the same steps, takes a sixth off the fit's
/// work with the validation captures' means over six seeds within 0.006 IoU; half in
/// the epochs from the middle on, or a quarter in the averaged ones, lost 0.02–0.03 on
/// the non-confocal captures (docs/recon.md, "Fewer pairs a step where the iterates
/// are averaged").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AverageBatch {
    /// The batch in force: the fit before 2026-12-05, bit for bit.
    #[default]
    Same,
    /// Half the batch in force, rounded up.
    Half,
    /// This many pairs, at most the batch in force (and at least one).
    Pairs(usize),
}

impl AverageBatch {
    /// The pairs a step takes in the averaged epochs where `batch` is in force.
    pub fn of(self, batch: usize) -> usize {
        let batch = batch.max(1);
        match self {
            Self::Same => batch,
            Self::Half => batch.div_ceil(2),
            Self::Pairs(n) => n.clamp(1, batch),
        }
    }
}

/// [`TrainConfig::average_from`]'s default: the last third, the epochs after the
/// learning rate's last decay.
fn default_average_from() -> f64 {
    2.0 / 3.0
}

impl TrainConfig {
    /// The counted epoch from which iterates are averaged, of `epochs`; `None`: never.
    pub fn average_start(&self, epochs: usize) -> Option<usize> {
        let from = self.average_from.max(self.densify.until);
        if !(from < 1.0) {
            return None;
        }
        Some(((from * epochs as f64 - 1e-9).ceil() as usize).min(epochs.saturating_sub(1)))
    }

    /// The pairs an epoch of a fit on `pairs` transients trains on: all of them, or
    /// [`TrainConfig::epoch_pairs`] where that is fewer.
    pub fn pairs_per_epoch(&self, pairs: usize) -> usize {
        match self.epoch_pairs {
            0 => pairs,
            cap => pairs.min(cap),
        }
    }

    /// The pairs an epoch of a fit on `pairs` transients trains on and the pairs each of
    /// its steps takes: [`TrainConfig::pairs_per_epoch`] in batches of `batch_size`, or
    /// in an averaged epoch (`averaged`) [`TrainConfig::average_batch`]'s pairs a step
    /// and as many steps as the other epochs take, so fewer pairs.
    pub fn epoch_plan(&self, pairs: usize, averaged: bool) -> (usize, usize) {
        let take = self.pairs_per_epoch(pairs);
        let batch = self.batch_size.max(1);
        let per_step = if averaged {
            self.average_batch.of(batch)
        } else {
            batch
        };
        if per_step >= batch {
            return (take, batch);
        }
        ((take.div_ceil(batch) * per_step).min(take), per_step)
    }

    /// The pair visits of the counted epochs of a fit on `pairs` transients (each
    /// renders every primitive once, forward and backward): what its time goes with.
    pub fn counted_pair_visits(&self, pairs: usize) -> usize {
        let epochs = self.counted_epochs(pairs);
        let averaged = self.average_start(epochs).map_or(0, |start| epochs - start);
        (epochs - averaged) * self.epoch_plan(pairs, false).0 + averaged * self.epoch_plan(pairs, true).0
    }

    /// The counted epochs of a fit on `pairs` transients: `epochs`, or more where that
    /// many would take fewer than `min_steps` optimiser steps (⌈pairs an epoch / batch⌉
    /// an epoch).
    pub fn counted_epochs(&self, pairs: usize) -> usize {
        let per_epoch = self
            .pairs_per_epoch(pairs)
            .div_ceil(self.batch_size.max(1))
            .max(1);
        self.epochs.max(self.min_steps.div_ceil(per_epoch))
    }
}

/// Whether a round of densification follows counted epoch `done` of `epochs`: of the
/// first ⌊`until` · `epochs`⌋ epochs, every one if they are no more than `rounds`, else
/// `rounds` of them evenly spread, the last at the end of the span. A fit whose
/// epochs are set gets a round after each epoch of its first half, as long as that
/// half holds no more epochs than `rounds`; a small capture, which the step floor
/// ([`TrainConfig::counted_epochs`]) gives many epochs, gets `rounds` rounds spread
/// over them.
pub fn densify_after(done: usize, epochs: usize, d: &DensifySettings) -> bool {
    let span = (d.until * epochs as f64 + 1e-9).floor() as usize;
    if done == 0 || done >= epochs || done > span || d.rounds == 0 {
        return false;
    }
    done * d.rounds / span > (done - 1) * d.rounds / span
}

/// Per-transient gains: what a real relay's albedo from spot to spot, a laser's
/// drifting power and a detector's efficiency with angle multiply each transient by,
/// and no capture file states. Estimated jointly with the fit when asked for, on a
/// slower time scale than the scene: after every counted epoch from [`GAIN_START`] of
/// them to the end, the gains are estimated afresh from the data and the fit's
/// rendering ([`estimate_pair_gains`]) and the log-gains move [`GAIN_STEP`] of the way
/// to the estimate; the gains multiply each group's transients in the model. A laser
/// falloff divided out from a file's metadata is the starting value.
///
/// Rounds that go on to the end let the gains give back what an early fit's own
/// errors put into them once the scene has improved (three rounds before averaging,
/// which the fit then kept, cost the confocal wall with its falloff known 0.984 →
/// 0.954 IoU; rounds to the end keep 0.984, and score 0.969, 0.984 and 0.974 without
/// the falloff, with a 3× smooth gain and with ±30 % random gains, where gains 1 score
/// 0.925, 0.882 and 0.916; means of three seeds).
///
/// Where the data already carry their gains it is not worth its cost (docs/recon.md,
/// "Gains from the data"): on the noisy sparse capture, whose falloff the file names,
/// it costs 0.010 IoU (0.957 → 0.947, three seeds) and a fifth more time, and with a
/// fixed laser, per detection point, 0.02–0.07. So [`PairGains::Auto`], what plans
/// and `periscope recon` take by default, estimates them only where nothing else
/// gives them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PairGains {
    /// Every transient's gain is 1 (the paper's model).
    #[default]
    None,
    /// [`PairGains::Illumination`] where the capture's gains are unknown: the laser
    /// visits more than one point and no transient carries a known gain
    /// ([`TransientSet::has_gains`]: neither a file's named laser falloff nor the
    /// relay's albedo from its scan); [`PairGains::None`] otherwise
    /// ([`PairGains::resolve`]).
    Auto,
    /// One gain per illumination point, where the laser visits more than one
    /// (confocal and scanned-laser captures); none with a fixed laser.
    Illumination,
    /// One gain per detection point with a fixed laser (per illumination point
    /// otherwise).
    Detection,
}

impl PairGains {
    /// The kind of estimate `self` asks for on `data`: [`PairGains::Auto`] becomes
    /// [`PairGains::Illumination`] where no transient of `data` has a known gain and
    /// the laser visits more than one point, else [`PairGains::None`]; the others are
    /// themselves.
    pub fn resolve(self, data: &TransientSet) -> PairGains {
        match self {
            PairGains::Auto if data.has_gains() => PairGains::None,
            PairGains::Auto if gain_groups(data.pairs(), PairGains::Illumination).is_some() => {
                PairGains::Illumination
            }
            PairGains::Auto => PairGains::None,
            kind => kind,
        }
    }
}

/// [`PairGains::Illumination`] and [`PairGains::Detection`] re-estimate the gains after
/// every counted epoch from this fraction of them on: late enough that the fit has
/// found the scene's rough shape, early enough that it has not bent the scene to
/// explain the gains (starting at 10 % or 40 % scored no better; docs/recon.md).
pub const GAIN_START: f64 = 0.25;

/// The counted epoch after which the first round of gain estimation comes, of
/// `epochs`: [`GAIN_START`] of them, at least the first; a round follows every epoch
/// from there to the last but one, `epochs − gain_start_epoch(epochs)` rounds.
pub fn gain_start_epoch(epochs: usize) -> usize {
    ((GAIN_START * epochs as f64).round() as usize).max(1)
}

/// Each round moves the log-gains this fraction of the way to the new estimate.
pub const GAIN_STEP: f64 = 0.5;

/// A gain estimate is shrunk towards the others by `s / (s + s0)` in the logarithm, `s`
/// the signal the rendering gives its point: `s0` is this many photons for photon
/// counts (a gain known to about 1/√30, 18 %, counts half) ...
const GAIN_PRIOR_COUNTS: f64 = 30.0;

/// ... and, for anything (and at least, for counts), this fraction of the median
/// point's signal: a point the scene barely reaches tells its gain poorly.
const GAIN_PRIOR_FRACTION: f64 = 0.05;

/// Gains are kept within this factor of their (signal-weighted geometric) mean.
const MAX_GAIN_SPREAD: f64 = 10.0;

/// The gain group of each pair and each group's relay point for `kind`: by
/// illumination point where the laser visits more than one, else by detection point
/// for [`PairGains::Detection`]; `None` where there is nothing to estimate (one group).
/// [`PairGains::Auto`] groups as [`PairGains::Illumination`] (whether it estimates at
/// all is [`PairGains::resolve`]'s).
pub fn gain_groups(pairs: &[crate::transient::Pair], kind: PairGains) -> Option<(Vec<usize>, Vec<DVec3>)> {
    let by = |key: &dyn Fn(&crate::transient::Pair) -> DVec3| {
        let mut ids = std::collections::HashMap::new();
        let mut points = Vec::new();
        let groups: Vec<usize> = pairs
            .iter()
            .map(|p| {
                let x = key(p);
                *ids.entry(x.to_array().map(f64::to_bits)).or_insert_with(|| {
                    points.push(x);
                    points.len() - 1
                })
            })
            .collect();
        (groups, points)
    };
    let lit = by(&|p| p.xi);
    let chosen = match kind {
        PairGains::None => return None,
        PairGains::Illumination | PairGains::Auto => lit,
        PairGains::Detection if lit.1.len() > 1 => lit,
        PairGains::Detection => by(&|p| p.xd),
    };
    (chosen.1.len() > 1).then_some(chosen)
}

/// Each pair's gain in the model, estimated from the data `data` and the fit's
/// rendering of it at unit gain (`rendered`, [`render_set`]'s layout) under `loss`, per
/// the groups `kind` asks for ([`gain_groups`]): each group's scale of the rendering
/// that explains its data (for photon counts under the Poisson deviance the
/// maximum-likelihood scale with the background, by Newton's method; otherwise the
/// counts above the background over the rendering's, or the least-squares scale for
/// L2); a quadratic over the relay through all groups' (in the logarithm, weighted by
/// the signal they get, each shrunk by `s / (s + s0)` towards the others, `s0`
/// `GAIN_PRIOR_FRACTION` of the median signal, and at least `GAIN_PRIOR_COUNTS` for
/// photon counts) is the smooth part, and each group keeps its own departure from it
/// by `s / (s + median)`, and for photon counts further by `τ² / (τ² + v)`: `v` its
/// estimate's counting noise (the inverse Fisher information, in the logarithm), `τ²`
/// the departures' spread less that noise, so that departures the counts cannot tell
/// from noise are not taken for albedo. Normalised to a signal-weighted
/// geometric mean of 1, within `MAX_GAIN_SPREAD` of it. `None` where there is one
/// group or no signal.
pub fn estimate_pair_gains(
    data: &TransientSet,
    rendered: &[f64],
    loss: Loss,
    kind: PairGains,
) -> Option<Vec<f64>> {
    let bins = data.axis().bins;
    let (groups, points) = gain_groups(data.pairs(), kind)?;
    let n = points.len();
    let background = match loss {
        Loss::Poisson { background } => Some(background),
        Loss::L2 => None,
    };
    let (mut num, mut den, mut signal) = (vec![0.0f64; n], vec![0.0f64; n], vec![0.0f64; n]);
    // Each pair's recorded bins only: past its window the data holds zeros nobody
    // measured.
    let recorded = |c: usize| {
        let kept = data.recorded(c);
        (
            &data.histogram(c)[kept.clone()],
            &rendered[c * bins..(c + 1) * bins][kept],
        )
    };
    for (c, &g) in groups.iter().enumerate() {
        let (h, r) = recorded(c);
        let rs: f64 = r.iter().sum();
        signal[g] += rs;
        match background {
            // Poisson: the rate's scale that matches the counts above the
            // background (the maximum-likelihood scale without one).
            Some(b) => {
                num[g] += h.iter().map(|&v| f64::from(v) - b).sum::<f64>();
                den[g] += rs;
            }
            // L2: the least-squares scale.
            None => {
                num[g] += h.iter().zip(r).map(|(&v, &m)| f64::from(v) * m).sum::<f64>();
                den[g] += r.iter().map(|m| m * m).sum::<f64>();
            }
        }
    }
    // Poisson: each group's maximum-likelihood scale, by Newton's method from the
    // ratio above (which it equals without a background): the bins the rendering
    // reaches weigh by r/(g r + b), so the background's bins add no noise, and the
    // Fisher information gives each estimate's noise, 1/(g² I) in the logarithm.
    let mut noise = vec![0.0f64; n];
    if let (Some(b), true) = (background, data.is_photon_counts()) {
        let mut by_group: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (c, &g) in groups.iter().enumerate() {
            by_group[g].push(c);
        }
        for (g, members) in by_group.iter().enumerate() {
            let mut scale = (num[g] / den[g]).clamp(1e-3, 1e3);
            if !scale.is_finite() || den[g] <= 0.0 {
                continue;
            }
            let sums = |scale: f64| {
                let (mut f, mut df, mut info) = (-den[g], 0.0, 0.0);
                for &c in members {
                    let (h, r) = recorded(c);
                    for (&v, &m) in h.iter().zip(r) {
                        if m <= 0.0 {
                            continue;
                        }
                        let rate = scale * m + b;
                        let v = f64::from(v);
                        f += m * v / rate;
                        df -= m * m * v / (rate * rate);
                        info += m * m / rate;
                    }
                }
                (f, df, info)
            };
            for _ in 0..12 {
                let (f, df, _) = sums(scale);
                if df >= 0.0 || !f.is_finite() {
                    break;
                }
                let next = scale - f / df;
                let next = if next > 0.0 { next } else { 0.5 * scale };
                let done = (next - scale).abs() <= 1e-6 * scale;
                scale = next;
                if done {
                    break;
                }
            }
            let (_, _, info) = sums(scale);
            num[g] = scale * den[g];
            noise[g] = if info > 0.0 {
                1.0 / (scale * scale * info)
            } else {
                f64::INFINITY
            };
        }
    }
    let mut sorted: Vec<f64> = signal.iter().copied().filter(|s| *s > 0.0).collect();
    sorted.sort_by(f64::total_cmp);
    let &median = sorted.get(sorted.len() / 2)?;
    let mut s0 = GAIN_PRIOR_FRACTION * median;
    if data.is_photon_counts() {
        s0 = s0.max(GAIN_PRIOR_COUNTS);
    }
    let limit = MAX_GAIN_SPREAD.ln();
    // Each point's own estimate, and how far to trust it.
    let raw: Vec<Option<f64>> = (0..n)
        .map(|g| {
            let r = num[g] / den[g];
            (r.is_finite() && r > 0.0 && signal[g] > 0.0).then(|| r.ln().clamp(-limit, limit))
        })
        .collect();
    let trust: Vec<f64> = (0..n)
        .map(|g| {
            if raw[g].is_some() {
                signal[g] / (signal[g] + s0)
            } else {
                0.0
            }
        })
        .collect();
    let raw_log: Vec<f64> = raw.iter().map(|r| r.unwrap_or(0.0)).collect();
    let weights: Vec<f64> = (0..n).map(|g| trust[g] * signal[g]).collect();
    // The smooth part (a laser's falloff, a detector's angular response), fitted
    // over all points; each point's own departure from it (its albedo) kept as far
    // as its signal tells it, half at the median point's.
    let smooth = smooth_log_gains(&points, &raw_log, &weights);
    let keep = departure_shrinkage(&noise, &raw, &raw_log, &smooth, &weights);
    let mut log_gain: Vec<f64> = (0..n)
        .map(|g| {
            let own = if raw[g].is_some() {
                keep[g] * signal[g] / (signal[g] + median) * (raw_log[g] - smooth[g])
            } else {
                0.0
            };
            (smooth[g] + own).clamp(-limit, limit)
        })
        .collect();
    // The fit's own scale (the albedo and the matched gain) carries the mean.
    let total: f64 = signal.iter().sum();
    if total > 0.0 {
        let mean = log_gain.iter().zip(&signal).map(|(l, s)| l * s).sum::<f64>() / total;
        log_gain
            .iter_mut()
            .for_each(|l| *l = (*l - mean).clamp(-limit, limit));
    }
    Some(groups.iter().map(|&g| log_gain[g].exp()).collect())
}

/// How much of each group's departure from the smooth part of the gains its photon
/// counts can tell (empirical Bayes): the departures' spread `τ²` is their weighted
/// variance less the counting noise's, each group's own noise `v` (`noise`: the
/// inverse Fisher information of its scale, in the logarithm), and a group keeps
/// `τ² / (τ² + v)` of its departure. All 1 where no group has counting noise
/// (intensities, the L2 loss).
fn departure_shrinkage(
    noise: &[f64],
    raw: &[Option<f64>],
    raw_log: &[f64],
    smooth: &[f64],
    weights: &[f64],
) -> Vec<f64> {
    let n = raw.len();
    if noise.iter().all(|v| *v == 0.0) {
        return vec![1.0; n];
    }
    let (mut total, mut spread, mut counting) = (0.0, 0.0, 0.0);
    for g in (0..n).filter(|&g| raw[g].is_some() && noise[g].is_finite()) {
        let d = raw_log[g] - smooth[g];
        total += weights[g];
        spread += weights[g] * d * d;
        counting += weights[g] * noise[g];
    }
    if total <= 0.0 {
        return vec![0.0; n];
    }
    let tau2 = ((spread - counting) / total).max(0.0);
    tracing::debug!(
        tau = tau2.sqrt(),
        noise = (counting / total).sqrt(),
        "gain departures"
    );
    noise.iter().map(|v| tau2 / (tau2 + v)).collect()
}

/// The smooth part of log-gains `log_gain` at `points` (weights `w`): a quadratic in
/// the two in-plane coordinates of the points' fitted plane, by weighted least
/// squares; the mean where fewer than six points or no plane fit.
pub(crate) fn smooth_log_gains(points: &[DVec3], log_gain: &[f64], w: &[f64]) -> Vec<f64> {
    let total: f64 = w.iter().sum();
    let mean = if total > 0.0 {
        log_gain.iter().zip(w).map(|(l, w)| l * w).sum::<f64>() / total
    } else {
        0.0
    };
    let flat = vec![mean; points.len()];
    let Some(plane) = (points.len() >= 6)
        .then(|| crate::linalg::fit_plane(points))
        .flatten()
    else {
        return flat;
    };
    // Coordinates scaled to about ±1, so the normal equations are well conditioned.
    let coords: Vec<[f64; 2]> = points
        .iter()
        .map(|p| [(*p - plane.centre).dot(plane.u), (*p - plane.centre).dot(plane.v)])
        .collect();
    let reach = coords
        .iter()
        .fold(0.0f64, |m, c| m.max(c[0].abs()).max(c[1].abs()))
        .max(f64::MIN_POSITIVE);
    let basis = |c: [f64; 2]| {
        let (u, v) = (c[0] / reach, c[1] / reach);
        [1.0, u, v, u * u, u * v, v * v]
    };
    let mut a = [[0.0f64; 6]; 6];
    let mut b = [0.0f64; 6];
    for ((c, &l), &w) in coords.iter().zip(log_gain).zip(w) {
        let f = basis(*c);
        for i in 0..6 {
            b[i] += w * f[i] * l;
            for j in 0..6 {
                a[i][j] += w * f[i] * f[j];
            }
        }
    }
    match crate::linalg::solve(a, b, 1e-10) {
        Some(k) => coords
            .iter()
            .map(|c| basis(*c).iter().zip(&k).map(|(f, k)| f * k).sum())
            .collect(),
        None => flat,
    }
}

/// Which data term a fit uses, resolved once the fit has data ([`Trainer::render_options`]
/// shows the outcome).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LossChoice {
    /// [`Loss::Poisson`], with the background [`estimate_background`] finds, when no
    /// bin is negative: photon counts, and rendered or rebinned intensities, whose
    /// noise (shot noise, Monte Carlo noise) also grows with the signal; [`Loss::L2`]
    /// for data with negative bins (background-subtracted or filtered), which no rate
    /// can explain.
    #[default]
    Auto,
    /// [`Loss::L2`], the paper's.
    L2,
    /// [`Loss::Poisson`]; the data must be non-negative.
    Poisson,
}

/// The first pair of `set` with a negative bin, if any: such data cannot be a rate's
/// counts ([`Loss::Poisson`]).
pub fn first_negative(set: &TransientSet) -> Option<usize> {
    (0..set.len()).find(|&i| set.histogram(i).iter().any(|&c| c < 0.0))
}

/// Bins of margin, each side, that [`estimate_background`] leaves between the path
/// lengths light from the ROI can take and the bins it reads as background only (the
/// pulse's width and a rebinned histogram's spread).
pub const BACKGROUND_MARGIN_BINS: f64 = 5.0;

/// The fewest background-only bins, over all transients, that [`estimate_background`]
/// takes the mean of; with fewer it falls back to the percentile.
pub const MIN_BACKGROUND_BINS: usize = 2048;

/// The background counts per bin and pair of `set`, for [`Loss::Poisson`]: at least
/// 1e-3 of the peak of the histograms' mean, so the rate stays positive on data
/// without any background; 0 for an empty set.
///
/// Where the set recorded at least [`MIN_BACKGROUND_BINS`] bins outside every path
/// through the volume before it was cut to it ([`TransientSet::ambient`]: a capture
/// file's window usually reaches well past the scene), their mean count. Else, with
/// `roi`, the mean count of every bin no light from inside it can reach: a bin
/// wholly shorter than the shortest path through the box (each leg at least its
/// point's distance to the box) or longer than the longest (each leg at most the
/// distance to its farthest corner), [`BACKGROUND_MARGIN_BINS`] to spare. That mean is
/// the ambient and dark level without bias, where the capture's window reaches past
/// the scene (at least [`MIN_BACKGROUND_BINS`] such bins). Otherwise, and without
/// `roi`, the 10th percentile over bins of the histograms' mean (most bins of a
/// capture see no hidden surface), which reads the level about 1.3 of its noise's
/// deviations low: 3 % at ten times a validation scene's light in ambient, 33 % at its
/// 0.05 counts a bin. Every figure reads only the bins each pair recorded
/// ([`TransientSet::recorded`]): past a pair's window its zeros are no background.
pub fn estimate_background(set: &TransientSet, roi: Option<&RoiBox>) -> f64 {
    let axis = *set.axis();
    let bins = axis.bins;
    if set.is_empty() || bins == 0 {
        return 0.0;
    }
    // Each bin's counts over the pairs that recorded it, and how many did.
    let mut total = vec![0.0f64; bins];
    let mut recorded = vec![0usize; bins];
    for i in 0..set.len() {
        let h = set.histogram(i);
        for b in set.recorded(i) {
            total[b] += f64::from(h[b]).max(0.0);
            recorded[b] += 1;
        }
    }
    let mut mean: Vec<f64> = total
        .iter()
        .zip(&recorded)
        .filter(|&(_, &n)| n > 0)
        .map(|(&t, &n)| t / n as f64)
        .collect();
    if mean.is_empty() {
        return 0.0;
    }
    let peak = mean.iter().fold(0.0f64, |m, &t| m.max(t));
    let floor = 1e-3 * peak;
    if let Some((mean, n)) = set.ambient()
        && n >= MIN_BACKGROUND_BINS
    {
        return mean.max(floor);
    }
    if let Some(roi) = roi {
        let (lo_corner, hi_corner) = (roi.min(), roi.max());
        let near = |p: DVec3| p.distance(p.clamp(lo_corner, hi_corner));
        let far = |p: DVec3| {
            let d = (p - roi.centre).abs() + roi.half;
            d.length()
        };
        let margin = BACKGROUND_MARGIN_BINS * axis.width;
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (i, pair) in set.pairs().iter().enumerate() {
            let shortest = near(pair.xi) + near(pair.xd) - margin;
            let longest = far(pair.xi) + far(pair.xd) + margin;
            let h = set.histogram(i);
            for b in set.recorded(i) {
                if axis.edge(b as isize + 1) < shortest || axis.edge(b as isize) > longest {
                    sum += f64::from(h[b]).max(0.0);
                    n += 1;
                }
            }
        }
        if n >= MIN_BACKGROUND_BINS {
            return (sum / n as f64).max(floor);
        }
    }
    mean.sort_by(f64::total_cmp);
    mean[(mean.len() - 1) / 10].max(floor)
}

/// The shared initial scale when none is set: half the mean spacing of K primitives
/// filling the ROI's volume, `(volume / K)^(1/3) / 2` (the paper's default).
pub fn default_initial_scale(roi: &RoiBox, primitives: usize) -> f64 {
    0.5 * (roi.volume() / primitives.max(1) as f64).cbrt()
}

/// The scale adaptive density control splits down to when none is set: half the
/// spacing of K primitives tiling a surface as large as the ROI's largest face,
/// `(area / K)^(1/2) / 2`. Third-bounce light comes from surfaces, not volumes, so
/// that is the detail K primitives can hold; the volume's spacing, where fits start,
/// is several times coarser (37 mm against 11 mm for 2,000 primitives in a 1 m box,
/// wider than a letter's stroke).
pub fn default_target_scale(roi: &RoiBox, primitives: usize) -> f64 {
    let e = 2.0 * roi.half;
    let largest_face = (e.x * e.y).max(e.y * e.z).max(e.x * e.z);
    0.5 * (largest_face / primitives.max(1) as f64).sqrt()
}

/// At most this many of a capture's pairs (evenly spaced) judge its
/// [`resolvable_separation`].
const SEPARATION_PAIRS: usize = 4096;

/// Bins of path-length error that [`resolvable_separation`] allows a fit: chosen on
/// independent renders of the two-torso kind (docs/recon.md, "The mannequin").
pub const SEPARATION_BINS: f64 = 4.0;

/// How finely the capture's pairs place a point laterally at `at`, in metres.
///
/// A point's path length for a pair is its distance to the pair's two points, whose
/// gradient is `g = ui + ud`. Moving the point by `δ` along a direction `e` across the
/// pairs' mean gradient changes its path length by `δ·(g·e)`. Only the differences of
/// that change from pair to pair place it across (a change shared by every pair is a
/// change of depth). So an error of `w` in path length, from the bins, the model or
/// the noise, misplaces a fitted primitive by about `w / s` across, where
/// `s = max(g·e) − min(g·e)` over the pairs that see `at`, on the narrowest direction.
/// This returns [`SEPARATION_BINS`] such errors: `4w / s`, with `w` the bin, or the
/// timing jitter's full width at half maximum where that is wider.
///
/// Splits finer than that leave the children free to drift into lumps, and an image
/// resolved finer shows the lumps instead of the surface. Examples on 5 mm bins:
/// - a planar relay a metre wide, half a metre from the scene: 8 mm confocal, 15 mm
///   with a fixed laser;
/// - the central 0.3 m of it, confocal: 22 mm;
/// - one laser spot on one back and a 0.3 × 0.6 m patch of detection points on the
///   other (two torsos as the relay): about 64 mm.
///
/// `None` without pairs that see `at`.
pub fn resolvable_separation(set: &TransientSet, at: DVec3, jitter: f64) -> Option<f64> {
    let pairs = set.pairs();
    let stride = pairs.len().div_ceil(SEPARATION_PAIRS).max(1);
    let gradients: Vec<DVec3> = pairs
        .iter()
        .step_by(stride)
        .filter_map(|p| {
            let (ui, ud) = ((at - p.xi).normalize_or_zero(), (at - p.xd).normalize_or_zero());
            let seen = p.ni.dot(ui) > 0.0 && p.nd.dot(ud) > 0.0;
            seen.then_some(ui + ud)
        })
        .collect();
    let mean = gradients.iter().sum::<DVec3>().normalize_or_zero();
    if mean == DVec3::ZERO {
        return None;
    }
    // The gradients across the mean, and their width on the narrowest direction:
    // the same whichever way the relay is turned.
    let (a, b) = mean.any_orthonormal_pair();
    let across: Vec<[f64; 2]> = gradients.iter().map(|g| [g.dot(a), g.dot(b)]).collect();
    let narrowest = minimum_width(&across);
    let w = set.axis().width.max(2.0 * (2.0 * 2f64.ln()).sqrt() * jitter);
    Some(if narrowest > 0.0 {
        SEPARATION_BINS * w / narrowest
    } else {
        f64::INFINITY
    })
}

/// The width of a set of points in the plane on its narrowest direction (0 for fewer
/// than three points or points on a line): the least, over the edges of their convex
/// hull, of the farthest hull point's distance from the edge's line, which is where
/// the narrowest direction lies (a set's width is least across one of its hull's
/// edges).
fn minimum_width(points: &[[f64; 2]]) -> f64 {
    let mut p: Vec<[f64; 2]> = points.to_vec();
    p.sort_by(|u, v| u[0].total_cmp(&v[0]).then(u[1].total_cmp(&v[1])));
    p.dedup();
    if p.len() < 3 {
        return 0.0;
    }
    let cross =
        |o: [f64; 2], u: [f64; 2], v: [f64; 2]| (u[0] - o[0]) * (v[1] - o[1]) - (u[1] - o[1]) * (v[0] - o[0]);
    // Andrew's monotone chain: the lower hull, then the upper, each without its last
    // point (the other's first).
    let chain = |points: &mut dyn Iterator<Item = [f64; 2]>| {
        let mut chain: Vec<[f64; 2]> = Vec::new();
        for q in points {
            while chain.len() >= 2 && cross(chain[chain.len() - 2], chain[chain.len() - 1], q) <= 0.0 {
                chain.pop();
            }
            chain.push(q);
        }
        chain.pop();
        chain
    };
    let mut hull = chain(&mut p.iter().copied());
    hull.extend(chain(&mut p.iter().rev().copied()));
    if hull.len() < 3 {
        return 0.0;
    }
    let width = (0..hull.len())
        .map(|i| {
            let (u, v) = (hull[i], hull[(i + 1) % hull.len()]);
            let length = (v[0] - u[0]).hypot(v[1] - u[1]);
            hull.iter().map(|&q| cross(u, v, q).abs()).fold(0.0f64, f64::max) / length
        })
        .fold(f64::INFINITY, f64::min);
    // Points on a line not along an axis keep a width of their rounding.
    let extent = hull
        .iter()
        .map(|q| (q[0] - hull[0][0]).hypot(q[1] - hull[0][1]))
        .fold(0.0f64, f64::max);
    if width <= 1e-9 * extent { 0.0 } else { width }
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            primitives: 2000,
            init: Init::Uniform,
            initial_scale: None,
            initial_albedo: 1.0,
            scale_bounds: None,
            epochs: 12,
            min_steps: 0,
            batch_size: 4,
            epoch_pairs: 0,
            adam: AdamWSettings::default(),
            // Constant-rate Adam on batches of 4 noisy transients does not settle;
            // decaying at a third and two thirds of the epochs does (docs/recon.md).
            schedule: Schedule {
                warmup_steps: 20,
                milestones: vec![1.0 / 3.0, 2.0 / 3.0],
                gamma: 0.3,
            },
            render: RenderOptions::default(),
            loss: LossChoice::Auto,
            prune: PruneSettings::default(),
            densify: DensifySettings::default(),
            average_from: default_average_from(),
            average_batch: AverageBatch::Same,
            gain_pairs: 512,
            pair_gains: PairGains::default(),
            seed: 0,
            converge: None,
            surface: None,
            coarse: None,
        }
    }
}

/// The primitives a fit of `primitives` starts with at `grow_from`
/// ([`DensifySettings::grow_from`]): at least one.
pub fn starting_primitives(primitives: usize, grow_from: f64) -> usize {
    ((primitives as f64 * grow_from).round() as usize).clamp(1, primitives.max(1))
}

/// The primitives' initial scale and whether their places came from data.
#[derive(Clone, Copy, Debug)]
struct Placement {
    scale: f64,
    from_data: bool,
}

/// The most primitives a [`TrainEvent::Snapshot`] carries.
pub const SNAPSHOT_MAX: usize = 2048;

/// Progress of a fit, for the CLI, the HTTP event stream and the logs alike.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum TrainEvent {
    /// The gain was matched and optimisation starts.
    Initialised {
        /// Primitives K.
        primitives: usize,
        /// Transients available.
        pairs: usize,
        /// The matched global gain g.
        gain: f64,
    },
    /// New transients arrived from the capture.
    DataAdded {
        /// Transients now available.
        pairs: usize,
    },
    /// An epoch finished.
    Epoch {
        /// Counted epoch index (1-based), or 0 for a live epoch during capture.
        epoch: usize,
        /// Optimiser steps so far.
        step: usize,
        /// Mean mini-batch loss over the epoch.
        loss: f64,
        /// Transients the epoch trained on.
        pairs: usize,
        /// Primitives in the cloud.
        primitives: usize,
    },
    /// The primitives after an epoch, for live displays: the centres and weights
    /// (albedo × largest cross-section, m²) of the [`SNAPSHOT_MAX`] heaviest.
    Snapshot {
        /// Centres, metres.
        centres: Vec<[f32; 3]>,
        /// Weights, in the order of `centres`.
        weights: Vec<f32>,
    },
    /// Adaptive density control split `moved` large primitives, each into its own
    /// slot and that of a primitive that carried no signal.
    Densified {
        /// The counted epoch after which it ran.
        epoch: usize,
        /// Primitives split (and as many relocated).
        moved: usize,
    },
    /// The fit's result became the mean of its last iterates
    /// ([`TrainConfig::average_from`]).
    Averaged {
        /// Optimiser steps averaged.
        steps: usize,
    },
    /// Pruning ran.
    Pruned {
        /// Primitives before.
        before: usize,
        /// Primitives kept.
        kept: usize,
    },
    /// The last stage's loss stopped falling before its counted epochs were spent
    /// ([`TrainConfig::converge`]): the fit ends after this epoch.
    Converged {
        /// The counted epoch after which it stopped.
        epoch: usize,
        /// The counted epochs it had.
        of: usize,
        /// Optimiser steps taken.
        step: usize,
    },
    /// The fit stopped because it was cancelled.
    Cancelled {
        /// Optimiser steps done.
        step: usize,
    },
}

/// A token that stops a running fit at the next optimiser step.
#[derive(Clone, Debug, Default)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    /// A token that is not cancelled.
    pub fn new() -> Self {
        Self::default()
    }

    /// Requests cancellation.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::SeqCst);
    }

    /// Whether cancellation was requested.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::SeqCst)
    }
}

/// Why a fit could not run.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    /// The configuration cannot work.
    #[error("invalid reconstruction settings: {0}")]
    Config(String),
    /// Building the cloud failed.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// Transients were rejected.
    #[error(transparent)]
    Transient(#[from] TransientError),
    /// No primitive is visible from any pair, so the gain cannot be matched.
    #[error(
        "no primitive in the region of interest is visible from any pair: check that the ROI lies in front of the relay surface (on the side its normals point to) and within the time axis"
    )]
    NothingVisible,
    /// The histograms' total is negative, which no non-negative scene explains.
    #[error(
        "the histograms sum to {total:.3e} over the pairs the gain is matched on: 3D-GTR fits a non-negative scene, which cannot explain data whose total is negative (background subtracted with the wrong sign, or an inverted capture?); check the capture's sign, or use method = \"fbp\", which does not depend on it"
    )]
    NegativeTotal {
        /// The sampled pairs' total, weighted as in the fit.
        total: f64,
    },
    /// The GPU the fit was asked to run on failed ([`Trainer::use_gpu`], strict).
    #[error(transparent)]
    Gpu(#[from] GpuError),
}

/// How a fit ended.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TrainSummary {
    /// Counted epochs completed.
    pub epochs: usize,
    /// Optimiser steps taken.
    pub steps: usize,
    /// Loss of the last epoch.
    pub final_loss: f64,
    /// Whether the fit was cancelled.
    pub cancelled: bool,
    /// Pairs per mini-batch in force ([`TrainConfig::batch_size`], or
    /// [`TrainConfig::coarse`]'s).
    pub batch_size: usize,
    /// Pairs a step in the averaged epochs ([`TrainConfig::average_batch`] of the
    /// batch in force).
    pub average_batch: usize,
    /// The surface prior's spread in force, metres (`None`: off).
    pub surface_spread: Option<f64>,
    /// Whether the data counted as a coarse capture and the fit took
    /// [`TrainConfig::coarse`]'s settings.
    pub coarse: bool,
    /// The per-transient gains the fit estimated ([`PairGains::Illumination`] or
    /// [`PairGains::Detection`]), or [`PairGains::None`] where it estimated none
    /// ([`TrainConfig::pair_gains`] resolved on the data, [`PairGains::resolve`]).
    pub pair_gains: PairGains,
}

/// A fit in progress.
pub struct Trainer {
    /// How the initial primitives were placed, to place them again for a coarse
    /// capture that starts with more of them.
    placement: Placement,
    config: TrainConfig,
    /// Whether [`TrainConfig::coarse`]'s settings were taken.
    coarse: bool,
    data: TransientSet,
    cloud: GaussianCloud,
    start_centres: Vec<f64>,
    adam: AdamW,
    options: RenderOptions,
    gain_set: bool,
    rng: ChaCha8Rng,
    step: usize,
    epochs_done: usize,
    /// The running mean of the iterates and how many it holds, while averaging
    /// ([`TrainConfig::average_from`]).
    average: Option<(GaussianCloud, usize)>,
    kernels: Vec<Kernel>,
    /// Each pair's gain in the model ([`PairGains`]), 1 until estimated.
    pair_gains: Vec<f64>,
    /// Gain rounds done.
    gain_rounds: usize,
    /// The kind of gains the rounds estimated ([`PairGains::resolve`]).
    gains_estimated: PairGains,
    /// The map slopes of each primitive, refreshed with `kernels`.
    slopes: Vec<MapSlopes>,
    grads: RawGrads,
    /// Each averaged epoch's steps and summed mini-batch loss, for the convergence
    /// test ([`TrainConfig::converge`]).
    averaged_losses: Vec<(usize, f64)>,
    /// A shuffled pass over the data and how far the epochs have taken it, when an
    /// epoch trains on part of the data ([`TrainConfig::epoch_pairs`]).
    pass: Vec<usize>,
    pass_at: usize,
    /// Where the model goes after each streamed batch's live training, and the live
    /// steps each batch gets at least ([`Trainer::report_live_model`]).
    live_model: Option<(Sender<LiveModel>, usize)>,
    /// The GPU the steps run on ([`Trainer::use_gpu`]), and whether its failure is the
    /// fit's (otherwise the fit goes on on the CPU).
    gpu: Option<(Arc<Gpu>, bool)>,
    /// A strict GPU's failure, for [`Trainer::run`] to return.
    gpu_failure: Option<GpuError>,
}

/// The fit as it stands after a streamed batch's live training: what an adaptive
/// capture chooses its next pairs from ([`Trainer::report_live_model`]).
#[derive(Clone, Debug)]
pub struct LiveModel {
    /// The primitives as kernels.
    pub kernels: Vec<Kernel>,
    /// The render options in force (matched gain, chosen loss).
    pub options: RenderOptions,
    /// Transients fitted so far.
    pub pairs: usize,
    /// Optimiser steps taken.
    pub step: usize,
}

impl Trainer {
    /// Validates the settings and places the primitives. `data` may be empty when
    /// transients will be streamed in; the gain is matched once data is there.
    pub fn new(config: TrainConfig, roi: RoiBox, data: TransientSet) -> Result<Self, TrainError> {
        if config.primitives == 0 {
            return Err(TrainError::Config(
                "the number of primitives must be at least 1".into(),
            ));
        }
        if config.batch_size == 0 || config.coarse.is_some_and(|c| c.batch_size == 0) {
            return Err(TrainError::Config("the batch size must be at least 1".into()));
        }
        let min_half = roi.half.min_element();
        let bounds = config.scale_bounds.unwrap_or(ScaleBounds {
            min: 5e-4,
            max: (0.5 * min_half).max(1e-3),
        });
        let scale = config
            .initial_scale
            .unwrap_or_else(|| default_initial_scale(&roi, config.primitives))
            .clamp(bounds.min * 1.01, bounds.max * 0.99);
        if !(config.initial_albedo.is_finite() && config.initial_albedo > 0.0) {
            return Err(TrainError::Config("the initial albedo must be positive".into()));
        }
        let grows = [Some(config.densify.grow_from), config.coarse.map(|c| c.grow_from)];
        if grows.into_iter().flatten().any(|f| !(f > 0.0 && f <= 1.0)) {
            return Err(TrainError::Config(
                "the fraction of the primitives a fit starts with must be above 0 and at most 1".into(),
            ));
        }
        let placement = Placement {
            scale,
            from_data: !data.is_empty(),
        };
        let cloud = initial_cloud(
            roi,
            bounds,
            starting_primitives(config.primitives, config.densify.grow_from),
            scale,
            config.initial_albedo,
            &config.init,
            &data,
            config.seed,
        )?;
        let options = config.render;
        let mut trainer = Self {
            placement,
            adam: AdamW::new(config.adam),
            rng: ChaCha8Rng::seed_from_u64(config.seed),
            start_centres: cloud.centres.clone(),
            cloud,
            data,
            options,
            gain_set: false,
            step: 0,
            epochs_done: 0,
            average: None,
            kernels: Vec::new(),
            pair_gains: Vec::new(),
            gain_rounds: 0,
            gains_estimated: PairGains::None,
            slopes: Vec::new(),
            grads: RawGrads::default(),
            averaged_losses: Vec::new(),
            pass: Vec::new(),
            pass_at: 0,
            live_model: None,
            gpu: None,
            gpu_failure: None,
            config,
            coarse: false,
        };
        trainer.match_gain()?;
        Ok(trainer)
    }

    /// Matches the gain g so the rendering's total equals the data's, once there is
    /// data. Zero data leaves g = 1 (nothing to fit).
    fn match_gain(&mut self) -> Result<(), TrainError> {
        if self.gain_set || self.data.is_empty() {
            return Ok(());
        }
        self.choose_coarse_fit()?;
        let step = (self.data.len() / self.config.gain_pairs.max(1)).max(1);
        let sample = self
            .data
            .subset(&(0..self.data.len()).step_by(step).collect::<Vec<_>>());
        let unit = RenderOptions {
            gain: 1.0,
            ..self.options
        };
        let rendered: f64 = render_set(&self.cloud.kernels(), &sample, &unit)
            .chunks(sample.axis().bins)
            .enumerate()
            .map(|(i, h)| sample.weight(i) as f64 * h[sample.recorded(i)].iter().sum::<f64>())
            .sum();
        if rendered <= 0.0 || !rendered.is_finite() {
            return Err(TrainError::NothingVisible);
        }
        self.options.loss = self.resolve_loss()?;
        // The model has no background: match its total to the data's above it.
        let background = match self.options.loss {
            Loss::Poisson { background } => {
                let weighted_bins: f64 = (0..sample.len())
                    .map(|i| sample.weight(i) as f64 * sample.recorded(i).len() as f64)
                    .sum();
                background * weighted_bins
            }
            Loss::L2 => 0.0,
        };
        let total = sample.total_counts();
        if total < 0.0 {
            // With a negative total every step would only shrink the albedo towards
            // an empty scene, which the fit would then report as its result.
            return Err(TrainError::NegativeTotal { total });
        }
        let measured = if total - background > 0.0 {
            total - background
        } else {
            total
        };
        self.options.gain = if measured > 0.0 { measured / rendered } else { 1.0 };
        self.gain_set = true;
        tracing::info!(loss = ?self.options.loss, gain = self.options.gain, "fit data term and gain");
        Ok(())
    }

    /// The data term [`TrainConfig::loss`] asks for, given the data so far.
    fn resolve_loss(&self) -> Result<Loss, TrainError> {
        let poisson = || Loss::Poisson {
            background: estimate_background(&self.data, Some(self.cloud.roi())),
        };
        Ok(match self.config.loss {
            LossChoice::L2 => Loss::L2,
            LossChoice::Auto if first_negative(&self.data).is_none() => poisson(),
            LossChoice::Auto => Loss::L2,
            LossChoice::Poisson => {
                if let Some(i) = first_negative(&self.data) {
                    return Err(TrainError::Config(format!(
                        "loss = \"poisson\" needs non-negative data (counts or intensities), but the histogram of pair {i} has negative bins (background-subtracted data?); use loss = \"l2\""
                    )));
                }
                poisson()
            }
        })
    }

    /// Adds transients (same time axis) to the data being fitted.
    pub fn add(&mut self, more: &TransientSet) -> Result<(), TrainError> {
        self.data.extend(more)?;
        // New transients start at gain 1 until the next estimate.
        self.pair_gains.resize(self.data.len(), 1.0);
        self.match_gain()
    }

    /// Asks [`Trainer::run`] to send the model to `tx` each time a streamed batch has
    /// had its live training, just before it waits for the next batch, and to train
    /// each batch for at least `min_steps` live steps (whole epochs, at least
    /// [`LIVE_EPOCHS_PER_BATCH`]). The capture waits for the model and chooses the next
    /// pairs from it, so the choices depend on the batches alone, never on timing.
    pub fn report_live_model(&mut self, tx: Sender<LiveModel>, min_steps: usize) {
        self.live_model = Some((tx, min_steps));
    }

    /// Runs the fit's steps on `gpu` from now on, in f32, the parameters resident there
    /// through each epoch ([`crate::gpu::fit_steps`]: the mini-batch's render,
    /// residuals and backward pass, the chain rule and AdamW), and a round of gain
    /// estimation's rendering of the whole capture; densification, pruning and the
    /// gain estimates themselves stay here, between epochs. With `strict`, a failure of
    /// the GPU ends the fit with [`TrainError::Gpu`]; otherwise the fit says so in the
    /// log and takes the epoch again on the CPU.
    pub fn use_gpu(&mut self, gpu: Arc<Gpu>, strict: bool) {
        self.gpu = Some((gpu, strict));
    }

    /// Whether the steps run on a GPU (one that failed without `strict` no longer does).
    pub fn on_gpu(&self) -> bool {
        self.gpu.is_some()
    }

    /// The current primitives.
    pub fn cloud(&self) -> &GaussianCloud {
        &self.cloud
    }

    /// The settings in force: the configured ones, with [`TrainConfig::coarse`]'s in
    /// place of the batch size and the surface prior once the data chose them.
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// The render options in force, including the matched gain.
    pub fn render_options(&self) -> &RenderOptions {
        &self.options
    }

    /// The data being fitted.
    pub fn data(&self) -> &TransientSet {
        &self.data
    }

    /// Optimiser steps taken.
    pub fn steps(&self) -> usize {
        self.step
    }

    /// One pass over the data in shuffled mini-batches; returns the mean batch loss, or
    /// `None` when cancelled part-way (the cloud is valid either way), or when a strict
    /// GPU failed ([`Trainer::use_gpu`]; [`Trainer::run`] returns its error).
    pub fn epoch(&mut self, cancel: &CancelToken) -> Option<f64> {
        self.epoch_kept_warm(cancel, true)
    }

    /// [`Trainer::epoch`]; with `warm` (and on the CPU), the pool's other workers
    /// wait for the step's parallel regions awake ([`keep_warm`]) instead of sleeping
    /// between them. A sleeping worker woke late to every region: a fit on two
    /// threads kept them 1.78 busy, and took 7 % longer (`periscope recon`,
    /// confocal_planar, 2026-12-08), for the same bits. [`Trainer::run`] keeps them
    /// warm once the capture has ended, and in an adaptive capture's live epochs,
    /// which run while the capture waits for them; not in a streamed capture's live
    /// epochs, where a core the fit leaves idle is the capture's.
    fn epoch_kept_warm(&mut self, cancel: &CancelToken, warm: bool) -> Option<f64> {
        // On a worker of the thread pool, so that the step's parallel regions hand work
        // to the other workers without waking this thread up each time (a call from
        // outside the pool injects the region and sleeps until it is done).
        let warm = warm && self.gpu.is_none();
        let done = std::sync::atomic::AtomicBool::new(false);
        rayon::scope(|s| {
            let done = &done;
            if warm {
                let fitting = rayon::current_thread_index();
                for _ in 1..rayon::current_num_threads() {
                    s.spawn(move |_| keep_warm(done, fitting));
                }
            }
            let _end = EndOfEpoch(done);
            self.epoch_on_pool(cancel)
        })
    }

    fn epoch_on_pool(&mut self, cancel: &CancelToken) -> Option<f64> {
        if self.gpu_failure.is_some() {
            // A strict GPU failed outside an epoch (a round of gain estimation).
            return None;
        }
        let n = self.data.len();
        let (take, batch_size) = self.config.epoch_plan(n, self.average.is_some());
        let order: Vec<usize> = if take >= n {
            let mut order: Vec<usize> = (0..n).collect();
            order.shuffle(&mut self.rng);
            order
        } else {
            // The next `take` pairs of a shuffled pass over the data, a new pass when
            // this one has fewer left (or the data grew).
            if self.pass.len() != n || self.pass_at + take > n {
                self.pass = (0..n).collect();
                self.pass.shuffle(&mut self.rng);
                self.pass_at = 0;
            }
            self.pass_at += take;
            self.pass[self.pass_at - take..self.pass_at].to_vec()
        };
        if let Some((gpu, strict)) = self.gpu.clone() {
            match self.epoch_on_gpu(&gpu, &order, batch_size, cancel) {
                Ok(loss) => return loss,
                Err(e) if strict => {
                    self.gpu_failure = Some(e);
                    return None;
                }
                Err(e) => {
                    tracing::warn!(error = %e, step = self.step, "the GPU failed: the fit goes on on the CPU");
                    self.gpu = None;
                }
            }
        }
        let mut total = 0.0;
        let mut batches = 0usize;
        for batch in order.chunks(batch_size) {
            if cancel.is_cancelled() {
                return None;
            }
            self.refresh_kernels();
            let gains = (self.gain_rounds > 0).then_some(self.pair_gains.as_slice());
            let loss = batch_loss_grad_with(
                &self.cloud,
                &self.kernels,
                Some(&self.slopes),
                &self.data,
                batch,
                &self.options,
                gains,
                &mut self.grads,
            );
            if let Some(prior) = self.config.surface {
                prior.add_gradient(
                    &self.kernels,
                    &self.slopes,
                    self.cloud.roi(),
                    loss,
                    &mut self.grads,
                );
            }
            let factor = self.config.schedule.factor(
                self.step,
                self.epochs_done,
                self.config.counted_epochs(self.data.len()),
            );
            let mean = self.average.as_mut().map(|(mean, n)| {
                *n += 1;
                (mean, *n)
            });
            let skipped = self
                .adam
                .step_averaged(&mut self.cloud, &self.grads, factor, mean);
            if skipped > 0 {
                tracing::warn!(
                    skipped,
                    step = self.step,
                    "non-finite gradient entries were skipped"
                );
            }
            self.step += 1;
            total += loss;
            batches += 1;
        }
        Some(if batches == 0 { 0.0 } else { total / batches as f64 })
    }

    /// The epoch's mini-batches of `order` on `gpu`, the parameters resident there
    /// from step to step ([`crate::gpu::fit_steps`]): the same batches, schedule and
    /// running mean as the CPU's steps, in f32. The cloud, the optimiser's moments and
    /// the mean come back at the end (or at a cancellation, after the steps taken);
    /// on an error nothing here has changed, so the CPU can take the epoch over.
    fn epoch_on_gpu(
        &mut self,
        gpu: &Gpu,
        order: &[usize],
        batch_size: usize,
        cancel: &CancelToken,
    ) -> Result<Option<f64>, GpuError> {
        use crate::gpu::{Optimiser, Resident, Step};
        self.refresh_kernels();
        let mut state = Resident::of(
            &self.cloud,
            &self.adam,
            self.average.as_ref().map(|(mean, _)| mean),
        );
        let optimiser = Optimiser::of(&self.cloud, self.adam.settings());
        let batches: Vec<&[usize]> = order.chunks(batch_size).collect();
        let gains = (self.gain_rounds > 0).then_some(self.pair_gains.as_slice());
        let counted = self.config.counted_epochs(self.data.len());
        let (step0, t0) = (self.step, self.adam.steps_taken());
        let mean0 = self.average.as_ref().map(|(_, k)| *k);
        let mut step = |i: usize| {
            let (pairs, data, weights) = super::render::gpu_batch(&self.data, batches[i], gains);
            Step {
                pairs,
                data,
                weights,
                factor: self.config.schedule.factor(step0 + i, self.epochs_done, counted),
                t: t0 + i as u64 + 1,
                mean_of: mean0.map(|k| k + i + 1),
            }
        };
        // The surface prior's terms at the epoch's start: the steps take its gradient
        // with these column means and weights.
        let prior = self.config.surface.and_then(|p| {
            p.terms(&self.kernels, self.cloud.roi())
                .map(|terms| (p.depth_index(), terms))
        });
        let done = crate::gpu::fit_steps(
            gpu,
            &self.kernels,
            &mut state,
            &optimiser,
            batches.len(),
            &mut step,
            self.data.axis(),
            &self.options,
            prior.as_ref().map(|(axis, terms)| (*axis, terms.as_slice())),
            &|| cancel.is_cancelled(),
        )?;
        let taken = done.losses.len();
        if taken == 0 {
            return Ok(None);
        }
        state.write_back(
            &mut self.cloud,
            &mut self.adam,
            taken,
            self.average.as_mut().map(|(mean, k)| {
                *k += taken;
                mean
            }),
        );
        self.step += taken;
        if done.skipped > 0 {
            tracing::warn!(
                skipped = done.skipped,
                step = self.step,
                "non-finite gradient entries were skipped"
            );
        }
        if taken < batches.len() {
            return Ok(None);
        }
        Ok(Some(done.losses.iter().sum::<f64>() / taken as f64))
    }

    fn refresh_kernels(&mut self) {
        let cloud = &self.cloud;
        let n = cloud.len();
        self.kernels.resize(
            n,
            Kernel::new(Default::default(), Default::default(), Default::default(), 0.0),
        );
        self.slopes.resize(n, MapSlopes::default());
        self.kernels
            .par_chunks_mut(REFRESH_CHUNK)
            .zip(self.slopes.par_chunks_mut(REFRESH_CHUNK))
            .enumerate()
            .for_each(|(c, (kernels, slopes))| {
                cloud.kernels_and_slopes_into(c * REFRESH_CHUNK, kernels, slopes)
            });
    }

    /// Runs the fit to completion: live epochs while `feed` is open, then the counted
    /// epochs ([`TrainConfig::counted_epochs`]), then pruning. Events go to `on_event`.
    pub fn run(
        &mut self,
        feed: Option<Receiver<TransientSet>>,
        cancel: &CancelToken,
        on_event: &mut dyn FnMut(&TrainEvent),
    ) -> Result<TrainSummary, TrainError> {
        let mut feed = feed;
        let mut announced = false;
        let mut live_epochs_on_same_data = 0usize;
        let mut batch_arrived_at = self.step;
        let mut final_loss = f64::NAN;
        loop {
            // Take in the next batch once the data so far has had its live epochs (at
            // once when there is none yet): one batch at a time, waiting for it, so
            // what each epoch sees depends only on the batches, never on timing.
            let min_live_steps = self.live_model.as_ref().map_or(0, |(_, n)| *n);
            if let Some(rx) = &feed
                && (self.data.is_empty()
                    || (live_epochs_on_same_data >= LIVE_EPOCHS_PER_BATCH
                        && self.step - batch_arrived_at >= min_live_steps))
            {
                if !self.data.is_empty() && self.live_model.is_some() {
                    self.refresh_kernels();
                    let (tx, _) = self.live_model.as_ref().expect("checked");
                    // A capture that has stopped listening is not the fit's concern.
                    let _ = tx.send(LiveModel {
                        kernels: self.kernels.clone(),
                        options: self.options,
                        pairs: self.data.len(),
                        step: self.step,
                    });
                }
                match rx.recv() {
                    Ok(more) => {
                        self.add(&more)?;
                        live_epochs_on_same_data = 0;
                        batch_arrived_at = self.step;
                        on_event(&TrainEvent::DataAdded {
                            pairs: self.data.len(),
                        });
                    }
                    Err(_) => feed = None,
                }
            }
            if cancel.is_cancelled() {
                on_event(&TrainEvent::Cancelled { step: self.step });
                return Ok(self.summary(final_loss, true));
            }
            if self.data.is_empty() {
                if feed.is_none() {
                    return Err(TrainError::Config(
                        "there are no transients to reconstruct from".into(),
                    ));
                }
                continue;
            }
            if !announced {
                on_event(&TrainEvent::Initialised {
                    primitives: self.cloud.len(),
                    pairs: self.data.len(),
                    gain: self.options.gain,
                });
                announced = true;
            }
            // Fixed once the data is complete (no more arrives after the feed closes).
            let epochs = self.config.counted_epochs(self.data.len());
            if feed.is_none() && self.epochs_done >= epochs {
                break;
            }
            if feed.is_none()
                && self.average.is_none()
                && self
                    .config
                    .average_start(epochs)
                    .is_some_and(|start| self.epochs_done >= start)
            {
                self.average = Some((self.cloud.clone(), 0));
            }
            // Nothing competes for the cores once the capture has ended, nor while an
            // adaptive capture waits, laser off, for the model this training makes
            // (its live epochs run only then: the fit waits for the next batch while
            // the capture measures it).
            let warm = feed.is_none() || self.live_model.is_some();
            let Some(loss) = self.epoch_kept_warm(cancel, warm) else {
                if let Some(e) = self.gpu_failure.take() {
                    return Err(e.into());
                }
                on_event(&TrainEvent::Cancelled { step: self.step });
                return Ok(self.summary(final_loss, true));
            };
            final_loss = loss;
            // What the epoch trained on, and in steps of how many pairs.
            let (trained, per_step) = self.config.epoch_plan(self.data.len(), self.average.is_some());
            let counted = feed.is_none();
            if counted {
                self.epochs_done += 1;
            } else {
                live_epochs_on_same_data += 1;
            }
            on_event(&TrainEvent::Epoch {
                epoch: if counted { self.epochs_done } else { 0 },
                step: self.step,
                loss,
                pairs: trained,
                primitives: self.cloud.len(),
            });
            if counted && self.average.is_some() {
                let steps = trained.div_ceil(per_step);
                self.averaged_losses.push((steps, loss * steps as f64));
                if self.epochs_done < epochs && self.converged() {
                    on_event(&TrainEvent::Converged {
                        epoch: self.epochs_done,
                        of: epochs,
                        step: self.step,
                    });
                    break;
                }
            }
            if counted && self.gains_due(epochs) {
                self.estimate_gains();
            }
            if counted && self.densify_due(epochs) {
                let moved = self.densify();
                on_event(&TrainEvent::Densified {
                    epoch: self.epochs_done,
                    moved,
                });
            }
            on_event(&self.snapshot());
        }
        if let Some((mean, n)) = self.average.take()
            && n > 0
        {
            self.cloud = mean;
            self.cloud.renormalise_rotations();
            on_event(&TrainEvent::Averaged { steps: n });
        }
        let before = self.cloud.len();
        let start = starting_primitives(self.config.primitives, self.config.densify.grow_from);
        if start < self.config.primitives {
            tracing::info!(
                from = start,
                to = before,
                of = self.config.primitives,
                "the fit grew in its densification rounds ([gtr] grow-from sets where it starts)"
            );
        }
        let kept = self.prune();
        on_event(&TrainEvent::Pruned { before, kept });
        Ok(self.summary(final_loss, false))
    }

    /// Whether the averaged epochs have stopped improving ([`Convergence`]).
    fn converged(&self) -> bool {
        let Some(c) = self.config.converge else {
            return false;
        };
        let done: usize = self.averaged_losses.iter().map(|(n, _)| n).sum();
        if done < c.min_steps.max(2 * c.window) {
            return false;
        }
        // The latest window of whole epochs, then the one before it.
        let mut windows = [(0usize, 0.0f64); 2];
        let mut w = 0;
        for &(n, sum) in self.averaged_losses.iter().rev() {
            windows[w].0 += n;
            windows[w].1 += sum;
            if windows[w].0 >= c.window {
                w += 1;
                if w == 2 {
                    break;
                }
            }
        }
        if w < 2 {
            return false;
        }
        let [(n_late, late), (n_early, early)] = windows;
        let (late, early) = (late / n_late as f64, early / n_early as f64);
        late.is_finite() && early.is_finite() && late >= (1.0 - c.tolerance) * early
    }

    /// Whether a round of gain estimation follows counted epoch `epochs_done` of
    /// `epochs`: after every counted epoch from [`GAIN_START`] of them on.
    fn gains_due(&self, epochs: usize) -> bool {
        if self.config.pair_gains.resolve(&self.data) == PairGains::None || self.data.len() < 2 {
            return false;
        }
        self.epochs_done >= gain_start_epoch(epochs) && self.epochs_done < epochs
    }

    /// Estimates each gain group's gain afresh from the data and the current fit
    /// ([`PairGains`], [`estimate_pair_gains`]) and moves the log-gains [`GAIN_STEP`]
    /// of the way to it (from 1 before the first round); returns the smallest and
    /// largest gain.
    pub fn estimate_gains(&mut self) -> (f64, f64) {
        let kind = self.config.pair_gains.resolve(&self.data);
        if kind == PairGains::None || gain_groups(self.data.pairs(), kind).is_none() {
            // One laser point (or one detection point), or gains the data carry
            // already: nothing to estimate, and no rendering of the whole capture spent
            // on finding that out.
            return (1.0, 1.0);
        }
        if self.gain_rounds == 0 && self.config.pair_gains == PairGains::Auto {
            tracing::info!(
                "no transient's gain is known (no laser falloff named by the file, no relay albedo from a scan): each illumination point's gain is estimated from the data ([gtr] pair-gains = \"none\" keeps them at 1)"
            );
        }
        self.refresh_kernels();
        let rendered = self.render_for_gains();
        let Some(gains) = estimate_pair_gains(&self.data, &rendered, self.options.loss, kind) else {
            return (1.0, 1.0);
        };
        self.gains_estimated = kind;
        if self.gain_rounds == 0 || self.pair_gains.len() != gains.len() {
            self.pair_gains = gains.iter().map(|g| g.powf(GAIN_STEP)).collect();
        } else {
            for (old, new) in self.pair_gains.iter_mut().zip(&gains) {
                *old = (old.ln() + GAIN_STEP * (new.ln() - old.ln())).exp();
            }
        }
        self.gain_rounds += 1;
        let (lo, hi) = self
            .pair_gains
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(l, h), &g| (l.min(g), h.max(g)));
        tracing::info!(
            round = self.gain_rounds,
            min = lo,
            max = hi,
            "per-transient gains estimated from the data"
        );
        (lo, hi)
    }

    /// The whole capture rendered from the current kernels for a round of gain
    /// estimation ([`render_set`]'s layout): on the fit's GPU where it has one (in f32,
    /// widened), since a round renders every pair; on the CPU otherwise, or after a
    /// GPU failure (a strict fit records it, and its next epoch ends the fit with it).
    fn render_for_gains(&mut self) -> Vec<f64> {
        if let Some((gpu, strict)) = self.gpu.clone() {
            let axis = self.data.axis();
            match crate::gpu::render_pairs(&gpu, &self.kernels, self.data.pairs(), axis, &self.options) {
                Ok(out) => {
                    let mut out: Vec<f64> = out.into_iter().map(f64::from).collect();
                    super::render::apply_known_gains(&self.data, &mut out);
                    return out;
                }
                Err(e) if strict => self.gpu_failure = Some(e),
                Err(e) => {
                    tracing::warn!(error = %e, step = self.step, "the GPU failed: the fit goes on on the CPU");
                    self.gpu = None;
                }
            }
        }
        render_set(&self.kernels, &self.data, &self.options)
    }

    /// Each pair's gain in the model (all 1 before the first estimate).
    pub fn pair_gains(&self) -> Vec<f64> {
        if self.gain_rounds == 0 {
            vec![1.0; self.data.len()]
        } else {
            self.pair_gains.clone()
        }
    }

    /// Whether a round of densification follows counted epoch `epochs_done` of
    /// `epochs` ([`densify_after`]).
    fn densify_due(&self, epochs: usize) -> bool {
        densify_after(self.epochs_done, epochs, &self.config.densify)
    }

    /// The heaviest primitives as a [`TrainEvent::Snapshot`].
    fn snapshot(&self) -> TrainEvent {
        let mut weighted: Vec<([f32; 3], f32)> = (0..self.cloud.len())
            .map(|k| {
                let g = self.cloud.kernel(k);
                let w = g.rho * g.pi.max_element();
                (
                    g.x.as_vec3().to_array(),
                    if w.is_finite() { w as f32 } else { 0.0 },
                )
            })
            .collect();
        if weighted.len() > SNAPSHOT_MAX {
            weighted.select_nth_unstable_by(SNAPSHOT_MAX, |a, b| b.1.total_cmp(&a.1));
            weighted.truncate(SNAPSHOT_MAX);
        }
        let (centres, weights) = weighted.into_iter().unzip();
        TrainEvent::Snapshot { centres, weights }
    }

    fn summary(&self, final_loss: f64, cancelled: bool) -> TrainSummary {
        TrainSummary {
            epochs: self.epochs_done,
            steps: self.step,
            final_loss,
            cancelled,
            batch_size: self.config.batch_size,
            average_batch: self.config.average_batch.of(self.config.batch_size),
            surface_spread: self.config.surface.map(|p| p.spread),
            coarse: self.coarse,
            pair_gains: if self.gain_rounds > 0 {
                self.gains_estimated
            } else {
                PairGains::None
            },
        }
    }

    /// One round of adaptive density control ([`densify`]) with the configured
    /// settings; the split primitives start with fresh optimiser moments. Returns how
    /// many primitives were split.
    pub fn densify(&mut self) -> usize {
        let d = self.config.densify;
        let target = d.target_scale.unwrap_or_else(|| self.split_floor());
        let before = self.cloud.len();
        let grow = self.growth_allowed();
        let moved = densify(&mut self.cloud, d.dead_fraction, target, grow);
        let n = self.cloud.len();
        if n > before {
            self.adam.grow(n);
            self.start_centres
                .extend_from_slice(&self.cloud.centres[3 * before..]);
            tracing::debug!(from = before, to = n, "the fit grew");
        }
        for &(parent, slot) in &moved {
            self.adam.reset(parent);
            self.adam.reset(slot);
        }
        moved.len()
    }

    /// How many primitives this round may add: what K leaves, in a fit that grows
    /// ([`DensifySettings::grow_from`] below 1); none in one that does not.
    fn growth_allowed(&self) -> usize {
        let k = self.config.primitives;
        if starting_primitives(k, self.config.densify.grow_from) >= k {
            return 0;
        }
        k.saturating_sub(self.cloud.len())
    }

    /// The scale splits stop at when none is set: [`default_target_scale`], or, where
    /// the capture places points less finely, the scale whose split children (√3 of
    /// it apart) lie [`resolvable_separation`] apart at the ROI's centre. Finer
    /// children drifted into lumps that an image shows instead of the surface
    /// (docs/recon.md, "The mannequin").
    pub fn split_floor(&self) -> f64 {
        let (capacity, resolved) = self.floor_and_capacity();
        let roi = self.cloud.roi();
        resolved.map_or(capacity, |d| capacity.max(d).min(roi.half.max_element()))
    }

    /// The ROI's capacity ([`default_target_scale`]) and the scale whose split
    /// children lie [`resolvable_separation`] apart at its centre, where the data say.
    fn floor_and_capacity(&self) -> (f64, Option<f64>) {
        let roi = self.cloud.roi();
        let capacity = default_target_scale(roi, self.config.primitives);
        let resolved =
            resolvable_separation(&self.data, roi.centre, self.options.sigma_sys).map(|d| d / 3f64.sqrt());
        (capacity, resolved)
    }

    /// Takes [`TrainConfig::coarse`]'s settings if the data place points coarsely;
    /// once, at the first data, before any step: where the coarse fit starts with more
    /// primitives, they are placed again.
    fn choose_coarse_fit(&mut self) -> Result<(), TrainError> {
        let (capacity, resolved) = self.floor_and_capacity();
        let ratio = resolved.map_or(0.0, |f| f / capacity);
        let coarse = ratio >= CoarseFit::FROM_RATIO;
        tracing::info!(
            resolved_split_m = resolved,
            capacity_m = capacity,
            ratio,
            coarse,
            "what the capture resolves at the ROI's centre against what its primitives can hold"
        );
        if let Some(c) = self.config.coarse.take()
            && coarse
        {
            tracing::info!(
                batch = c.batch_size,
                surface_spread_m = c.surface.map(|p| p.spread),
                "a coarse capture: the fit takes its settings for one ([gtr] batch and surface-spread set them)"
            );
            self.config.batch_size = c.batch_size;
            self.config.surface = c.surface;
            self.config.densify.grow_from = c.grow_from;
            self.config.average_batch = c.average_batch;
            self.coarse = true;
            let count = starting_primitives(self.config.primitives, c.grow_from);
            if count != self.cloud.len() && self.step == 0 {
                let none = self.data.subset(&[]);
                self.cloud = initial_cloud(
                    *self.cloud.roi(),
                    self.cloud.scale_bounds(),
                    count,
                    self.placement.scale,
                    self.config.initial_albedo,
                    &self.config.init,
                    if self.placement.from_data {
                        &self.data
                    } else {
                        &none
                    },
                    self.config.seed,
                )?;
                self.start_centres = self.cloud.centres.clone();
                self.adam = AdamW::new(self.config.adam);
            }
        }
        Ok(())
    }

    /// Removes primitives at the ROI boundary, with negligible weight, or never moved;
    /// returns how many remain.
    pub fn prune(&mut self) -> usize {
        let s = self.config.prune;
        let cloud = &self.cloud;
        let prims: Vec<_> = (0..cloud.len()).map(|k| cloud.primitive(k)).collect();
        let mean_weight = prims.iter().map(Primitive::weight).sum::<f64>() / prims.len().max(1) as f64;
        let roi = *cloud.roi();
        let start = &self.start_centres;
        let keep = |k: usize| {
            let p = &prims[k];
            let rel = ((p.centre - roi.centre) / roi.half).abs().max_element();
            let c0 = cloud.centre_of_raw(&start[3 * k..3 * k + 3]);
            rel <= 1.0 - s.boundary_margin
                && p.weight() >= s.min_weight_fraction * mean_weight
                && p.centre.distance(c0) >= s.min_motion
        };
        let keep_mask: Vec<bool> = (0..prims.len()).map(keep).collect();
        let n = self.cloud.len();
        self.adam.retain(n, |k| keep_mask[k]);
        self.cloud.retain(|k| keep_mask[k]);
        let kept_start: Vec<f64> = (0..n)
            .filter(|&k| keep_mask[k])
            .flat_map(|k| self.start_centres[3 * k..3 * k + 3].to_vec())
            .collect();
        self.start_centres = kept_start;
        self.cloud.len()
    }
}

/// Sets its flag when dropped: the epoch's end, however it ends (a panic included), so
/// [`keep_warm`] never outlives it.
struct EndOfEpoch<'a>(&'a std::sync::atomic::AtomicBool);

impl Drop for EndOfEpoch<'_> {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Release);
    }
}

/// Keeps a worker of the pool taking the epoch's parallel work as it comes, until
/// `done`: without it the worker sleeps between a step's regions and each region
/// waits for it to wake. Returns at once on `fitting`, the thread running the epoch
/// (which may pop it while it waits in a join).
fn keep_warm(done: &std::sync::atomic::AtomicBool, fitting: Option<usize>) {
    if rayon::current_thread_index() == fitting {
        return;
    }
    while !done.load(std::sync::atomic::Ordering::Acquire) {
        match rayon::yield_now() {
            Some(rayon::Yield::Executed) => {}
            Some(rayon::Yield::Idle) => std::thread::yield_now(),
            None => return,
        }
    }
}

#[cfg(test)]
mod surface_tests {
    use glam::DQuat;
    use rand::Rng;

    use super::*;

    /// A cloud of `n` primitives scattered through a 1 m box, with their kernels and
    /// slopes.
    fn cloud(n: usize) -> (GaussianCloud, Vec<Kernel>, Vec<MapSlopes>) {
        let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.2), DVec3::new(0.5, 0.5, 1.2)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 1e-3, max: 0.2 }).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for _ in 0..n {
            cloud
                .push(Primitive {
                    // Few columns, so each holds several primitives at different depths.
                    centre: DVec3::new(
                        rng.random_range(-0.2..0.2),
                        rng.random_range(-0.2..0.2),
                        rng.random_range(0.4..1.0),
                    ),
                    scale: DVec3::new(
                        rng.random_range(0.005..0.05),
                        rng.random_range(0.005..0.05),
                        rng.random_range(0.002..0.02),
                    ),
                    rotation: DQuat::from_rotation_y(rng.random_range(-0.5..0.5)),
                    albedo: rng.random_range(0.1..2.0),
                })
                .unwrap();
        }
        let kernels = cloud.kernels();
        let slopes = (0..n).map(|k| cloud.slopes(k)).collect();
        (cloud, kernels, slopes)
    }

    /// The depth axes a relay may face along: +z (our instrument's walls), −y (a
    /// Zaragoza wall) and +x.
    const AXES: [DepthAxis; 3] = [
        DepthAxis::Z,
        DepthAxis {
            axis: 1,
            positive: false,
        },
        DepthAxis {
            axis: 0,
            positive: true,
        },
    ];

    /// A prior of 2 cm spread on 10 cm columns along each of [`AXES`].
    fn priors() -> impl Iterator<Item = SurfacePrior> {
        AXES.into_iter().map(|axis| SurfacePrior {
            spread: 0.02,
            cell: 0.1,
            axis,
        })
    }

    #[test]
    fn the_surface_priors_gradient_matches_finite_differences() {
        priors().for_each(priors_gradient_matches_finite_differences);
    }

    /// `prior`'s gradient on a cloud scattered through a box against central
    /// differences of P, along its axis only.
    fn priors_gradient_matches_finite_differences(prior: SurfacePrior) {
        let a = prior.depth_index();
        let (cloud, kernels, slopes) = cloud(40);
        let roi = *cloud.roi();
        let loss = 0.3;
        let mut grads = RawGrads::zeros(cloud.len());
        let p = prior.add_gradient(&kernels, &slopes, &roi, loss, &mut grads);
        assert!(
            p > 0.0,
            "primitives at different depths in a column cost something"
        );
        // Only the depths move: every other entry is untouched.
        assert!(
            grads
                .centres
                .iter()
                .enumerate()
                .all(|(j, g)| j % 3 == a || *g == 0.0)
        );
        assert!(grads.scales.iter().chain(&grads.albedo).all(|g| *g == 0.0));
        let value = |cloud: &GaussianCloud| {
            let kernels = cloud.kernels();
            let slopes: Vec<MapSlopes> = (0..cloud.len()).map(|k| cloud.slopes(k)).collect();
            prior.add_gradient(&kernels, &slopes, &roi, loss, &mut RawGrads::zeros(cloud.len()))
        };
        let h = 1e-6;
        let mut moved = 0;
        for i in 0..cloud.len() {
            let (mut plus, mut minus) = (cloud.clone(), cloud.clone());
            plus.centres[3 * i + a] += h;
            minus.centres[3 * i + a] -= h;
            let fd = (value(&plus) - value(&minus)) / (2.0 * h);
            let g = grads.centres[3 * i + a];
            assert!(
                (fd - g).abs() <= 1e-6 * p.max(1e-12) + 1e-4 * g.abs(),
                "primitive {i}: {g} against {fd}"
            );
            moved += usize::from(g != 0.0);
        }
        assert!(moved > cloud.len() / 2, "only {moved} primitives were pulled");
    }

    #[test]
    fn the_surface_prior_leaves_a_column_at_one_depth_alone() {
        priors().for_each(leaves_a_column_at_one_depth_alone);
    }

    fn leaves_a_column_at_one_depth_alone(prior: SurfacePrior) {
        let a = prior.depth_index();
        let (mut cloud, kernels, _) = cloud(40);
        let roi = *cloud.roi();
        let spread = |kernels: &[Kernel]| {
            let (means, _, _) = prior.column_means(kernels, &roi).unwrap();
            kernels
                .iter()
                .zip(&means)
                .map(|(k, m)| (k.x[a] - m).abs())
                .fold(0.0, f64::max)
        };
        let before = spread(&kernels);
        assert!(before > 0.05, "{before}");
        // Every primitive moved to its column's mean depth.
        let (means, _, _) = prior.column_means(&kernels, &roi).unwrap();
        for (i, m) in means.iter().enumerate() {
            cloud.centres[3 * i + a] = ((m - roi.centre[a]) / roi.half[a]).atanh();
        }
        let after = spread(&cloud.kernels());
        assert!(after < 1e-9, "{after} m between a column's depths at their mean");
        // One surface per column already: P is zero and nothing is pulled.
        let kernels = cloud.kernels();
        let slopes: Vec<MapSlopes> = (0..cloud.len()).map(|k| cloud.slopes(k)).collect();
        let mut grads = RawGrads::zeros(cloud.len());
        let p = prior.add_gradient(&kernels, &slopes, cloud.roi(), 0.3, &mut grads);
        assert!(p < 1e-12 && grads.centres.iter().all(|g| g.abs() < 1e-6), "{p}");
    }
}

#[cfg(test)]
mod width_tests {
    use super::minimum_width;

    /// The least width of known shapes, whatever their order or turn.
    #[test]
    fn the_least_width_of_known_shapes() {
        let turn = |p: &[[f64; 2]], a: f64| -> Vec<[f64; 2]> {
            p.iter()
                .map(|q| [q[0] * a.cos() - q[1] * a.sin(), q[0] * a.sin() + q[1] * a.cos()])
                .collect()
        };
        // A 1 × 3 rectangle with points inside and on its edges.
        let rectangle = [
            [0.0, 0.0],
            [3.0, 0.0],
            [3.0, 1.0],
            [0.0, 1.0],
            [1.5, 0.5],
            [1.0, 0.0],
            [2.0, 1.0],
        ];
        // An equilateral triangle of side 1: its height.
        let triangle = [[0.0, 0.0], [1.0, 0.0], [0.5, 3f64.sqrt() / 2.0]];
        for a in [0.0, 0.3, 1.0, 2.5] {
            assert!((minimum_width(&turn(&rectangle, a)) - 1.0).abs() < 1e-12, "{a}");
            assert!(
                (minimum_width(&turn(&triangle, a)) - 3f64.sqrt() / 2.0).abs() < 1e-12,
                "{a}"
            );
            let line = turn(&[[0.0, 0.0], [1.0, 0.0], [2.5, 0.0], [4.0, 0.0]], a);
            assert_eq!(minimum_width(&line), 0.0, "{a}");
        }
        assert_eq!(minimum_width(&[[0.0, 0.0], [1.0, 1.0]]), 0.0);
        assert_eq!(minimum_width(&[[2.0, 2.0]; 5]), 0.0);
    }
}

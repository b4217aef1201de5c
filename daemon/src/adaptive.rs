//! Adaptive capture: the running 3D-GTR fit chooses the next pairs to measure
//! (docs/adaptive.md).
//!
//! A capture, or its replay on a stored capture, measures a first batch spread over
//! the candidate pairs (farthest-point order over both relay points), then asks the fit,
//! after each batch's live training, which candidates would tell it most: the
//! D-optimal gain of each candidate's information about the primitives' centres
//! ([`periscope_recon::adaptive`]), chosen greedily among the candidates that keep the
//! measured pairs spread (`coverage`), with a share of each batch kept for the
//! candidates farthest from everything measured (what the fit has not found cannot ask
//! to be looked at). A batch is measured in the order of a
//! nearest-neighbour tour of the galvos. The capture ends at the pair budget, or once a
//! batch's mean gain has fallen below `stop-gain` of the first choice's.
use rand::SeedableRng;
use rand::seq::{IndexedRandom, SliceRandom};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use periscope_recon::Pair;
use periscope_recon::adaptive::{
    Coverage, InformationSums, Recorded, WHOLE_AXIS, choose, choose_spread_near, farthest_points,
    farthest_points_from, terms_of, tour, travel,
};
use periscope_recon::gtr::LiveModel;
use periscope_recon::transient::TimeAxis;

use crate::config::{ConfigError, TomlSource};

/// The first batch when `first` is not set: this fraction of the budget ...
const FIRST_FRACTION: f64 = 0.25;
/// ... and each next batch: this fraction of it ...
const BATCH_FRACTION: f64 = 0.0625;
/// ... each at least this many pairs.
const MIN_BATCH: usize = 8;

/// Candidates scored for one choice at most (a seeded sample of the rest beyond it),
/// and measured pairs whose terms are held at once: with each pair's terms capped
/// ([`periscope_recon::adaptive::MAX_TERMS`]), a choice holds at most about 170 MB of
/// terms, and at most 16 MB of strengths for the prior however many were measured.
const MAX_SCORED: usize = 8192;

/// What one choice holds at most beside the fit, bytes, for the plan's budget: the
/// scored candidates' terms (of `candidates`, at most 8,192: about 170 MB)
/// and the strengths for the prior (16 MB), with the information sums over the fit's
/// `primitives`, their inverse and a copy (about 72 B each a primitive).
pub fn choice_bytes(candidates: usize, primitives: usize) -> u64 {
    let terms = (candidates.min(MAX_SCORED) * periscope_recon::adaptive::MAX_TERMS * 40) as u64;
    terms + (16 << 20) + 3 * 72 * primitives as u64
}

/// The default share of each chosen batch taken by distance instead of by gain. Half:
/// measured against a quarter, three quarters and none on the validation captures
/// (three seeds, half or an eighth of their pairs; docs/adaptive.md).
const DEFAULT_EXPLORE: f64 = 0.5;
/// The default spread a pick by gain keeps: 0.7 of the farthest candidate's distance,
/// measured against 0 (by gain alone), 0.5 and 0.85 on the validation captures (three
/// seeds, an eighth to half of their pairs; docs/adaptive.md).
const DEFAULT_COVERAGE: f64 = 0.7;
/// The default live optimiser steps each batch gets before the next choice.
const DEFAULT_LIVE_STEPS: usize = 512;

/// How the next pairs are chosen.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Order {
    /// By the running fit (the adaptive capture).
    Adaptive,
    /// Farthest-point order over the candidates: an even spread, the uniform grid's
    /// coarse-to-fine order on a grid.
    Uniform,
    /// A seeded random order.
    Random,
}

impl std::fmt::Display for Order {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Order::Adaptive => "adaptive",
            Order::Uniform => "uniform",
            Order::Random => "random",
        })
    }
}

/// Validated `[adaptive]` settings (`[recon.adaptive]` in a plan).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AdaptiveSettings {
    /// Pairs to measure at most; 0: half of the candidates.
    pub pairs: usize,
    /// Pairs in the first batch; 0: a quarter of the budget.
    pub first: usize,
    /// Pairs in each later batch; 0: a sixteenth of the budget.
    pub batch: usize,
    /// The capture stops once a batch's mean gain per pair falls below this fraction of
    /// the first chosen batch's; 0: never (the budget alone ends it).
    pub stop_gain: f64,
    /// The share of each chosen batch taken farthest from what was measured.
    pub explore: f64,
    /// The rest of the batch is chosen by gain among the candidates at least this
    /// fraction as far from everything measured or chosen as the farthest candidate
    /// is (0: by gain alone; 1: by distance alone).
    pub coverage: f64,
    /// Live optimiser steps each batch gets before the next choice, at least.
    pub live_steps: usize,
    /// Seed of the random order (replays).
    pub seed: u64,
    /// A live capture chooses no more batches once it has run this long, seconds
    /// (the batch being measured is finished); 0: no time budget.
    pub seconds: f64,
}

impl Default for AdaptiveSettings {
    fn default() -> Self {
        Self {
            pairs: 0,
            first: 0,
            batch: 0,
            stop_gain: 0.0,
            explore: DEFAULT_EXPLORE,
            coverage: DEFAULT_COVERAGE,
            live_steps: DEFAULT_LIVE_STEPS,
            seed: 0,
            seconds: 0.0,
        }
    }
}

/// The `[adaptive]` table as written.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub(crate) struct RawAdaptive {
    pairs: Option<usize>,
    first: Option<usize>,
    batch: Option<usize>,
    stop_gain: Option<f64>,
    explore: Option<f64>,
    coverage: Option<f64>,
    live_steps: Option<usize>,
    seed: Option<u64>,
    seconds: Option<f64>,
}

/// Validates an `[adaptive]` table whose keys are named `{prefix}adaptive.KEY`.
pub(crate) fn adaptive_settings(
    src: &TomlSource,
    prefix: &str,
    raw: RawAdaptive,
) -> Result<AdaptiveSettings, ConfigError> {
    let key = |k: &str| format!("{prefix}adaptive.{k}");
    let d = AdaptiveSettings::default();
    let s = AdaptiveSettings {
        pairs: raw.pairs.unwrap_or(d.pairs),
        first: raw.first.unwrap_or(d.first),
        batch: raw.batch.unwrap_or(d.batch),
        stop_gain: raw.stop_gain.unwrap_or(d.stop_gain),
        explore: raw.explore.unwrap_or(d.explore),
        coverage: raw.coverage.unwrap_or(d.coverage),
        live_steps: raw.live_steps.unwrap_or(d.live_steps),
        seed: raw.seed.unwrap_or(d.seed),
        seconds: raw.seconds.unwrap_or(d.seconds),
    };
    const MOST: usize = 1 << 24;
    for (name, v) in [("pairs", s.pairs), ("first", s.first), ("batch", s.batch)] {
        if v > MOST {
            return Err(src.invalid(
                &key(name),
                format!("{v} is out of range: give 0 (the default) or a count of pairs up to {MOST}"),
            ));
        }
    }
    if s.pairs > 0 && s.first > s.pairs {
        return Err(src.invalid(
            &key("first"),
            format!(
                "{} is more than adaptive.pairs ({}): the first batch is part of the budget",
                s.first, s.pairs
            ),
        ));
    }
    if !(s.stop_gain.is_finite() && (0.0..1.0).contains(&s.stop_gain)) {
        return Err(src.invalid(
            &key("stop-gain"),
            format!("{} is out of range: give a fraction of the first batch's gain, 0 to 1 but under 1 (e.g. 0.05); 0 stops at the budget only", s.stop_gain),
        ));
    }
    for (name, v, what) in [
        ("explore", s.explore, "the share of each batch chosen by distance"),
        (
            "coverage",
            s.coverage,
            "the fraction of the farthest candidate's distance a pick by gain must keep",
        ),
    ] {
        if !(v.is_finite() && (0.0..=1.0).contains(&v)) {
            return Err(src.invalid(&key(name), format!("{v} is out of range: give {what}, 0 to 1")));
        }
    }
    if !(s.seconds.is_finite() && (0.0..=1e7).contains(&s.seconds)) {
        return Err(src.invalid(
            &key("seconds"),
            format!(
                "{} is out of range: give the capture's time budget in seconds, 0 (none) to 10000000",
                s.seconds
            ),
        ));
    }
    if s.live_steps > 1_000_000 {
        return Err(src.invalid(
            &key("live-steps"),
            format!(
                "{} is out of range: give 0 to 1000000 optimiser steps",
                s.live_steps
            ),
        ));
    }
    Ok(s)
}

/// One batch chosen, for the events and `adaptive.json`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct BatchChoice {
    /// The batch's index (0: the first batch).
    pub batch: usize,
    /// How it was chosen: `spread`, `adaptive`, `uniform` or `random`; `resumed` for
    /// a resumed capture's first batch that finishes pairs an earlier session stopped
    /// in the middle of ([`Selector::resumed_batch`]).
    pub how: String,
    /// The candidates chosen, in the order they are measured.
    pub pairs: Vec<usize>,
    /// Their illumination points, metres (for the dashboard's 3-D view).
    pub illumination: Vec<[f64; 3]>,
    /// Their detection points, metres.
    pub detection: Vec<[f64; 3]>,
    /// Each one's gain when chosen (nats); 0 for those taken by distance.
    pub gains: Vec<f64>,
    /// How many were taken by distance (`explore`).
    pub explored: usize,
    /// The mean gain of a whole batch's picks by gain, chosen without keeping the
    /// spread, relative to the first chosen batch that saw anything (`None` before
    /// one has, and in the uniform and random orders).
    pub relative_gain: Option<f64>,
    /// The galvos' travel over the batch's tour, metres on the relay (the longer arm's).
    pub travel_m: f64,
    /// Pairs measured once this batch is.
    pub measured: usize,
}

/// How many pairs an adaptive capture over some candidates measures: at most
/// `budget`, the first `first` of them spread over the candidates, the rest in
/// batches of `batch` chosen by the fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sizes {
    /// Pairs measured at most.
    pub budget: usize,
    /// The first batch.
    pub first: usize,
    /// Each later batch.
    pub batch: usize,
}

impl Sizes {
    /// The sizes for `candidates` candidate pairs under `s`.
    pub fn of(candidates: usize, s: &AdaptiveSettings) -> Self {
        let budget = match s.pairs {
            0 => candidates.div_ceil(2),
            b => b.min(candidates),
        };
        let auto = |f: f64| ((budget as f64 * f).round() as usize).max(MIN_BATCH);
        let first = match s.first {
            0 => auto(FIRST_FRACTION),
            n => n,
        }
        .min(budget);
        let batch = match s.batch {
            0 => auto(BATCH_FRACTION),
            n => n,
        };
        Self { budget, first, batch }
    }

    /// What [`Sizes::of`] took that `s` did not say, for `candidates` candidates: a
    /// budget past the candidates (all of them are measured), and a first batch that
    /// is the whole budget (nothing is chosen), each naming its key.
    pub fn notes(candidates: usize, s: &AdaptiveSettings) -> Vec<String> {
        let sizes = Self::of(candidates, s);
        let mut notes = Vec::new();
        if s.pairs > candidates {
            notes.push(format!(
                "recon.adaptive.pairs = {} is more than the {candidates} candidate pairs: all of them are the budget",
                s.pairs
            ));
        }
        if s.first > 0 && s.first >= sizes.budget && sizes.budget < candidates {
            notes.push(format!(
                "recon.adaptive.first = {} is the whole budget of {} pairs ({}): the fit chooses nothing; \
                 give a smaller first batch, or set recon.adaptive.pairs",
                s.first,
                sizes.budget,
                if s.pairs == 0 {
                    "half the candidates"
                } else {
                    "recon.adaptive.pairs"
                }
            ));
        } else if s.first == 0 && sizes.first >= sizes.budget && sizes.budget < candidates {
            notes.push(format!(
                "recon.adaptive.pairs = {} is no more than the first batch, which spreads at least {MIN_BATCH} pairs over the candidates: \
                 the fit chooses nothing; give a larger budget, or measure the candidates' own layout without mode = \"adaptive\"",
                s.pairs
            ));
        }
        notes
    }

    /// Choices the fit makes when the budget alone ends the capture.
    pub fn rounds(&self) -> usize {
        (self.budget - self.first).div_ceil(self.batch.max(1))
    }
}

/// Chooses the batches of an adaptive capture (or of a replay in another order) from
/// a fixed list of candidate pairs.
pub struct Selector {
    candidates: Vec<Pair>,
    /// The hidden path lengths each candidate's recording covers (or would).
    recorded: Vec<Recorded>,
    settings: AdaptiveSettings,
    order: Order,
    sizes: Sizes,
    measured: Vec<usize>,
    is_measured: Vec<bool>,
    /// Each candidate's distance to the nearest measured, kept as pairs are taken (a
    /// batch's choice then costs what the batch does, not a pass over the candidates
    /// for every pair measured before it).
    coverage: Coverage,
    /// The random order's permutation.
    shuffled: Vec<usize>,
    /// The stopping rule's reference: the gain it reads ([`Selector::next`]) at the first
    /// chosen batch whose fit saw anything.
    first_gain: Option<f64>,
    batches: usize,
    /// Why the selection stopped, once it has.
    stopped: Option<String>,
}

impl Selector {
    /// A selector over `candidates` (at least one).
    pub fn new(candidates: Vec<Pair>, settings: AdaptiveSettings, order: Order) -> Self {
        let n = candidates.len();
        let sizes = Sizes::of(n, &settings);
        let mut shuffled: Vec<usize> = (0..n).collect();
        shuffled.shuffle(&mut ChaCha8Rng::seed_from_u64(settings.seed));
        Self {
            recorded: vec![WHOLE_AXIS; n],
            candidates,
            settings,
            order,
            sizes,
            measured: Vec::new(),
            is_measured: vec![false; n],
            coverage: Coverage::new(n),
            shuffled,
            first_gain: None,
            batches: 0,
            stopped: None,
        }
    }

    /// Each candidate's recording covers only the hidden path lengths `recorded[i]`
    /// (its time window less its legs; without this, the whole axis): the information
    /// a candidate offers is what falls in its window, as the fit reads only those bins.
    pub fn with_recorded(mut self, recorded: Vec<Recorded>) -> Self {
        assert_eq!(
            recorded.len(),
            self.candidates.len(),
            "one recording per candidate"
        );
        self.recorded = recorded;
        self
    }

    /// The pairs the capture will measure at most.
    pub fn budget(&self) -> usize {
        self.sizes.budget
    }

    /// The candidates measured so far, in order.
    pub fn measured(&self) -> &[usize] {
        &self.measured
    }

    /// Why the selection ended before the budget, if it did.
    pub fn stopped(&self) -> Option<&str> {
        self.stopped.as_deref()
    }

    /// Ends the selection early: no batch is chosen after this (a live capture's time
    /// budget, `seconds`).
    pub fn stop(&mut self, why: String) {
        self.stopped.get_or_insert(why);
    }

    fn take(
        &mut self,
        batch: Vec<usize>,
        gains: Vec<f64>,
        explored: usize,
        how: &str,
        relative: Option<f64>,
    ) -> BatchChoice {
        let from = self.measured.last().map(|&i| self.candidates[i]);
        let order = tour(&self.candidates, &batch, from.as_ref());
        let gain_of: std::collections::HashMap<usize, f64> = batch.iter().copied().zip(gains).collect();
        let gains: Vec<f64> = order
            .iter()
            .map(|i| gain_of.get(i).copied().unwrap_or(0.0))
            .collect();
        let mut at = from;
        let mut travel_m = 0.0;
        for &i in &order {
            if let Some(p) = at {
                travel_m += travel(&p, &self.candidates[i]);
            }
            at = Some(self.candidates[i]);
        }
        for &i in &order {
            self.is_measured[i] = true;
            self.coverage.take(&self.candidates, i);
        }
        self.measured.extend_from_slice(&order);
        let choice = BatchChoice {
            batch: self.batches,
            how: how.into(),
            illumination: order.iter().map(|&i| self.candidates[i].xi.to_array()).collect(),
            detection: order.iter().map(|&i| self.candidates[i].xd.to_array()).collect(),
            pairs: order,
            gains,
            explored,
            relative_gain: relative,
            travel_m,
            measured: self.measured.len(),
        };
        self.batches += 1;
        choice
    }

    /// The first `n` candidates of the seeded shuffle not yet measured: the random
    /// order's next batch, whatever a resume marked measured before it.
    fn next_shuffled(&self, n: usize) -> Vec<usize> {
        self.shuffled
            .iter()
            .copied()
            .filter(|&i| !self.is_measured[i])
            .take(n)
            .collect()
    }

    /// Marks candidates already measured (a resumed capture's stored pairs, in the
    /// order they were measured), without choosing anything.
    pub fn resume(&mut self, measured: &[usize]) {
        for &i in measured {
            if i < self.candidates.len() && !self.is_measured[i] {
                self.is_measured[i] = true;
                self.coverage.take(&self.candidates, i);
                self.measured.push(i);
            }
        }
    }

    /// Batches chosen so far (the next one's number).
    pub fn batches(&self) -> usize {
        self.batches
    }

    /// Numbers the next batch on from `n` batches an earlier session chose and
    /// measured (a resumed capture; see [`Selector::resume`]).
    pub fn resume_batches(&mut self, n: usize) {
        self.batches = self.batches.max(n);
    }

    /// What is left of the first batch after [`Selector::resume`]: `None` when the
    /// pairs already measured cover it.
    pub fn first_rest(&mut self) -> Option<BatchChoice> {
        self.resumed_batch(&[])
    }

    /// A resumed capture's first batch (after [`Selector::resume`]): the candidates
    /// in `carried` an earlier session stopped in the middle of (their partial sums
    /// hold laser time already spent; as many as the budget has room for, in index
    /// order), then what is left of the first batch spread around every pair taken.
    /// Its `how` is `resumed` where it carries any, else `spread`. `None` when there
    /// is neither.
    pub fn resumed_batch(&mut self, carried: &[usize]) -> Option<BatchChoice> {
        let mut batch: Vec<usize> = carried
            .iter()
            .copied()
            .filter(|&i| i < self.candidates.len() && !self.is_measured[i])
            .collect();
        batch.sort_unstable();
        batch.dedup();
        batch.truncate(self.sizes.budget.saturating_sub(self.measured.len()));
        let n = self.sizes.first.saturating_sub(self.measured.len() + batch.len());
        let mut coverage = self.coverage.clone();
        for &i in &batch {
            coverage.take(&self.candidates, i);
        }
        let how = if batch.is_empty() { "spread" } else { "resumed" };
        let spread = farthest_points_from(&self.candidates, &coverage, n);
        let explored = spread.len();
        batch.extend(spread);
        if batch.is_empty() {
            return None;
        }
        let k = batch.len();
        Some(self.take(batch, vec![0.0; k], explored, how, None))
    }

    /// Another batch spread around what was measured: for a fit that has nothing to
    /// choose from yet (every histogram so far flagged and left out). `None` once the
    /// budget is spent.
    pub fn spread(&mut self) -> Option<BatchChoice> {
        let n = self
            .sizes
            .batch
            .min(self.sizes.budget.saturating_sub(self.measured.len()));
        if n == 0 || self.stopped.is_some() {
            return None;
        }
        let batch = farthest_points_from(&self.candidates, &self.coverage, n);
        let k = batch.len();
        Some(self.take(batch, vec![0.0; k], k, "spread", None))
    }

    /// The first batch: spread over the candidates (random in the random order).
    pub fn first(&mut self) -> BatchChoice {
        let n = self.sizes.first;
        match self.order {
            Order::Random => {
                let batch = self.next_shuffled(n);
                let k = batch.len();
                self.take(batch, vec![0.0; k], 0, "random", None)
            }
            Order::Adaptive | Order::Uniform => {
                let batch = farthest_points(&self.candidates, &[], n);
                let how = if self.order == Order::Uniform {
                    "uniform"
                } else {
                    "spread"
                };
                let k = batch.len();
                self.take(batch, vec![0.0; k], k, how, None)
            }
        }
    }

    /// The next batch, chosen from `model` (the fit after the measured pairs' live
    /// training) on the time axis `axis`; `None` once the budget is spent or the
    /// expected gain has fallen below `stop-gain`.
    pub fn next(&mut self, model: &LiveModel, axis: &TimeAxis) -> Option<BatchChoice> {
        let left = self.sizes.budget.saturating_sub(self.measured.len());
        if left == 0 || self.stopped.is_some() {
            return None;
        }
        let n = self.sizes.batch.min(left);
        match self.order {
            Order::Random => {
                let batch = self.next_shuffled(n);
                let k = batch.len();
                Some(self.take(batch, vec![0.0; k], 0, "random", None))
            }
            Order::Uniform => {
                let batch = farthest_points_from(&self.candidates, &self.coverage, n);
                let k = batch.len();
                Some(self.take(batch, vec![0.0; k], k, "uniform", None))
            }
            Order::Adaptive => self.next_adaptive(model, axis, n),
        }
    }

    fn next_adaptive(&mut self, model: &LiveModel, axis: &TimeAxis, n: usize) -> Option<BatchChoice> {
        let mut open: Vec<usize> = (0..self.candidates.len())
            .filter(|&i| !self.is_measured[i])
            .collect();
        if open.len() > MAX_SCORED {
            // A seeded sample, new each batch: the terms of every candidate of a huge
            // relay need not be held at once.
            let mut rng =
                ChaCha8Rng::seed_from_u64(self.settings.seed ^ (self.batches as u64).rotate_left(32));
            open = open.choose_multiple(&mut rng, MAX_SCORED).copied().collect();
            open.sort_unstable();
        }
        let pairs = |idx: &[usize]| -> Vec<Pair> { idx.iter().map(|&i| self.candidates[i]).collect() };
        let recorded = |idx: &[usize]| -> Vec<Recorded> { idx.iter().map(|&i| self.recorded[i]).collect() };
        let terms =
            |idx: &[usize]| terms_of(&model.kernels, &pairs(idx), &recorded(idx), axis, &model.options);
        let mut sums = InformationSums::new(model.kernels.len());
        for chunk in self.measured.chunks(MAX_SCORED) {
            sums.add(&terms(chunk));
        }
        let open_terms = terms(&open);
        let mut info = sums.finish(&open_terms);
        let by_gain = |n: usize| n - ((n as f64 * self.settings.explore).round() as usize).min(n);
        let mean_gain = |chosen: &[periscope_recon::adaptive::Choice]| {
            if chosen.is_empty() {
                0.0
            } else {
                chosen.iter().map(|c| c.gain).sum::<f64>() / chosen.len() as f64
            }
        };
        // The stopping rule and the events read the gain of the pairs the fit would
        // choose by gain alone: how much is left to learn, wherever it lies. The picks
        // that keep the spread gain less, by how far the best lie from the eligible.
        // As many as a whole batch chooses by gain, and at least one, so that a last,
        // short batch or one taken wholly by distance is not read as nothing left.
        let reference = by_gain(self.sizes.batch).max(1);
        let free = choose(&mut info.clone(), &open_terms, reference);
        let mean = mean_gain(&free);
        let chosen = if self.settings.coverage > 0.0 {
            choose_spread_near(
                &mut info,
                &open_terms,
                &pairs(&open),
                open.iter().map(|&i| self.coverage.nearest(i)).collect(),
                by_gain(n),
                self.settings.coverage,
            )
        } else {
            choose(&mut info, &open_terms, by_gain(n))
        };
        // The first batch whose pairs see anything sets the reference; until one does,
        // nothing is known to have fallen.
        if self.first_gain.is_none() && mean > 0.0 {
            self.first_gain = Some(mean);
        }
        let relative = self.first_gain.map(|first| mean / first);
        if let Some(relative) = relative
            && self.settings.stop_gain > 0.0
            && relative < self.settings.stop_gain
        {
            self.stopped = Some(format!(
                "the expected gain of the next batch fell to {relative:.3} of the first chosen batch's (adaptive.stop-gain = {})",
                self.settings.stop_gain
            ));
            return None;
        }
        let mut batch: Vec<usize> = chosen.iter().map(|c| open[c.index]).collect();
        let mut gains: Vec<f64> = chosen.iter().map(|c| c.gain).collect();
        // The rest by distance from everything measured or chosen: what the fit has
        // not found cannot ask to be looked at.
        let mut taken = self.coverage.clone();
        for &i in &batch {
            taken.take(&self.candidates, i);
        }
        let spread = farthest_points_from(&self.candidates, &taken, n - batch.len());
        let by_distance = spread.len();
        gains.extend(std::iter::repeat_n(0.0, by_distance));
        // With the spread kept, a pick no candidate within reach had a gain for was
        // taken by distance too.
        let explored = by_distance + chosen.iter().filter(|c| c.gain == 0.0).count();
        batch.extend(spread);
        Some(self.take(batch, gains, explored, "adaptive", relative))
    }
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DVec3};
    use periscope_recon::gtr::{Kernel, RenderOptions};

    use super::*;

    /// Sizes the settings did not say are told by key: a budget past the candidates,
    /// and a first batch that leaves the fit nothing to choose (until 2026-12-06 both
    /// were taken silently); the defaults say nothing.
    #[test]
    fn sizes_the_settings_did_not_say_are_noted_by_key() {
        let notes = |s: AdaptiveSettings| Sizes::notes(576, &s);
        assert!(notes(AdaptiveSettings::default()).is_empty());
        let n = notes(AdaptiveSettings {
            pairs: 5000,
            ..AdaptiveSettings::default()
        });
        assert!(
            n.len() == 1 && n[0].contains("recon.adaptive.pairs = 5000"),
            "{n:?}"
        );
        let n = notes(AdaptiveSettings {
            first: 1000,
            ..AdaptiveSettings::default()
        });
        assert!(
            n.len() == 1 && n[0].contains("recon.adaptive.first = 1000") && n[0].contains("288"),
            "{n:?}"
        );
        assert!(
            notes(AdaptiveSettings {
                pairs: 100,
                first: 40,
                ..AdaptiveSettings::default()
            })
            .is_empty()
        );
        // A budget the default first batch takes whole (it spreads at least 8).
        let n = notes(AdaptiveSettings {
            pairs: 6,
            ..AdaptiveSettings::default()
        });
        assert!(
            n.len() == 1 && n[0].contains("recon.adaptive.pairs = 6 is no more than the first batch"),
            "{n:?}"
        );
        assert!(
            notes(AdaptiveSettings {
                pairs: 9,
                ..AdaptiveSettings::default()
            })
            .is_empty()
        );
    }

    fn wall(n: usize) -> Vec<Pair> {
        (0..n * n)
            .map(|i| {
                let (x, y) = (
                    (i % n) as f64 / (n - 1) as f64 - 0.5,
                    (i / n) as f64 / (n - 1) as f64 - 0.5,
                );
                Pair::confocal(DVec3::new(x, y, 0.0), DVec3::Z)
            })
            .collect()
    }

    fn model(kernels: Vec<Kernel>) -> LiveModel {
        LiveModel {
            kernels,
            options: RenderOptions::default(),
            pairs: 0,
            step: 0,
        }
    }

    fn axis() -> TimeAxis {
        TimeAxis {
            start: 0.0,
            width: 0.01,
            bins: 400,
        }
    }

    /// A round primitive of 2 cm scale and unit albedo at (x, y, z).
    fn blob(x: f64, y: f64, z: f64) -> Kernel {
        Kernel::new(DVec3::new(x, y, z), DMat3::IDENTITY, DVec3::splat(0.02), 1.0)
    }

    /// Runs every order over a 12 × 12 wall to a budget of 60 pairs (a first batch of
    /// `first`, then batches of 16) after resuming from `stored`, with a fit that sees a
    /// target over one quadrant; each order's batch sizes and measured pairs.
    fn to_the_budget(stored: &[usize], first: usize) -> Vec<(Order, Vec<usize>, Vec<usize>)> {
        let target = blob(0.3, 0.3, 0.5);
        [Order::Adaptive, Order::Uniform, Order::Random]
            .into_iter()
            .map(|order| {
                let settings = AdaptiveSettings {
                    pairs: 60,
                    first,
                    batch: 16,
                    ..Default::default()
                };
                let mut s = Selector::new(wall(12), settings, order);
                s.resume(stored);
                let first = if stored.is_empty() {
                    Some(s.first())
                } else {
                    s.first_rest()
                };
                let mut sizes: Vec<usize> = first.iter().map(|b| b.pairs.len()).collect();
                while let Some(b) = s.next(&model(vec![target]), &axis()) {
                    sizes.push(b.pairs.len());
                }
                (order, sizes, s.measured().to_vec())
            })
            .collect()
    }

    /// How many different pairs `measured` holds.
    fn distinct(measured: &[usize]) -> usize {
        let mut m = measured.to_vec();
        m.sort_unstable();
        m.dedup();
        m.len()
    }

    #[test]
    fn every_order_measures_each_candidate_at_most_once_and_stops_at_the_budget() {
        for (order, sizes, measured) in to_the_budget(&[], 20) {
            assert_eq!(sizes, vec![20, 16, 16, 8], "{order}");
            assert_eq!(distinct(&measured), 60, "{order}");
        }
    }

    #[test]
    fn a_resumed_capture_measures_each_candidate_at_most_once_in_every_order() {
        // Stored pairs that are not the order's own prefix (another seed's shuffle, or
        // a capture resumed under another order): the rest of the budget goes to pairs
        // not yet measured.
        let stored: Vec<usize> = (0..144).rev().step_by(7).collect();
        for (order, sizes, measured) in to_the_budget(&stored, 30) {
            assert_eq!(sizes, vec![9, 16, 14], "{order}");
            assert_eq!(&measured[..stored.len()], &stored[..], "{order}");
            assert_eq!(distinct(&measured), 60, "{order}: a candidate measured twice");
        }
    }

    /// A resumed capture's first batch finishes the pairs stopped in the middle of
    /// (those not measured, as many as the budget has room for) and spreads what is
    /// left of the first batch around them and the pairs stored; past the first batch
    /// it is those pairs alone, and with none it is `first_rest`'s spread.
    #[test]
    fn a_resumed_batch_finishes_the_pairs_stopped_in_first() {
        let settings = |pairs, first| AdaptiveSettings {
            pairs,
            first,
            batch: 16,
            ..Default::default()
        };
        let resumed = |pairs, first, stored: &[usize], carried: &[usize]| {
            let mut s = Selector::new(wall(12), settings(pairs, first), Order::Adaptive);
            s.resume(stored);
            s.resumed_batch(carried)
        };
        // Inside the first batch: the carried pair (stored ones and out-of-range
        // indices ignored), then the spread, none of it stored.
        let b = resumed(60, 10, &[0, 143], &[143, 77, 77, 500]).unwrap();
        assert_eq!((b.how.as_str(), b.pairs.len(), b.explored), ("resumed", 8, 7));
        assert!(b.pairs.contains(&77) && !b.pairs.contains(&0) && !b.pairs.contains(&143));
        assert_eq!(distinct(&b.pairs), 8);
        // Past the first batch: the carried pairs alone, as many as the budget allows.
        let b = resumed(12, 10, &(0..10).collect::<Vec<_>>(), &[40, 30, 20]).unwrap();
        assert_eq!((b.how.as_str(), b.explored), ("resumed", 0));
        let mut pairs = b.pairs.clone();
        pairs.sort_unstable();
        assert_eq!(
            pairs,
            vec![20, 30],
            "the two the budget has room for, lowest first"
        );
        // Nothing carried: first_rest's spread, or nothing once the first batch is in.
        let b = resumed(60, 10, &[5], &[]).unwrap();
        assert_eq!((b.how.as_str(), b.pairs.len(), b.explored), ("spread", 9, 9));
        assert!(resumed(60, 10, &(0..10).collect::<Vec<_>>(), &[]).is_none());
    }

    /// A first batch of 16, then one of 32 chosen by gain alone (nothing taken for
    /// coverage), to a budget of 48.
    fn by_gain_alone() -> AdaptiveSettings {
        AdaptiveSettings {
            pairs: 48,
            first: 16,
            batch: 32,
            explore: 0.0,
            coverage: 0.0,
            ..Default::default()
        }
    }

    #[test]
    fn the_adaptive_order_looks_where_the_fit_sees_something() {
        // A target over one corner of the wall: with nothing explored, the chosen pairs
        // crowd towards it; uniform ones do not.
        let target = blob(0.35, 0.35, 0.3);
        let mean_distance = |order: Order| {
            let settings = by_gain_alone();
            let mut s = Selector::new(wall(16), settings, order);
            s.first();
            let b = s.next(&model(vec![target]), &axis()).unwrap();
            let wall = wall(16);
            b.pairs
                .iter()
                .map(|&i| wall[i].xi.truncate().distance(target.x.truncate()))
                .sum::<f64>()
                / b.pairs.len() as f64
        };
        let (adaptive, uniform) = (mean_distance(Order::Adaptive), mean_distance(Order::Uniform));
        assert!(
            adaptive < 0.7 * uniform,
            "adaptive {adaptive} m, uniform {uniform} m"
        );
    }

    /// Candidates near the target whose time window ends before its light arrives (a
    /// window short of the volume, their legs longer) are not chosen for it: they would
    /// record zeros the fit leaves out. Before, each was weighed as if it recorded the
    /// whole axis, and the batch went to them first.
    #[test]
    fn the_adaptive_order_passes_over_pairs_whose_window_misses_the_target() {
        let target = blob(0.35, 0.35, 0.3);
        let candidates = wall(16);
        let blind: Vec<bool> = candidates
            .iter()
            .map(|p| p.xi.truncate().distance(target.x.truncate()) < 0.25)
            .collect();
        let recorded: Vec<Recorded> = blind
            .iter()
            .map(|&b| if b { (0.0, 0.4) } else { WHOLE_AXIS })
            .collect();
        let settings = by_gain_alone();
        let batch = |recorded: Option<Vec<Recorded>>| {
            let s = Selector::new(candidates.clone(), settings.clone(), Order::Adaptive);
            let mut s = match recorded {
                Some(r) => s.with_recorded(r),
                None => s,
            };
            let first = s.first();
            let b = s.next(&model(vec![target]), &axis()).unwrap();
            (first.pairs, b.pairs)
        };
        let (first, chosen) = batch(Some(recorded));
        let blinded = chosen.iter().filter(|&&i| blind[i]).count();
        assert_eq!(blinded, 0, "{chosen:?}");
        // The same fit without the windows goes to them.
        let (first_all, chosen_all) = batch(None);
        assert_eq!(first, first_all, "the first batch is spread, not weighed");
        let blinded_all = chosen_all.iter().filter(|&&i| blind[i]).count();
        assert!(blinded_all >= 8, "{blinded_all} of {chosen_all:?}");
    }

    #[test]
    fn a_fit_that_sees_nothing_more_stops_the_capture_when_asked_to() {
        // Gains fall as pairs near the only target are measured; with a high stop-gain
        // the selector stops before the budget and says why.
        let target = blob(0.0, 0.0, 0.4);
        let settings = AdaptiveSettings {
            pairs: 200,
            first: 16,
            batch: 16,
            stop_gain: 0.9,
            explore: 0.0,
            ..Default::default()
        };
        let mut s = Selector::new(wall(16), settings, Order::Adaptive);
        s.first();
        let mut n = 0;
        while s.next(&model(vec![target]), &axis()).is_some() {
            n += 1;
            assert!(n < 20);
        }
        assert!(s.measured().len() < 200);
        assert!(s.stopped().unwrap().contains("stop-gain"), "{:?}", s.stopped());
    }

    /// The stopping rule reads the gain of a whole batch's picks by gain, and only
    /// from the first batch that sees anything: batches taken wholly by distance, of
    /// one pair, or the budget's short last one, and a first fit that sees nothing, do
    /// not end a capture that has not fallen. (It did: the gain of no picks was 0, and
    /// a reference of 0 read every later batch as fallen to nothing.)
    #[test]
    fn the_stopping_rule_needs_a_fall_from_a_batch_that_saw_something() {
        let target = blob(0.0, 0.0, 0.4);
        // Far beyond the time axis: no candidate sees it.
        let unseen = blob(0.0, 0.0, 40.0);
        let run = |explore: f64, batch: usize, pairs: usize, kernels: &[Vec<Kernel>]| {
            let settings = AdaptiveSettings {
                pairs,
                first: 16,
                batch,
                stop_gain: 0.01,
                explore,
                ..Default::default()
            };
            let mut s = Selector::new(wall(16), settings, Order::Adaptive);
            s.first();
            let mut relative = Vec::new();
            // The fits in turn, the last one's kernels from then on.
            for i in 0.. {
                let k = &kernels[i.min(kernels.len() - 1)];
                match s.next(&model(k.clone()), &axis()) {
                    Some(b) => relative.push(b.relative_gain),
                    None => break,
                }
            }
            (s.measured().len(), s.stopped().map(str::to_owned), relative)
        };
        let seen = [vec![target]];
        for (explore, batch) in [(1.0, 8), (0.5, 1)] {
            let (measured, stopped, relative) = run(explore, batch, 40, &seen);
            assert_eq!(
                measured, 40,
                "explore {explore}, batch {batch}: stopped early: {stopped:?}"
            );
            assert_eq!(relative[0], Some(1.0), "the first choice is the reference");
            assert!(
                relative.iter().all(|r| r.is_some_and(|r| r > 0.01)),
                "{relative:?}"
            );
        }
        // 16 + 2 × 8 + a last batch of 3.
        let (measured, stopped, _) = run(0.5, 8, 35, &seen);
        assert_eq!(measured, 35, "the short last batch was measured: {stopped:?}");
        // A first fit that sees nothing sets no reference; the next that does, does.
        let (measured, stopped, relative) = run(0.5, 8, 40, &[vec![unseen], vec![target]]);
        assert_eq!(measured, 40, "{stopped:?}");
        assert_eq!(relative[0], None, "nothing seen, nothing to compare with");
        assert_eq!(relative[1], Some(1.0));
    }

    #[test]
    fn settings_out_of_range_name_their_key() {
        let src = TomlSource::from_text("recon.toml", "");
        let bad = |raw: RawAdaptive| adaptive_settings(&src, "", raw).unwrap_err().to_string();
        let e = bad(RawAdaptive {
            stop_gain: Some(1.5),
            ..Default::default()
        });
        assert!(e.contains("adaptive.stop-gain"), "{e}");
        let e = bad(RawAdaptive {
            pairs: Some(10),
            first: Some(20),
            ..Default::default()
        });
        assert!(e.contains("adaptive.first"), "{e}");
        let e = bad(RawAdaptive {
            explore: Some(-0.1),
            ..Default::default()
        });
        assert!(e.contains("adaptive.explore"), "{e}");
        let e = bad(RawAdaptive {
            coverage: Some(f64::NAN),
            ..Default::default()
        });
        assert!(e.contains("adaptive.coverage"), "{e}");
    }
}

//! Where to measure next, from a running 3D-GTR fit: the information each candidate
//! pair would add about the primitives' positions (adaptive capture).
//!
//! A primitive's pulse in a pair's histogram, of `N` expected counts (the window's
//! amplitude), mean hidden path length μ and spread σ, locates the primitive's centre
//! along the path length's gradient `g = ui + ud` (the unit vectors from the two relay
//! points). Its Fisher information about the centre is rank one, `J = c g gᵀ`:
//! - Poisson counts (the fit's Poisson loss, background β per bin): `c = N/σ² · η`, the
//!   localisation precision of a pulse of N photons, with `η = p/(p + β)` for its peak
//!   bin's expected count `p` (the background's share of the variance there);
//! - noise-free data fitted by least squares (rendered captures, constant noise):
//!   `c = N²/σ³`, up to the noise variance, a constant shared by every pair.
//!
//! A pair records only part of the axis where its time window stops short of the
//! volume's paths (its legs shift the window; the fit reads only the bins it recorded,
//! [`crate::transient::TransientSet::recorded`]). A pulse cut by the window informs
//! only through the bins inside it, and its amplitude is learnt from those same bins:
//! its `c` is scaled by the share of the information about its place left once the
//! amplitude is fitted there, the Schur complement `ΔF − (Δφ)²/ΔΦ` over the recorded
//! `z = (L − μ)/σ`, with `F(z) = Φ(z) − z φ(z)`, under the Poisson model, and the same
//! at `√2 z` under least squares (whose weights are `φ²`); half a pulse holds
//! `1/2 − 1/π` of it ([`recorded_share`]).
//!
//! The pairs measured so far give primitive `k` the information `M_k = Σ J`. A
//! candidate's value is the D-optimal gain, the fall in the log-volume of every
//! primitive's uncertainty ellipsoid:
//! `Σ_k ln det(M_k + λI + J_k) − ln det(M_k + λI) = Σ_k ln(1 + c_k g_kᵀ (M_k + λI)⁻¹ g_k)`
//! (the matrix determinant lemma). The prior precision λ is the information a typical
//! measured pair gives a primitive it sees (the 90th percentile of `c|g|²` over the
//! measured pairs' terms), so the criterion does not depend on the data's scale. A
//! primitive no measured pair has located gains most from a pair that sees it; one
//! located along one direction gains most from a pair whose gradient is across it.
//!
//! The gain of a set of pairs is submodular (adding a pair never raises another's
//! gain), so a batch is chosen greedily with lazy re-evaluation: a candidate's stale
//! gain bounds its current one, and it is taken once its refreshed gain still leads.
use std::cmp::Ordering;
use std::collections::BinaryHeap;

use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::gtr::kernel::evaluate;
use crate::gtr::{Kernel, Loss, RenderOptions};
use crate::special::{INV_SQRT_2PI, norm_cdf, norm_pdf};
use crate::transient::{Pair, TimeAxis};

/// A term below this fraction of its pair's largest is dropped: it adds at most that
/// fraction of a nat to any gain, and keeping it would cost memory on every candidate.
const TERM_FLOOR: f64 = 1e-6;

/// A pair keeps at most this many terms, its strongest: a candidate's memory is then
/// bounded whatever the primitives (a diffuse early fit sees most of them from every
/// pair), and a term outside a pair's 512 strongest adds little to its gain.
pub const MAX_TERMS: usize = 512;

/// The percentile of the measured terms' `c|g|²` that sets the prior precision λ.
const PRIOR_PERCENTILE: f64 = 0.9;

/// One primitive's information from one pair: `c g gᵀ`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Term {
    /// The primitive's index in the kernels.
    pub primitive: u32,
    /// The information per unit of `|g|²` along `g`.
    pub c: f64,
    /// The path length's gradient with respect to the primitive's centre.
    pub g: DVec3,
}

impl Term {
    fn strength(&self) -> f64 {
        self.c * self.g.length_squared()
    }
}

/// The hidden path lengths `(from, to)`, metres, a pair's recording covers: its time
/// window less its legs.
pub type Recorded = (f64, f64);

/// A recording that covers the whole axis.
pub const WHOLE_AXIS: Recorded = (f64::NEG_INFINITY, f64::INFINITY);

/// The share of the information about its mean μ that a Gaussian pulse (spread σ)
/// gives through the path lengths `[from, to]`, its amplitude learnt from the same
/// bins. With `z = (L − μ)/σ`, the information about (amplitude, place) has densities
/// `(φ, z φ, z² φ)` under the Poisson model (no background) and `(φ², z φ², z² φ²)`
/// under least squares; the place's, the amplitude unknown, is the Schur complement
/// `ΔF − (Δφ)² / ΔΦ` with `F(z) = Φ(z) − z φ(z)`, the differences taken between the
/// limits at `z` (Poisson) or `√2 z` (least squares). On the whole line the amplitude
/// and the place are independent and the share is 1; half a pulse gives 0.18, not
/// 0.5. 0 for an empty range (or a spread that is not positive, or NaN).
pub fn recorded_share(mu: f64, sigma: f64, (from, to): Recorded, loss: Loss) -> f64 {
    if !(sigma > 0.0 && mu.is_finite()) || from.is_nan() || to.is_nan() {
        return 0.0;
    }
    let scale = match loss {
        Loss::Poisson { .. } => 1.0,
        Loss::L2 => std::f64::consts::SQRT_2,
    };
    // Φ, φ and F at a limit (their limits at ±∞).
    let at = |x: f64| {
        let z = scale * (x - mu) / sigma;
        if z.is_infinite() {
            let c = if z > 0.0 { 1.0 } else { 0.0 };
            (c, 0.0, c)
        } else {
            let (cdf, pdf) = (norm_cdf(z), norm_pdf(z));
            (cdf, pdf, cdf - z * pdf)
        }
    };
    let ((c0, p0, f0), (c1, p1, f1)) = (at(from), at(to));
    // The information's entries over the range (amplitude, amplitude × place, place),
    // each over the whole line's place entry; the place's information with the
    // amplitude unknown is their Schur complement.
    let (amplitude, both, place) = (c1 - c0, p0 - p1, f1 - f0);
    if !(amplitude > 0.0) {
        return 0.0;
    }
    (place - both * both / amplitude).clamp(0.0, 1.0)
}

/// The information `pair` gives each primitive of `kernels` it sees (terms of at
/// least a millionth of the largest, and the [`MAX_TERMS`] strongest at most), under
/// the noise model of `opt.loss`, through the bins of `axis` its recording covers
/// (`recorded`, [`WHOLE_AXIS`] for all) and the fit renders (the pulse's evaluated
/// window): a pulse they cut gives the share of its information that falls inside
/// ([`recorded_share`]), one the recording misses gives none.
pub fn pair_terms(
    kernels: &[Kernel],
    pair: &Pair,
    recorded: Recorded,
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Vec<Term> {
    // What the fit reads of a pulse: the bins it renders (its evaluated window, on the
    // axis) that the recording covers.
    let read = |lo: usize, hi: usize| {
        (
            recorded.0.max(axis.edge(lo as isize)),
            recorded.1.min(axis.edge(hi as isize)),
        )
    };
    let mut terms: Vec<Term> = kernels
        .iter()
        .enumerate()
        .filter_map(|(k, kernel)| {
            let e = evaluate(kernel, pair, axis, opt)?;
            let w = e.window;
            let (n, sigma) = (w.amplitude, w.sigma);
            if !(n > 0.0 && sigma > 0.0) {
                return None;
            }
            let c = match opt.loss {
                Loss::Poisson { background } => {
                    // The pulse's peak bin, and the share of its variance that is its own.
                    let peak = n * axis.width.min(sigma) * INV_SQRT_2PI / sigma;
                    n / (sigma * sigma) * peak / (peak + background.max(0.0))
                }
                Loss::L2 => n * n / (sigma * sigma * sigma),
            } * recorded_share(w.mu, sigma, read(w.lo, w.hi), opt.loss);
            let term = Term {
                primitive: k as u32,
                c,
                g: e.path_gradient(),
            };
            (term.strength() > 0.0 && term.strength().is_finite()).then_some(term)
        })
        .collect();
    let top = terms.iter().map(Term::strength).fold(0.0, f64::max);
    terms.retain(|t| t.strength() >= TERM_FLOOR * top);
    if terms.len() > MAX_TERMS {
        // The strongest, in primitive order (so the sums add in a fixed order).
        // Ties go to the lower primitive, so the cut does not rest on the sort.
        terms.select_nth_unstable_by(MAX_TERMS, |a, b| {
            b.strength()
                .total_cmp(&a.strength())
                .then(a.primitive.cmp(&b.primitive))
        });
        terms.truncate(MAX_TERMS);
        terms.sort_unstable_by_key(|t| t.primitive);
    }
    terms
}

/// [`pair_terms`] for every pair, each through its own recording (`recorded[i]` for
/// `pairs[i]`), in parallel.
pub fn terms_of(
    kernels: &[Kernel],
    pairs: &[Pair],
    recorded: &[Recorded],
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Vec<Vec<Term>> {
    assert_eq!(pairs.len(), recorded.len(), "one recording per pair");
    pairs
        .par_iter()
        .zip(recorded)
        .map(|(p, &r)| pair_terms(kernels, p, r, axis, opt))
        .collect()
}

/// What the measured pairs tell about each primitive's centre: the inverse of its
/// information plus the prior, `(M_k + λI)⁻¹`.
#[derive(Clone, Debug)]
pub struct Information {
    inverse: Vec<DMat3>,
    lambda: f64,
}

/// The measured pairs' information summed primitive by primitive, taken in as many
/// chunks as the caller likes (a large capture's terms need not be held at once), and
/// the strengths that set the prior.
#[derive(Clone, Debug)]
pub struct InformationSums {
    sums: Vec<DMat3>,
    /// The terms' strengths: of the `seen` so far, those whose place is a multiple of
    /// `stride` (1 until there are [`MAX_STRENGTHS`] of them).
    strengths: Vec<f64>,
    stride: usize,
    seen: usize,
}

/// Strengths held for the prior's percentile at most (16 MB). Beyond it every other
/// one held is dropped and the stride doubles: a fixed, evenly spread sample, so the
/// memory of a choice stays bounded however many pairs were measured. Every term
/// counts below it: 4,096 pairs of [`MAX_TERMS`] terms.
const MAX_STRENGTHS: usize = 1 << 21;

impl InformationSums {
    /// Nothing measured yet, for `primitives` primitives.
    pub fn new(primitives: usize) -> Self {
        Self {
            sums: vec![DMat3::ZERO; primitives],
            strengths: Vec::new(),
            stride: 1,
            seen: 0,
        }
    }

    /// Adds measured pairs' terms.
    pub fn add(&mut self, measured: &[Vec<Term>]) {
        for t in measured.iter().flatten() {
            let m = &mut self.sums[t.primitive as usize];
            *m += DMat3::from_cols(t.g * (t.c * t.g.x), t.g * (t.c * t.g.y), t.g * (t.c * t.g.z));
            self.keep_strength(t.strength());
        }
    }

    /// Holds `s` for the percentile, or passes over it (see [`MAX_STRENGTHS`]).
    fn keep_strength(&mut self, s: f64) {
        let place = self.seen;
        self.seen += 1;
        if !place.is_multiple_of(self.stride) {
            return;
        }
        self.strengths.push(s);
        if self.strengths.len() >= MAX_STRENGTHS {
            // Held strength i is place i·stride: keep the even i, the multiples of
            // twice the stride.
            let mut i = 0usize;
            self.strengths.retain(|_| {
                i += 1;
                !i.is_multiple_of(2)
            });
            self.stride *= 2;
        }
    }

    /// The information with its prior: λ from the measured terms, or from
    /// `candidates`' where no measured pair sees anything.
    pub fn finish(mut self, candidates: &[Vec<Term>]) -> Information {
        let lambda = percentile(&mut self.strengths)
            .or_else(|| prior_precision(candidates))
            .unwrap_or(1.0);
        let prior = DMat3::IDENTITY * lambda;
        Information {
            inverse: self.sums.iter().map(|m| (*m + prior).inverse()).collect(),
            lambda,
        }
    }
}

impl Information {
    /// The information of `primitives` primitives from the `measured` pairs' terms;
    /// λ from those terms, or from `candidates`' where no measured pair sees anything.
    pub fn new(primitives: usize, measured: &[Vec<Term>], candidates: &[Vec<Term>]) -> Self {
        let mut sums = InformationSums::new(primitives);
        sums.add(measured);
        sums.finish(candidates)
    }

    /// The prior precision λ.
    pub fn prior(&self) -> f64 {
        self.lambda
    }

    /// The D-optimal gain (nats) of measuring a pair with these terms next.
    pub fn gain(&self, terms: &[Term]) -> f64 {
        terms
            .iter()
            .map(|t| {
                let a = self.inverse[t.primitive as usize];
                (t.c * t.g.dot(a * t.g)).ln_1p()
            })
            .sum()
    }

    /// Adds a measured pair's terms (Sherman–Morrison on each primitive's inverse).
    pub fn add(&mut self, terms: &[Term]) {
        for t in terms {
            let a = &mut self.inverse[t.primitive as usize];
            let ag = *a * t.g;
            let denom = 1.0 + t.c * t.g.dot(ag);
            let scale = t.c / denom;
            *a -= DMat3::from_cols(ag * (ag.x * scale), ag * (ag.y * scale), ag * (ag.z * scale));
        }
    }
}

/// λ: the [`PRIOR_PERCENTILE`] of the terms' `c|g|²`; `None` when there are none.
fn prior_precision(terms: &[Vec<Term>]) -> Option<f64> {
    percentile(&mut terms.iter().flatten().map(Term::strength).collect::<Vec<_>>())
}

/// The [`PRIOR_PERCENTILE`] of `s` (reordered); `None` when empty or not above 0.
fn percentile(s: &mut [f64]) -> Option<f64> {
    if s.is_empty() {
        return None;
    }
    let i = ((s.len() - 1) as f64 * PRIOR_PERCENTILE).round() as usize;
    let (_, v, _) = s.select_nth_unstable_by(i, f64::total_cmp);
    (*v > 0.0).then_some(*v)
}

/// A candidate taken into a batch, and the gain it had when taken (nats, given the
/// measured pairs and the batch's earlier choices).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Choice {
    /// Its index in the candidates.
    pub index: usize,
    /// Its gain when chosen.
    pub gain: f64,
}

/// A heap entry: a candidate's gain as of a round, ordered by gain then by lower index.
struct Entry {
    gain: f64,
    index: usize,
    round: usize,
}

impl PartialEq for Entry {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}
impl Eq for Entry {}
impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        self.gain
            .total_cmp(&other.gain)
            .then_with(|| other.index.cmp(&self.index))
    }
}

/// The candidates that see anything, by their gain as of round 0.
fn ranked(info: &Information, candidates: &[Vec<Term>]) -> BinaryHeap<Entry> {
    candidates
        .par_iter()
        .enumerate()
        .map(|(index, terms)| Entry {
            gain: info.gain(terms),
            index,
            round: 0,
        })
        .collect::<Vec<_>>()
        .into_iter()
        .filter(|e| e.gain > 0.0)
        .collect()
}

/// Puts candidate `index` back into `heap` with its gain as of `round`, unless it no
/// longer sees anything.
fn refresh(
    heap: &mut BinaryHeap<Entry>,
    info: &Information,
    candidates: &[Vec<Term>],
    index: usize,
    round: usize,
) {
    let gain = info.gain(&candidates[index]);
    if gain > 0.0 {
        heap.push(Entry { gain, index, round });
    }
}

/// Chooses up to `n` of the `candidates` (each a pair's terms) greedily by gain, adding
/// each choice's information to `info` as it is taken; candidates whose gain is 0 (they
/// see nothing) are never taken. Deterministic: ties go to the lower index.
pub fn choose(info: &mut Information, candidates: &[Vec<Term>], n: usize) -> Vec<Choice> {
    let mut heap = ranked(info, candidates);
    let mut chosen = Vec::with_capacity(n.min(candidates.len()));
    while chosen.len() < n {
        let Some(top) = heap.pop() else { break };
        if top.round == chosen.len() {
            info.add(&candidates[top.index]);
            chosen.push(Choice {
                index: top.index,
                gain: top.gain,
            });
            continue;
        }
        refresh(&mut heap, info, candidates, top.index, chosen.len());
    }
    chosen
}

/// [`choose`] with the spread kept: each pick is the candidate of highest gain among
/// those at least `coverage` times as far from every pair of `taken` and every pick
/// before it as the farthest open candidate is (distance over both relay points, as
/// [`farthest_points`] measures it); where none of those sees anything, the farthest
/// itself, with gain 0. `coverage` 0 chooses by gain alone (as [`choose`], except that
/// it fills the batch by distance once no candidate sees anything), 1 by distance alone
/// (as [`farthest_points`] once something is taken; with nothing taken every candidate
/// is equally far, and the first pick is the one of highest gain).
///
/// `pairs` are the candidates' pairs, in the order of their `terms`. The picks then
/// leave no hole in the measured pairs much wider than the farthest-point order would,
/// and within that the fit's information decides: a fit of few pairs cannot see what it
/// has not found, and a refit of pairs crowded where the first fit looked sees the rest
/// of the scene worse (docs/adaptive.md).
pub fn choose_spread(
    info: &mut Information,
    terms: &[Vec<Term>],
    pairs: &[Pair],
    taken: &[Pair],
    n: usize,
    coverage: f64,
) -> Vec<Choice> {
    let mut spread = Spread::new(pairs);
    for p in taken {
        spread.relax(p);
    }
    choose_spread_near(info, terms, pairs, spread.nearest, n, coverage)
}

/// [`choose_spread`] with each candidate's squared distance to the nearest pair taken
/// given (`nearest`, infinite where none is; a [`Coverage`] keeps it), instead of
/// measured from every pair taken.
pub fn choose_spread_near(
    info: &mut Information,
    terms: &[Vec<Term>],
    pairs: &[Pair],
    nearest: Vec<f64>,
    n: usize,
    coverage: f64,
) -> Vec<Choice> {
    assert_eq!(terms.len(), pairs.len(), "one pair a candidate's terms");
    assert_eq!(nearest.len(), pairs.len(), "one distance a candidate");
    // Candidates by their last computed gain (lazy greedy, as in `choose`).
    let mut heap = ranked(info, terms);
    let mut spread = Spread {
        pairs,
        nearest,
        used: vec![false; pairs.len()],
    };
    let share = coverage.clamp(0.0, 1.0).powi(2);
    let mut chosen = Vec::with_capacity(n.min(terms.len()));
    let mut too_near = Vec::new();
    while chosen.len() < n {
        // The farthest open candidate, and the distance a pick must keep.
        let Some((far, far_d)) = spread.farthest() else {
            break;
        };
        let floor = if share == 0.0 {
            f64::NEG_INFINITY
        } else {
            share * far_d
        };
        // The first open candidate out of the heap that keeps the distance is the
        // best of them; those too near are set aside for later picks, whose floor
        // is lower.
        let pick = loop {
            let Some(top) = heap.pop() else { break None };
            if !spread.is_open(top.index) {
                continue;
            }
            if spread.nearest[top.index] < floor {
                too_near.push(top);
                continue;
            }
            if top.round == chosen.len() {
                break Some(top);
            }
            refresh(&mut heap, info, terms, top.index, chosen.len());
        };
        heap.extend(too_near.drain(..));
        let (index, gain) = match pick {
            Some(top) => {
                info.add(&terms[top.index]);
                (top.index, top.gain)
            }
            None => (far, 0.0),
        };
        spread.take(index);
        chosen.push(Choice { index, gain });
    }
    chosen
}

/// Which of a list of candidate pairs are taken, and each one's squared distance (over
/// both relay points) to the nearest taken: kept by a capture as it measures, one pass
/// over the candidates a pair, so that choosing a batch ([`farthest_points_from`],
/// [`choose_spread_near`]) costs what the batch does, not a pass for every pair
/// measured before it.
#[derive(Clone, Debug)]
pub struct Coverage {
    nearest: Vec<f64>,
    used: Vec<bool>,
}

impl Coverage {
    /// `n` candidates, none taken.
    pub fn new(n: usize) -> Self {
        Self {
            nearest: vec![f64::INFINITY; n],
            used: vec![false; n],
        }
    }

    /// Takes candidate `i` of `pairs` (the list this covers).
    pub fn take(&mut self, pairs: &[Pair], i: usize) {
        let mut spread = Spread {
            pairs,
            nearest: std::mem::take(&mut self.nearest),
            used: std::mem::take(&mut self.used),
        };
        spread.take(i);
        (self.nearest, self.used) = (spread.nearest, spread.used);
    }

    /// Candidate `i`'s squared distance to the nearest taken (infinite with none).
    pub fn nearest(&self, i: usize) -> f64 {
        self.nearest[i]
    }

    /// Whether any candidate is taken.
    pub fn any_taken(&self) -> bool {
        self.used.iter().any(|&u| u)
    }
}

/// Each pair's squared distance to the nearest pair taken, and which are taken: the
/// bookkeeping of [`farthest_points`] and [`choose_spread`].
struct Spread<'a> {
    pairs: &'a [Pair],
    nearest: Vec<f64>,
    used: Vec<bool>,
}

impl<'a> Spread<'a> {
    /// Nothing taken: every pair infinitely far.
    fn new(pairs: &'a [Pair]) -> Self {
        Self {
            pairs,
            nearest: vec![f64::INFINITY; pairs.len()],
            used: vec![false; pairs.len()],
        }
    }

    /// Brings every pair's distance down to `from`'s where that is nearer.
    fn relax(&mut self, from: &Pair) {
        self.nearest
            .par_iter_mut()
            .zip(self.pairs.par_iter())
            .for_each(|(d, p)| *d = d.min(pair_distance_squared(p, from)));
    }

    /// Takes pair `i`: it is no longer open, and the others are measured from it too.
    fn take(&mut self, i: usize) {
        self.used[i] = true;
        self.relax(&self.pairs[i]);
    }

    fn is_open(&self, i: usize) -> bool {
        !self.used[i]
    }

    /// The open pair farthest from those taken, and its squared distance; ties go to
    /// the lower index.
    fn farthest(&self) -> Option<(usize, f64)> {
        self.nearest
            .iter()
            .enumerate()
            .filter(|(i, _)| !self.used[*i])
            .max_by(|a, b| a.1.total_cmp(b.1).then_with(|| b.0.cmp(&a.0)))
            .map(|(i, d)| (i, *d))
    }
}

/// The distance between two pairs: both relay points' displacements together.
fn pair_distance_squared(a: &Pair, b: &Pair) -> f64 {
    a.xi.distance_squared(b.xi) + a.xd.distance_squared(b.xd)
}

/// Up to `n` of `pairs` not in `taken`, each the farthest from every pair taken or
/// chosen before it (distance over both relay points): a space-filling order over any
/// relay and any pair layout. With nothing taken, the first is the pair nearest the
/// pairs' mean. Deterministic: ties go to the lower index.
pub fn farthest_points(pairs: &[Pair], taken: &[usize], n: usize) -> Vec<usize> {
    if n == 0 {
        return Vec::new();
    }
    let mut spread = Spread::new(pairs);
    for &i in taken {
        spread.take(i);
    }
    if taken.is_empty() && !pairs.is_empty() {
        let k = pairs.len() as f64;
        let mean = pairs
            .iter()
            .fold(Pair::confocal(DVec3::ZERO, DVec3::Z), |m, p| Pair {
                xi: m.xi + p.xi / k,
                xd: m.xd + p.xd / k,
                ..m
            });
        for (d, p) in spread.nearest.iter_mut().zip(pairs) {
            *d = -pair_distance_squared(p, &mean);
        }
    }
    farthest_loop(spread, n, taken.is_empty())
}

/// [`farthest_points`] after the pairs `coverage` has taken (of `pairs`, the list it
/// covers): the same picks, without a pass over the candidates for each pair taken.
pub fn farthest_points_from(pairs: &[Pair], coverage: &Coverage, n: usize) -> Vec<usize> {
    assert_eq!(coverage.nearest.len(), pairs.len(), "the coverage of these pairs");
    if n == 0 {
        return Vec::new();
    }
    if !coverage.any_taken() {
        return farthest_points(pairs, &[], n);
    }
    let spread = Spread {
        pairs,
        nearest: coverage.nearest.clone(),
        used: coverage.used.clone(),
    };
    farthest_loop(spread, n, false)
}

fn farthest_loop(mut spread: Spread<'_>, n: usize, from_the_mean: bool) -> Vec<usize> {
    let mut out = Vec::with_capacity(n.min(spread.pairs.len()));
    while out.len() < n {
        let Some((i, _)) = spread.farthest() else { break };
        out.push(i);
        if out.len() == 1 && from_the_mean {
            spread.nearest.fill(f64::INFINITY);
        }
        spread.take(i);
    }
    out
}

/// The galvos' travel between two pairs: the longer of the two relay points' moves
/// (the arms move at once).
pub fn travel(a: &Pair, b: &Pair) -> f64 {
    a.xi.distance(b.xi).max(a.xd.distance(b.xd))
}

/// `chosen` (indices into `pairs`) in the order a nearest-neighbour tour visits them
/// from `from` (the last pair measured; else the first chosen): the batch's
/// information does not depend on its order, the galvos' travel does.
pub fn tour(pairs: &[Pair], chosen: &[usize], from: Option<&Pair>) -> Vec<usize> {
    let mut left: Vec<usize> = chosen.to_vec();
    let mut out = Vec::with_capacity(left.len());
    let mut at = match from {
        Some(p) => *p,
        None => match left.first() {
            Some(&i) => pairs[i],
            None => return out,
        },
    };
    while !left.is_empty() {
        let (j, _) = left
            .iter()
            .enumerate()
            .min_by(|a, b| {
                travel(&at, &pairs[*a.1])
                    .total_cmp(&travel(&at, &pairs[*b.1]))
                    .then_with(|| a.1.cmp(b.1))
            })
            .expect("not empty");
        let i = left.swap_remove(j);
        at = pairs[i];
        out.push(i);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wall(n: usize, pitch: f64) -> Vec<Pair> {
        let mut out = Vec::new();
        for y in 0..n {
            for x in 0..n {
                let c = DVec3::new(
                    (x as f64 - (n - 1) as f64 / 2.0) * pitch,
                    (y as f64 - (n - 1) as f64 / 2.0) * pitch,
                    0.0,
                );
                out.push(Pair::confocal(c, DVec3::Z));
            }
        }
        out
    }

    fn axis() -> TimeAxis {
        TimeAxis {
            start: 0.0,
            width: 0.005,
            bins: 512,
        }
    }

    fn whole(pairs: &[Pair]) -> Vec<Recorded> {
        vec![WHOLE_AXIS; pairs.len()]
    }

    fn kernel(x: DVec3, rho: f64) -> Kernel {
        Kernel::new(x, DMat3::IDENTITY, DVec3::splat(0.01), rho)
    }

    /// However many terms are measured, the strengths held for the prior stay under
    /// the cap, as an even sample whose 90th percentile is the whole set's.
    #[test]
    fn the_strengths_held_for_the_prior_stay_bounded_and_representative() {
        let mut sums = InformationSums::new(1);
        let n = 5 * MAX_STRENGTHS / 2;
        // Strengths 1..=n in a scrambled but fixed order.
        for i in 0..n {
            sums.keep_strength(((i * 7_919) % n + 1) as f64);
        }
        assert!(
            sums.strengths.len() < MAX_STRENGTHS,
            "{} held",
            sums.strengths.len()
        );
        assert!(
            sums.strengths.len() > MAX_STRENGTHS / 4,
            "{} held",
            sums.strengths.len()
        );
        assert_eq!(sums.stride, 4, "thinned twice");
        let p = percentile(&mut sums.strengths).expect("positive strengths");
        let truth = 0.9 * n as f64;
        assert!(
            (p - truth).abs() < 1e-3 * truth,
            "90th percentile {p} against {truth}"
        );
        // Below the cap every strength is held.
        let mut few = InformationSums::new(1);
        for i in 0..1_000 {
            few.keep_strength(i as f64);
        }
        assert_eq!(few.strengths.len(), 1_000);
    }

    #[test]
    fn the_gain_of_a_pair_falls_once_a_pair_like_it_is_measured() {
        let kernels = vec![kernel(DVec3::new(0.0, 0.0, 0.5), 1.0)];
        let pairs = wall(5, 0.1);
        let opt = RenderOptions::default();
        let terms = terms_of(&kernels, &pairs, &whole(&pairs), &axis(), &opt);
        let mut info = Information::new(1, &[], &terms);
        let before: Vec<f64> = terms.iter().map(|t| info.gain(t)).collect();
        assert!(before.iter().all(|g| *g > 0.0), "{before:?}");
        info.add(&terms[12]);
        let after: Vec<f64> = terms.iter().map(|t| info.gain(t)).collect();
        for (b, a) in before.iter().zip(&after) {
            assert!(a < b, "a measurement raised a gain: {b} -> {a}");
        }
        // The pair measured and its neighbours lose most; a corner, whose gradient
        // points another way, keeps more of its gain.
        let lost = |i: usize| after[i] / before[i];
        assert!(lost(12) < lost(0), "{} vs {}", lost(12), lost(0));
    }

    #[test]
    fn sherman_morrison_matches_the_inverse_of_the_summed_information() {
        let kernels = vec![kernel(DVec3::new(0.05, -0.02, 0.6), 0.7)];
        let pairs = wall(4, 0.2);
        let opt = RenderOptions::default();
        let terms = terms_of(&kernels, &pairs, &whole(&pairs), &axis(), &opt);
        // Half summed and inverted, half added by Sherman–Morrison.
        let (first, rest) = terms.split_at(terms.len() / 2);
        let mut info = Information::new(1, first, &[]);
        for t in rest {
            info.add(t);
        }
        let mut m = DMat3::IDENTITY * info.prior();
        for t in terms.iter().flatten() {
            m += DMat3::from_cols(t.g * (t.c * t.g.x), t.g * (t.c * t.g.y), t.g * (t.c * t.g.z));
        }
        let exact = m.inverse();
        let got = info.inverse[0];
        let scale = exact.to_cols_array().iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for (a, b) in got.to_cols_array().iter().zip(exact.to_cols_array()) {
            assert!((a - b).abs() <= 1e-9 * scale, "{a} vs {b}");
        }
    }

    #[test]
    fn a_batch_starts_with_the_pair_that_sees_most_and_chooses_each_pair_once() {
        // One primitive over the centre of a wall: the pair straight below it (nearest,
        // cosines 1) locates it best; each later choice gains less, none repeats.
        let kernels = vec![kernel(DVec3::new(0.0, 0.0, 0.4), 1.0)];
        let pairs = wall(9, 0.1);
        let opt = RenderOptions::default();
        let terms = terms_of(&kernels, &pairs, &whole(&pairs), &axis(), &opt);
        let mut info = Information::new(1, &[], &terms);
        let chosen = choose(&mut info, &terms, 20);
        assert_eq!(chosen.len(), 20);
        assert_eq!(chosen[0].index, 40, "{chosen:?}");
        assert!(chosen.windows(2).all(|w| w[0].gain >= w[1].gain), "{chosen:?}");
        let mut seen: Vec<usize> = chosen.iter().map(|c| c.index).collect();
        seen.sort();
        seen.dedup();
        assert_eq!(seen.len(), 20);
        // Lazy greedy takes what plain greedy (every gain refreshed each time) takes.
        let mut plain = Information::new(1, &[], &terms);
        let mut left: Vec<usize> = (0..pairs.len()).collect();
        for c in &chosen {
            let best = left
                .iter()
                .copied()
                .max_by(|a, b| {
                    plain
                        .gain(&terms[*a])
                        .total_cmp(&plain.gain(&terms[*b]))
                        .then_with(|| b.cmp(a))
                })
                .unwrap();
            assert_eq!(best, c.index);
            assert!((plain.gain(&terms[best]) - c.gain).abs() <= 1e-12 * c.gain);
            plain.add(&terms[best]);
            left.retain(|i| *i != best);
        }
        // Deterministic.
        let mut again = Information::new(1, &[], &terms);
        assert_eq!(choose(&mut again, &terms, 20), chosen);
    }

    #[test]
    fn a_spread_batch_keeps_its_distance_and_chooses_by_gain_within_it() {
        // One primitive over a corner of a wall whose centre was measured: by gain
        // alone the batch crowds that corner; with the spread kept, every pick is at
        // least `coverage` times as far from the pairs before it as the farthest open
        // candidate was, and among those the ones nearer the primitive come first.
        let kernels = vec![kernel(DVec3::new(0.3, 0.3, 0.4), 1.0)];
        let pairs = wall(9, 0.1);
        let opt = RenderOptions::default();
        let terms = terms_of(&kernels, &pairs, &whole(&pairs), &axis(), &opt);
        let taken = [pairs[40]];
        let spread_of = |idx: &[usize]| {
            // The largest distance from any open pair to the pairs taken or chosen.
            let near: Vec<Pair> = taken
                .iter()
                .copied()
                .chain(idx.iter().map(|&i| pairs[i]))
                .collect();
            (0..pairs.len())
                .filter(|i| *i != 40 && !idx.contains(i))
                .map(|i| {
                    near.iter()
                        .map(|p| pair_distance_squared(&pairs[i], p))
                        .fold(f64::INFINITY, f64::min)
                        .sqrt()
                })
                .fold(0.0, f64::max)
        };
        let mut greedy = Information::new(1, &terms[40..41], &terms);
        let by_gain: Vec<usize> = choose(&mut greedy, &terms, 8).iter().map(|c| c.index).collect();
        let mut info = Information::new(1, &terms[40..41], &terms);
        let spread = choose_spread(&mut info, &terms, &pairs, &taken, 8, 0.7);
        let idx: Vec<usize> = spread.iter().map(|c| c.index).collect();
        assert_eq!(idx.len(), 8);
        for (k, c) in spread.iter().enumerate() {
            let before = &idx[..k];
            let near: Vec<Pair> = taken
                .iter()
                .copied()
                .chain(before.iter().map(|&i| pairs[i]))
                .collect();
            let d = near
                .iter()
                .map(|p| pair_distance_squared(&pairs[c.index], p))
                .fold(f64::INFINITY, f64::min)
                .sqrt();
            assert!(d >= 0.7 * spread_of(before) - 1e-12, "pick {k} at {d} m");
        }
        assert!(
            spread_of(&idx) < spread_of(&by_gain),
            "the spread batch leaves a hole {} m wide, by gain alone {} m",
            spread_of(&idx),
            spread_of(&by_gain)
        );
        // The first pick is the eligible pair of highest gain, near the primitive, not
        // the farthest-point order's first (the lowest-index corner).
        let fresh = Information::new(1, &terms[40..41], &terms);
        let reach = 0.7 * spread_of(&[]);
        let best = (0..pairs.len())
            .filter(|&i| pairs[i].xi.distance(pairs[40].xi) * 2f64.sqrt() >= reach - 1e-12)
            .max_by(|&a, &b| fresh.gain(&terms[a]).total_cmp(&fresh.gain(&terms[b])))
            .unwrap();
        assert_eq!(idx[0], best, "{idx:?}");
        assert_ne!(idx[0], farthest_points(&pairs, &[40], 1)[0]);
        assert!(pairs[idx[0]].xi.x > 0.2 && pairs[idx[0]].xi.y > 0.2, "{idx:?}");
        assert!(spread[0].gain > 0.0);
        // Coverage 0 takes what `choose` takes; coverage 1 what `farthest_points` takes.
        let mut a = Information::new(1, &terms[40..41], &terms);
        let none: Vec<usize> = choose_spread(&mut a, &terms, &pairs, &taken, 8, 0.0)
            .iter()
            .map(|c| c.index)
            .collect();
        assert_eq!(none, by_gain);
        let mut b = Information::new(1, &terms[40..41], &terms);
        let all = choose_spread(&mut b, &terms, &pairs, &taken, 4, 1.0);
        let mut far: Vec<usize> = all.iter().map(|c| c.index).collect();
        far.sort();
        assert_eq!(far, vec![0, 8, 72, 80]);
        // Deterministic.
        let mut again = Information::new(1, &terms[40..41], &terms);
        assert_eq!(choose_spread(&mut again, &terms, &pairs, &taken, 8, 0.7), spread);
    }

    #[test]
    fn a_pair_keeps_its_strongest_terms_only() {
        // More primitives than a pair keeps terms for: the nearest (strongest) stay.
        let kernels: Vec<Kernel> = (0..MAX_TERMS + 300)
            .map(|i| kernel(DVec3::new(0.0, 0.0, 0.3 + 0.001 * i as f64), 1.0))
            .collect();
        let pair = Pair::confocal(DVec3::ZERO, DVec3::Z);
        let terms = pair_terms(&kernels, &pair, WHOLE_AXIS, &axis(), &RenderOptions::default());
        assert_eq!(terms.len(), MAX_TERMS);
        assert!(terms.windows(2).all(|w| w[0].primitive < w[1].primitive));
        assert_eq!(terms.last().unwrap().primitive as usize, MAX_TERMS - 1);
    }

    /// The closed forms against the integrals they stand for, by the midpoint rule: the
    /// Schur complement of the (amplitude, place) information over the range, over the
    /// place's information on the whole line.
    #[test]
    fn the_recorded_share_is_the_information_the_range_holds() {
        let (mu, sigma) = (1.3, 0.04);
        let poisson = Loss::Poisson { background: 0.0 };
        let numeric = |(from, to): Recorded, loss: Loss| {
            // The densities of the (amplitude, both, place) entries at x.
            let density = |x: f64| {
                let z = (x - mu) / sigma;
                let w = match loss {
                    Loss::Poisson { .. } => norm_pdf(z),
                    Loss::L2 => norm_pdf(z).powi(2),
                };
                [w, z * w, z * z * w]
            };
            let integral = |a: f64, b: f64| {
                let n = 200_000;
                let h = (b - a) / n as f64;
                (0..n).fold([0.0; 3], |s, i| {
                    let d = density(a + (i as f64 + 0.5) * h);
                    [s[0] + d[0] * h, s[1] + d[1] * h, s[2] + d[2] * h]
                })
            };
            let clip = |x: f64| x.clamp(mu - 12.0 * sigma, mu + 12.0 * sigma);
            let whole = integral(mu - 12.0 * sigma, mu + 12.0 * sigma)[2];
            let [aa, am, mm] = integral(clip(from), clip(to));
            if aa > 0.0 {
                (mm - am * am / aa) / whole
            } else {
                0.0
            }
        };
        for loss in [poisson, Loss::L2] {
            assert_eq!(recorded_share(mu, sigma, WHOLE_AXIS, loss), 1.0);
            assert_eq!(recorded_share(mu, sigma, (mu + 1.0, mu - 1.0), loss), 0.0);
            assert_eq!(recorded_share(0.0, 0.0, WHOLE_AXIS, loss), 0.0);
            let half = recorded_share(mu, sigma, (f64::NEG_INFINITY, mu), loss);
            assert!(
                (half - (0.5 - 2.0 * norm_pdf(0.0).powi(2))).abs() < 1e-12,
                "{half}"
            );
            for range in [
                (mu - 0.3 * sigma, mu + 1.7 * sigma),
                (mu + 0.5 * sigma, f64::INFINITY),
                (0.0, mu - 2.0 * sigma),
                (0.0, mu),
            ] {
                let (closed, integral) = (recorded_share(mu, sigma, range, loss), numeric(range, loss));
                assert!(
                    (closed - integral).abs() < 1e-6,
                    "{loss:?} {range:?}: {closed} against {integral}"
                );
            }
        }
    }

    /// A pair whose window stops before a primitive's pulse tells nothing about it; one
    /// whose window stops at the pulse's middle, 0.18 of the whole (half the pulse,
    /// whose amplitude must be learnt from the same bins).
    #[test]
    fn a_pair_informs_only_through_the_bins_its_window_records() {
        let kernels = vec![kernel(DVec3::new(0.0, 0.0, 0.5), 1.0)];
        let pair = Pair::confocal(DVec3::ZERO, DVec3::Z);
        let opt = RenderOptions {
            loss: Loss::Poisson { background: 0.0 },
            ..Default::default()
        };
        let whole = pair_terms(&kernels, &pair, WHOLE_AXIS, &axis(), &opt);
        assert_eq!(whole.len(), 1);
        let mu = evaluate(&kernels[0], &pair, &axis(), &opt).unwrap().window.mu;
        assert!(pair_terms(&kernels, &pair, (0.0, mu - 0.2), &axis(), &opt).is_empty());
        let half = pair_terms(&kernels, &pair, (0.0, mu), &axis(), &opt);
        assert_eq!(half.len(), 1);
        // 1/2 − 1/π, less the evaluated window's tails beyond 4 σ.
        let expected = 0.5 - std::f64::consts::FRAC_1_PI;
        assert!(
            (half[0].c / whole[0].c - expected).abs() < 2e-3,
            "{half:?} {whole:?}"
        );
        assert_eq!(half[0].g, whole[0].g);
        // Past the axis's end counts as unrecorded too: the fit reads no bin there.
        let short = TimeAxis {
            bins: (mu / axis().width).round() as usize,
            ..axis()
        };
        let cut = pair_terms(&kernels, &pair, WHOLE_AXIS, &short, &opt);
        assert!(cut.len() == 1 && cut[0].c < 0.3 * whole[0].c, "{cut:?}");
    }

    #[test]
    fn pairs_that_see_nothing_are_never_chosen() {
        // Behind the wall: no pair sees the primitive.
        let kernels = vec![kernel(DVec3::new(0.0, 0.0, -0.4), 1.0)];
        let pairs = wall(3, 0.1);
        let terms = terms_of(
            &kernels,
            &pairs,
            &whole(&pairs),
            &axis(),
            &RenderOptions::default(),
        );
        assert!(terms.iter().all(Vec::is_empty));
        let mut info = Information::new(1, &[], &terms);
        assert!(choose(&mut info, &terms, 4).is_empty());
        // Keeping the spread, each pick falls back to the farthest pair, with gain 0.
        let spread = choose_spread(&mut info, &terms, &pairs, &[pairs[4]], 4, 0.7);
        let idx: Vec<usize> = spread.iter().map(|c| c.index).collect();
        assert_eq!(idx, farthest_points(&pairs, &[4], 4));
        assert!(spread.iter().all(|c| c.gain == 0.0), "{spread:?}");
    }

    /// A coverage kept pair by pair picks what the pairs taken, given whole, pick.
    #[test]
    fn a_kept_coverage_picks_as_the_taken_pairs_do() {
        let pairs = wall(9, 0.05);
        let taken = [40, 3, 77, 12, 58];
        let mut coverage = Coverage::new(pairs.len());
        assert!(!coverage.any_taken());
        assert_eq!(
            farthest_points_from(&pairs, &coverage, 6),
            farthest_points(&pairs, &[], 6)
        );
        for &i in &taken {
            coverage.take(&pairs, i);
        }
        assert_eq!(
            farthest_points_from(&pairs, &coverage, 12),
            farthest_points(&pairs, &taken, 12)
        );
        let open: Vec<usize> = (0..pairs.len()).filter(|i| !taken.contains(i)).collect();
        let open_pairs: Vec<Pair> = open.iter().map(|&i| pairs[i]).collect();
        let taken_pairs: Vec<Pair> = taken.iter().map(|&i| pairs[i]).collect();
        let terms: Vec<Vec<Term>> = open
            .iter()
            .map(|&i| {
                vec![Term {
                    primitive: (i % 7) as u32,
                    c: 1.0 + (i % 5) as f64,
                    g: DVec3::new(1.0, (i % 3) as f64, 0.5),
                }]
            })
            .collect();
        let mut a = Information::new(7, &[], &terms);
        let mut b = a.clone();
        let whole = choose_spread(&mut a, &terms, &open_pairs, &taken_pairs, 8, 0.6);
        let near = open.iter().map(|&i| coverage.nearest(i)).collect();
        let kept = choose_spread_near(&mut b, &terms, &open_pairs, near, 8, 0.6);
        let idx = |c: &[Choice]| c.iter().map(|c| c.index).collect::<Vec<_>>();
        assert_eq!(idx(&whole), idx(&kept));
    }

    #[test]
    fn farthest_points_start_central_and_fill_the_aperture() {
        let pairs = wall(5, 0.1);
        let order = farthest_points(&pairs, &[], 5);
        assert_eq!(order[0], 12, "the centre first");
        // Then the corners.
        let mut corners = order[1..5].to_vec();
        corners.sort();
        assert_eq!(corners, vec![0, 4, 20, 24]);
        // Taken pairs are skipped and pushed from.
        let more = farthest_points(&pairs, &order, 25);
        assert_eq!(more.len(), 20);
        assert!(more.iter().all(|i| !order.contains(i)));
    }

    #[test]
    fn a_tour_visits_each_chosen_pair_once_and_travels_less_than_the_given_order() {
        let pairs = wall(6, 0.1);
        let chosen: Vec<usize> = vec![0, 35, 5, 30, 1, 34, 6, 29];
        let path = tour(&pairs, &chosen, Some(&pairs[0]));
        let mut sorted = path.clone();
        sorted.sort();
        let mut expect = chosen.clone();
        expect.sort();
        assert_eq!(sorted, expect);
        let length =
            |order: &[usize]| -> f64 { order.windows(2).map(|w| travel(&pairs[w[0]], &pairs[w[1]])).sum() };
        assert!(
            length(&path) < length(&chosen),
            "{} vs {}",
            length(&path),
            length(&chosen)
        );
    }
}

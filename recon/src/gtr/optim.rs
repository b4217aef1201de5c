//! AdamW (Loshchilov & Hutter) with one learning rate and weight decay per parameter
//! group, and a step/epoch schedule: linear warm-up, then milestone decay.
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{GaussianCloud, RawGrads};

/// Primitives per parallel work item of an update (eight at the default 2,000).
const PRIMITIVE_CHUNK: usize = 256;

/// Learning rate and decoupled weight decay of one parameter group.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupSettings {
    /// Learning rate (step size in raw-parameter units).
    pub lr: f64,
    /// Decoupled weight decay coefficient (0 = plain Adam).
    pub weight_decay: f64,
}

/// Settings of every group plus Adam's constants.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamWSettings {
    /// Centres (θx).
    pub centres: GroupSettings,
    /// Scales (θs).
    pub scales: GroupSettings,
    /// Rotations (raw quaternions).
    pub rotations: GroupSettings,
    /// Albedo (θρ).
    pub albedo: GroupSettings,
    /// First-moment decay β1.
    pub beta1: f64,
    /// Second-moment decay β2.
    pub beta2: f64,
    /// Denominator guard ε.
    pub eps: f64,
}

impl Default for AdamWSettings {
    fn default() -> Self {
        let g = |lr| GroupSettings {
            lr,
            weight_decay: 0.0,
        };
        Self {
            centres: g(0.01),
            scales: g(0.01),
            rotations: g(0.005),
            albedo: g(0.02),
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-12,
        }
    }
}

/// Learning-rate schedule: a multiplier on every group's rate.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Schedule {
    /// Steps over which the rate rises linearly from 0 to its full value.
    pub warmup_steps: usize,
    /// Fractions of the counted epochs after which the rate is multiplied by `gamma`:
    /// a fraction f takes effect from epoch ⌊f·epochs⌋ (at least 1), so `[1/3, 2/3]`
    /// decays at epochs 5 and 10 of 16.
    pub milestones: Vec<f64>,
    /// The decay factor at each milestone.
    pub gamma: f64,
}

impl Default for Schedule {
    fn default() -> Self {
        Self {
            warmup_steps: 20,
            milestones: Vec::new(),
            gamma: 0.5,
        }
    }
}

impl Schedule {
    /// The multiplier at optimiser step `step` (counted from 0) during counted epoch
    /// `epoch` of `epochs` (0 during the live epochs of a streamed fit).
    pub fn factor(&self, step: usize, epoch: usize, epochs: usize) -> f64 {
        let warm = if self.warmup_steps == 0 {
            1.0
        } else {
            ((step + 1) as f64 / self.warmup_steps as f64).min(1.0)
        };
        let passed = self
            .milestones
            .iter()
            .filter(|&&f| epoch >= Self::milestone_epoch(f, epochs))
            .count();
        warm * self.gamma.powi(passed as i32)
    }

    /// The counted epoch from which the milestone at fraction `f` of `epochs` applies:
    /// ⌊f·epochs⌋, at least 1 (the tiny slack keeps ⌊(1/3)·15⌋ at 5 despite rounding).
    pub fn milestone_epoch(f: f64, epochs: usize) -> usize {
        ((f * epochs as f64 + 1e-9).floor() as usize).max(1)
    }
}

/// Entries per primitive of each group: centres, scales, rotations, albedo.
const WIDTHS: [usize; 4] = [3, 3, 4, 1];

/// The rotations' group.
const ROTATIONS: usize = 2;

/// One group's arrays for one chunk of primitives, as an update reads and writes them.
struct GroupChunk<'a> {
    params: &'a mut [f64],
    grad: &'a [f64],
    m: &'a mut [f64],
    v: &'a mut [f64],
    /// The running mean's entries, when iterates are averaged.
    mean: Option<&'a mut [f64]>,
}

#[derive(Clone, Debug, Default)]
struct Moments {
    m: Vec<f64>,
    v: Vec<f64>,
}

/// One parallel chunk of an AdamW update.
struct AdamChunk<'a> {
    params: &'a mut [f64],
    grad: &'a [f64],
    m: &'a mut [f64],
    v: &'a mut [f64],
    beta: (f64, f64),
    bias: (f64, f64),
    eps: f64,
    lr: f64,
    weight_decay: f64,
}

impl crate::simd::Work for AdamChunk<'_> {
    type Output = usize;

    /// The update of every entry with a finite gradient; entries without one keep
    /// their parameter and moments. Written without a branch, so that it compiles to
    /// vector divisions and square roots.
    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) -> usize {
        let Self {
            params,
            grad,
            m,
            v,
            beta: (beta1, beta2),
            bias: (bc1, bc2),
            eps,
            lr,
            weight_decay,
        } = self;
        let mut skipped = 0;
        for i in 0..params.len().min(grad.len()).min(m.len()).min(v.len()) {
            let g = grad[i];
            let ok = g.is_finite();
            let g = if ok { g } else { 0.0 };
            let mi = beta1 * m[i] + (1.0 - beta1) * g;
            let vi = beta2 * v[i] + (1.0 - beta2) * g * g;
            let update = (mi / bc1) / ((vi / bc2).sqrt() + eps);
            let p = params[i] - lr * (update + weight_decay * params[i]);
            m[i] = if ok { mi } else { m[i] };
            v[i] = if ok { vi } else { v[i] };
            params[i] = if ok { p } else { params[i] };
            skipped += usize::from(!ok);
        }
        skipped
    }
}

/// The optimiser state for one cloud.
#[derive(Clone, Debug)]
pub struct AdamW {
    settings: AdamWSettings,
    moments: [Moments; 4],
    t: u64,
}

impl AdamW {
    /// A fresh optimiser.
    pub fn new(settings: AdamWSettings) -> Self {
        Self {
            settings,
            moments: Default::default(),
            t: 0,
        }
    }

    /// The settings.
    pub fn settings(&self) -> &AdamWSettings {
        &self.settings
    }

    /// Applies one update with learning-rate multiplier `factor`. Gradients that are
    /// not finite are treated as zero for that entry, so a degenerate pair can never
    /// poison the parameters; returns how many such entries were skipped.
    pub fn step(&mut self, cloud: &mut GaussianCloud, grads: &RawGrads, factor: f64) -> usize {
        self.step_averaged(cloud, grads, factor, None)
    }

    /// [`AdamW::step`], then, with `mean = Some((mean, n))`, adds the updated cloud to
    /// the running mean of the last `n` iterates (`mean += (cloud − mean)/n`, entry by
    /// entry; `mean` has the cloud's layout). One parallel pass over chunks of
    /// primitives does the update, the rotations' renormalisation and the mean, so
    /// every thread has work throughout. Element by element, so neither the split nor
    /// the thread count changes the result.
    pub fn step_averaged(
        &mut self,
        cloud: &mut GaussianCloud,
        grads: &RawGrads,
        factor: f64,
        mean: Option<(&mut GaussianCloud, usize)>,
    ) -> usize {
        self.t += 1;
        let s = self.settings;
        let bc1 = 1.0 - s.beta1.powi(self.t.min(i32::MAX as u64) as i32);
        let bc2 = 1.0 - s.beta2.powi(self.t.min(i32::MAX as u64) as i32);
        let settings = [s.centres, s.scales, s.rotations, s.albedo];
        let params = [
            &mut cloud.centres,
            &mut cloud.scales,
            &mut cloud.rotations,
            &mut cloud.albedo,
        ];
        let grads = [&grads.centres, &grads.scales, &grads.rotations, &grads.albedo];
        for (moments, params) in self.moments.iter_mut().zip(&params) {
            if moments.m.len() != params.len() {
                moments.m = vec![0.0; params.len()];
                moments.v = vec![0.0; params.len()];
            }
        }
        let (mean, w) = match mean {
            Some((mean, n)) => (Some(mean), 1.0 / n.max(1) as f64),
            None => (None, 0.0),
        };
        // Every group's arrays cut at the same primitives: chunk c of group g holds
        // primitives c·PRIMITIVE_CHUNK.. of it, WIDTHS[g] entries each.
        let mut chunks: Vec<[Option<GroupChunk<'_>>; 4]> = Vec::new();
        let means = match mean {
            Some(m) => [
                Some(&mut m.centres),
                Some(&mut m.scales),
                Some(&mut m.rotations),
                Some(&mut m.albedo),
            ],
            None => [None, None, None, None],
        };
        let groups = params.into_iter().zip(grads).zip(&mut self.moments).zip(means);
        for (g, (((params, grad), moments), mean)) in groups.enumerate() {
            let width = WIDTHS[g] * PRIMITIVE_CHUNK;
            let mut mean = mean.map(|m| m.chunks_mut(width));
            let parts = params
                .chunks_mut(width)
                .zip(grad.chunks(width))
                .zip(moments.m.chunks_mut(width))
                .zip(moments.v.chunks_mut(width));
            for (c, (((params, grad), m), v)) in parts.enumerate() {
                if chunks.len() <= c {
                    chunks.push([None, None, None, None]);
                }
                chunks[c][g] = Some(GroupChunk {
                    params,
                    grad,
                    m,
                    v,
                    mean: mean.as_mut().and_then(Iterator::next),
                });
            }
        }
        chunks
            .into_par_iter()
            .map(|groups| {
                let mut skipped = 0;
                for (g, chunk) in groups.into_iter().enumerate() {
                    let Some(GroupChunk {
                        params,
                        grad,
                        m,
                        v,
                        mean,
                    }) = chunk
                    else {
                        continue;
                    };
                    skipped += crate::simd::dispatch(AdamChunk {
                        params: &mut *params,
                        grad,
                        m,
                        v,
                        beta: (s.beta1, s.beta2),
                        bias: (bc1, bc2),
                        eps: s.eps,
                        lr: settings[g].lr * factor,
                        weight_decay: settings[g].weight_decay,
                    });
                    if g == ROTATIONS {
                        params.chunks_exact_mut(4).for_each(super::model::renormalise);
                    }
                    if let Some(mean) = mean {
                        mean.iter_mut()
                            .zip(&*params)
                            .for_each(|(m, x)| *m += (x - *m) * w);
                    }
                }
                skipped
            })
            .sum()
    }

    /// Steps taken so far (Adam's t).
    pub(crate) fn steps_taken(&self) -> u64 {
        self.t
    }

    /// Group `g`'s moments (centres, scales, rotations, albedo) for `len` entries:
    /// zeros where none are kept yet, as the next step would start them.
    pub(crate) fn moments(&self, g: usize, len: usize) -> (&[f64], &[f64]) {
        let m = &self.moments[g];
        if m.m.len() == len {
            (&m.m, &m.v)
        } else {
            (&[], &[])
        }
    }

    /// Replaces group `g`'s moments with the state after steps taken elsewhere (on a
    /// GPU, `crate::gpu::fit_steps`).
    pub(crate) fn set_moments(&mut self, g: usize, m: Vec<f64>, v: Vec<f64>) {
        self.moments[g] = Moments { m, v };
    }

    /// Counts `steps` steps taken elsewhere ([`AdamW::set_moments`]).
    pub(crate) fn advance(&mut self, steps: u64) {
        self.t += steps;
    }

    /// Forgets the moments of primitive `k`, as for a primitive just placed: its
    /// next updates start from zero momentum instead of the history of what was there.
    pub fn reset(&mut self, k: usize) {
        for (moments, width) in self.moments.iter_mut().zip(WIDTHS) {
            if moments.m.len() >= width * (k + 1) {
                moments.m[width * k..width * (k + 1)].fill(0.0);
                moments.v[width * k..width * (k + 1)].fill(0.0);
            }
        }
    }

    /// Zero moments for primitives appended to the cloud, up to `n` of them in all (a
    /// fit that grows: [`crate::gtr::DensifySettings::grow_from`]). Before the first
    /// step there are none to extend.
    pub fn grow(&mut self, n: usize) {
        for (moments, width) in self.moments.iter_mut().zip(WIDTHS) {
            if !moments.m.is_empty() && moments.m.len() < n * width {
                moments.m.resize(n * width, 0.0);
                moments.v.resize(n * width, 0.0);
            }
        }
    }

    /// Drops the moments of primitives removed by `keep` (same rule as
    /// [`GaussianCloud::retain`]), so optimisation can continue after pruning.
    pub fn retain(&mut self, n: usize, keep: impl Fn(usize) -> bool) {
        let kept: Vec<usize> = (0..n).filter(|&k| keep(k)).collect();
        for (moments, width) in self.moments.iter_mut().zip(WIDTHS) {
            if moments.m.len() != n * width {
                continue;
            }
            let gather = |v: &[f64]| {
                kept.iter()
                    .flat_map(|&k| v[width * k..width * (k + 1)].to_vec())
                    .collect()
            };
            moments.m = gather(&moments.m);
            moments.v = gather(&moments.v);
        }
    }
}

#[cfg(test)]
mod tests {
    use glam::{DQuat, DVec3};
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    use super::*;
    use crate::gtr::model::{Primitive, ScaleBounds};
    use crate::roi::RoiBox;

    /// The update as written in the paper, one entry at a time, for comparison.
    fn reference_update(
        p: &mut f64,
        g: f64,
        m: &mut f64,
        v: &mut f64,
        s: &AdamWSettings,
        group: GroupSettings,
        t: i32,
        factor: f64,
    ) -> bool {
        if !g.is_finite() {
            return false;
        }
        *m = s.beta1 * *m + (1.0 - s.beta1) * g;
        *v = s.beta2 * *v + (1.0 - s.beta2) * g * g;
        let update = (*m / (1.0 - s.beta1.powi(t))) / ((*v / (1.0 - s.beta2.powi(t))).sqrt() + s.eps);
        *p -= group.lr * factor * (update + group.weight_decay * *p);
        true
    }

    /// Three chunks of primitives and a partial one, a non-finite gradient entry, a
    /// rotation pushed to zero, weight decay and the running mean: the chunked
    /// parallel update gives the entry-by-entry reference's bits.
    #[test]
    fn the_chunked_step_is_the_entrywise_update() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.2), DVec3::new(0.5, 0.5, 1.0)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 1e-3, max: 0.2 }).unwrap();
        let n = 3 * PRIMITIVE_CHUNK + 17;
        for _ in 0..n {
            cloud
                .push(Primitive {
                    centre: DVec3::new(rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4), 0.6),
                    scale: DVec3::splat(rng.random_range(0.01..0.05)),
                    rotation: DQuat::from_rotation_z(rng.random_range(0.0..3.0)),
                    albedo: rng.random_range(0.1..2.0),
                })
                .unwrap();
        }
        let mut settings = AdamWSettings::default();
        settings.scales.weight_decay = 0.01;
        let random = |len: usize, rng: &mut ChaCha8Rng| -> Vec<f64> {
            (0..len).map(|_| rng.random_range(-1.0..1.0)).collect()
        };
        let mut adam = AdamW::new(settings);
        let mut want = cloud.clone();
        let mut moments = [
            (vec![0.0; 3 * n], vec![0.0; 3 * n]),
            (vec![0.0; 3 * n], vec![0.0; 3 * n]),
            (vec![0.0; 4 * n], vec![0.0; 4 * n]),
            (vec![0.0; n], vec![0.0; n]),
        ];
        let mut mean = cloud.clone();
        let mut want_mean = cloud.clone();
        for step in 1..=3 {
            let mut grads = RawGrads {
                centres: random(3 * n, &mut rng),
                scales: random(3 * n, &mut rng),
                rotations: random(4 * n, &mut rng),
                albedo: random(n, &mut rng),
            };
            grads.centres[7] = f64::NAN;
            grads.albedo[PRIMITIVE_CHUNK + 3] = f64::INFINITY;
            if step == 1 {
                // Rotation 600 collapses to zero (no gradient, no momentum yet): it
                // becomes the identity.
                let q = &want.rotations[4 * 600..4 * 601];
                grads.rotations[4 * 600..4 * 601]
                    .iter_mut()
                    .zip(q)
                    .for_each(|(g, _)| *g = 0.0);
                cloud.rotations[4 * 600..4 * 601].fill(0.0);
                want.rotations[4 * 600..4 * 601].fill(0.0);
            }
            let factor = 0.5 + 0.25 * step as f64;
            let skipped = adam.step_averaged(&mut cloud, &grads, factor, Some((&mut mean, step)));
            let mut want_skipped = 0;
            let groups = [
                (&mut want.centres, &grads.centres, settings.centres),
                (&mut want.scales, &grads.scales, settings.scales),
                (&mut want.rotations, &grads.rotations, settings.rotations),
                (&mut want.albedo, &grads.albedo, settings.albedo),
            ];
            for ((params, grad, group), (m, v)) in groups.into_iter().zip(&mut moments) {
                for i in 0..params.len() {
                    if !reference_update(
                        &mut params[i],
                        grad[i],
                        &mut m[i],
                        &mut v[i],
                        &settings,
                        group,
                        step as i32,
                        factor,
                    ) {
                        want_skipped += 1;
                    }
                }
            }
            want.renormalise_rotations();
            let w = 1.0 / step as f64;
            for (m, x) in [
                (&mut want_mean.centres, &want.centres),
                (&mut want_mean.scales, &want.scales),
                (&mut want_mean.rotations, &want.rotations),
                (&mut want_mean.albedo, &want.albedo),
            ] {
                m.iter_mut().zip(x).for_each(|(m, x)| *m += (x - *m) * w);
            }
            assert_eq!(skipped, want_skipped, "step {step}");
            let bits = |c: &GaussianCloud| -> Vec<u64> {
                [&c.centres, &c.scales, &c.rotations, &c.albedo]
                    .into_iter()
                    .flatten()
                    .map(|v| v.to_bits())
                    .collect()
            };
            assert_eq!(bits(&cloud), bits(&want), "step {step}");
            assert_eq!(bits(&mean), bits(&want_mean), "step {step}");
            if step == 1 {
                assert_eq!(&cloud.rotations[4 * 600..4 * 601], &[1.0, 0.0, 0.0, 0.0]);
            }
        }
    }

    #[test]
    fn schedule_warms_up_then_decays_at_milestones() {
        let s = Schedule {
            warmup_steps: 4,
            milestones: vec![0.2, 0.5],
            gamma: 0.1,
        };
        assert_eq!(s.factor(0, 0, 10), 0.25);
        assert_eq!(s.factor(3, 0, 10), 1.0);
        assert_eq!(s.factor(100, 1, 10), 1.0);
        assert!((s.factor(100, 2, 10) - 0.1).abs() < 1e-15);
        assert!((s.factor(100, 7, 10) - 0.01).abs() < 1e-15);
        // The same fractions scale with the epochs: epoch 7 of 40 is before both.
        assert_eq!(s.factor(100, 7, 40), 1.0);
    }

    #[test]
    fn milestones_at_thirds_fall_on_whole_epochs() {
        for (epochs, at) in [
            (12, [4, 8]),
            (15, [5, 10]),
            (16, [5, 10]),
            (3, [1, 2]),
            (1, [1, 1]),
        ] {
            let got = [1.0 / 3.0, 2.0 / 3.0].map(|f| Schedule::milestone_epoch(f, epochs));
            assert_eq!(got, at, "{epochs} epochs");
        }
    }
}

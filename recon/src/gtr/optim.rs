//! AdamW (Loshchilov & Hutter) with one learning rate and weight decay per parameter
//! group, and a step/epoch schedule: linear warm-up, then milestone decay.
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::model::{GaussianCloud, RawGrads};

/// Parameters per parallel work item of an update.
const PARALLEL_CHUNK: usize = 8192;

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
        self.t += 1;
        let s = self.settings;
        let bc1 = 1.0 - s.beta1.powi(self.t.min(i32::MAX as u64) as i32);
        let bc2 = 1.0 - s.beta2.powi(self.t.min(i32::MAX as u64) as i32);
        let groups = [
            (&mut cloud.centres, &grads.centres, s.centres),
            (&mut cloud.scales, &grads.scales, s.scales),
            (&mut cloud.rotations, &grads.rotations, s.rotations),
            (&mut cloud.albedo, &grads.albedo, s.albedo),
        ];
        let mut skipped = 0;
        for ((params, grad, group), moments) in groups.into_iter().zip(self.moments.iter_mut()) {
            if moments.m.len() != params.len() {
                moments.m = vec![0.0; params.len()];
                moments.v = vec![0.0; params.len()];
            }
            let lr = group.lr * factor;
            // Element-wise, so the parallel split cannot change the result.
            skipped += params
                .par_chunks_mut(PARALLEL_CHUNK)
                .zip(grad.par_chunks(PARALLEL_CHUNK))
                .zip(moments.m.par_chunks_mut(PARALLEL_CHUNK))
                .zip(moments.v.par_chunks_mut(PARALLEL_CHUNK))
                .map(|(((params, grad), m), v)| {
                    crate::simd::dispatch(AdamChunk {
                        params,
                        grad,
                        m,
                        v,
                        beta: (s.beta1, s.beta2),
                        bias: (bc1, bc2),
                        eps: s.eps,
                        lr,
                        weight_decay: group.weight_decay,
                    })
                })
                .sum::<usize>();
        }
        cloud.renormalise_rotations();
        skipped
    }

    /// Forgets the moments of primitive `k`, as for a primitive just placed: its
    /// next updates start from zero momentum instead of the history of what was there.
    pub fn reset(&mut self, k: usize) {
        for (moments, width) in self.moments.iter_mut().zip([3, 3, 4, 1]) {
            if moments.m.len() >= width * (k + 1) {
                moments.m[width * k..width * (k + 1)].fill(0.0);
                moments.v[width * k..width * (k + 1)].fill(0.0);
            }
        }
    }

    /// Drops the moments of primitives removed by `keep` (same rule as
    /// [`GaussianCloud::retain`]), so optimisation can continue after pruning.
    pub fn retain(&mut self, n: usize, keep: impl Fn(usize) -> bool) {
        let kept: Vec<usize> = (0..n).filter(|&k| keep(k)).collect();
        for (moments, width) in self.moments.iter_mut().zip([3, 3, 4, 1]) {
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
    use super::*;

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

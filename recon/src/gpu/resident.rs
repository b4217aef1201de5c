//! The fit's state and steps as the GPU path takes them ([`super::fit_steps`]), in
//! both builds: a build without the `gpu` feature names them too.
use crate::gtr::{AdamW, AdamWSettings, GaussianCloud};
use crate::transient::Pair;

/// Entries per primitive of the cloud's groups: centres, scales, rotations, albedo.
const WIDTHS: [usize; 4] = [3, 3, 4, 1];

/// The fit's optimiser state in the GPU's layout, [`RAW`] f32 a primitive: θx (3),
/// θs (3), the raw quaternion (w, x, y, z) and θρ, as
/// [`crate::gtr::GaussianCloud`] keeps them; AdamW's two moments and the running mean
/// of the iterates (while the fit averages) in the same layout.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Resident {
    /// Raw parameters.
    pub raw: Vec<f32>,
    /// AdamW's first moments.
    pub m1: Vec<f32>,
    /// AdamW's second moments.
    pub m2: Vec<f32>,
    /// The running mean of the iterates, when the fit averages them.
    pub mean: Option<Vec<f32>>,
}

/// Raw parameters a primitive ([`Resident`]).
pub const RAW: usize = 11;

/// What the parameter maps and AdamW take besides the parameters: the cloud's ROI and
/// scale bounds, and the optimiser's settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Optimiser {
    /// The ROI's centre and half sizes (x = c + h ⊙ tanh θx).
    pub centre: glam::DVec3,
    /// See `centre`.
    pub half: glam::DVec3,
    /// ln s_min and ln s_max − ln s_min.
    pub log_min: f64,
    /// See `log_min`.
    pub log_span: f64,
    /// Each group's learning rate (centres, scales, rotations, albedo), before the
    /// schedule's factor.
    pub lr: [f64; 4],
    /// Each group's decoupled weight decay.
    pub decay: [f64; 4],
    /// Adam's β1, β2 and ε.
    pub beta1: f64,
    /// See `beta1`.
    pub beta2: f64,
    /// See `beta1`.
    pub eps: f64,
}

/// One optimiser step of [`super::fit_steps`]: its mini-batch, as [`super::batch_gradient`] takes
/// one, and its place in the schedule.
#[derive(Clone, Debug)]
pub struct Step {
    /// The batch's pairs.
    pub pairs: Vec<Pair>,
    /// Their measured histograms, one after the other.
    pub data: Vec<f32>,
    /// Each pair's weight (over the batch size), gain in the model, and first and end
    /// recorded bin ([`super::batch_gradient`]).
    pub weights: Vec<[f32; 4]>,
    /// The learning-rate schedule's multiplier.
    pub factor: f64,
    /// AdamW's step count after this step (its bias corrections are 1 − βᵗ).
    pub t: u64,
    /// While averaging: n, the iterates the running mean holds with this step's.
    pub mean_of: Option<usize>,
}

/// What [`super::fit_steps`] did.
#[derive(Clone, Debug, PartialEq)]
pub struct Steps {
    /// Each step's mini-batch loss, in order.
    pub losses: Vec<f64>,
    /// Gradient entries that were not finite, skipped as the CPU's AdamW skips them.
    pub skipped: u64,
}

impl Resident {
    /// The state of `cloud`, the moments of `adam` (zeros where it has taken no step
    /// with these primitives) and the running mean `mean`, in the GPU's layout.
    pub fn of(cloud: &GaussianCloud, adam: &AdamW, mean: Option<&GaussianCloud>) -> Self {
        let n = cloud.len();
        let moments: [(&[f64], &[f64]); 4] = std::array::from_fn(|g| adam.moments(g, WIDTHS[g] * n));
        let zeros = |v: &[f64], g: usize| {
            if v.is_empty() {
                vec![0.0; WIDTHS[g] * n]
            } else {
                v.to_vec()
            }
        };
        let m1: [Vec<f64>; 4] = std::array::from_fn(|g| zeros(moments[g].0, g));
        let m2: [Vec<f64>; 4] = std::array::from_fn(|g| zeros(moments[g].1, g));
        Resident {
            raw: pack(&groups(cloud), n),
            m1: pack(&m1.each_ref().map(Vec::as_slice), n),
            m2: pack(&m2.each_ref().map(Vec::as_slice), n),
            mean: mean.map(|m| pack(&groups(m), n)),
        }
    }

    /// Writes the state back after `steps` steps taken on the GPU: the cloud's raw
    /// parameters, the optimiser's moments and step count, and the running mean
    /// (where one is kept on both sides).
    pub fn write_back(
        &self,
        cloud: &mut GaussianCloud,
        adam: &mut AdamW,
        steps: usize,
        mean: Option<&mut GaussianCloud>,
    ) {
        let n = cloud.len();
        set_groups(cloud, unpack(&self.raw, n));
        for (g, (m, v)) in unpack(&self.m1, n)
            .into_iter()
            .zip(unpack(&self.m2, n))
            .enumerate()
        {
            adam.set_moments(g, m, v);
        }
        adam.advance(steps as u64);
        if let (Some(mean), Some(raw)) = (mean, &self.mean) {
            set_groups(mean, unpack(raw, n));
        }
    }
}

impl Optimiser {
    /// The maps of `cloud` and the optimiser `settings`.
    pub fn of(cloud: &GaussianCloud, settings: &AdamWSettings) -> Self {
        let s = settings;
        let roi = cloud.roi();
        let (log_min, log_span) = cloud.log_scale_map();
        let groups = [s.centres, s.scales, s.rotations, s.albedo];
        Optimiser {
            centre: roi.centre,
            half: roi.half,
            log_min,
            log_span,
            lr: groups.map(|g| g.lr),
            decay: groups.map(|g| g.weight_decay),
            beta1: s.beta1,
            beta2: s.beta2,
            eps: s.eps,
        }
    }
}

/// The raw arrays of `cloud`, group by group.
fn groups(cloud: &GaussianCloud) -> [&[f64]; 4] {
    [&cloud.centres, &cloud.scales, &cloud.rotations, &cloud.albedo]
}

/// Replaces the raw arrays of `cloud`.
fn set_groups(cloud: &mut GaussianCloud, [centres, scales, rotations, albedo]: [Vec<f64>; 4]) {
    (cloud.centres, cloud.scales, cloud.rotations, cloud.albedo) = (centres, scales, rotations, albedo);
}

/// Four group arrays of `n` primitives in the GPU's layout: each primitive's entries
/// together, group after group.
fn pack(groups: &[&[f64]; 4], n: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(RAW * n);
    for k in 0..n {
        for (g, width) in WIDTHS.into_iter().enumerate() {
            out.extend(groups[g][width * k..width * (k + 1)].iter().map(|&v| v as f32));
        }
    }
    out
}

/// [`pack`] undone.
fn unpack(v: &[f32], n: usize) -> [Vec<f64>; 4] {
    let mut out: [Vec<f64>; 4] = WIDTHS.map(|w| Vec::with_capacity(w * n));
    for raw in v.chunks_exact(RAW) {
        let mut at = 0;
        for (g, width) in WIDTHS.into_iter().enumerate() {
            out[g].extend(raw[at..at + width].iter().map(|&x| f64::from(x)));
            at += width;
        }
    }
    out
}

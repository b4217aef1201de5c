//! Recovery: transients rendered from a few known primitives are fitted from a random
//! start, and the fitted centres must land within 1 cm of the true ones. Runs on a
//! planar relay and on an S-shaped one with a few hundred non-confocal pairs.
use glam::{DQuat, DVec3};
use periscope_recon::gtr::{
    CancelToken, GaussianCloud, Init, Primitive, RenderOptions, ScaleBounds, Schedule, TrainConfig,
    TrainEvent, Trainer, render_set,
};
use periscope_recon::{Pair, RoiBox, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The acceptance bound on centre error.
const CENTRE_TOLERANCE_M: f64 = 0.01;

fn roi() -> RoiBox {
    RoiBox::from_bounds(DVec3::new(-0.3, -0.3, 0.4), DVec3::new(0.3, 0.3, 0.8)).unwrap()
}

fn truth() -> Vec<Primitive> {
    [
        (DVec3::new(-0.12, 0.08, 0.55), 0.015),
        (DVec3::new(0.10, -0.05, 0.62), 0.012),
        (DVec3::new(0.02, 0.15, 0.70), 0.018),
    ]
    .into_iter()
    .map(|(centre, s)| Primitive {
        centre,
        scale: DVec3::new(s, 0.8 * s, 1.2 * s),
        rotation: DQuat::from_rotation_y(0.4),
        albedo: 1.0,
    })
    .collect()
}

/// Relay height and normal: flat, or S-shaped (undulating along x).
fn relay(s_shaped: bool, x: f64, y: f64) -> (DVec3, DVec3) {
    if !s_shaped {
        return (DVec3::new(x, y, 0.0), DVec3::Z);
    }
    let (a, k) = (0.08, std::f64::consts::PI * 1.5);
    let z = a * (k * x).sin();
    let slope = a * k * (k * x).cos();
    (DVec3::new(x, y, z), DVec3::new(-slope, 0.0, 1.0).normalize())
}

fn measured(s_shaped: bool, n_pairs: usize, seed: u64) -> TransientSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let axis = TimeAxis::from_seconds(0.6, 32e-12, 240);
    let mut geometry = TransientSet::new(axis).unwrap();
    for _ in 0..n_pairs {
        let (xi, ni) = relay(s_shaped, rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        let (xd, nd) = relay(s_shaped, rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        geometry
            .push(Pair { xi, ni, xd, nd }, &vec![0.0; axis.bins])
            .unwrap();
    }
    let mut cloud = GaussianCloud::new(roi(), ScaleBounds { min: 5e-4, max: 0.15 }).unwrap();
    truth().into_iter().for_each(|p| cloud.push(p).unwrap());
    let opt = RenderOptions {
        gain: 1.0,
        ..RenderOptions::default()
    };
    let rendered = render_set(&cloud.kernels(), &geometry, &opt);
    let peak = rendered.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut set = TransientSet::new(axis).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        let h: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
            .iter()
            .map(|&v| (100.0 * v / peak) as f32)
            .collect();
        set.push(*pair, &h).unwrap();
    }
    set
}

fn fit(set: TransientSet, seed: u64) -> (Vec<Primitive>, Vec<f64>) {
    let config = TrainConfig {
        primitives: 3,
        init: Init::Uniform,
        initial_scale: Some(0.03),
        epochs: 60,
        batch_size: 4,
        schedule: Schedule {
            warmup_steps: 20,
            milestones: vec![0.5, 0.75],
            gamma: 0.3,
        },
        seed,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(config, roi(), set).unwrap();
    let mut losses = Vec::new();
    trainer
        .run(None, &CancelToken::new(), &mut |e| {
            if let TrainEvent::Epoch { loss, .. } = e {
                losses.push(*loss)
            }
        })
        .unwrap();
    let cloud = trainer.cloud();
    ((0..cloud.len()).map(|k| cloud.primitive(k)).collect(), losses)
}

/// The largest distance from a true centre to its matched fitted centre, over the
/// best of the 3! assignments.
fn worst_centre_error(fitted: &[Primitive]) -> f64 {
    let truth = truth();
    assert_eq!(fitted.len(), truth.len(), "pruning removed a fitted primitive");
    let perms = [[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]];
    perms
        .iter()
        .map(|p| {
            (0..3)
                .map(|i| truth[i].centre.distance(fitted[p[i]].centre))
                .fold(0.0, f64::max)
        })
        .fold(f64::INFINITY, f64::min)
}

fn recover(s_shaped: bool, seed: u64) {
    let set = measured(s_shaped, 300, seed + 1);
    let (fitted, losses) = fit(set, seed + 5);
    let err = worst_centre_error(&fitted);
    let centres: Vec<_> = fitted.iter().map(|p| p.centre).collect();
    assert!(
        err < CENTRE_TOLERANCE_M,
        "s_shaped={s_shaped}, seed {seed}: worst centre error {:.4} m (tolerance {CENTRE_TOLERANCE_M} m); fitted {centres:?}; losses {:?} .. {:?}",
        err,
        losses.first(),
        losses.last()
    );
    assert!(
        losses.last() < losses.first(),
        "the loss did not decrease: {losses:?}"
    );
}

#[test]
fn recovers_known_gaussians_on_a_planar_relay() {
    (0..3).for_each(|seed| recover(false, seed));
}

#[test]
fn recovers_known_gaussians_on_an_s_shaped_relay() {
    (0..3).for_each(|seed| recover(true, seed));
}

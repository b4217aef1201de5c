//! Measures what seeding the primitives from a coarse backprojection buys over the
//! paper's uniform initialisation: the loss after each epoch for both, on the same
//! noisy planar-relay scene (a small letter-like arrangement of primitives).
//!
//! `cargo run --release -p periscope-recon --example init_convergence`
use glam::{DQuat, DVec3};
use periscope_recon::gtr::{
    CancelToken, GaussianCloud, Init, Primitive, RenderOptions, ScaleBounds, Schedule, TrainConfig,
    TrainEvent, Trainer, render_set,
};
use periscope_recon::{Pair, RoiBox, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn main() {
    let roi = RoiBox::from_bounds(DVec3::new(-0.4, -0.4, 0.4), DVec3::new(0.4, 0.4, 0.9)).unwrap();
    let axis = TimeAxis::from_seconds(0.6, 32e-12, 300);
    let mut truth = GaussianCloud::new(roi, ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
    // An "L": a vertical and a horizontal bar of small primitives at 0.65 m.
    for i in 0..10 {
        let t = i as f64 * 0.03;
        for centre in [
            DVec3::new(-0.1, -0.15 + t, 0.65),
            DVec3::new(-0.1 + t, -0.15, 0.65),
        ] {
            truth
                .push(Primitive {
                    centre,
                    scale: DVec3::new(0.015, 0.015, 0.004),
                    rotation: DQuat::IDENTITY,
                    albedo: 1.0,
                })
                .unwrap();
        }
    }
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut geometry = TransientSet::new(axis).unwrap();
    for _ in 0..1500 {
        let xi = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
        let xd = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
        let pair = Pair {
            xi,
            ni: DVec3::Z,
            xd,
            nd: DVec3::Z,
        };
        geometry.push(pair, &vec![0.0; axis.bins]).unwrap();
    }
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let peak = rendered.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut data = TransientSet::new(axis).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        // 200 counts at the peak with Poisson-like noise (Gaussian approximation).
        let h: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
            .iter()
            .map(|&v| {
                let mean = 200.0 * v / peak;
                (mean + mean.sqrt() * (rng.random::<f64>() - 0.5) * 3.46).max(0.0) as f32
            })
            .collect();
        data.push(*pair, &h).unwrap();
    }
    for (name, init) in [
        ("uniform", Init::Uniform),
        (
            "backprojection",
            Init::Backprojection {
                grid: [32, 32, 20],
                uniform_fraction: 0.2,
            },
        ),
    ] {
        let config = TrainConfig {
            primitives: 400,
            init,
            epochs: 12,
            seed: 1,
            schedule: Schedule {
                warmup_steps: 20,
                milestones: vec![1.0 / 3.0, 2.0 / 3.0],
                gamma: 0.3,
            },
            ..TrainConfig::default()
        };
        let mut trainer = Trainer::new(config, roi, data.clone()).unwrap();
        let mut losses = Vec::new();
        let start = std::time::Instant::now();
        trainer
            .run(None, &CancelToken::new(), &mut |e| {
                if let TrainEvent::Epoch { loss, .. } = e {
                    losses.push(*loss)
                }
            })
            .unwrap();
        let shown: Vec<String> = losses.iter().map(|l| format!("{l:.1}")).collect();
        println!(
            "{name:>15}: loss per epoch [{}] ({:.1} s)",
            shown.join(", "),
            start.elapsed().as_secs_f64()
        );
    }
}

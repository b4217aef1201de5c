//! The paper-scale 3D-GTR workload (issue: recon engine): 8,000 non-confocal pairs on
//! a curved 1 m relay, 512 bins of 32 ps, K = 10,000 primitives of 5–15 mm scale in a
//! 1 m × 1 m × 0.4 m ROI 0.5–0.9 m from the relay.
//!
//! Timed: one forward render of all pairs; one training epoch (forward + backward +
//! AdamW over shuffled mini-batches of 4 pairs, kernels refreshed every step).
//! Not timed: building the scene and the synthetic measurements, the gain matching.
//! Reports the median of the repetitions, Gaussian-pair evaluations per second, the
//! arithmetic rate (operations counted in the source) as a share of the 2-core f32 FMA
//! peak, and the process's peak resident memory. `GTR_BENCH_PAIRS` / `GTR_BENCH_K` shrink the
//! workload for quick looks; the defaults are the paper-scale numbers.
use std::time::Instant;

mod support;
use support::{median, peak_rss_mib, peak_share};

use glam::{DQuat, DVec3};
use periscope_recon::gtr::{
    CancelToken, GaussianCloud, Init, Primitive, RenderOptions, ScaleBounds, TrainConfig, Trainer,
    batch_loss_grad, render_set,
};
use periscope_recon::{Pair, RoiBox, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A curved 1 m × 1 m relay: z = 0.1 sin(πx) (a C/S-shaped panel), normals +z-ish.
fn relay_point(x: f64, y: f64) -> (DVec3, DVec3) {
    let z = 0.1 * (std::f64::consts::PI * x).sin();
    let slope = 0.1 * std::f64::consts::PI * (std::f64::consts::PI * x).cos();
    (DVec3::new(x, y, z), DVec3::new(-slope, 0.0, 1.0).normalize())
}

fn main() {
    let n_pairs = env("GTR_BENCH_PAIRS", 8000);
    let k = env("GTR_BENCH_K", 10_000);
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.5), DVec3::new(0.5, 0.5, 0.9)).unwrap();
    let axis = TimeAxis::from_seconds(0.8, 32e-12, 512);

    let mut geometry = TransientSet::new(axis).unwrap();
    for _ in 0..n_pairs {
        let (xi, ni) = relay_point(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        let (xd, nd) = relay_point(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        geometry
            .push(Pair { xi, ni, xd, nd }, &vec![0.0; axis.bins])
            .unwrap();
    }
    let bounds = ScaleBounds { min: 1e-3, max: 0.1 };
    let mut cloud = GaussianCloud::new(roi, bounds).unwrap();
    for _ in 0..k {
        let centre = DVec3::new(
            rng.random_range(-0.49..0.49),
            rng.random_range(-0.49..0.49),
            rng.random_range(0.51..0.89),
        );
        let scale = DVec3::new(
            rng.random_range(0.005..0.015),
            rng.random_range(0.005..0.015),
            rng.random_range(0.005..0.015),
        );
        let axis_dir = DVec3::new(rng.random(), rng.random(), rng.random()).normalize_or(DVec3::Z);
        cloud
            .push(Primitive {
                centre,
                scale,
                rotation: DQuat::from_axis_angle(axis_dir, rng.random_range(0.0..3.0)),
                albedo: rng.random_range(0.1..1.0),
            })
            .unwrap();
    }
    let kernels = cloud.kernels();
    let opt = RenderOptions::default();
    println!(
        "workload: {n_pairs} pairs x {k} primitives, {} bins of {:.2} mm path length",
        axis.bins,
        axis.width * 1e3
    );

    // The work per evaluation: bins in the window, and how many take the midpoint
    // series (kernels at least two bins wide) rather than the Φ table.
    let (mut bins_wide, mut bins_table, mut evaluated) = (0usize, 0usize, 0usize);
    for pair in geometry.pairs().iter().step_by(40) {
        for k in kernels.iter().step_by(10) {
            if let Some(e) = periscope_recon::gtr::kernel::evaluate(k, pair, &axis, &opt) {
                evaluated += 1;
                if axis.width / e.sigma <= periscope_recon::gtr::kernel::WIDE_DZ {
                    bins_wide += e.hi - e.lo;
                } else {
                    bins_table += e.hi - e.lo;
                }
            }
        }
    }
    let per_eval = |n: usize| n as f64 / evaluated.max(1) as f64;
    let (wide, table) = (per_eval(bins_wide), per_eval(bins_table));
    println!("bins per evaluation: {wide:.1} by the midpoint series, {table:.1} by the Φ table");
    // Operations per evaluation counted in the source (a multiply-add counts two):
    // geometry 120 forward and 200 more backward; per bin 15 (series) or 14 (table)
    // forward, 37 or 29 backward.
    let forward_flops = 120.0 + 15.0 * wide + 14.0 * table;
    let backward_flops = 200.0 + 37.0 * wide + 29.0 * table;

    let reps = env("GTR_BENCH_REPS", 3);
    let mut times = Vec::new();
    let mut rendered = Vec::new();
    for _ in 0..reps {
        let t = Instant::now();
        rendered = render_set(&kernels, &geometry, &opt);
        times.push(t.elapsed().as_secs_f64());
    }
    let forward = median(times);
    let evals = (n_pairs * k) as f64;
    println!(
        "forward render, all pairs: median {forward:.3} s ({:.1} M Gaussian-pair evaluations/s; {})",
        evals / forward / 1e6,
        peak_share(evals * forward_flops, forward)
    );

    // Measurements: the rendering itself, perturbed, so the fit has real residuals.
    let mut data = TransientSet::new(axis).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        let h: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
            .iter()
            .map(|&v| (v * 1.1) as f32)
            .collect();
        data.push(*pair, &h).unwrap();
    }
    let config = TrainConfig {
        primitives: k,
        init: Init::Uniform,
        initial_scale: Some(0.01),
        scale_bounds: Some(bounds),
        batch_size: 4,
        epochs: 1,
        ..TrainConfig::default()
    };
    // The loss gradient alone, over the same mini-batches an epoch takes (the
    // optimiser's and the kernel refresh's share is the epoch's time minus this).
    let mut grads = periscope_recon::gtr::RawGrads::zeros(cloud.len());
    let order: Vec<usize> = (0..data.len()).collect();
    let mut times = Vec::new();
    for _ in 0..reps {
        let t = Instant::now();
        for batch in order.chunks(4) {
            std::hint::black_box(batch_loss_grad(&cloud, &kernels, &data, batch, &opt, &mut grads));
        }
        times.push(t.elapsed().as_secs_f64());
    }
    let gradient = median(times);
    println!(
        "loss gradient, all mini-batches of 4 (no optimiser): median {gradient:.3} s ({:.1} M Gaussian-pair forward+backward evaluations/s; {})",
        evals / gradient / 1e6,
        peak_share(evals * (forward_flops + backward_flops), gradient)
    );
    let mut trainer = Trainer::new(config, roi, data).unwrap();
    let cancel = CancelToken::new();
    let mut times = Vec::new();
    for _ in 0..reps {
        let t = Instant::now();
        trainer.epoch(&cancel).unwrap();
        times.push(t.elapsed().as_secs_f64());
    }
    let epoch = median(times);
    println!(
        "training epoch (batch 4, forward + backward + AdamW): median {epoch:.3} s ({:.1} M Gaussian-pair forward+backward evaluations/s; {})",
        evals / epoch / 1e6,
        peak_share(evals * (forward_flops + backward_flops), epoch)
    );
    println!(
        "threads: {}, peak resident memory: {:.0} MiB",
        rayon::current_num_threads(),
        peak_rss_mib()
    );
}

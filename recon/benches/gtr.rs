//! The paper-scale 3D-GTR workload (issue: recon engine): 8,000 non-confocal pairs on
//! a curved 1 m relay, 512 bins of 32 ps, K = 10,000 primitives of 5–15 mm scale in a
//! 1 m × 1 m × 0.4 m ROI 0.5–0.9 m from the relay.
//!
//! Timed (criterion, one group `gtr`): one forward render of all pairs; the loss
//! gradient over every mini-batch of 4 pairs (no optimiser); one training epoch
//! (forward + backward + AdamW over shuffled mini-batches of 4 pairs, kernels refreshed
//! every step); and the same three on a GPU (`…, gpu`; docs/gpu.md) where a hardware
//! adapter is found (lavapipe with `PERISCOPE_BENCH_SOFTWARE_GPU=1`). Not timed: building the scene, the one render that makes the synthetic
//! measurements, the gain matching, building the trainer.
//!
//! Criterion's throughput is Gaussian-pair evaluations (pairs × primitives per
//! iteration), so its elem/s line is evaluations per second; its median time is the
//! figure to quote. Printed besides, once: the bins an evaluation covers on each
//! integration path, the arithmetic rate (operations counted in the source) of the last
//! sample as a share of the f32 FMA peak, and the process's peak resident memory.
//! `GTR_BENCH_PAIRS` / `GTR_BENCH_K` shrink the workload for quick looks; the defaults
//! are the paper-scale numbers. At paper scale each of the 10 samples is one run
//! (criterion warns that it cannot fit 10 samples in the measurement time and names the
//! time they take; two runs a sample would double a bench that already takes minutes).
use std::time::Duration;

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};

mod support;
use support::{LastSample, bench_gpu, f32_fma_peak_gflops, peak_rss_mib, peak_share};

use glam::{DQuat, DVec3};
use periscope_recon::gtr::{
    CancelToken, GaussianCloud, Init, Primitive, RenderOptions, ScaleBounds, TrainConfig, Trainer,
    batch_loss_grad, batch_loss_grad_gpu, render_set,
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

fn gtr(c: &mut Criterion) {
    let n_pairs = env("GTR_BENCH_PAIRS", 8000);
    let k = env("GTR_BENCH_K", 10_000);
    let mut rng = ChaCha8Rng::seed_from_u64(42);
    let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.5), DVec3::new(0.5, 0.5, 0.9)).unwrap();
    let bin_ps = env("GTR_BENCH_BIN_PS", 32);
    let axis = TimeAxis::from_seconds(0.8, bin_ps as f64 * 1e-12, 512);

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
    let mut windows = Vec::new();
    for pair in geometry.pairs().iter().step_by(40) {
        for k in kernels.iter().step_by(10) {
            if let Some(e) = periscope_recon::gtr::kernel::evaluate(k, pair, &axis, &opt) {
                evaluated += 1;
                windows.push(e.window);
                if axis.width / e.window.sigma <= periscope_recon::gtr::kernel::WIDE_DZ {
                    bins_wide += e.window.hi - e.window.lo;
                } else {
                    bins_table += e.window.hi - e.window.lo;
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
    println!(
        "counted operations per evaluation: {forward_flops:.0} forward, {:.0} forward + backward; \
         f32 FMA peak of {} threads: {:.0} GFLOP/s",
        forward_flops + backward_flops,
        rayon::current_num_threads(),
        f32_fma_peak_gflops(rayon::current_num_threads())
    );

    // Measurements: the rendering itself, perturbed, so the fit has real residuals.
    let rendered = render_set(&kernels, &geometry, &opt);
    let mut data = TransientSet::new(axis).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        let h: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
            .iter()
            .map(|&v| (v * 1.1) as f32)
            .collect();
        data.push(*pair, &h).unwrap();
    }

    let evals = (n_pairs * k) as f64;
    let mut group = c.benchmark_group("gtr");
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(20))
        .throughput(Throughput::Elements((n_pairs * k) as u64));

    let forward = LastSample::default();
    group.bench_function("forward render", |b| {
        b.iter_custom(|iters| forward.time(iters, || render_set(&kernels, &geometry, &opt)))
    });

    // The loss gradient alone, over the same mini-batches an epoch takes. On a worker
    // of the pool, as `Trainer::epoch` runs: called from outside it, each of a step's
    // parallel regions would be injected into the pool while this thread slept. Its
    // other workers sleep between the regions here, where the epoch keeps them awake
    // (`keep_warm`), so the epoch's time minus this is not the optimiser's share alone.
    let mut grads = periscope_recon::gtr::RawGrads::zeros(cloud.len());
    let order: Vec<usize> = (0..data.len()).collect();
    let gradient = LastSample::default();
    group.bench_function("loss gradient, batch 4", |b| {
        b.iter_custom(|iters| {
            gradient.time(iters, || {
                rayon::scope(|_| {
                    for batch in order.chunks(4) {
                        std::hint::black_box(batch_loss_grad(
                            &cloud, &kernels, &data, batch, &opt, &mut grads,
                        ));
                    }
                })
            })
        })
    });

    let config = TrainConfig {
        primitives: k,
        init: Init::Uniform,
        initial_scale: Some(0.01),
        scale_bounds: Some(bounds),
        batch_size: 4,
        epochs: 1,
        ..TrainConfig::default()
    };
    let mut trainer = Trainer::new(config.clone(), roi, data.clone()).unwrap();
    let cancel = CancelToken::new();
    let epoch = LastSample::default();
    group.bench_function("training epoch, batch 4", |b| {
        b.iter_custom(|iters| epoch.time(iters, || trainer.epoch(&cancel).unwrap()))
    });

    // The same three on a GPU (docs/gpu.md), where a hardware adapter is found.
    if let Some(periscope_recon::gpu::Compute::Gpu(gpu)) = bench_gpu() {
        group.bench_function("forward render, gpu", |b| {
            b.iter(|| {
                periscope_recon::gpu::render_pairs(&gpu, &kernels, geometry.pairs(), &axis, &opt).unwrap()
            })
        });
        group.bench_function("loss gradient, batch 4, gpu", |b| {
            b.iter(|| {
                rayon::scope(|_| {
                    for batch in order.chunks(4) {
                        std::hint::black_box(
                            batch_loss_grad_gpu(&gpu, &cloud, &kernels, &data, batch, &opt, &mut grads)
                                .unwrap(),
                        );
                    }
                })
            })
        });
        let mut trainer = Trainer::new(config, roi, data).unwrap();
        trainer.use_gpu(gpu, true);
        group.bench_function("training epoch, batch 4, gpu", |b| {
            b.iter(|| trainer.epoch(&cancel).unwrap())
        });
    }
    group.finish();

    // The per-bin loops alone, over the windows sampled above, on the vector path a
    // step takes: what they cost without the geometry, the chain rule, the threads and
    // the memory traffic of a step around them.
    let bins: usize = windows.iter().map(|w| w.hi - w.lo).sum();
    let dl: Vec<f64> = (0..axis.bins)
        .map(|b| ((b * 7919) % 101) as f64 / 100.0 - 0.5)
        .collect();
    let mut out = vec![0.0; axis.bins];
    let mut loops = c.benchmark_group("gtr per-bin loops");
    loops
        .sample_size(20)
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(bins as u64));
    let sums = LastSample::default();
    loops.bench_function("backward sums", |b| {
        b.iter_custom(|iters| {
            sums.time(iters, || {
                std::hint::black_box(periscope_recon::gtr::kernel::probe::sums(&windows, &axis, &dl));
            })
        })
    });
    let adds = LastSample::default();
    loops.bench_function("forward adds", |b| {
        b.iter_custom(|iters| {
            adds.time(iters, || {
                periscope_recon::gtr::kernel::probe::accumulate(&windows, &axis, &mut out);
                std::hint::black_box(&out);
            })
        })
    });
    loops.finish();
    let per_window = |t: Option<f64>| t.map_or(f64::NAN, |s| s * 1e9 / windows.len().max(1) as f64);
    println!(
        "per-bin loops alone, one thread, {} windows of {:.1} bins on average: backward sums {:.1} ns a \
         window, forward adds {:.1} ns a window",
        windows.len(),
        bins as f64 / windows.len().max(1) as f64,
        per_window(sums.seconds()),
        per_window(adds.seconds()),
    );

    // The arithmetic rate of the last sample of each (criterion's median above is the
    // figure to quote; these say how far it is from the CPU's peak).
    for (name, last, flops) in [
        ("forward render", &forward, forward_flops),
        (
            "loss gradient (no optimiser)",
            &gradient,
            forward_flops + backward_flops,
        ),
        (
            "training epoch (forward + backward + AdamW)",
            &epoch,
            forward_flops + backward_flops,
        ),
    ] {
        if let Some(t) = last.seconds() {
            println!(
                "{name}, last sample: {t:.3} s, {:.1} M Gaussian-pair evaluations/s; {}",
                evals / t / 1e6,
                peak_share(evals * flops, t)
            );
        }
    }
    println!(
        "threads: {}, peak resident memory: {:.0} MiB",
        rayon::current_num_threads(),
        peak_rss_mib()
    );
}

criterion_group!(benches, gtr);
criterion_main!(benches);

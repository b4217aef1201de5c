//! Relay geometry, virtual confocal synthesis and the conventional solvers (issue:
//! recon solvers), at the sizes the pipeline uses.
//!
//! Timed (criterion, one group `solvers`; the names in brackets are the benchmark ids,
//! which a filter on the command line picks, e.g. `-- 'fbp|synth$'`):
//! - [normals] normals of 100,000 points of a curved panel (16 neighbours);
//! - [lct64, lct128] LCT of a 64 × 64 × 512 and a 128 × 128 × 512 confocal scan (whole
//!   solver: cube, resampling, FFTs, Wiener filter, inverse; not the world-grid
//!   resampling); [lct_deep] of a 16 × 16 scan with 16,384 bins of 1 ps (4.9 m of
//!   path), where the light cone's spectrum is the cost;
//! - [fbp] FBP of 8,000 arbitrary pairs on a curved relay into a 128 × 128 × 64 volume
//!   (the default settings: `auto` takes the hierarchy on these pairs);
//! - [fbp_hierarchical, fbp_exact, fbp_one_laser, fbp_one_laser_hierarchical] the same
//!   pairs through the hierarchical backprojection at its default path error and
//!   through the exact path, and 8,000 pairs lit at one point (the two-torso kind)
//!   exactly and through the hierarchy;
//! - [fbp_grid] FBP of a 64 × 64 × 512 confocal scan on a level grid of half the voxel
//!   pitch into 32 × 32 × 81 (the 3D-GTR virtual scan of a 1 m validation capture,
//!   which takes FBP's grid path);
//! - [synth] virtual confocal synthesis of 64 × 64 × 512 from K = 10,000 Gaussians;
//! - [synth_lct] synthesis + LCT for the 64 × 64 virtual grid (the 0.6 s target);
//! - [splat_lct] the same LCT volume without the synthesis (`synth::splat_lct`);
//! - [adaptive_spread_remade, adaptive_spread_kept] an adaptive capture's spread of 128
//!   pairs among 65,536 candidates with 16,384 measured, from every measured pair and
//!   from the capture's kept distances (`adaptive::Coverage`);
//! - [fbp_gpu, fbp_grid_gpu, synth_gpu, synth_lct_gpu] the same on a GPU
//!   (docs/gpu.md), where a hardware adapter is found (a software one, lavapipe, with
//!   `PERISCOPE_BENCH_SOFTWARE_GPU=1`); the line saying why they were left out
//!   otherwise is printed first.
//!
//! Not timed: building scenes and inputs. Criterion's median time is the figure to
//! quote; its throughput line counts points (normals), transient bins in (LCT),
//! voxel-pairs (FBP) and Gaussian-relay-point evaluations (synthesis, and synthesis +
//! LCT end to end). Printed besides, once: the peak resident memory after the LCTs and
//! at the end, and FBP's counted arithmetic rate in its last sample as a share of the
//! f32 FMA peak. 10 samples each, two or more runs a sample except FBP (one run a
//! sample: criterion warns that 10 do not fit in the measurement time).
use std::time::Duration;

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};

mod support;
use support::{LastSample, bench_gpu, peak_rss_mib, peak_share};

use glam::{DMat3, DQuat, DVec3};
use periscope_recon::gtr::{Kernel, RenderOptions};
use periscope_recon::relay::{VirtualRelay, estimate_normals};
use periscope_recon::solver::{
    FbpBackprojection, FbpSettings, LctSettings, PlanarScan, fbp, fbp_on, lct_frame,
};
use periscope_recon::synth::{splat_lct, synthesise, synthesise_on};
use periscope_recon::{Pair, TimeAxis, TransientSet, VolumeGrid};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn curved(x: f64, y: f64) -> (DVec3, DVec3) {
    let z = 0.1 * (std::f64::consts::PI * x).sin();
    let slope = 0.1 * std::f64::consts::PI * (std::f64::consts::PI * x).cos();
    (DVec3::new(x, y, z), DVec3::new(-slope, 0.0, 1.0).normalize())
}

fn noise_scan(relay: &VirtualRelay, bins: usize, rng: &mut ChaCha8Rng) -> (TransientSet, PlanarScan) {
    noise_scan_of(relay, bins, 0.006, rng)
}

/// [`noise_scan`] with bins `width` metres of path long.
fn noise_scan_of(
    relay: &VirtualRelay,
    bins: usize,
    width: f64,
    rng: &mut ChaCha8Rng,
) -> (TransientSet, PlanarScan) {
    let axis = TimeAxis {
        start: 0.0,
        width,
        bins,
    };
    let mut set = TransientSet::new(axis).unwrap();
    let mut h = vec![0.0f32; bins];
    for x in relay.points() {
        h.iter_mut().for_each(|v| *v = rng.random::<f32>());
        set.push(Pair::confocal(x, relay.normal), &h).unwrap();
    }
    let scan = PlanarScan::full(*relay);
    (set, scan)
}

fn solvers(c: &mut Criterion) {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    println!("threads: {}", rayon::current_num_threads());
    let mut group = c.benchmark_group("solvers");
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1));

    // 0.24 s a run here: 5 s gives two or three runs a sample.
    group.measurement_time(Duration::from_secs(5));
    let points: Vec<DVec3> = (0..100_000)
        .map(|_| curved(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5)).0)
        .collect();
    group.throughput(Throughput::Elements(points.len() as u64));
    group.bench_function("normals", |b| {
        b.iter(|| estimate_normals(&points, 16, DVec3::new(0.0, 0.0, 2.0)).unwrap())
    });

    let settings = LctSettings::default();
    // 0.24 s and 1 s a run here: two or more runs a sample.
    for (name, n, seconds) in [("lct64", 64, 5), ("lct128", 128, 20)] {
        let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [1.0, 1.0], [n, n]).unwrap();
        let (set, scan) = noise_scan(&relay, 512, &mut rng);
        group
            .measurement_time(Duration::from_secs(seconds))
            .throughput(Throughput::Elements((n * n * 512) as u64));
        group.bench_function(name, |b| b.iter(|| lct_frame(&set, &scan, &settings).unwrap()));
    }
    // Fine bins over a deep volume: 16,384 bins of 0.3 mm (1 ps), 4.9 m of path, on a
    // 16 × 16 scan. Its own inputs (the rng of the benchmarks after it is untouched).
    {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [1.0, 1.0], [16, 16]).unwrap();
        let (set, scan) = noise_scan_of(&relay, 16_384, 0.0003, &mut rng);
        group
            .measurement_time(Duration::from_secs(10))
            .throughput(Throughput::Elements((16 * 16 * 16_384) as u64));
        group.bench_function("lct_deep", |b| {
            b.iter(|| lct_frame(&set, &scan, &settings).unwrap())
        });
    }
    println!("peak resident memory after the LCTs: {:.0} MiB", peak_rss_mib());

    let axis = TimeAxis::from_seconds(0.8, 32e-12, 512);
    let mut set = TransientSet::new(axis).unwrap();
    let mut h = vec![0.0f32; 512];
    for _ in 0..8000 {
        let (xi, ni) = curved(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        let (xd, nd) = curved(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        h.iter_mut().for_each(|v| *v = rng.random::<f32>());
        set.push(Pair { xi, ni, xd, nd }, &h).unwrap();
    }
    let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.5, 0.9], [128, 128, 64]).unwrap();
    let voxel_pairs = 8000 * grid.len() as u64;
    // 12 s a run here: one run a sample (two would take 4 minutes).
    group
        .measurement_time(Duration::from_secs(60))
        .throughput(Throughput::Elements(voxel_pairs));
    let fbp_last = LastSample::default();
    group.bench_function("fbp", |b| {
        b.iter(|| fbp(&set, &grid, &FbpSettings::default()).unwrap())
    });
    let hierarchical = FbpSettings {
        backprojection: FbpBackprojection::Hierarchical,
        ..FbpSettings::default()
    };
    group.bench_function("fbp_hierarchical", |b| {
        b.iter(|| fbp(&set, &grid, &hierarchical).unwrap())
    });
    let exact = FbpSettings {
        backprojection: FbpBackprojection::Exact,
        ..FbpSettings::default()
    };
    group.bench_function("fbp_exact", |b| {
        b.iter_custom(|iters| fbp_last.time(iters, || fbp(&set, &grid, &exact).unwrap()))
    });
    let mut one_laser = TransientSet::new(axis).unwrap();
    let (xi, ni) = curved(-0.3, 0.1);
    for _ in 0..8000 {
        let (xd, nd) = curved(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
        h.iter_mut().for_each(|v| *v = rng.random::<f32>());
        one_laser.push(Pair { xi, ni, xd, nd }, &h).unwrap();
    }
    // The exact path explicitly: the default, `auto`, takes the hierarchy here.
    group.bench_function("fbp_one_laser", |b| {
        b.iter(|| fbp(&one_laser, &grid, &exact).unwrap())
    });
    group.bench_function("fbp_one_laser_hierarchical", |b| {
        b.iter(|| fbp(&one_laser, &grid, &hierarchical).unwrap())
    });
    let gpu = bench_gpu();
    if let Some(gpu) = &gpu {
        group.bench_function("fbp_gpu", |b| {
            b.iter(|| fbp_on(&set, &grid, &FbpSettings::default(), gpu).unwrap())
        });
    }

    // A virtual scan that is no level grid (a curved relay's, as `periscope recon`
    // makes on the validation set's nonplanar_relay): 34 × 32 confocal points on the
    // curved panel onto the validation volume's 32 × 32 × 81 voxels. `auto` takes
    // leaves without merges here (merges would save under a third of their time).
    let mut curved_scan = TransientSet::new(TimeAxis::from_seconds(0.0, 16e-12, 512)).unwrap();
    for iy in 0..32 {
        for ix in 0..34 {
            let (x, n) = curved(-0.5 + (ix as f64 + 0.5) / 34.0, -0.5 + (iy as f64 + 0.5) / 32.0);
            h.iter_mut().for_each(|v| *v = rng.random::<f32>());
            curved_scan
                .push(
                    Pair {
                        xi: x,
                        ni: n,
                        xd: x,
                        nd: n,
                    },
                    &h,
                )
                .unwrap();
        }
    }
    let scan_grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.195, 1.005], [32, 32, 81]).unwrap();
    group
        .measurement_time(Duration::from_secs(10))
        .throughput(Throughput::Elements(
            curved_scan.len() as u64 * scan_grid.len() as u64,
        ));
    for (name, settings) in [
        ("fbp_curved_scan", &FbpSettings::default()),
        ("fbp_curved_scan_hierarchical", &hierarchical),
        ("fbp_curved_scan_exact", &exact),
    ] {
        group.bench_function(name, |b| {
            b.iter(|| fbp(&curved_scan, &scan_grid, settings).unwrap())
        });
    }

    // The virtual scan of `periscope recon` on a 1 m, 32 × 32 × 81 volume.
    let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [1.0, 1.0], [64, 64]).unwrap();
    let (set, _) = noise_scan(&relay, 512, &mut rng);
    let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.195, 1.005], [32, 32, 81]).unwrap();
    group
        .measurement_time(Duration::from_secs(10))
        .throughput(Throughput::Elements(set.len() as u64 * grid.len() as u64));
    group.bench_function("fbp_grid", |b| {
        b.iter(|| fbp(&set, &grid, &FbpSettings::default()).unwrap())
    });
    if let Some(gpu) = &gpu {
        group.bench_function("fbp_grid_gpu", |b| {
            b.iter(|| fbp_on(&set, &grid, &FbpSettings::default(), gpu).unwrap())
        });
    }

    let kernels: Vec<Kernel> = (0..10_000)
        .map(|_| {
            let x = DVec3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                rng.random_range(0.5..0.9),
            );
            let q = DQuat::from_euler(glam::EulerRot::XYZ, rng.random(), rng.random(), rng.random());
            let s = DVec3::new(
                rng.random_range(0.005..0.015),
                rng.random_range(0.005..0.015),
                rng.random_range(0.005..0.015),
            );
            Kernel::new(x, DMat3::from_quat(q), s, rng.random_range(0.1..1.0))
        })
        .collect();
    let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [1.0, 1.0], [64, 64]).unwrap();
    // 512 bins of 4.8 mm (16 ps) from path length 0: reaches 2.46 m, twice the
    // farthest ROI corner.
    let axis = TimeAxis::from_seconds(0.0, 16e-12, 512);
    let opt = RenderOptions::default();
    // 2.2–2.4 s a run here: 45 s gives two runs a sample.
    group
        .measurement_time(Duration::from_secs(45))
        .throughput(Throughput::Elements((relay.len() * kernels.len()) as u64));
    group.bench_function("synth", |b| {
        b.iter(|| synthesise(&kernels, &relay, axis, &opt).unwrap())
    });
    group.bench_function("synth_lct", |b| {
        b.iter(|| {
            let scan = synthesise(&kernels, &relay, axis, &opt).unwrap();
            lct_frame(&scan.set, &scan.scan, &settings).unwrap()
        })
    });
    // The same volume without the scan: each primitive splatted once, one filter.
    let volume = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.5, 0.9], [64, 64, 64]).unwrap();
    group.bench_function("splat_lct", |b| {
        b.iter(|| splat_lct(&kernels, &relay, &volume, axis, &opt, &settings).unwrap())
    });
    if let Some(gpu) = &gpu {
        group.bench_function("synth_gpu", |b| {
            b.iter(|| synthesise_on(gpu, &kernels, &relay, axis, &opt).unwrap())
        });
        group.bench_function("synth_lct_gpu", |b| {
            b.iter(|| {
                let scan = synthesise_on(gpu, &kernels, &relay, axis, &opt).unwrap();
                lct_frame(&scan.set, &scan.scan, &settings).unwrap()
            })
        });
    }
    // An adaptive capture's spread of the next batch: 128 pairs chosen among 65,536
    // confocal candidates (a 256 × 256 grid), 16,384 measured. `farthest_points`
    // measures every candidate against every pair measured; a capture keeps each
    // candidate's distance to the nearest measured pair instead (`Coverage`).
    {
        use periscope_recon::adaptive::{Coverage, farthest_points, farthest_points_from};
        let n = 256;
        let candidates: Vec<Pair> = (0..n * n)
            .map(|i| {
                let (x, y) = ((i % n) as f64 / n as f64 - 0.5, (i / n) as f64 / n as f64 - 0.5);
                Pair::confocal(DVec3::new(x, y, 0.0), DVec3::Z)
            })
            .collect();
        let measured = farthest_points(&candidates, &[], 16_384);
        let mut coverage = Coverage::new(candidates.len());
        for &i in &measured {
            coverage.take(&candidates, i);
        }
        group.bench_function("adaptive_spread_remade", |b| {
            b.iter(|| farthest_points(&candidates, &measured, 128))
        });
        group.bench_function("adaptive_spread_kept", |b| {
            b.iter(|| farthest_points_from(&candidates, &coverage, 128))
        });
    }
    group.finish();

    // Per voxel-pair, counted in the source: two squared distances (2 each after the
    // row constants), two roots, the index (4) and gain (1), the phasor's two
    // interpolations (2 × 4) and sums (2): 19 operations. Criterion's median is the
    // figure to quote; this says how far the last sample was from the CPU's peak.
    if let Some(t) = fbp_last.seconds() {
        println!(
            "FBP (exact path) 8000 pairs → 128 × 128 × 64, last sample {t:.3} s: {}",
            peak_share(19.0 * voxel_pairs as f64, t)
        );
    }
    println!("peak resident memory: {:.0} MiB", peak_rss_mib());
}

criterion_group!(benches, solvers);
criterion_main!(benches);

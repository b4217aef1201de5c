//! Relay geometry, virtual confocal synthesis and the conventional solvers (issue:
//! recon solvers), at the sizes the pipeline uses.
//!
//! Timed, each as the median of `SOLVER_BENCH_REPS` (default 3) runs after one warm-up:
//! - normals of 100,000 points of a curved panel (16 neighbours);
//! - LCT of a 64 × 64 × 512 and a 128 × 128 × 512 confocal scan (whole solver: cube,
//!   resampling, FFTs, Wiener filter, inverse; not the world-grid resampling);
//! - FBP of 8,000 arbitrary pairs on a curved relay into a 128 × 128 × 64 volume;
//! - virtual confocal synthesis of 64 × 64 × 512 from K = 10,000 Gaussians;
//! - synthesis + LCT for the 64 × 64 virtual grid (the 0.6 s target).
//!
//! Not timed: building scenes and inputs. `SOLVER_BENCH_ONLY` (comma list of
//! normals,lct64,lct128,fbp,synth,synth_lct) runs a subset.
use std::time::Instant;

mod support;
use support::{median, peak_rss_mib, peak_share};

use glam::{DMat3, DQuat, DVec3};
use periscope_recon::gtr::{Kernel, RenderOptions};
use periscope_recon::relay::{VirtualRelay, estimate_normals};
use periscope_recon::solver::{FbpSettings, LctSettings, PlanarScan, fbp, lct_frame};
use periscope_recon::synth::synthesise;
use periscope_recon::{Pair, TimeAxis, TransientSet, VolumeGrid};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> f64 {
    std::hint::black_box(f());
    median(
        (0..reps)
            .map(|_| {
                let t = Instant::now();
                std::hint::black_box(f());
                t.elapsed().as_secs_f64()
            })
            .collect(),
    )
}

fn curved(x: f64, y: f64) -> (DVec3, DVec3) {
    let z = 0.1 * (std::f64::consts::PI * x).sin();
    let slope = 0.1 * std::f64::consts::PI * (std::f64::consts::PI * x).cos();
    (DVec3::new(x, y, z), DVec3::new(-slope, 0.0, 1.0).normalize())
}

fn noise_scan(relay: &VirtualRelay, bins: usize, rng: &mut ChaCha8Rng) -> (TransientSet, PlanarScan) {
    let axis = TimeAxis {
        start: 0.0,
        width: 0.006,
        bins,
    };
    let mut set = TransientSet::new(axis).unwrap();
    let mut h = vec![0.0f32; bins];
    for x in relay.points() {
        h.iter_mut().for_each(|v| *v = rng.random::<f32>());
        set.push(Pair::confocal(x, relay.normal), &h).unwrap();
    }
    let scan = PlanarScan {
        relay: *relay,
        cells: (0..relay.len()).collect(),
    };
    (set, scan)
}

fn main() {
    let reps: usize = std::env::var("SOLVER_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let only = std::env::var("SOLVER_BENCH_ONLY").unwrap_or_default();
    let run = |name: &str| only.is_empty() || only.split(',').any(|o| o == name);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    println!("threads: {}, repetitions: {reps}", rayon::current_num_threads());

    if run("normals") {
        let points: Vec<DVec3> = (0..100_000)
            .map(|_| curved(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5)).0)
            .collect();
        let t = time(reps, || {
            estimate_normals(&points, 16, DVec3::new(0.0, 0.0, 2.0)).unwrap()
        });
        println!("normals, 100k points, k = 16:            {t:8.3} s");
    }
    let settings = LctSettings::default();
    for (name, n) in [("lct64", 64), ("lct128", 128)] {
        if run(name) {
            let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [1.0, 1.0], [n, n]).unwrap();
            let (set, scan) = noise_scan(&relay, 512, &mut rng);
            let t = time(reps, || lct_frame(&set, &scan, &settings).unwrap());
            println!(
                "LCT {n} × {n} × 512:                    {t:8.3} s   (peak RSS so far {:.0} MiB)",
                peak_rss_mib()
            );
        }
    }
    if run("fbp") {
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
        let t = time(reps, || fbp(&set, &grid, &FbpSettings::default()).unwrap());
        let voxel_pairs = 8000.0 * grid.len() as f64;
        let rate = voxel_pairs / t / 1e9;
        // Per voxel-pair, counted in the source: two squared distances (2 each after
        // the row constants), two roots, the index (4) and gain (1), the phasor's two
        // interpolations (2 × 4) and sums (2): 19 operations.
        println!(
            "FBP 8000 pairs → 128 × 128 × 64:         {t:8.3} s   ({rate:.2} G voxel-pairs/s; {})",
            peak_share(19.0 * voxel_pairs, t)
        );
    }
    if run("synth") || run("synth_lct") {
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
        if run("synth") {
            let t = time(reps, || synthesise(&kernels, &relay, axis, &opt).unwrap());
            let rate = 4096.0 * 10_000.0 / t / 1e6;
            println!("synthesis 64 × 64 × 512, K = 10,000:     {t:8.3} s   ({rate:.1} M evaluations/s)");
        }
        if run("synth_lct") {
            let t = time(reps, || {
                let scan = synthesise(&kernels, &relay, axis, &opt).unwrap();
                lct_frame(&scan.set, &scan.scan, &settings).unwrap()
            });
            println!("synthesis + LCT, 64 × 64 × 512:          {t:8.3} s   (target 0.6 s)");
        }
    }
    println!("peak RSS: {:.0} MiB", peak_rss_mib());
}

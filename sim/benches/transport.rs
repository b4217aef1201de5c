//! Third-bounce simulation at the size CI captures use (issue: sim): 8,000 pairs ×
//! 512 bins of 32 ps, a hidden mesh of about 2,000 triangles (a mannequin), visibility
//! included, then Poisson noise on every histogram.
//!
//! Timed (median of `SIM_BENCH_REPS`, default 3): building the world (BVH, hidden
//! samples) plus transport plus noise, for two pair layouts: 80 laser spots × 100
//! detection spots (180 distinct relay points) and 8,000 confocal spots (8,000
//! distinct points, the worst case for the per-point visibility tables).
//! Not timed: building the scene meshes.
use std::time::Instant;

use glam::DVec3;
use periscope_sim::scene::{ShapeKind, Surface};
use periscope_sim::{Detector, Instrument, Mesh, Scene, SpotPair, SurfaceHit, World, sample_counts, shapes};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn spot(x: f64, y: f64) -> SurfaceHit {
    SurfaceHit {
        point: DVec3::new(x, y, 0.0),
        normal: DVec3::Z,
        albedo: 0.8,
        distance: 2.0,
        on_relay: true,
    }
}

fn main() {
    let reps: usize = std::env::var("SIM_BENCH_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(3);
    let mut hidden = shapes::mannequin(1.0);
    // Finer limbs bring the figure to about 2,000 triangles.
    hidden.append(
        &Mesh::ellipsoid(DVec3::new(0.05, 0.05, 0.05), 24)
            .transformed(glam::DMat3::IDENTITY, DVec3::new(0.25, 0.9, 0.0)),
    );
    hidden.append(
        &Mesh::ellipsoid(DVec3::new(0.05, 0.05, 0.05), 16)
            .transformed(glam::DMat3::IDENTITY, DVec3::new(-0.25, 0.9, 0.0)),
    );
    let hidden = hidden.transformed(glam::DMat3::IDENTITY, DVec3::new(0.0, -0.5, 0.7));
    let triangles = hidden.triangles.len();
    let scene = Scene {
        name: "bench".into(),
        relay: Surface {
            label: "relay".into(),
            shape: ShapeKind::Plane,
            mesh: shapes::plane([2.0, 2.0]),
            albedo: 0.8,
        },
        hidden: vec![Surface {
            label: "hidden[0]".into(),
            shape: ShapeKind::Mannequin,
            mesh: hidden,
            albedo: 0.85,
        }],
    };
    let inst = Instrument {
        laser: DVec3::new(-0.1, 0.0, 2.0),
        spad: DVec3::new(0.1, 0.0, 2.0),
    };
    let det = Detector {
        bin_width: 32e-12,
        pile_up: true,
        ..Detector::example()
    };
    let grid = |i: usize, n: usize| -0.8 + 1.6 * (i as f64 + 0.5) / n as f64;
    let mut scanned = Vec::new();
    for l in 0..80 {
        for d in 0..100 {
            scanned.push(SpotPair {
                illumination: spot(grid(l % 10, 10), grid(l / 10, 8)),
                detection: spot(grid(d % 10, 10), grid(d / 10, 10)),
            });
        }
    }
    let confocal: Vec<SpotPair> = (0..8000)
        .map(|i| {
            let s = spot(grid(i % 100, 100), grid(i / 100, 80));
            SpotPair {
                illumination: s,
                detection: s,
            }
        })
        .collect();
    println!(
        "threads: {}, hidden triangles: {triangles}",
        rayon::current_num_threads()
    );
    for (name, pairs) in [
        ("80 lasers × 100 detectors", &scanned),
        ("8,000 confocal spots", &confocal),
    ] {
        let mut samples = 0;
        let mut counts = 0u64;
        let t = median(
            (0..reps)
                .map(|_| {
                    let start = Instant::now();
                    let world = World::new(scene.clone(), 0.005, 7);
                    samples = world.sample_count();
                    let expected = world.third_bounce(&inst, pairs, &det, 0.01);
                    counts = expected
                        .iter()
                        .enumerate()
                        .map(|(i, e)| {
                            sample_counts(e, 7, i as u64)
                                .iter()
                                .map(|&c| c as u64)
                                .sum::<u64>()
                        })
                        .sum();
                    start.elapsed().as_secs_f64()
                })
                .collect(),
        );
        println!(
            "{name}: {t:.3} s for 8,000 pairs × 512 bins ({samples} hidden samples, {counts} counts, target < 10 s)"
        );
    }
}

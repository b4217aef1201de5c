//! Third-bounce simulation at the size CI captures use (issue: sim): 8,000 pairs ×
//! 512 bins of 32 ps, a hidden mesh of about 2,000 triangles (a mannequin), visibility
//! included, then Poisson noise on every histogram.
//!
//! Timed (criterion, group `transport`, 10 samples): building the world (BVH, hidden
//! samples) plus transport plus noise, for two pair layouts: 80 laser spots × 100
//! detection spots (180 distinct relay points) and 8,000 confocal spots (8,000
//! distinct points, the worst case for the per-point visibility tables). Criterion's
//! median is the figure to quote (target < 10 s); its throughput line counts pairs.
//! Not timed: building the scene meshes. Printed once per layout that ran: the hidden
//! samples and the total counts of the last run.
use std::cell::Cell;
use std::time::Duration;

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use periscope_sim::scene::{ShapeKind, Surface};
use periscope_sim::{Detector, Instrument, Mesh, Scene, SpotPair, SurfaceHit, World, sample_counts, shapes};

fn spot(x: f64, y: f64) -> SurfaceHit {
    SurfaceHit {
        point: DVec3::new(x, y, 0.0),
        normal: DVec3::Z,
        albedo: 0.8,
        distance: 2.0,
        on_relay: true,
    }
}

fn transport(c: &mut Criterion) {
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
            variation: None,
        },
        hidden: vec![Surface {
            label: "hidden[0]".into(),
            shape: ShapeKind::Mannequin,
            mesh: hidden,
            albedo: 0.85,
            variation: None,
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

    let mut group = c.benchmark_group("transport");
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_secs(1))
        // 0.7 s and 7 s a run here: three runs a sample for the scanned layout, one for
        // the confocal one (criterion warns that 10 samples do not fit; two runs a
        // sample would take two and a half minutes). `--quick` stops after 20 s.
        .measurement_time(Duration::from_secs(20));
    let mut last = Vec::new();
    for (name, pairs) in [
        ("80 lasers x 100 detectors", &scanned),
        ("8000 confocal spots", &confocal),
    ] {
        // Hidden samples and total counts of the last run, printed after the group.
        let (samples, counts) = (Cell::new(0), Cell::new(0u64));
        group.throughput(Throughput::Elements(pairs.len() as u64));
        group.bench_function(name, |b| {
            b.iter(|| {
                let world = World::new(scene.clone(), 0.005, 7);
                samples.set(world.sample_count());
                let expected = world.third_bounce(&inst, pairs, &det, 0.01);
                counts.set(
                    expected
                        .iter()
                        .enumerate()
                        .map(|(i, e)| {
                            sample_counts(e, 7, i as u64)
                                .iter()
                                .map(|&c| c as u64)
                                .sum::<u64>()
                        })
                        .sum(),
                );
            })
        });
        last.push((name, samples.get(), counts.get()));
    }
    group.finish();
    for (name, samples, counts) in last.into_iter().filter(|l| l.1 > 0) {
        println!("{name}: 8,000 pairs × 512 bins, {samples} hidden samples, {counts} counts");
    }
}

criterion_group!(benches, transport);
criterion_main!(benches);

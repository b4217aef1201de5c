//! E-stop latency: about 100 emergency stops while the LOS scan dwells and about 100
//! while a capture dwells (10 s dwells, so every stop lands mid-acquisition), through
//! `Service::estop` exactly as `POST /api/v1/estop` calls it, on the simulator in real
//! time. Measured per stop: from the call to the moment the simulated laser controller
//! switched emission off (its own log), and to the e-stop's return (laser off, run
//! aborted, arms parked). Not timed: starting each run, which waits until the laser is
//! on and then a random 5–60 ms so the stop lands at an arbitrary point of a dwell.
//!
//! `cargo bench -p periscope-daemon --bench safety` (release). Criterion (group
//! `estop`, one iteration a stop, `iter_custom` summing the measured latencies) times
//! the e-stop → laser-off latency of each stage: its median is the figure to quote.
//! Printed after each stage, from the same stops (warm-up included): median, 90th
//! percentile and maximum of both latencies.
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, criterion_group, criterion_main};
use periscope_daemon::config::TomlSource;
use periscope_daemon::service::Service;
use periscope_sim::devices::Rig;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

// The plan the tests share (the end-to-end crate's `SmallPlan`).
#[allow(dead_code, unreachable_pub)]
#[path = "../../tests/support/plan.rs"]
mod small_plan;
use small_plan::SmallPlan;

fn plan(los_dwell_ms: f64, pair_dwell_ms: f64) -> String {
    SmallPlan::named("estop-bench")
        .set("los.grid", [6, 6])
        .set("los.dwell-ms", los_dwell_ms)
        .set("pairs.grid", [3, 3])
        .set("pairs.offset-mm", 0.0)
        .set("acquisition.dwell-ms", pair_dwell_ms)
        .set("recon.volume.shape", [8, 8, 8])
        .toml()
}

fn service(runs: &Path) -> Arc<Service> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/instrument/sim.toml");
    let mut text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[sim]\n", "[sim]\ntime-scale = 1.0\n");
    text.push_str(&format!("\n[api]\nruns-dir = \"{}\"\n", runs.display()));
    Service::open(TomlSource::from_text(path, text), None).unwrap()
}

fn stats(name: &str, mut v: Vec<Duration>) {
    if v.is_empty() {
        return;
    }
    v.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    println!(
        "{name:<44} median {:>7.2} ms   p90 {:>7.2} ms   max {:>7.2} ms   ({} tries)",
        ms(v[v.len() / 2]),
        ms(v[v.len() * 9 / 10]),
        ms(*v.last().unwrap()),
        v.len()
    );
}

/// One stop: starts a run, waits until it is in `stage` with the laser on and then a
/// random 5–60 ms (not timed), e-stops it and waits until it is aborted. Returns the
/// latencies to the laser's switch-off and to the e-stop's return.
fn stop(svc: &Service, rig: &Rig, stage: &str, plan: &str, rng: &mut ChaCha8Rng) -> (Duration, Duration) {
    let id = svc.submit(plan.to_owned()).unwrap().id;
    let start = Instant::now();
    while !(svc.status(&id).unwrap().stage == stage && rig.emission()) {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "run {id} never reached {stage}"
        );
        std::thread::sleep(Duration::from_micros(500));
    }
    std::thread::sleep(Duration::from_millis(rng.random_range(5..60)));
    let t = Instant::now();
    let report = svc.estop().unwrap();
    let done = t.elapsed();
    let off_at = rig.off_since(t).expect("the laser is on after the e-stop");
    assert!(report.parked && report.warnings.is_empty(), "{report:?}");
    // Release the queue hold the e-stop put on nothing (no queued runs here).
    while svc.status(&id).unwrap().state != periscope_daemon::run_dir::RunState::Aborted {
        std::thread::sleep(Duration::from_millis(1));
    }
    (off_at - t, done)
}

fn safety(c: &mut Criterion) {
    let mut rng = ChaCha8Rng::seed_from_u64(17);
    let mut group = c.benchmark_group("estop");
    // One iteration is one stop, and the laser goes off 0.06–0.16 ms after the call
    // here: a warm-up of a few stops and 10 ms of measured latency make about 100
    // stops (each takes about a tenth of a second of untimed set-up).
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_micros(500))
        .measurement_time(Duration::from_millis(10));
    for (stage, plan) in [
        ("los-scan", plan(10_000.0, 20.0)),
        ("capture", plan(1.0, 10_000.0)),
    ] {
        let runs = tempfile::tempdir().unwrap();
        let svc = service(runs.path());
        let worker = svc.start_worker();
        let rig = periscope_daemon::devices::sim::rig_of(svc.backend())
            .unwrap()
            .clone();
        let (mut off, mut done) = (Vec::new(), Vec::new());
        group.bench_function(format!("{stage}: e-stop to laser off"), |b| {
            b.iter_custom(|iters| {
                let mut sum = Duration::ZERO;
                for _ in 0..iters {
                    let (o, d) = stop(&svc, &rig, stage, &plan, &mut rng);
                    sum += o;
                    off.push(o);
                    done.push(d);
                }
                sum
            })
        });
        stats(&format!("{stage}: e-stop → simulated laser off"), off);
        stats(
            &format!("{stage}: e-stop → returned (off, aborted, parked)"),
            done,
        );
        svc.shutdown();
        worker.join().unwrap();
    }
    group.finish();
}

criterion_group!(benches, safety);
criterion_main!(benches);

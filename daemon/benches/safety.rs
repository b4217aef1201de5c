//! E-stop latency: 100 emergency stops while the LOS scan dwells and 100 while a
//! capture dwells (10 s dwells, so every stop lands mid-acquisition), through
//! `Service::estop` exactly as `POST /api/v1/estop` calls it, on the simulator in real
//! time. Timed: from the call to the moment the simulated laser controller switched
//! emission off (its own log), and to the e-stop's return (laser off, run aborted, arms
//! parked). Not timed: starting each run, which waits until the laser is on and then a
//! random 5–60 ms so the stop lands at an arbitrary point of a dwell.
//!
//! `cargo bench -p periscope-daemon --bench safety` (release); prints median, 90th
//! percentile and maximum.
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use periscope_daemon::api::Service;
use periscope_daemon::config::TomlSource;
use rand::{Rng, SeedableRng};

const TRIES: usize = 100;

fn plan(los_dwell_ms: f64, pair_dwell_ms: f64) -> String {
    format!(
        r#"
name = "estop-bench"
[los]
angles-deg = {{ x = [-12.0, 12.0], y = [-12.0, 12.0] }}
grid = [6, 6]
dwell-ms = {los_dwell_ms}
[relay]
depth-m = [1.7, 3.0]
neighbours = 8
detection = {{ min = [-0.4, -0.4, -0.1], max = [0.4, 0.4, 0.1] }}
[pairs]
mode = "confocal"
grid = [3, 3]
[acquisition]
dwell-ms = {pair_dwell_ms}
[recon]
method = "fbp"
[recon.volume]
x = [-0.4, 0.4]
y = [-0.4, 0.4]
z = [0.3, 0.9]
shape = [8, 8, 8]
"#
    )
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

fn measure(stage: &str, plan: &str, rng: &mut rand_chacha::ChaCha8Rng) {
    let runs = tempfile::tempdir().unwrap();
    let svc = service(runs.path());
    let worker = svc.start_worker();
    let rig = svc.rig().unwrap().clone();
    let (mut off, mut done) = (Vec::new(), Vec::new());
    for _ in 0..TRIES {
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
        done.push(t.elapsed());
        let off_at = rig.off_since(t).expect("the laser is on after the e-stop");
        off.push(off_at - t);
        assert!(report.parked && report.warnings.is_empty(), "{report:?}");
        // Release the queue hold the e-stop put on nothing (no queued runs here).
        while svc.status(&id).unwrap().state != periscope_daemon::store::RunState::Aborted {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    stats(&format!("{stage}: e-stop → simulated laser off"), off);
    stats(
        &format!("{stage}: e-stop → returned (off, aborted, parked)"),
        done,
    );
    svc.shutdown();
    worker.join().unwrap();
}

fn main() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
    measure("los-scan", &plan(10_000.0, 20.0), &mut rng);
    measure("capture", &plan(1.0, 10_000.0), &mut rng);
}

//! A run's reconstruction is the same bit for bit whatever the timing: the fit that
//! streams alongside the capture schedules its live epochs by the batches received,
//! never by the clock, so a capture slowed down pair by pair (a busy machine, a slow
//! instrument) gives the same Gaussians and the same volume as one at full speed. The
//! simulator's in-process devices give the same run as its wire-level ones.
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Duration;

use periscope_daemon::config::{InstrumentConfig, TomlSource};
use periscope_daemon::events::{EventSink, RunEvent};
use periscope_daemon::pipeline::{self, Control, Run};
use periscope_recon::gtr::TrainEvent;

mod common;
use common::SmallPlan;

/// A 12 × 12 confocal grid: the fit starts at 64 pairs and takes the rest in batches of
/// 32 while the capture runs.
fn plan() -> String {
    SmallPlan::named("reproducible")
        .set("los.grid", [32, 32])
        .set("pairs.grid", [12, 12])
        .set("acquisition.dwell-ms", 5.0)
        .set("recon.method", "gtr")
        .set("recon.solver", "fbp")
        .set("recon.volume.shape", [16, 16, 16])
        .set("recon.gtr.primitives", 300)
        .set("recon.gtr.epochs", 4)
        .set("recon.gtr.virtual-grid", [16, 16])
        .toml()
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Runs the plan on the simulated instrument, sleeping `pause` after each stored pair;
/// returns the run directory and the number of live epochs (run during the capture).
fn run(tmp: &Path, name: &str, pause: Duration) -> (PathBuf, usize) {
    run_on(tmp, name, pause, "wire")
}

/// [`run`] with `sim.devices` set to `devices`.
fn run_on(tmp: &Path, name: &str, pause: Duration, devices: &str) -> (PathBuf, usize) {
    let path = root().join("configs/instrument/sim.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[sim]\n", &format!("[sim]\ndevices = \"{devices}\"\n"));
    let src = TomlSource::from_text(path, text);
    let config = InstrumentConfig::from_source(&src).unwrap();
    let rig = periscope_daemon::devices::sim::SimBackend::from_config(&config)
        .unwrap()
        .unwrap();
    let plan = TomlSource::from_text(tmp.join("plan.toml"), plan());
    let (dir, _, _) = pipeline::prepare(&plan, &src, Some(&tmp.join(name)), "test").unwrap();
    let events = EventSink::open(&dir).unwrap();
    let live = Arc::new(AtomicUsize::new(0));
    let counter = live.clone();
    events.listen(move |e| {
        if let RunEvent::Pair { .. } = e {
            std::thread::sleep(pause);
        }
        if let RunEvent::Train(TrainEvent::Epoch { epoch: 0, .. }) = e {
            counter.fetch_add(1, Ordering::SeqCst);
        }
    });
    Run::open(&dir, Control::new(), Some(events), Some(&rig))
        .unwrap()
        .execute()
        .unwrap();
    (dir, live.load(Ordering::SeqCst))
}

#[test]
fn a_slowed_capture_reconstructs_the_same_volume_bit_for_bit() {
    let tmp = tempfile::tempdir().unwrap();
    let (fast, live_fast) = run(tmp.path(), "fast", Duration::ZERO);
    let (slow, live_slow) = run(tmp.path(), "slow", Duration::from_millis(15));
    for f in ["histograms.bin", "gaussians.ply", "volume.npy", "depth.npy"] {
        let (a, b) = (
            std::fs::read(fast.join(f)).unwrap(),
            std::fs::read(slow.join(f)).unwrap(),
        );
        assert!(a == b, "{f} differs between a fast and a slowed capture");
    }
    // The fit streamed: one live epoch per batch in both (122 of the 144 grid pairs
    // land on the scanned relay: batches at 64, 96 and 122 pairs).
    let planned = std::fs::read_to_string(fast.join("pairs.json"))
        .unwrap()
        .matches("\"xi\"")
        .count();
    assert!(planned > 96, "{planned} pairs: too few to stream two batches");
    let batches = 1 + (planned - 64).div_ceil(32);
    assert_eq!((live_fast, live_slow), (batches, batches));
}

#[test]
fn in_process_devices_give_the_wire_devices_run_bit_for_bit() {
    let tmp = tempfile::tempdir().unwrap();
    let (wire, _) = run_on(tmp.path(), "wire", Duration::ZERO, "wire");
    let (local, _) = run_on(tmp.path(), "in-process", Duration::ZERO, "in-process");
    for f in [
        "relay.ply",
        "pairs.json",
        "histograms.bin",
        "gaussians.ply",
        "volume.npy",
    ] {
        let (a, b) = (
            std::fs::read(wire.join(f)).unwrap(),
            std::fs::read(local.join(f)).unwrap(),
        );
        assert!(!a.is_empty(), "{f} is empty");
        assert!(
            a == b,
            "{f} differs between the wire-level and the in-process devices"
        );
    }
}

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
    let (dir, live, _) = run_plan(tmp, name, pause, devices, &plan());
    (dir, live)
}

/// What a run's listener saw of an adaptive capture's choices: how many batches were
/// chosen, and how many of those the laser was on for while the fit chose them.
#[derive(Debug, Default, PartialEq)]
struct Choices {
    batches: usize,
    chosen_with_the_laser_on: usize,
}

/// Runs `plan` (see [`run`]); also returns what the listener saw of adaptive choices.
fn run_plan(tmp: &Path, name: &str, pause: Duration, devices: &str, plan: &str) -> (PathBuf, usize, Choices) {
    run_plan_with(tmp, name, pause, devices, plan, |_| {})
}

/// [`run_plan`], with `before` given the prepared run's directory before it runs.
fn run_plan_with(
    tmp: &Path,
    name: &str,
    pause: Duration,
    devices: &str,
    plan: &str,
    before: impl FnOnce(&Path),
) -> (PathBuf, usize, Choices) {
    let path = root().join("configs/instrument/sim.toml");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[sim]\n", &format!("[sim]\ndevices = \"{devices}\"\n"));
    let src = TomlSource::from_text(path, text);
    let config = InstrumentConfig::from_source(&src).unwrap();
    let rig = periscope_daemon::devices::sim::SimBackend::from_config(&config)
        .unwrap()
        .unwrap();
    let plan = TomlSource::from_text(tmp.join("plan.toml"), plan.to_owned());
    let (dir, _, _) = pipeline::prepare(&plan, &src, Some(&tmp.join(name)), "test").unwrap();
    before(&dir);
    let events = EventSink::open(&dir).unwrap();
    let live = Arc::new(AtomicUsize::new(0));
    let counter = live.clone();
    let choices = Arc::new(std::sync::Mutex::new((Choices::default(), false)));
    let seen = choices.clone();
    events.listen(move |e| {
        if let RunEvent::Pair { .. } = e {
            std::thread::sleep(pause);
        }
        if let RunEvent::Train(TrainEvent::Epoch { epoch: 0, .. }) = e {
            counter.fetch_add(1, Ordering::SeqCst);
        }
        let mut seen = seen.lock().unwrap();
        match e {
            RunEvent::Safety { emission, .. } => seen.1 = *emission,
            RunEvent::PairsChosen(_) => {
                seen.0.batches += 1;
                if seen.1 {
                    seen.0.chosen_with_the_laser_on += 1;
                }
            }
            _ => {}
        }
    });
    Run::open(&dir, Control::new(), Some(events), Some(&rig))
        .unwrap()
        .execute()
        .unwrap();
    let choices = std::mem::take(&mut choices.lock().unwrap().0);
    (dir, live.load(Ordering::SeqCst), choices)
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

/// An adaptive capture (`[pairs] mode = "adaptive"`) over the same 12 × 12 grid: the
/// fit chooses each batch after the last one's live training, so a slowed capture
/// chooses the same pairs and reconstructs the same volume bit for bit; it measures its
/// budget and no more, and the laser is off whenever the fit is choosing.
#[test]
fn an_adaptive_capture_chooses_the_same_pairs_however_slow_the_instrument() {
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 60\nfirst = 24\nbatch = 12\nlive-steps = 32\n";
    assert!(adaptive.contains("candidates"), "the plan's [pairs] mode");
    let tmp = tempfile::tempdir().unwrap();
    let (fast, _, fast_choices) = run_plan(tmp.path(), "fast", Duration::ZERO, "wire", &adaptive);
    let (slow, _, slow_choices) = run_plan(tmp.path(), "slow", Duration::from_millis(15), "wire", &adaptive);
    for f in ["histograms.bin", "gaussians.ply", "volume.npy"] {
        let (a, b) = (
            std::fs::read(fast.join(f)).unwrap(),
            std::fs::read(slow.join(f)).unwrap(),
        );
        assert!(a == b, "{f} differs between a fast and a slowed adaptive capture");
    }
    let chosen = |dir: &Path| -> Vec<serde_json::Value> {
        std::fs::read_to_string(dir.join("events.jsonl"))
            .unwrap()
            .lines()
            .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
            .filter(|v| v["event"] == "pairs-chosen")
            .map(|v| serde_json::json!({"how": v["how"], "pairs": v["pairs"], "gains": v["gains"], "measured": v["measured"]}))
            .collect()
    };
    let (a, b) = (chosen(&fast), chosen(&slow));
    assert_eq!(a, b, "the choices differ");
    // 24 spread, then three batches of 12 chosen by the fit: 60 pairs measured.
    assert_eq!(a.len(), 4, "{a:?}");
    assert_eq!(a[0]["how"], "spread");
    assert!(
        a[1..]
            .iter()
            .all(|b| b["how"] == "adaptive" && b["pairs"].as_array().unwrap().len() == 12)
    );
    assert_eq!(a[3]["measured"], 60);
    let stored = periscope_daemon::store::HistogramLog::recover(&fast)
        .unwrap()
        .1
        .records
        .len();
    assert_eq!(stored, 60, "pairs measured");
    assert_eq!(
        fast_choices,
        Choices {
            batches: 4,
            chosen_with_the_laser_on: 0
        }
    );
    assert_eq!(fast_choices, slow_choices);
}

/// The time budget (`[recon.adaptive] seconds`) ends the choosing: a budget shorter
/// than the first batch leaves that batch, measured whole, and nothing chosen after it.
#[test]
fn an_adaptive_capture_stops_choosing_at_its_time_budget() {
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 60\nfirst = 24\nbatch = 12\nlive-steps = 32\nseconds = 0.001\n";
    let tmp = tempfile::tempdir().unwrap();
    let (dir, live, choices) = run_plan(tmp.path(), "timed", Duration::ZERO, "wire", &adaptive);
    assert_eq!(choices.batches, 1, "{choices:?}");
    let stored = periscope_daemon::store::HistogramLog::recover(&dir)
        .unwrap()
        .1
        .records
        .len();
    assert_eq!(stored, 24, "the first batch, whole");
    assert!(dir.join("volume.npy").is_file());
    // Out of time before the first choice: no live training is waited for, and
    // run.json says what ended the capture.
    assert_eq!(live, 0, "live trainings started");
    let info = periscope_daemon::run_dir::RunInfo::load(&dir).unwrap();
    let why = info.adaptive_stopped.expect("the time budget ended the capture");
    assert!(why.contains("adaptive.seconds"), "{why}");
}

/// A capture whose batch fills its pair budget ends there: no live training is waited
/// for after it (no choice needs one), and however long it took, no stop before the
/// budget is recorded. Before 2026-12-07 it waited for the live training and then,
/// past `seconds`, recorded the time budget as having ended a capture that had
/// measured every pair.
#[test]
fn an_adaptive_capture_that_measures_its_budget_is_not_recorded_as_stopped_early() {
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 24\nfirst = 24\nbatch = 12\nlive-steps = 32\nseconds = 0.001\n";
    let tmp = tempfile::tempdir().unwrap();
    let (dir, live, choices) = run_plan(tmp.path(), "whole", Duration::ZERO, "wire", &adaptive);
    assert_eq!(
        (choices.batches, live),
        (1, 0),
        "{choices:?}, live trainings {live}"
    );
    let stored = periscope_daemon::store::HistogramLog::recover(&dir)
        .unwrap()
        .1
        .records
        .len();
    assert_eq!(stored, 24);
    let info = periscope_daemon::run_dir::RunInfo::load(&dir).unwrap();
    assert_eq!(info.adaptive_stopped, None);
    assert!(dir.join("volume.npy").is_file());
}

/// The time budget counts every session of a resumed capture: a run whose earlier
/// sessions spent its `seconds` (as run.json records them) measures its first batch
/// and chooses nothing after it, where a fresh one of the same plan chooses on.
#[test]
fn a_resumed_adaptive_capture_counts_the_time_its_earlier_sessions_spent() {
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 60\nfirst = 24\nbatch = 12\nlive-steps = 32\nseconds = 600\n";
    let tmp = tempfile::tempdir().unwrap();
    let spent = |dir: &Path| {
        let mut info = periscope_daemon::run_dir::RunInfo::load(dir).unwrap();
        info.adaptive_seconds = 600.0;
        info.save(dir).unwrap();
    };
    let (dir, _, choices) = run_plan_with(tmp.path(), "spent", Duration::ZERO, "wire", &adaptive, spent);
    assert_eq!(choices.batches, 1, "{choices:?}");
    let info = periscope_daemon::run_dir::RunInfo::load(&dir).unwrap();
    assert!(info.adaptive_seconds > 600.0, "{}", info.adaptive_seconds);
    let (fresh, _, choices) = run_plan(tmp.path(), "fresh", Duration::ZERO, "wire", &adaptive);
    assert_eq!(choices.batches, 4, "{choices:?}");
    let info = periscope_daemon::run_dir::RunInfo::load(&fresh).unwrap();
    assert!(info.adaptive_seconds > 0.0 && info.adaptive_seconds < 600.0);
}

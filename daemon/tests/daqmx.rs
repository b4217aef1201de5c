//! A whole run with both galvo pairs and the laser on an NI DAQ device, through the
//! real FFI path: the daemon's hardware backend opens the DAQmx drivers and the
//! MultiHarp driver on the stand-in library (`standins`), by the paths in an ordinary
//! lab config; one simulated rig answers both, as one bench does (the DAQ's analog
//! outputs move its mirrors, its gate line its laser).
//!
//! The capture completes with the relay found and every pair stored; then the stop
//! matrix's measuring stages (LOS scan, capture) × every event run on this bench,
//! asserting on the rig's own emission log: laser off within 50 ms of the event, never
//! on again, both arms parked, the run left paused, aborted or failed as it should be.
//! A DAQ that vanishes mid-capture drops the gate (power loss) and fails the run; a run
//! stuck with the laser on loses it to the DAQ's hardware watchdog with nobody at the
//! e-stop. `periscope devices` lists what NI-DAQmx sees.
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

use periscope_daemon::config::TomlSource;
use periscope_daemon::events::{EventSink, RunEvent, Stage};
use periscope_daemon::pipeline::{self, Control, Run};
use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_standins::client::{Standin, exclusive};

#[path = "common/standin_matrix.rs"]
mod standin_matrix;
use standin_matrix::PLAN;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The shipped simulated instrument's text at `time_scale`, its scene path absolute.
fn sim_text(time_scale: f64) -> String {
    let scene = root().join("configs/scenes/wall-letter.toml");
    std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("../scenes/wall-letter.toml", &scene.to_string_lossy())
        .replace("[sim]\n", &format!("[sim]\ntime-scale = {time_scale}\n"))
}

/// The same instrument as a lab config: `backend = "hardware"`, both galvo pairs on
/// `Dev1`'s analog outputs and the laser on its digital lines through `library`
/// (NI-DAQmx's place), `laser_extra` added to `[laser]`; the histogrammer a MultiHarp
/// through the same library, bins 20 ps wide (its 5 ps base resolution × 4).
fn lab_text(time_scale: f64, library: &Path, laser_extra: &str) -> String {
    let text = sim_text(time_scale);
    let text = text[..text.find("[sim]").unwrap()].to_owned();
    let lib = library.display();
    let mut out = String::new();
    for line in text.lines() {
        let line = match line {
            l if l.starts_with("backend") => "backend = \"hardware\"".to_owned(),
            l if l.starts_with("bin-width-ps") => "bin-width-ps = 20.0".to_owned(),
            l => l.to_owned(),
        };
        out.push_str(&line);
        out.push('\n');
        if line.starts_with("[galvo.laser]") {
            out.push_str(&format!(
                "scanner = \"pivot\"\ndriver = \"daqmx\"\nlibrary = \"{lib}\"\nchannels = [\"Dev1/ao0\", \"Dev1/ao1\"]\n\
                 volts-per-deg = [0.4, 0.4]\noffsets-v = [0.1, -0.1]\nmax-slew-deg-per-ms = 4.0\n"
            ));
        } else if line.starts_with("[galvo.spad]") {
            out.push_str(&format!(
                "scanner = \"pivot\"\ndriver = \"daqmx\"\nlibrary = \"{lib}\"\nchannels = [\"Dev1/ao2\", \"Dev1/ao3\"]\n\
                 volts-per-deg = [0.4, -0.4]\nmax-slew-deg-per-ms = 4.0\n"
            ));
        } else if line.starts_with("[laser]") {
            out.push_str(&format!(
                "laser-line = \"Dev1/port0/line0\"\ninterlock-line = \"Dev1/port0/line1\"\n\
                 diffuser-line = \"Dev1/port0/line2\"\n{laser_extra}"
            ));
        } else if line.starts_with("[tdc]") {
            out.push_str(&format!(
                "driver = \"multiharp\"\nlibrary = \"{lib}\"\nchannel = 1\n"
            ));
        }
    }
    out
}

/// A fresh stand-in at `time_scale`, its DAQ wired by the lab config that reaches it.
fn bench(dir: &Path, time_scale: f64, laser_extra: &str) -> (Standin, TomlSource) {
    let s = Standin::load();
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, sim_text(time_scale)).unwrap();
    s.setup(&rig);
    let lab = dir.join("lab.toml");
    let text = lab_text(time_scale, &s.path(), laser_extra);
    std::fs::write(&lab, &text).unwrap();
    s.daq_setup(&lab);
    (s, TomlSource::from_text(lab, text))
}

/// A prepared run of `plan` on the lab config.
fn prepare(dir: &Path, lab: &TomlSource, plan: &str) -> PathBuf {
    let plan_src = TomlSource::from_text(dir.join("plan.toml"), plan.to_owned());
    let (run, _, _) = pipeline::prepare(&plan_src, lab, Some(&dir.join("run")), "test").unwrap();
    run
}

#[test]
fn a_whole_capture_runs_with_the_galvos_and_the_laser_on_a_daq() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 0.0, "");
    let dir = prepare(tmp.path(), &lab, PLAN);
    s.clear_calls();
    let planned = standin_matrix::whole_capture(&dir);
    // The histograms came through MHLib's calls: one StartMeas per LOS point and pair;
    // the mirrors moved through DAQmx's analog writes, the laser through its gate line
    // with the watchdog armed first.
    let calls = s.calls();
    assert!(
        calls
            .iter()
            .filter(|c| c.starts_with("DAQmxWriteAnalogF64(periscope-galvo-spad"))
            .count()
            > planned
    );
    let armed = calls
        .iter()
        .position(|c| c.starts_with("DAQmxStartTask(watchdog)"))
        .unwrap();
    let on = calls
        .iter()
        .position(|c| c == "DAQmxWriteDigitalLines(periscope-laser-gate, [1])")
        .unwrap();
    assert!(armed < on, "the watchdog runs before the gate goes high");
    assert_eq!(
        s.daq_counters().0,
        0,
        "no write drove an arm past the rig's hard limits"
    );
    let starts = calls.iter().filter(|c| c.starts_with("MH_StartMeas(")).count();
    assert_eq!(starts, 64 + planned, "64 LOS points and the planned pairs");
    assert!(
        calls.iter().any(|c| c == "MH_StartMeas(0, 10)") && calls.iter().any(|c| c == "MH_StartMeas(0, 30)")
    );
    // The laser went on for the measuring stages only, and is off; both arms parked.
    let log = s.emission_log();
    assert!(
        log.iter().any(|(_, on, _)| *on),
        "the laser was switched on to measure"
    );
    assert!(!s.emission());
    assert_eq!(s.parked(), (true, true));
}

/// A fresh bench and prepared run for one case of the stop matrix.
fn matrix_bench(tmp: &Path) -> (Standin, PathBuf) {
    let (s, lab) = bench(tmp, 1.0, "");
    let dir = prepare(tmp, &lab, PLAN);
    (s, dir)
}

#[test]
fn los_scan_on_the_daq() {
    standin_matrix::check_stage(Stage::LosScan, &matrix_bench);
}

#[test]
fn capture_on_the_daq() {
    standin_matrix::check_stage(Stage::Capture, &matrix_bench);
}

/// Runs the plan in real time until the first pair is stored, then `during(s)`; waits
/// for the run to return.
fn capture_then(
    laser_extra: &str,
    during: impl FnOnce(&Standin, &Control) + Send + 'static,
) -> (Standin, PathBuf, Result<(), String>) {
    capture_plan_then(PLAN, laser_extra, during)
}

/// [`capture_then`] with `plan`.
fn capture_plan_then(
    plan: &str,
    laser_extra: &str,
    during: impl FnOnce(&Standin, &Control) + Send + 'static,
) -> (Standin, PathBuf, Result<(), String>) {
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 1.0, laser_extra);
    let dir = prepare(tmp.path(), &lab, plan);
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    let (tx, rx) = mpsc::channel::<()>();
    let mut armed = true;
    events.listen(move |e| {
        if armed && matches!(e, RunEvent::Pair { .. }) {
            armed = false;
            let _ = tx.send(());
        }
    });
    let trigger = {
        let control = control.clone();
        std::thread::spawn(move || {
            if rx.recv().is_ok() {
                during(&s, &control);
            }
            s
        })
    };
    let result = Run::open(&dir, control, Some(events), None)
        .and_then(|run| run.execute().map(drop))
        .map_err(|e| e.to_string());
    let s = trigger.join().unwrap();
    let keep = tmp.keep();
    (s, keep.join("run"), result)
}

#[test]
fn a_daq_that_vanishes_mid_capture_drops_the_gate_and_fails_the_run() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let (s, dir, result) = capture_then("", |s, _| {
        std::thread::sleep(Duration::from_millis(7));
        s.daq_vanish();
    });
    let e = result.unwrap_err();
    assert!(e.contains("DAQmxErrorDeviceRemoved"), "{e}");
    assert!(!s.emission());
    let log = s.emission_log();
    let (_, on, cause) = *log.last().unwrap();
    assert!(
        !on && cause == 3,
        "the gate dropped with the device's power: {log:?}"
    );
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Failed);
    let _ = std::fs::remove_dir_all(dir.parent().unwrap());
}

/// The interlock loop opened for 60 ms and closed again inside a pair's 300 ms dwell,
/// so the run's own reading after the pair finds it closed: the DAQ's gate stays high
/// throughout, and the driver latches it low when its keepalive reads the loop open,
/// so the run finds the emission lost and suspends, to measure that pair again. Until
/// 2026-12-08 the gate stayed high, the driver read emission on, and the stand-in's
/// laser (latched off by the loop, as the serial controller's is) left that pair and
/// every one after it dark and stored as whole.
#[test]
fn an_interlock_opened_and_closed_mid_capture_latches_the_daq_gate_low() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let blip: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let b = blip.clone();
    // The keepalive reads the loop every 25 ms.
    let plan = PLAN.replace("dwell-ms = 30.0", "dwell-ms = 300.0");
    assert_ne!(plan, PLAN);
    let (s, dir, result) = capture_plan_then(&plan, "watchdog-ms = 100\n", move |s, _| {
        std::thread::sleep(Duration::from_millis(20));
        *b.lock().unwrap() = Some(Instant::now());
        s.set_interlock(false);
        std::thread::sleep(Duration::from_millis(60));
        s.set_interlock(true);
    });
    let e = result.expect_err("the run went on after the loop opened");
    assert!(e.contains("emission"), "{e}");
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
    assert!(!s.emission());
    // Nothing gated the laser on after the loop opened.
    let opened = blip.lock().unwrap().unwrap();
    let log = s.emission_log();
    assert!(log.iter().all(|(at, on, _)| !on || *at < opened), "{log:?}");
    let _ = std::fs::remove_dir_all(dir.parent().unwrap());
}

#[test]
fn a_run_stuck_with_the_laser_on_loses_it_to_the_daqs_watchdog_without_an_estop() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let hung: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let h = hung.clone();
    // Stall limit 300 ms, watchdog 200 ms: off within about half a second of the hang.
    let (s, dir, _) = capture_then("stall-ms = 300\nwatchdog-ms = 200\n", move |s, control| {
        control.inject_hang(Stage::Capture, Duration::from_millis(1500));
        let t = Instant::now();
        *h.lock().unwrap() = Some(t);
        while s.emission() && t.elapsed() < Duration::from_secs(3) {
            std::thread::sleep(Duration::from_millis(2));
        }
    });
    let t = hung.lock().unwrap().unwrap();
    let log = s.emission_log();
    let (off_at, on, cause) = *log
        .iter()
        .rev()
        .find(|(at, on, _)| !on && *at > t)
        .expect("switched off during the hang");
    assert!(!on);
    assert_eq!(
        cause, 1,
        "the DAQ's watchdog switched it off, not the host: {log:?}"
    );
    let after = off_at.saturating_duration_since(t);
    assert!(
        after <= Duration::from_millis(300 + 200 + 250),
        "off {after:?} after the hang began"
    );
    eprintln!(
        "stuck run on the DAQ: laser off {:.0} ms after the hang began",
        after.as_secs_f64() * 1e3
    );
    assert!(!s.emission());
    let _ = std::fs::remove_dir_all(dir.parent().unwrap());
}

/// A gate that will not go low when the run stops (its writes fail: a DAQ whose
/// digital output hangs) keeps its hardware watchdog armed and unfed, so the watchdog
/// drives it low within its timeout. Until 2026-12-06 the switch-off cleared the
/// watchdog whatever the write did, and the laser stayed on with nothing left to end
/// it (the stand-in's emission stayed on for the whole wait).
#[test]
fn a_gate_that_will_not_go_low_is_ended_by_the_daqs_watchdog() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let stopped: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let at = stopped.clone();
    let (s, dir, _) = capture_then("watchdog-ms = 200\n", move |s, control| {
        // Every write of the gate low on the way out fails: the capture's own
        // switch-off, the run's make-safe, and the driver's close.
        for _ in 0..3 {
            s.daq_fail_next("DAQmxWriteDigitalLines", -200_279);
        }
        let t = Instant::now();
        *at.lock().unwrap() = Some(t);
        control.pause();
        while s.emission() && t.elapsed() < Duration::from_secs(3) {
            std::thread::sleep(Duration::from_millis(2));
        }
    });
    let t = stopped.lock().unwrap().unwrap();
    let log = s.emission_log();
    let (off_at, _, cause) = *log
        .iter()
        .rev()
        .find(|(at, on, _)| !on && *at > t)
        .unwrap_or_else(|| panic!("the laser stayed on after the run stopped: {log:?}"));
    assert_eq!(cause, 1, "the DAQ's watchdog switched it off: {log:?}");
    let after = off_at.saturating_duration_since(t);
    assert!(
        after <= Duration::from_millis(200 + 250),
        "off {after:?} after the stop"
    );
    assert!(!s.emission());
    let _ = std::fs::remove_dir_all(dir.parent().unwrap());
}

/// `periscope devices` with the stand-in as NI-DAQmx's library, set up in the child
/// process from `PERISCOPE_STANDIN_CONFIG` and `PERISCOPE_STANDIN_DAQ_CONFIG`.
fn devices(dir: &Path, library: &Path) -> (String, bool) {
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, sim_text(0.0)).unwrap();
    let lab = dir.join("lab.toml");
    std::fs::write(&lab, lab_text(0.0, library, "")).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(["devices", "--instrument"])
        .arg(&lab)
        .env(periscope_standins::CONFIG_ENV, &rig)
        .env(periscope_standins::DAQ_CONFIG_ENV, &lab)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        out.status.success(),
    )
}

#[test]
fn periscope_devices_lists_the_daq_devices_or_says_the_library_is_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let library = periscope_standins::client::library_path();
    let (out, ok) = devices(tmp.path(), &library);
    assert!(ok, "{out}");
    assert!(
        out.contains(&format!("NI-DAQmx at {}: 1 device", library.display())),
        "{out}"
    );
    assert!(out.contains("Dev1  PCIe-6363  serial 1A2B3C4"), "{out}");
    assert!(out.contains("interlock read on Dev1/port0/line1"), "{out}");
    assert!(
        out.contains("laser arm  PCIe-6363 (Dev1, analog outputs)"),
        "{out}"
    );

    let missing = Path::new("/nonexistent/libnidaqmx.so");
    let (out, ok) = devices(tmp.path(), missing);
    assert!(!ok);
    assert!(
        out.contains("cannot load /nonexistent/libnidaqmx.so") && out.contains("install NI-DAQmx"),
        "{out}"
    );
}

/// An e-stop while the run is stuck with the DAQ's tasks started: both arms park
/// through the run's own analog-output tasks, which hold their channels (a second task
/// on them is refused, as NI-DAQmx refuses it). Until 2026-12-06 the e-stop parked by
/// opening each arm anew, which the reserved channels refused: the report said not
/// parked, and the mirrors stayed where the hung run had left them.
#[test]
fn an_estop_parks_both_arms_on_the_daq_while_the_run_hangs() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 1.0, "");
    standin_matrix::estop_while_the_run_hangs(tmp.path(), &s, &lab, true);
}

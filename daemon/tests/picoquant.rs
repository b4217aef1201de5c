//! A whole run on a PicoQuant counter, through the real FFI path: the daemon's
//! hardware backend opens the serial galvo driver on the stand-in's pseudo-terminals
//! and the MultiHarp driver on the stand-in library (`standins`), by the
//! paths in an ordinary lab config; one simulated rig answers both, as one bench does.
//!
//! The capture completes with the relay found and every pair stored; then the stop
//! matrix's measuring stages (LOS scan, capture) × every event run on this counter,
//! asserting on the rig's own emission log: laser off within 50 ms of the event, never
//! on again, both arms parked, the run left paused, aborted or failed as it should be.
//! `periscope devices` lists the counters the library sees, or says plainly that the
//! library is not there.
use std::path::{Path, PathBuf};

use periscope_daemon::check;
use periscope_daemon::config::{InstrumentConfig, TomlSource};
use periscope_daemon::events::Stage;
use periscope_daemon::pipeline::{self};
use periscope_daemon::plan::Plan;
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

/// The same instrument as a lab config: `backend = "hardware"`, each galvo arm on its
/// serial port, the histogrammer a MultiHarp through `library`, bins 20 ps wide (its
/// 5 ps base resolution × 4; the shipped 16 ps is not available on a MultiHarp).
fn lab_text(time_scale: f64, ports: (&str, &str), library: &Path) -> String {
    let text = sim_text(time_scale);
    let text = text[..text.find("[sim]").unwrap()].to_owned();
    // The simulator's arms turn their rays about one pivot.
    let serial = |port: &str| {
        format!("scanner = \"pivot\"\nserial = {{ port = \"{port}\", baud = 115200, timeout-ms = 500 }}\n")
    };
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
            out.push_str(&serial(ports.0));
        } else if line.starts_with("[galvo.spad]") {
            out.push_str(&serial(ports.1));
        } else if line.starts_with("[tdc]") {
            out.push_str(&format!(
                "driver = \"multiharp\"\nlibrary = \"{}\"\nchannel = 1\n",
                library.display()
            ));
        }
    }
    out
}

/// A fresh stand-in at `time_scale`, its galvos served; the lab config that reaches it.
fn bench(dir: &Path, time_scale: f64) -> (Standin, TomlSource) {
    let s = Standin::load();
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, sim_text(time_scale)).unwrap();
    s.setup(&rig);
    let (laser, spad) = s.serve_galvos();
    let lab = dir.join("lab.toml");
    let text = lab_text(time_scale, (&laser, &spad), &s.path());
    std::fs::write(&lab, &text).unwrap();
    (s, TomlSource::from_text(lab, text))
}

/// A prepared run of `plan` on the lab config.
fn prepare(dir: &Path, lab: &TomlSource, plan: &str) -> PathBuf {
    let plan_src = TomlSource::from_text(dir.join("plan.toml"), plan.to_owned());
    let (run, _, _) = pipeline::prepare(&plan_src, lab, Some(&dir.join("run")), "test").unwrap();
    run
}

#[test]
fn a_whole_capture_runs_on_the_multiharp_and_the_simulated_galvos() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 0.0);
    let dir = prepare(tmp.path(), &lab, PLAN);
    s.clear_calls();
    let planned = standin_matrix::whole_capture(&dir);
    // The histograms came through MHLib's calls: one StartMeas per LOS point and pair.
    let calls = s.calls();
    let starts = calls.iter().filter(|c| c.starts_with("MH_StartMeas(")).count();
    assert_eq!(starts, 64 + planned, "64 LOS points and the planned pairs");
    assert!(
        calls.iter().any(|c| c == "MH_StartMeas(0, 10)") && calls.iter().any(|c| c == "MH_StartMeas(0, 30)")
    );
    assert!(
        calls.iter().any(|c| c == "MH_SetBinning(0, 2)"),
        "20 ps = 5 ps × 2^2"
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

/// A lab config whose laser arm's limits reach past what its controller reports
/// (`LIM`: the stand-in's galvos keep the rig's ±20°, the config says ±25°): refused
/// when the devices open, naming the key, before any light; it failed mid-capture at
/// the first target past the controller's limits.
#[test]
fn limits_past_the_controllers_own_are_refused_when_the_devices_open() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 0.0);
    let limits = "angle-limits-deg = { x = [-20.0, 20.0], y = [-20.0, 20.0] }";
    assert!(lab.text().contains(limits));
    let wide = lab.text().replacen(
        limits,
        "angle-limits-deg = { x = [-25.0, 25.0], y = [-20.0, 20.0] }",
        1,
    );
    let wide = TomlSource::from_text(lab.path(), wide);
    let dir = prepare(tmp.path(), &wide, PLAN);
    let run =
        periscope_daemon::pipeline::Run::open(&dir, periscope_daemon::pipeline::Control::new(), None, None);
    let e = match run.and_then(|r| r.execute().map(drop)) {
        Ok(()) => panic!("a run opened with limits past the controller's"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains("galvo.laser.angle-limits-deg") && e.contains("hard limits"),
        "{e}"
    );
    assert!(
        !s.emission_log().iter().any(|(_, on, _)| *on),
        "the laser went on"
    );
    assert!(s.parked().0, "the laser arm is not parked");
}

/// A bench whose laser pulses at 20 MHz where the lab config says 10: the run waits
/// out the MultiHarp's rate meter once the laser is on (the stand-in, as the vendor's
/// demos say, shows the old rate for 400 ms after `SetSyncDiv`), reads the sync
/// rate, and fails before the first `StartMeas`, naming both keys; the laser is off and
/// both arms parked. Verified only against the stand-in.
#[test]
fn a_sync_rate_the_config_does_not_expect_fails_the_run_before_the_multiharp_measures() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = Standin::load();
    let rig = tmp.path().join("rig.toml");
    std::fs::write(
        &rig,
        sim_text(0.0).replacen("[sim]\n", "[sim]\ntrue-rep-rate-mhz = 20.0\n", 1),
    )
    .unwrap();
    s.setup(&rig);
    let (laser, spad) = s.serve_galvos();
    let text = lab_text(0.0, (&laser, &spad), &s.path());
    let lab = TomlSource::from_text(tmp.path().join("lab.toml"), text);
    let dir = prepare(tmp.path(), &lab, PLAN);
    s.clear_calls();
    let run =
        periscope_daemon::pipeline::Run::open(&dir, periscope_daemon::pipeline::Control::new(), None, None);
    let e = match run.and_then(|r| r.execute().map(drop)) {
        Ok(()) => panic!("a run on a laser at twice its configured rate"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains("sync rate of 20.0000 MHz")
            && e.contains("laser.rep-rate-mhz = 10 over tdc.sync-divider = 1"),
        "{e}"
    );
    let calls = s.calls();
    assert!(
        calls.iter().any(|c| c.starts_with("MH_GetSyncRate(")),
        "{calls:?}"
    );
    assert!(!calls.iter().any(|c| c.starts_with("MH_StartMeas(")), "{calls:?}");
    assert!(!s.emission());
    assert_eq!(s.parked(), (true, true));
}

/// A capture of [`PLAN`] on the stand-in bench in real time, with `fault` done to the
/// stand-in once the 14th pair is measured: late enough that the capture's laser has
/// been on for the rate meter's 400 ms, so the pair after the fault is judged (19
/// pairs of 30 ms). The stand-in's call log is cleared before the run opens.
fn capture_with_a_fault(
    tmp: &Path,
    fault: impl Fn(&Standin) + Send + Sync + 'static,
) -> (Standin, PathBuf, Result<(), pipeline::PipelineError>) {
    use periscope_daemon::events::{EventSink, RunEvent};
    let (s, lab) = bench(tmp, 1.0);
    let dir = prepare(tmp, &lab, PLAN);
    let events = EventSink::open(&dir).unwrap();
    let s2 = s;
    events.listen(move |e| {
        if let RunEvent::Pair { done: 14, .. } = e {
            fault(&s2);
        }
    });
    s.clear_calls();
    let run = periscope_daemon::pipeline::Run::open(
        &dir,
        periscope_daemon::pipeline::Control::new(),
        Some(events),
        None,
    )
    .unwrap();
    let result = run.execute().map(drop);
    (s, dir, result)
}

/// The MultiHarp drops off the bus in the middle of a capture and is back at once: its
/// driver reopens it (initialised again, its rate meter showing no sync for 400 ms),
/// and the run reads the sync again after that latency instead of failing on the
/// first reading, and completes with every pair.
#[test]
fn a_multiharp_reopened_mid_capture_is_not_taken_for_a_lost_sync() {
    use periscope_drivers::picoquant::Family;
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, dir, result) = capture_with_a_fault(tmp.path(), |s| s.vanish(Family::MultiHarp, 0, 0));
    result.unwrap();
    let calls = s.calls();
    let inits = calls.iter().filter(|c| c.starts_with("MH_Initialize(")).count();
    assert!(inits >= 2, "the counter was not reopened: {calls:?}");
    // The pair measured while the reopened meter read no sync was measured again, and
    // stored once: one StartMeas more than the LOS points and pairs.
    let planned = std::fs::read(dir.join("pairs.json")).unwrap();
    let planned = serde_json::from_slice::<Vec<serde_json::Value>>(&planned)
        .unwrap()
        .len();
    let starts = calls.iter().filter(|c| c.starts_with("MH_StartMeas(")).count();
    assert_eq!(starts, 64 + planned + 1, "{planned} planned");
    let log = periscope_daemon::store::read_log(&dir).unwrap();
    let mut seen: Vec<u32> = log.records.iter().map(|r| r.pair).collect();
    seen.sort_unstable();
    assert_eq!(seen, (0..planned as u32).collect::<Vec<_>>());
    let info = periscope_daemon::run_dir::RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, periscope_daemon::run_dir::RunState::Completed);
    assert!(!s.emission());
    assert_eq!(s.parked(), (true, true));
}

/// The laser's sync stops in the middle of a capture (the stand-in's `SyncStops`: the
/// pair being measured is whole, the rate meter then reads 0): the run's own sync check
/// after the pair stops it with an error naming the sync cable, the laser off and both
/// arms parked; every pair before is kept (the one measured under the reading of 0 is
/// measured again on resume, as `sync_verdict` does with any reading off). The same
/// with the driver before 2026-12-07, whose histogram was flagged saturated: this holds
/// the daemon's end of it through the production loader.
#[test]
fn a_sync_that_stops_mid_capture_stops_the_run_laser_off_and_keeps_its_pairs() {
    use periscope_drivers::picoquant::Family;
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, dir, result) = capture_with_a_fault(tmp.path(), |s| s.sync_stops(Family::MultiHarp, 0));
    let e = result.unwrap_err().to_string();
    assert!(e.contains("sync"), "{e}");
    assert!(!e.contains("saturated"), "{e}");
    assert!(!s.emission());
    assert_eq!(s.parked(), (true, true));
    let log = periscope_daemon::store::read_log(&dir).unwrap();
    assert!(log.records.len() >= 14, "{} pairs kept", log.records.len());
    let info = periscope_daemon::run_dir::RunInfo::load(&dir).unwrap();
    assert_ne!(info.state, periscope_daemon::run_dir::RunState::Completed);
    eprintln!("state {:?}, {} pairs kept: {e}", info.state, log.records.len());
}

/// A pause during the wait for the rate meter (400 ms with the laser on, before the
/// first LOS point) is answered within the wait's 20 ms poll: the laser is off within
/// the docs' 50 ms and the run ends paused, having measured nothing.
#[test]
fn a_pause_while_the_run_waits_for_the_sync_reading_is_answered_at_once() {
    use std::time::{Duration, Instant};
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 0.0);
    let dir = prepare(tmp.path(), &lab, PLAN);
    s.clear_calls();
    let control = periscope_daemon::pipeline::Control::new();
    let watcher = {
        let (s, control) = (s, control.clone());
        std::thread::spawn(move || {
            let started = Instant::now();
            while !s.emission() && started.elapsed() < Duration::from_secs(20) {
                std::thread::sleep(Duration::from_micros(200));
            }
            std::thread::sleep(Duration::from_millis(100));
            let paused = Instant::now();
            control.pause();
            paused
        })
    };
    let run = periscope_daemon::pipeline::Run::open(&dir, control, None, None).unwrap();
    let e = run
        .execute()
        .map(drop)
        .expect_err("the run went on after the pause");
    let returned = Instant::now();
    let paused = watcher.join().unwrap();
    assert!(e.to_string().contains("paused"), "{e}");
    assert!(
        returned - paused < Duration::from_millis(500),
        "{:?}",
        returned - paused
    );
    let off = s
        .emission_log()
        .into_iter()
        .find(|(at, on, _)| !on && *at >= paused)
        .map(|(at, _, _)| at)
        .expect("the laser went off");
    assert!(off - paused < Duration::from_millis(50), "{:?}", off - paused);
    assert!(!s.calls().iter().any(|c| c.starts_with("MH_StartMeas(")));
    assert_eq!(s.parked(), (true, true));
}

/// A fresh bench and prepared run for one case of the stop matrix.
fn matrix_bench(tmp: &Path) -> (Standin, PathBuf) {
    let (s, lab) = bench(tmp, 1.0);
    let dir = prepare(tmp, &lab, PLAN);
    (s, dir)
}

#[test]
fn los_scan_on_the_multiharp() {
    standin_matrix::check_stage(Stage::LosScan, &matrix_bench);
}

#[test]
fn capture_on_the_multiharp() {
    standin_matrix::check_stage(Stage::Capture, &matrix_bench);
}

/// `periscope devices` with the stand-in as `tdc.library`, set up in the child process
/// from `PERISCOPE_STANDIN_CONFIG` (its galvo ports do not exist, so opening the
/// instrument then fails: the listing comes first).
fn devices(dir: &Path, library: &Path) -> (String, bool) {
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, sim_text(0.0)).unwrap();
    let lab = dir.join("lab.toml");
    let text = lab_text(
        0.0,
        ("/dev/periscope-no-such-port-1", "/dev/periscope-no-such-port-2"),
        library,
    );
    std::fs::write(&lab, text).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(["devices", "--instrument"])
        .arg(&lab)
        .env(periscope_standins::CONFIG_ENV, &rig)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        out.status.success(),
    )
}

#[test]
fn periscope_devices_lists_the_counters_or_says_the_library_is_missing() {
    let tmp = tempfile::tempdir().unwrap();
    let library = periscope_standins::client::library_path();
    let (out, _) = devices(tmp.path(), &library);
    assert!(
        out.contains(&format!("MHLib 3.1 at {}: 1 MultiHarp found", library.display())),
        "{out}"
    );
    assert!(out.contains("index 0  serial 1045678  MultiHarp 150 4P"), "{out}");

    let missing = Path::new("/nonexistent/mh150/mhlib.so");
    let (out, ok) = devices(tmp.path(), missing);
    assert!(!ok);
    assert!(
        out.contains("cannot load /nonexistent/mh150/mhlib.so") && out.contains("install PicoQuant's MHLib"),
        "{out}"
    );
}

/// `periscope check` names what the MultiHarp would refuse of a plan before the run
/// opens it: the same settings its driver refuses (`Family::settings`), with the
/// plan's key; and the offsets it suggests for the TDC window are whole nanoseconds.
#[test]
fn check_names_what_the_multiharp_would_refuse_before_the_run() {
    let tmp = tempfile::tempdir().unwrap();
    let ports = ("/dev/periscope-no-such-port-1", "/dev/periscope-no-such-port-2");
    let lab = TomlSource::from_text(
        tmp.path().join("lab.toml"),
        lab_text(0.0, ports, Path::new("/nonexistent/mhlib.so")),
    );
    let inst = InstrumentConfig::from_source(&lab).unwrap();
    let demo = std::fs::read_to_string(root().join("configs/plans/demo.toml")).unwrap();
    let warnings = |edit: &dyn Fn(&str) -> String| {
        let text = edit(&demo);
        assert_ne!(text, demo, "the edit changed nothing");
        let plan =
            Plan::from_source(&TomlSource::from_text(tmp.path().join("plan.toml"), text), &inst).unwrap();
        check::check(&plan, &inst).warnings
    };
    let acquisition =
        |lines: &'static str| move |t: &str| t.replace("[acquisition]\n", &format!("[acquisition]\n{lines}"));
    let refusals = |w: &[String]| {
        w.iter()
            .filter(|w| w.contains("refuses"))
            .cloned()
            .collect::<Vec<_>>()
    };

    // Whole milliseconds and nanoseconds, 1,024 bins: nothing to refuse.
    assert_eq!(
        refusals(&warnings(&acquisition("bins = 1024\n"))),
        Vec::<String>::new()
    );
    // Each dwell on its own: only the stage it belongs to is refused.
    for (from, to, stage) in [
        ("dwell-ms = 20.0", "dwell-ms = 20.5", "acquisition:"),
        ("dwell-ms = 1.0", "dwell-ms = 0.5", "los:"),
    ] {
        let w = refusals(&warnings(&|t: &str| t.replace(from, to)));
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(stage) && w[0].contains("whole milliseconds"),
            "{w:?}"
        );
    }
    // The offset, which both share, is named once.
    let w = refusals(&warnings(&acquisition("offset-ns = 12.5\n")));
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(w[0].contains("whole nanoseconds"), "{w:?}");
    // A window that starts past the LOS returns: the offset it names is whole, and
    // the plan that takes it has nothing refused and nothing short.
    let w = warnings(&acquisition("offset-ns = 20\n"));
    let window = w
        .iter()
        .find(|w| w.contains("acquisition.offset-ns at most "))
        .unwrap_or_else(|| panic!("{w:?}"));
    let at = window.find("at most ").unwrap() + "at most ".len();
    let offset: String = window[at..]
        .chars()
        .take_while(|c| c.is_ascii_digit() || *c == '.')
        .collect();
    let offset = offset.trim_end_matches('.');
    assert!(!offset.is_empty() && !offset.contains('.'), "{window}");
    let fixed = format!("offset-ns = {offset}\n");
    let w = warnings(&|t: &str| t.replace("[acquisition]\n", &format!("[acquisition]\n{fixed}")));
    assert!(
        refusals(&w).is_empty() && !w.iter().any(|w| w.contains("none of")),
        "{w:?}"
    );
}

/// An e-stop while the run is stuck holding both controllers' serial ports, which the
/// driver opens exclusively (`TIOCEXCL`, as the `serialport` crate opens every port):
/// both arms park through the run's own links, with an out-of-band `PARK` (reported
/// as sent, unconfirmed: the answers are on the link the stuck run reads). Until
/// 2026-12-06 the e-stop parked by opening each port anew, which the exclusive opens
/// refused, and the arms stayed where the run had left them.
#[test]
fn an_estop_parks_both_arms_on_their_serial_ports_while_the_run_hangs() {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (s, lab) = bench(tmp.path(), 1.0);
    standin_matrix::estop_while_the_run_hangs(tmp.path(), &s, &lab, false);
}

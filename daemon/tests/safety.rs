//! The laser is off whenever nobody is measuring, whatever fails: every pipeline stage
//! × every event (pause, abort, e-stop, an unplugged histogrammer, a panic), against
//! the simulated devices in real time. Each case asserts the simulated laser's own
//! emission state (the firmware's log of when emission changed and why), never the
//! daemon's belief about it: off within 50 ms of the event, never on again after it,
//! both arms parked when the run returns, and the run left in the state it should be in, with its data resumable. The
//! measuring stages run the matrix again on the simulator's in-process devices.
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, mpsc};
use std::time::{Duration, Instant};

use periscope_daemon::config::{InstrumentConfig, TomlSource};
use periscope_daemon::devices::sim::{SimBackend, rig_of};
use periscope_daemon::events::{EventSink, RunEvent, Stage};
use periscope_daemon::pipeline::{self, Control, PipelineError, Run};
use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_daemon::store::read_log;
use periscope_drivers::galvo::EmergencyOff;
use periscope_sim::devices::{EmissionCause, Rig};

mod common;
use common::SmallPlan;

/// The bound on how long emission may outlast a pause, abort or e-stop (the
/// issue's, for the simulator).
const EMISSION_BOUND: Duration = Duration::from_millis(50);

/// How long a stopped optimiser may take to notice (one step of this small fit, with
/// headroom for a loaded CI machine).
const TRAINER_BOUND: Duration = Duration::from_secs(2);

/// Small and real-time: 64 LOS points of 10 ms, 25 pairs of 30 ms, a tiny fit.
fn plan() -> String {
    small_plan().toml()
}

/// [`plan`], to set more on.
fn small_plan() -> SmallPlan {
    SmallPlan::named("safety")
        .set("los.grid", [8, 8])
        .set("los.dwell-ms", 10.0)
        .set("pairs.grid", [5, 5])
        .set("acquisition.dwell-ms", 30.0)
        .set("recon.method", "gtr")
        .set("recon.volume.shape", [16, 16, 16])
        .set("recon.gtr.primitives", 200)
        .set("recon.gtr.epochs", 40)
        .set("recon.gtr.virtual-grid", [16, 16])
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The default simulated instrument in real time.
fn instrument() -> TomlSource {
    instrument_on(Devices::Wire)
}

/// How the run reaches the simulated devices (`sim.devices`).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Devices {
    /// The real drivers over the simulator's wire.
    Wire,
    /// The simulator's controller model and histogrammer, in process.
    InProcess,
}

/// The default simulated instrument in real time, its devices reached by `devices`.
fn instrument_on(devices: Devices) -> TomlSource {
    let path = root().join("configs/instrument/sim.toml");
    let devices = match devices {
        Devices::Wire => "wire",
        Devices::InProcess => "in-process",
    };
    let text = std::fs::read_to_string(&path).unwrap().replace(
        "[sim]\n",
        &format!("[sim]\ntime-scale = 1.0\ndevices = \"{devices}\"\n"),
    );
    TomlSource::from_text(path, text)
}

/// A prepared run directory and the rig it will run on.
fn prepare(tmp: &Path, plan: &str) -> (PathBuf, SimBackend) {
    prepare_on(tmp, plan, Devices::Wire)
}

/// [`prepare`] with the devices reached by `devices`.
fn prepare_on(tmp: &Path, plan: &str, devices: Devices) -> (PathBuf, SimBackend) {
    let src = instrument_on(devices);
    let config = InstrumentConfig::from_source(&src).unwrap();
    let rig = periscope_daemon::devices::sim::SimBackend::from_config(&config)
        .unwrap()
        .unwrap();
    let plan_src = TomlSource::from_text(tmp.join("plan.toml"), plan.to_owned());
    let (dir, _, _) = pipeline::prepare(&plan_src, &src, Some(&tmp.join("run")), "test").unwrap();
    (dir, rig)
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Event {
    Pause,
    Abort,
    Estop,
    /// A stop signal to `periscope run`: the laser off directly, then the run paused
    /// (the signal thread's order, the reverse of the e-stop's).
    Signal,
    DeviceError,
    Panic,
    /// A panic in another thread of the process (a fit's, an API handler's): the panic
    /// hook switches the laser off and latches it.
    PanicElsewhere,
}

const EVENTS: [Event; 7] = [
    Event::Pause,
    Event::Abort,
    Event::Estop,
    Event::Signal,
    Event::DeviceError,
    Event::Panic,
    Event::PanicElsewhere,
];

/// What one case did.
struct Outcome {
    /// From the event to emission off (zero: it was already off).
    off_after: Duration,
    /// From the event to the run's return.
    returned_after: Duration,
    /// The run's stored state.
    state: RunState,
    result: Result<(), String>,
}

/// Fires `event` at the run, as the service and the signal handlers would.
fn fire(event: Event, stage: Stage, control: &Control, rig: &Rig, laser: &OnceLock<EmergencyOff>) {
    match event {
        Event::Pause => control.pause(),
        Event::Abort => control.abort(),
        Event::Estop => {
            // The service's order: the run told to abort, then the laser directly.
            control.abort();
            if let Some(off) = laser.get() {
                off.laser_off().unwrap();
            }
        }
        Event::Signal => {
            if let Some(off) = laser.get() {
                off.laser_off().unwrap();
            }
            std::thread::sleep(Duration::from_millis(1));
            control.pause();
        }
        Event::DeviceError => rig.unplug_tdc(1_000),
        Event::Panic => control.inject_panic(stage),
        Event::PanicElsewhere => {
            let elsewhere = std::thread::Builder::new()
                .name("elsewhere".into())
                .spawn(|| panic!("injected in another thread"))
                .unwrap();
            assert!(elsewhere.join().is_err());
        }
    }
}

/// Runs the plan and fires `event` in `stage`: while measuring (LOS, capture) from
/// another thread a few milliseconds into a dwell, elsewhere at the stage's start.
fn run_case(stage: Stage, event: Event, devices: Devices) -> Outcome {
    // As the binary does at start.
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare_on(tmp.path(), &plan(), devices);
    let control = Control::new();
    let laser: Arc<OnceLock<EmergencyOff>> = Arc::new(OnceLock::new());
    let fired: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let events = EventSink::open(&dir).unwrap();
    let (tx, rx) = mpsc::channel::<()>();
    {
        let (control, rig, laser, fired) = (control.clone(), rig.clone(), laser.clone(), fired.clone());
        let mut armed = true;
        events.listen(move |e| {
            if !armed {
                return;
            }
            let now = match (stage, e) {
                (Stage::LosScan, RunEvent::LosPoint { .. }) | (Stage::Capture, RunEvent::Pair { .. }) => {
                    // Mid-dwell, from another thread.
                    let _ = tx.send(());
                    armed = false;
                    return;
                }
                (Stage::LosScan | Stage::Capture, _) => return,
                (s, RunEvent::StageStarted { stage }) if *stage == s => true,
                _ => false,
            };
            if now {
                armed = false;
                *fired.lock().unwrap() = Some(Instant::now());
                fire(event, stage, &control, &rig, &laser);
            }
        });
    }
    let trigger = {
        let (control, rig, laser, fired) = (control.clone(), rig.clone(), laser.clone(), fired.clone());
        std::thread::spawn(move || {
            if rx.recv().is_ok() {
                std::thread::sleep(Duration::from_millis(7));
                *fired.lock().unwrap() = Some(Instant::now());
                fire(event, stage, &control, &rig, &laser);
            }
        })
    };
    let result = match Run::open(&dir, control, Some(events), Some(&rig)) {
        Ok(run) => {
            let _ = laser.set(run.emergency_off());
            run.execute().map(drop)
        }
        Err(e) => Err(e),
    };
    let returned = Instant::now();
    trigger.join().unwrap();
    let t = fired
        .lock()
        .unwrap()
        .unwrap_or_else(|| panic!("{event:?} in {stage:?} never fired: {result:?}"));
    assert!(
        !rig.emission(),
        "{event:?} in {stage:?}: the laser is on after the run returned"
    );
    let off = rig.off_since(t).expect("off");
    let switched_on_after: Vec<_> = rig
        .emission_changes()
        .into_iter()
        .filter(|c| c.on && c.at > t)
        .collect();
    assert!(
        switched_on_after.is_empty(),
        "{event:?} in {stage:?}: emission went on again after the event: {switched_on_after:?}"
    );
    assert_eq!(
        rig.parked(),
        (true, true),
        "{event:?} in {stage:?}: both arms parked after the run returned (laser, SPAD)"
    );
    let info = RunInfo::load(&dir).unwrap();
    Outcome {
        off_after: off - t,
        returned_after: returned.saturating_duration_since(t),
        state: info.state,
        result: result.map_err(|e: PipelineError| e.to_string()),
    }
}

fn expected_state(stage: Stage, event: Event) -> RunState {
    match event {
        // A signal's laser off latches the run's driver: whether the run meets it at a
        // switch-on or as emission lost, it ends paused (resumable), as asked.
        Event::Pause | Event::Signal => RunState::Paused,
        Event::Abort | Event::Estop => RunState::Aborted,
        // Nothing talks to the histogrammer after the capture: the run completes, and
        // making the instrument safe reports the unplugged device.
        Event::DeviceError if stage == Stage::Reconstruction => RunState::Completed,
        Event::DeviceError | Event::Panic => RunState::Failed,
        // The latch stops the run where it next needs the laser (at once while it
        // measures, at the capture's switch-on before then): failed, naming the panic.
        // After the capture it needs none, and completes.
        Event::PanicElsewhere if stage == Stage::Reconstruction => RunState::Completed,
        Event::PanicElsewhere => RunState::Failed,
    }
}

/// One case at a time: the panic hook switches off every laser in the process, as it
/// should in the daemon (one instrument), so concurrent cases would disturb each other.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn check_stage(stage: Stage) {
    check_stage_on(stage, Devices::Wire);
}

fn check_stage_on(stage: Stage, devices: Devices) {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let mut table = String::new();
    for event in EVENTS {
        // While the run opens, no laser of its is open for the panic hook to switch
        // off: a panic elsewhere then leaves the run alone.
        if event == Event::PanicElsewhere && stage == Stage::Opening {
            continue;
        }
        let o = run_case(stage, event, devices);
        table.push_str(&format!(
            "{:<15} {:<12} off after {:>6.1} ms, run returned after {:>7.1} ms, state {:?}: {}\n",
            stage.name(),
            format!("{event:?}"),
            o.off_after.as_secs_f64() * 1e3,
            o.returned_after.as_secs_f64() * 1e3,
            o.state,
            o.result.as_ref().err().map_or("ok", String::as_str),
        ));
        assert!(
            o.off_after <= EMISSION_BOUND,
            "{event:?} in {stage:?}: emission lasted {:?} after the event\n{table}",
            o.off_after
        );
        assert!(
            o.returned_after <= TRAINER_BOUND,
            "{event:?} in {stage:?}: the run took {:?} to stop\n{table}",
            o.returned_after
        );
        assert_eq!(
            o.state,
            expected_state(stage, event),
            "{event:?} in {stage:?}\n{table}"
        );
        if event == Event::Panic {
            let e = o.result.as_ref().unwrap_err();
            assert!(
                e.contains("internal error in stage") && e.contains(stage.name()),
                "{e}"
            );
        }
        if event == Event::PanicElsewhere && stage != Stage::Reconstruction {
            let e = o.result.as_ref().unwrap_err();
            assert!(
                e.contains("internal error")
                    && e.contains("thread `elsewhere`")
                    && e.contains("injected in another thread"),
                "{e}"
            );
        }
    }
    eprint!("{table}");
}

#[test]
fn opening() {
    check_stage(Stage::Opening);
}

#[test]
fn los_scan() {
    check_stage(Stage::LosScan);
}

#[test]
fn relay() {
    check_stage(Stage::Relay);
}

#[test]
fn planning() {
    check_stage(Stage::Planning);
}

#[test]
fn capture() {
    check_stage(Stage::Capture);
}

#[test]
fn reconstruction() {
    check_stage(Stage::Reconstruction);
}

// The matrix's measuring stages on the in-process devices: the pipeline's safety logic
// holds whatever implements the device traits.

#[test]
fn los_scan_in_process() {
    check_stage_on(Stage::LosScan, Devices::InProcess);
}

#[test]
fn capture_in_process() {
    check_stage_on(Stage::Capture, Devices::InProcess);
}

/// A capture stopped while the disk stalls: the histogram log's last sync (its records
/// are kept) waits 400 ms, and the laser must not wait with it. Until 2026-12-06 the
/// log was synced and closed as the capture returned, before the run switched the laser
/// off: a pause or abort then left it on for the disk's stall.
#[test]
fn a_stopped_capture_switches_the_laser_off_before_it_waits_on_a_stalling_disk() {
    use std::sync::atomic::Ordering;
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let stall = Duration::from_millis(400);
    for event in [Event::Pause, Event::Abort] {
        periscope_daemon::store::SLOW_SYNC_MS.store(stall.as_millis() as u64, Ordering::SeqCst);
        let o = run_case(Stage::Capture, event, Devices::Wire);
        periscope_daemon::store::SLOW_SYNC_MS.store(0, Ordering::SeqCst);
        assert!(
            o.off_after <= EMISSION_BOUND,
            "{event:?} with the disk stalling: emission lasted {:?} after the event",
            o.off_after
        );
        assert!(
            o.returned_after >= stall,
            "{event:?}: the run returned after {:?}, before the stalled sync ({stall:?}) it should have waited for",
            o.returned_after
        );
        assert_eq!(o.state, expected_state(Stage::Capture, event));
    }
}

/// Runs (or resumes) the run in `dir` on `rig`, with `on_pair` called on the pipeline
/// thread after each stored pair (with the pairs done so far).
fn execute(
    dir: &Path,
    rig: &SimBackend,
    control: Control,
    mut on_pair: impl FnMut(usize) + Send + 'static,
) -> Result<(), PipelineError> {
    let events = EventSink::open(dir).unwrap();
    events.listen(move |e| {
        if let RunEvent::Pair { done, .. } = e {
            on_pair(*done);
        }
    });
    let run = Run::open(dir, control, Some(events), Some(rig))?;
    run.execute().map(drop)
}

/// Every planned pair stored exactly once.
fn assert_each_pair_once(dir: &Path) {
    let planned: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(dir.join("pairs.json")).unwrap()).unwrap();
    let log = read_log(dir).unwrap();
    let mut seen: Vec<u32> = log.records.iter().map(|r| r.pair).collect();
    seen.sort_unstable();
    assert_eq!(seen, (0..planned.len() as u32).collect::<Vec<_>>());
}

#[test]
fn a_paused_and_a_panicked_capture_resume_with_every_pair_once() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    periscope_daemon::signals::install_panic_hook();
    for panic in [false, true] {
        let tmp = tempfile::tempdir().unwrap();
        let (dir, rig) = prepare(tmp.path(), &plan());
        let control = Control::new();
        let c = control.clone();
        let r = execute(&dir, &rig, control, move |done| {
            if done == 6 {
                if panic {
                    c.inject_panic(Stage::Capture)
                } else {
                    c.pause()
                }
            }
        });
        assert!(r.is_err());
        assert!(!rig.emission());
        let info = RunInfo::load(&dir).unwrap();
        let want = if panic { RunState::Failed } else { RunState::Paused };
        assert_eq!(info.state, want, "{r:?}");
        let kept = read_log(&dir).unwrap().records.len();
        assert!((6..=7).contains(&kept), "{kept} pairs kept");
        execute(&dir, &rig, Control::new(), |_| {}).unwrap();
        assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
        assert_each_pair_once(&dir);
        assert!(!rig.emission());
    }
}

/// A run that stops for a reason of its own (here a panic) as it is asked to abort ends
/// aborted, not failed and resumable: the abort was answered as under way. Until
/// 2026-12-08 only a stop taken at a checkpoint honoured it.
#[test]
fn a_run_that_fails_as_it_is_asked_to_abort_ends_aborted() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    periscope_daemon::signals::install_panic_hook();
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let control = Control::new();
    let c = control.clone();
    let r = execute(&dir, &rig, control.clone(), move |done| {
        if done == 6 {
            // The panic comes first at the next checkpoint, before the abort is read.
            c.inject_panic(Stage::Capture);
            assert!(c.abort_by("bob"));
        }
    });
    assert!(r.is_err(), "{r:?}");
    assert!(!rig.emission());
    common::assert_aborted_keeping_error(&dir, &control, "bob", "injected panic");
    assert!((6..=7).contains(&read_log(&dir).unwrap().records.len()));
}

/// An adaptive capture waits for its fit to choose each batch with the laser off; a
/// pause while it waits ends the run paused within the poll (the laser already off),
/// and the resumed run measures the rest of its budget, each pair once.
#[test]
fn an_adaptive_capture_paused_while_its_fit_chooses_resumes_to_its_budget() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 15\nfirst = 6\nbatch = 3\nlive-steps = 16\n";
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &adaptive);
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    // The first live epoch: the first batch is stored and the capture waits for the fit.
    let (c, r2) = (control.clone(), rig.clone());
    let fired = Arc::new(Mutex::new(None::<(Instant, bool)>));
    let at = fired.clone();
    events.listen(move |e| {
        if let RunEvent::Train(periscope_recon::gtr::TrainEvent::Epoch { epoch: 0, .. }) = e {
            let mut at = at.lock().unwrap();
            if at.is_none() {
                *at = Some((Instant::now(), r2.emission()));
                c.pause();
            }
        }
    });
    let t = Instant::now();
    let r = Run::open(&dir, control, Some(events), Some(&rig))
        .unwrap()
        .execute();
    assert!(r.is_err(), "{r:?}");
    let (when, emitting) = fired.lock().unwrap().expect("a live epoch ran");
    assert!(!emitting, "the laser was on while the fit chose");
    assert!(
        when.elapsed() < TRAINER_BOUND + Duration::from_secs(1),
        "the pause took {:?}",
        when.elapsed()
    );
    assert!(t.elapsed() < Duration::from_secs(60));
    assert!(!rig.emission());
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
    assert_eq!(
        read_log(&dir).unwrap().records.len(),
        6,
        "the first batch is kept"
    );
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
    let mut seen: Vec<u32> = read_log(&dir).unwrap().records.iter().map(|r| r.pair).collect();
    assert_eq!(seen.len(), 15, "the budget");
    seen.sort_unstable();
    seen.dedup();
    assert_eq!(seen.len(), 15, "a pair measured twice");
    assert!(!rig.emission());
    // The resumed session numbers its batches on from the first's (until 2026-12-06
    // it began at 0 again, and events.jsonl held two batch 0s).
    let batches: Vec<u64> = std::fs::read_to_string(dir.join("events.jsonl"))
        .unwrap()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v["event"] == "pairs-chosen")
        .filter_map(|v| v["batch"].as_u64())
        .collect();
    assert_eq!(
        batches,
        (0..batches.len() as u64).collect::<Vec<_>>(),
        "{batches:?}"
    );
}

/// A pause in the middle of the LOS scan keeps the rows it measured (`los.jsonl`),
/// and the resume scans only the rest: its first LOS progress is past the kept rows,
/// and the relay comes from all of them. Until 2026-12-07 the scan's returns lived in
/// memory only, and every resume scanned the whole grid again with the laser on.
#[test]
fn a_pause_in_the_los_scan_keeps_its_rows_and_the_resume_scans_the_rest() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    let c = control.clone();
    events.listen(move |e| {
        if let RunEvent::LosPoint { done: 24, .. } = e {
            c.pause();
        }
    });
    let r = Run::open(&dir, control, Some(events), Some(&rig))
        .unwrap()
        .execute();
    assert!(matches!(r, Err(PipelineError::Paused(0))), "{r:?}");
    assert!(!rig.emission());
    assert!(!dir.join("relay.ply").exists());
    let lines = || {
        std::fs::read_to_string(dir.join("los.jsonl"))
            .unwrap()
            .lines()
            .count()
    };
    assert_eq!(lines(), 3, "the rows measured before the pause");
    let events = EventSink::open(&dir).unwrap();
    let progress = Arc::new(Mutex::new(Vec::new()));
    let seen = progress.clone();
    events.listen(move |e| {
        if let RunEvent::LosPoint { done, .. } = e {
            seen.lock().unwrap().push(*done);
        }
    });
    Run::open(&dir, Control::new(), Some(events), Some(&rig))
        .unwrap()
        .execute()
        .unwrap();
    assert_eq!(
        *progress.lock().unwrap(),
        [32, 40, 48, 56, 64],
        "rows scanned on resume"
    );
    assert_eq!(lines(), 8);
    assert!(dir.join("relay.ply").is_file());
    assert_each_pair_once(&dir);
    assert!(!rig.emission());
}

/// A scan whose rows make no relay (here the plan's depth window holds none of the
/// wall's returns: too few points) sets its rows aside, so a resume scans again
/// instead of failing on the same rows for good once the cause is put right; each
/// failed scan's rows are kept under a name of their own.
#[test]
fn a_scan_that_makes_no_relay_keeps_its_rows_aside_and_a_resume_scans_again() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &small_plan().set("relay.depth-m", [0.1, 0.2]).toml());
    let lines = |name: &str| std::fs::read_to_string(dir.join(name)).unwrap().lines().count();
    for kept in ["los.jsonl.failed", "los.jsonl.failed.1"] {
        let e = execute(&dir, &rig, Control::new(), |_| {}).unwrap_err();
        assert!(matches!(e, PipelineError::Relay(_)), "{e}");
        assert!(!rig.emission());
        assert!(!dir.join("los.jsonl").exists());
        assert_eq!(lines(kept), 8, "{kept}: the failed scan's rows");
    }
}

/// Runs a capture of four repeats of `dwell_ms` a pair and, 2.5 dwells into the pair
/// after the third (its third repeat), calls `stop` with the run's control, its
/// laser's direct off and the rig. Returns the run's directory and the rig.
fn stopped_mid_repeats(
    tmp: &Path,
    dwell_ms: u64,
    stop: impl Fn(&Control, &EmergencyOff, &SimBackend) + Send + Sync + 'static,
) -> (PathBuf, SimBackend) {
    stopped_mid_repeats_of(tmp, small_plan(), 3, dwell_ms, stop)
}

/// [`stopped_mid_repeats`] of `plan`, 2.5 dwells into the pair after the `after`th.
fn stopped_mid_repeats_of(
    tmp: &Path,
    plan: SmallPlan,
    after: usize,
    dwell_ms: u64,
    stop: impl Fn(&Control, &EmergencyOff, &SimBackend) + Send + Sync + 'static,
) -> (PathBuf, SimBackend) {
    let repeats = plan
        .set("acquisition.repeats", 4)
        .set("acquisition.dwell-ms", dwell_ms as f64)
        .toml();
    let (dir, rig) = prepare(tmp, &repeats);
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    let laser: Arc<OnceLock<EmergencyOff>> = Arc::new(OnceLock::new());
    let stop = Arc::new(stop);
    {
        let (control, laser, rig) = (control.clone(), laser.clone(), rig.clone());
        events.listen(move |e| {
            if matches!(e, RunEvent::Pair { done, .. } if *done == after) {
                let (control, laser, stop, rig) = (control.clone(), laser.clone(), stop.clone(), rig.clone());
                std::thread::spawn(move || {
                    std::thread::sleep(Duration::from_millis(dwell_ms * 5 / 2));
                    stop(&control, laser.get().unwrap(), &rig);
                });
            }
        });
    }
    let run = Run::open(&dir, control, Some(events), Some(&rig)).unwrap();
    let _ = laser.set(run.emergency_off());
    assert!(run.execute().is_err(), "the run went on after the stop");
    assert!(!rig.emission());
    (dir, rig)
}

/// A pause in the middle of a pair's repeats keeps the repeats summed so far as a
/// partial record, and the resume measures only the rest on top of them: the pair's
/// whole record holds the partial sum bin for bin, and every pair is stored whole
/// once. Until 2026-12-07 the sum so far was dropped and the pair measured from its
/// first repeat again (at the plan's limits, up to 999 dwells of an hour lost). With
/// the disk stalling every sync by 400 ms, the laser is still off within the bound:
/// the partial record is written after it goes off, and synced after that (dwells of
/// 200 ms, so the stop comes more than the log's 0.5 s after its last sync, when an
/// append syncs).
#[test]
fn a_pause_in_the_middle_of_a_pairs_repeats_keeps_those_summed() {
    use std::sync::atomic::Ordering;
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let paused: Arc<OnceLock<Instant>> = Arc::default();
    let at = paused.clone();
    periscope_daemon::store::SLOW_SYNC_MS.store(400, Ordering::SeqCst);
    let (dir, rig) = stopped_mid_repeats(tmp.path(), 200, move |control, _, _| {
        let _ = at.set(Instant::now());
        control.pause();
    });
    periscope_daemon::store::SLOW_SYNC_MS.store(0, Ordering::SeqCst);
    let t = *paused.get().unwrap();
    let off = rig.off_since(t).expect("off") - t;
    assert!(off <= EMISSION_BOUND, "emission lasted {off:?} after the pause");
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
    let stopped = read_log(&dir).unwrap();
    assert_eq!(stopped.records.len(), 3, "the pairs before the stop");
    let [part] = stopped.partial.as_slice() else {
        panic!("no partial sum kept: {:?}", stopped.partial)
    };
    assert!(
        [200_000, 400_000, 600_000].contains(&part.dwell_us),
        "{} µs summed",
        part.dwell_us
    );
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_each_pair_once(&dir);
    let log = read_log(&dir).unwrap();
    assert!(log.partial.is_empty() && log.discarded_bytes == 0);
    let whole = log.records.iter().find(|r| r.pair == part.pair).unwrap();
    assert_eq!(whole.dwell_us, 800_000);
    assert!(
        whole.counts.iter().zip(&part.counts).all(|(w, p)| w >= p),
        "the whole sum does not hold the partial one"
    );
    let more: u64 = whole
        .counts
        .iter()
        .zip(&part.counts)
        .map(|(w, p)| u64::from(w - p))
        .sum();
    assert!(more > 0, "nothing measured on top of the partial sum");
}

/// An adaptive capture paused in the middle of a pair's repeats, in a batch the fit
/// chose, finishes that pair first when it resumes, on top of its partial sum: the
/// resumed session's first batch (`resumed`) holds it, and no partial sum is left
/// unused in the log. Until 2026-12-07 the resume chose afresh from a new fit, which
/// need not choose that pair again (here, and in every case tried, it did: the pair
/// is finished now by rule, not by what a fit on fewer pairs happens to choose).
#[test]
fn a_resumed_adaptive_capture_finishes_the_pair_it_stopped_in_the_middle_of() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let adaptive = small_plan()
        .set("pairs.mode", "adaptive")
        .set("pairs.candidates", "confocal")
        .set("recon.adaptive.pairs", 12)
        .set("recon.adaptive.first", 6)
        .set("recon.adaptive.batch", 3)
        .set("recon.adaptive.live-steps", 16);
    let (dir, rig) = stopped_mid_repeats_of(tmp.path(), adaptive, 7, 30, |control, _, _| control.pause());
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
    let stopped = read_log(&dir).unwrap();
    assert_eq!(stopped.records.len(), 7, "the pairs before the stop");
    let [part] = stopped.partial.as_slice() else {
        panic!("no partial sum kept: {:?}", stopped.partial)
    };
    let events = EventSink::open(&dir).unwrap();
    let chosen = Arc::new(Mutex::new(Vec::new()));
    {
        let chosen = chosen.clone();
        events.listen(move |e| {
            if let RunEvent::PairsChosen(c) = e {
                chosen
                    .lock()
                    .unwrap()
                    .push((c.batch, c.how.clone(), c.pairs.clone()));
            }
        });
    }
    Run::open(&dir, Control::new(), Some(events), Some(&rig))
        .unwrap()
        .execute()
        .unwrap();
    let log = read_log(&dir).unwrap();
    assert!(
        log.partial.is_empty(),
        "a partial sum left unused: {:?}",
        log.partial
    );
    let mut stored: Vec<u32> = log.records.iter().map(|r| r.pair).collect();
    stored.sort_unstable();
    stored.dedup();
    assert_eq!(stored.len(), 12, "the budget, each pair once");
    let whole = log.records.iter().find(|r| r.pair == part.pair).unwrap();
    assert_eq!(whole.dwell_us, 120_000);
    assert!(whole.counts.iter().zip(&part.counts).all(|(w, p)| w >= p));
    let chosen = chosen.lock().unwrap();
    let (number, how, first) = &chosen[0];
    assert_eq!(how, "resumed");
    assert_eq!(
        first,
        &[part.pair as usize],
        "the resumed batch: the pair stopped in"
    );
    // Numbered on past the batch it stopped in (the first batch, 0, then batch 1 of
    // three pairs, stopped in its second), as the dashboard keys batches by number.
    assert_eq!(*number, 2, "the resumed batch's number");
}

/// A stop that switches the laser off out of band before it asks the run to pause
/// (a signal's order) keeps no partial sum: a repeat that ended between the two may
/// have been partly dark, so the pair is measured again from its first repeat.
#[test]
fn a_signals_stop_in_the_middle_of_a_pairs_repeats_keeps_no_partial_sum() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = stopped_mid_repeats(tmp.path(), 30, |control, off, _| {
        off.laser_off().unwrap();
        std::thread::sleep(Duration::from_millis(1));
        control.pause();
    });
    let stopped = read_log(&dir).unwrap();
    assert!(stopped.partial.is_empty(), "{:?}", stopped.partial);
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_each_pair_once(&dir);
    assert!(
        read_log(&dir)
            .unwrap()
            .records
            .iter()
            .all(|r| r.dwell_us == 120_000)
    );
}

/// Nor does a pause that finds the pair's own checks failing: here the laser's sync
/// has changed rate under the repeats (another preset), which the pair's verdict would
/// have measured again, so the partial sum is not kept either.
#[test]
fn a_pause_under_a_sync_the_pair_would_refuse_keeps_no_partial_sum() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = stopped_mid_repeats(tmp.path(), 30, |control, _, rig| {
        rig.set_repetition_rate(12e6);
        std::thread::sleep(Duration::from_millis(5));
        control.pause();
    });
    rig.set_repetition_rate(10e6);
    let stopped = read_log(&dir).unwrap();
    assert!(stopped.partial.is_empty(), "{:?}", stopped.partial);
    assert_eq!(stopped.records.len(), 3);
}

/// The time budget holds while nothing can be fitted: with every histogram flagged
/// (overflowed, so left out of the fit) and the flagged-frames suspender off, each
/// next batch is spread, not chosen, and the budget's check comes before it. Until
/// 2026-12-07 only a fitted model's arrival was checked against `seconds`, so such a
/// capture measured its whole pair budget with the laser on, whatever the time said.
#[test]
fn an_adaptive_capture_with_nothing_to_fit_still_stops_at_its_time_budget() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 30\nfirst = 6\nbatch = 6\nlive-steps = 16\nseconds = 0.001\n"
        + "[suspend]\nflagged-frames = 0\n";
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &adaptive);
    let events = EventSink::open(&dir).unwrap();
    let r2 = rig.clone();
    events.listen(move |e| {
        if let RunEvent::StageStarted {
            stage: Stage::Capture,
        } = e
        {
            for _ in 0..200 {
                r2.inject(periscope_sim::devices::Fault::Tdc(
                    periscope_sim::devices::TdcFault::Overflow,
                ));
            }
        }
    });
    // Nothing fitted, nothing to reconstruct: how the run ends after the capture is
    // not what is asked here.
    let _ = Run::open(&dir, Control::new(), Some(events), Some(&rig))
        .unwrap()
        .execute();
    let log = read_log(&dir).unwrap();
    assert!(log.records.iter().all(|r| r.flags.overflow));
    assert_eq!(log.records.len(), 6, "the first batch and no more");
    let why = RunInfo::load(&dir).unwrap().adaptive_stopped;
    assert!(
        why.as_deref().is_some_and(|w| w.contains("adaptive.seconds")),
        "{why:?}"
    );
    assert!(!rig.emission());
}

/// An adaptive capture its stopping rule ended before the budget stays ended: paused
/// in its reconstruction and resumed, it chooses and measures nothing more (until
/// 2026-12-06 the resume went back to choosing, with the rule's reference gain
/// forgotten, and measured on toward the budget with the laser on again).
#[test]
fn an_adaptive_capture_its_stopping_rule_ended_stays_ended_when_resumed() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let adaptive = plan().replace(
        "mode = \"confocal\"",
        "mode = \"adaptive\"\ncandidates = \"confocal\"",
    ) + "[recon.adaptive]\npairs = 21\nfirst = 6\nbatch = 3\nlive-steps = 16\nstop-gain = 0.999\n";
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &adaptive);
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    let c = control.clone();
    events.listen(move |e| {
        if let RunEvent::StageStarted {
            stage: Stage::Reconstruction,
        } = e
        {
            c.pause();
        }
    });
    let r = Run::open(&dir, control, Some(events), Some(&rig))
        .unwrap()
        .execute();
    assert!(r.is_err(), "{r:?}");
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Paused);
    let why = info
        .adaptive_stopped
        .expect("the stopping rule ended the capture");
    let stored = read_log(&dir).unwrap().records.len();
    assert!((6..21).contains(&stored), "{stored}: {why}");
    let chosen = |dir: &Path| {
        std::fs::read_to_string(dir.join("events.jsonl"))
            .unwrap()
            .matches("\"pairs-chosen\"")
            .count()
    };
    let before = chosen(&dir);
    let emitted = rig.emission_changes().len();
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
    assert_eq!(
        read_log(&dir).unwrap().records.len(),
        stored,
        "measured after it had ended"
    );
    assert_eq!(chosen(&dir), before, "chose after it had ended");
    assert_eq!(rig.emission_changes().len(), emitted, "the laser went on again");
}

#[test]
fn a_histogrammer_unplugged_for_good_fails_the_capture_keeps_its_pairs_and_resumes_once_back() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let r2 = rig.clone();
    let control = Control::new();
    let r = execute(&dir, &rig, control.clone(), move |done| {
        if done == 8 {
            r2.unplug_tdc(u32::MAX);
        }
    });
    let e = r
        .expect_err("the capture went on without its histogrammer")
        .to_string();
    assert!(e.contains("histogrammer") || e.contains("TDC"), "{e}");
    assert!(!rig.emission());
    // The laser off and both arms parked are the safe state, and the run says so: the
    // histogrammer's failed abort is only a warning (until 2026-12-07 it made the run
    // report the instrument unsafe, with "switch the laser off by hand").
    assert_eq!(rig.parked(), (true, true));
    assert_eq!(control.made_safe(), Some(Ok(())));
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Failed);
    let kept = read_log(&dir).unwrap();
    assert!(
        (8..=9).contains(&kept.records.len()),
        "{} kept",
        kept.records.len()
    );
    assert_eq!(kept.discarded_bytes, 0);
    let log_before = std::fs::read(dir.join(periscope_daemon::store::HISTOGRAM_LOG)).unwrap();

    // Still unplugged: a resume fails before the laser goes on and stores nothing.
    let since = Instant::now();
    assert!(execute(&dir, &rig, Control::new(), |_| {}).is_err());
    assert!(rig.emission_changes().iter().all(|c| !c.on || c.at < since));
    assert_eq!(
        std::fs::read(dir.join(periscope_daemon::store::HISTOGRAM_LOG)).unwrap(),
        log_before
    );

    // Plugged back in: the resume measures the rest, and what was kept is unchanged.
    rig.plug_tdc();
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
    assert_each_pair_once(&dir);
    let after = read_log(&dir).unwrap();
    assert_eq!(after.records[..kept.records.len()], kept.records[..]);
    assert!(!rig.emission());
}

/// A prepared run on the default simulated instrument in real time whose laser really
/// pulses at `true_mhz` (`sim.true-rep-rate-mhz`; its config says 10 MHz).
fn prepare_pulsing_at(tmp: &Path, plan: &str, true_mhz: f64, divider: u32) -> (PathBuf, SimBackend) {
    let src = instrument();
    let text = src
        .text()
        .replacen("[sim]\n", &format!("[sim]\ntrue-rep-rate-mhz = {true_mhz}\n"), 1)
        .replacen("sync-divider = 1\n", &format!("sync-divider = {divider}\n"), 1);
    let src = TomlSource::from_text(src.path(), text);
    let rig = SimBackend::from_config(&InstrumentConfig::from_source(&src).unwrap())
        .unwrap()
        .unwrap();
    let plan_src = TomlSource::from_text(tmp.join("plan.toml"), plan.to_owned());
    let (dir, _, _) = pipeline::prepare(&plan_src, &src, Some(&tmp.join("run")), "test").unwrap();
    (dir, rig)
}

/// A laser that pulses at another rate than `laser.rep-rate-mhz` says (here twice
/// it): the pile-up correction would count the wrong cycles and the window's check
/// the wrong period, silently. The run reads the counter's sync rate once the laser is
/// on, before the first LOS point, and fails naming both keys and both rates; the
/// laser is off, both arms parked, nothing measured. (Before 2026-12-06 the sync
/// rate was never compared with the config.)
#[test]
fn a_laser_pulsing_at_another_rate_than_configured_fails_the_run_before_it_measures() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare_pulsing_at(tmp.path(), &plan(), 20.0, 1);
    let e = execute(&dir, &rig, Control::new(), |_| {})
        .expect_err("a run on a laser at twice its configured rate")
        .to_string();
    assert!(
        e.contains("sync rate of 20.0000 MHz")
            && e.contains("laser.rep-rate-mhz = 10 over tdc.sync-divider = 1 gives 10.0000 MHz"),
        "{e}"
    );
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Failed);
    assert!(!dir.join("relay.ply").exists(), "the LOS scan went on");
    assert!(read_log(&dir).map_or(true, |l| l.records.is_empty()));
    assert!(!rig.emission());
    assert_eq!(rig.parked(), (true, true));
}

/// With a divider of 2, a laser at twice its configured rate gives Periscope's counter
/// (whose meter counts after the divider) the laser's configured rate: that is a
/// fault, not a pass, and the run fails before it measures.
#[test]
fn a_laser_at_the_divider_times_its_configured_rate_is_not_taken_for_a_meter_before_the_divider() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare_pulsing_at(tmp.path(), &plan(), 20.0, 2);
    let e = execute(&dir, &rig, Control::new(), |_| {})
        .expect_err("a laser at twice its rate behind a divider of 2")
        .to_string();
    assert!(
        e.contains("sync rate of 10.0000 MHz") && e.contains("tdc.sync-divider = 2 gives 5.0000 MHz"),
        "{e}"
    );
    assert!(!rig.emission());
    assert_eq!(rig.parked(), (true, true));
}

/// The laser's rate changes in the middle of a capture (another preset): the pair
/// measured under it is not kept, the run fails with the laser off and the arms
/// parked, and the pairs before are kept; with the rate back, the resume measures the
/// rest, each pair once.
#[test]
fn a_laser_rate_that_changes_mid_capture_fails_the_run_and_keeps_the_pairs_before() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let r2 = rig.clone();
    let e = execute(&dir, &rig, Control::new(), move |done| {
        if done == 8 {
            r2.set_repetition_rate(12e6);
        }
    })
    .expect_err("the capture went on at another rate")
    .to_string();
    assert!(
        e.contains("sync rate of 12.0000 MHz") && e.contains("20.0 % off"),
        "{e}"
    );
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Failed);
    assert_eq!(read_log(&dir).unwrap().records.len(), 8);
    assert!(!rig.emission());
    assert_eq!(rig.parked(), (true, true));

    rig.set_repetition_rate(10e6);
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
    assert_each_pair_once(&dir);
}

/// A plan whose TDC window records none of the hidden paths its volume needs (the
/// shipped window, total paths of 3.6 to 8.5 m, so hidden ones to about 4.5 m, and a
/// volume 3.5 to 4 m deep, whose paths start at 7 m) stops once its pairs are planned,
/// before the first NLOS pair: the run fails naming the keys to change, stores no
/// histogram, and leaves the laser off and both arms parked. (Before 2026-12-05 it
/// captured every pair and reconstructed zeros.)
#[test]
fn a_tdc_window_that_records_none_of_the_volume_fails_before_the_first_pair() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let plan = SmallPlan::named("far-volume")
        .set("recon.volume.z", [3.5, 4.0])
        .toml();
    let (dir, rig) = prepare(tmp.path(), &plan);
    let e = execute(&dir, &rig, Control::new(), |_| {})
        .expect_err("a capture of paths the volume has none of")
        .to_string();
    assert!(
        e.contains("acquisition.offset-ns") && e.contains("[recon.volume]"),
        "{e}"
    );
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Failed);
    assert!(
        read_log(&dir).map_or(true, |l| l.records.is_empty()),
        "no NLOS histogram was measured"
    );
    assert!(!rig.emission());
    assert_eq!(rig.parked(), (true, true));
}

/// A window that records none of the relay's first bounces: the run fails after the
/// LOS scan, laser off and arms parked, naming the window and what to change, not the
/// relay thresholds (until 2026-12-06: "only 0 of 0 LOS points passed relay.depth-m
/// … widen them").
#[test]
fn a_tdc_window_that_records_none_of_the_relay_fails_naming_the_window() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let plan = SmallPlan::named("window-misses-relay")
        .set("acquisition.offset-ns", 60.0)
        .toml();
    let (dir, rig) = prepare(tmp.path(), &plan);
    let e = execute(&dir, &rig, Control::new(), |_| {})
        .expect_err("a capture whose window misses the relay")
        .to_string();
    assert!(
        e.contains("none of the 144 LOS points had a return inside the TDC window")
            && e.contains("acquisition.offset-ns")
            && e.contains("periscope check"),
        "{e}"
    );
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Failed);
    assert!(!rig.emission());
    assert_eq!(rig.parked(), (true, true));
}

#[test]
fn a_record_damaged_in_the_middle_of_the_log_is_measured_again_and_the_rest_kept() {
    use periscope_daemon::store::{DAMAGED_LOG, HISTOGRAM_LOG};
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let control = Control::new();
    let c = control.clone();
    let r = execute(&dir, &rig, control, move |done| {
        if done == 12 {
            c.pause();
        }
    });
    assert!(r.is_err());
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
    let before = read_log(&dir).unwrap().records;
    assert!((12..=13).contains(&before.len()), "{}", before.len());
    // Flip one bit in the counts of the fifth record (all records have one length).
    let path = dir.join(HISTOGRAM_LOG);
    let mut bytes = std::fs::read(&path).unwrap();
    let one = bytes.len() / before.len();
    assert_eq!(one * before.len(), bytes.len());
    bytes[4 * one + 40] ^= 0x10;
    std::fs::write(&path, &bytes).unwrap();
    let hit = before[4].pair;

    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Completed);
    assert_each_pair_once(&dir);
    assert!(!rig.emission());
    // Every undamaged record is kept as it was; the damaged pair was measured again;
    // the file as found is kept beside the log.
    let after = read_log(&dir).unwrap();
    for r in before.iter().filter(|r| r.pair != hit) {
        assert!(after.records.contains(r), "pair {} changed or was lost", r.pair);
    }
    assert!(after.records.iter().any(|r| r.pair == hit));
    assert_eq!(std::fs::read(dir.join(DAMAGED_LOG)).unwrap(), bytes);
}

/// The plan with a `[suspend]` table.
fn plan_with(suspend: &str) -> String {
    format!("{}\n[suspend]\n{suspend}\n", plan())
}

#[test]
fn an_opened_interlock_pauses_the_capture_with_the_laser_off_until_the_operator_resumes() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan_with("resume = \"operator\""));
    let r2 = rig.clone();
    let opened: Arc<Mutex<Option<Instant>>> = Arc::default();
    let o2 = opened.clone();
    let r = execute(&dir, &rig, Control::new(), move |done| {
        if done == 5 {
            *o2.lock().unwrap() = Some(Instant::now());
            r2.set_interlock(false);
        }
    });
    let Err(PipelineError::Suspended { reason, pairs }) = r else {
        panic!("{r:?}")
    };
    assert!(reason.contains("interlock"), "{reason}");
    assert!((5..=6).contains(&pairs), "{pairs}");
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Paused);
    assert!(info.error.unwrap().contains("interlock"));
    assert!(!rig.emission());
    // Nothing switched the laser on after the loop opened.
    let t = opened.lock().unwrap().unwrap();
    assert!(rig.emission_changes().iter().all(|c| !c.on || c.at < t));
    // While the loop is open a resume cannot switch the laser on; closed, it completes.
    rig.set_interlock(true);
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_each_pair_once(&dir);
    assert!(!rig.emission());
}

#[test]
fn an_interlock_that_closes_again_resumes_the_capture_by_itself() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan_with("resume = \"auto\"\nclear-for-s = 0.2"));
    let r2 = rig.clone();
    let window: Arc<Mutex<Option<(Instant, Instant)>>> = Arc::default();
    let w2 = window.clone();
    execute(&dir, &rig, Control::new(), move |done| {
        if done == 5 {
            let r3 = r2.clone();
            let w3 = w2.clone();
            let opened = Instant::now();
            r2.set_interlock(false);
            std::thread::spawn(move || {
                std::thread::sleep(Duration::from_millis(300));
                r3.set_interlock(true);
                *w3.lock().unwrap() = Some((opened, Instant::now()));
            });
        }
    })
    .unwrap();
    assert_each_pair_once(&dir);
    let (opened, closed) = window.lock().unwrap().unwrap();
    let changes = rig.emission_changes();
    // Off while the loop was open and for the clear time after; on again only then.
    let back_on = changes
        .iter()
        .find(|c| c.on && c.at > opened)
        .expect("the capture went on with the laser on");
    assert!(
        back_on.at >= closed + Duration::from_millis(200),
        "{:?}",
        back_on.at - closed
    );
    assert!(!rig.emission());
    let events = std::fs::read_to_string(dir.join("events.jsonl")).unwrap();
    assert!(events.contains("\"suspended\"") && events.contains("\"suspend-cleared\""));
}

#[test]
fn flagged_frames_and_a_count_rate_above_the_limit_suspend_the_capture() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    // Three overflowing frames in a row.
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan_with("flagged-frames = 3"));
    let r2 = rig.clone();
    let r = execute(&dir, &rig, Control::new(), move |done| {
        if done == 2 {
            for _ in 0..3 {
                r2.inject(periscope_sim::devices::Fault::Tdc(
                    periscope_sim::devices::TdcFault::Overflow,
                ));
            }
        }
    });
    let Err(PipelineError::Suspended { reason, .. }) = r else {
        panic!("{r:?}")
    };
    assert!(reason.contains("3 consecutive histograms"), "{reason}");
    assert!(!rig.emission());
    // Two flagged pairs were stored with their flags; the third is measured again.
    let log = read_log(&dir).unwrap();
    assert_eq!(log.records.iter().filter(|r| r.flags.overflow).count(), 2);
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert_each_pair_once(&dir);

    // A limit below what the wall returns: the first pair trips it.
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan_with("max-count-rate-hz = 1.0"));
    let r = execute(&dir, &rig, Control::new(), |_| {});
    let Err(PipelineError::Suspended { reason, pairs }) = r else {
        panic!("{r:?}")
    };
    assert!(
        reason.contains("count rate") && reason.contains("max-count-rate-hz"),
        "{reason}"
    );
    assert_eq!(pairs, 0);
    assert!(!rig.emission());

    // The same limit resumed automatically, with no clear time: it never clears, so
    // after a few resumes (waiting longer each time) the run waits for the operator.
    // Until 2026-12-06 it switched the laser on and off about 2,800 times a second, for
    // good, writing two events each time.
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(
        tmp.path(),
        &plan_with("max-count-rate-hz = 1.0\nresume = \"auto\"\nclear-for-s = 0"),
    );
    let t = Instant::now();
    let r = execute(&dir, &rig, Control::new(), |_| {});
    let Err(PipelineError::Suspended { reason, pairs }) = r else {
        panic!("{r:?}")
    };
    assert!(
        reason.contains("does not clear") && reason.contains("6 times"),
        "{reason}"
    );
    assert_eq!(pairs, 0);
    assert!(!rig.emission());
    let ons = rig.emission_changes().iter().filter(|c| c.on).count();
    assert!((5..=8).contains(&ons), "{ons} switch-ons");
    assert!(t.elapsed() >= Duration::from_millis(3750), "{:?}", t.elapsed());
    let events = std::fs::read_to_string(dir.join("events.jsonl")).unwrap();
    assert_eq!(events.matches("\"suspend-cleared\"").count(), 5);
    assert_eq!(RunInfo::load(&dir).unwrap().state, RunState::Paused);
}

/// An emergency off that the run meets as emission lost, with the stop request
/// arriving as it does (the e-stop's abort, here a hair after the laser went off):
/// the run ends aborted as asked, not held paused as a watchdog trip would leave it.
/// The abort is made at the moment the run reads the laser off, between that reading
/// and its decision, so the race the dashboard's e-stop once lost is met every time.
#[test]
fn an_emergency_off_met_as_emission_lost_ends_the_run_as_the_stop_asked() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let control = Control::new();
    let events = EventSink::open(&dir).unwrap();
    let laser: Arc<OnceLock<EmergencyOff>> = Arc::new(OnceLock::new());
    let off_at: Arc<Mutex<Option<Instant>>> = Arc::default();
    {
        let (control, laser, off_at) = (control.clone(), laser.clone(), off_at.clone());
        let mut aborted = false;
        events.listen(move |e| match e {
            RunEvent::Pair { done: 5, .. } => {
                laser.get().unwrap().laser_off().unwrap();
                *off_at.lock().unwrap() = Some(Instant::now());
            }
            RunEvent::Safety { emission: false, .. } if !aborted && off_at.lock().unwrap().is_some() => {
                aborted = true;
                control.abort_by("estop");
            }
            _ => {}
        });
    }
    let run = Run::open(&dir, control, Some(events), Some(&rig)).unwrap();
    let _ = laser.set(run.emergency_off());
    let r = run.execute();
    assert!(matches!(r, Err(PipelineError::Aborted(_))), "{r:?}");
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Aborted);
    assert!(!rig.emission());
    let t = off_at.lock().unwrap().unwrap();
    assert!(rig.emission_changes().iter().all(|c| !c.on || c.at < t));
    assert_eq!(rig.parked(), (true, true));
    // Nothing about a suspension reached the log: the run was stopped, not held.
    let log = std::fs::read_to_string(dir.join("events.jsonl")).unwrap();
    assert!(!log.contains("\"suspended\""), "{log}");
}

/// The API service on the real-time simulated instrument, its runs under `runs`.
fn service(runs: &Path) -> Arc<periscope_daemon::service::Service> {
    let src = instrument();
    let text = format!("{}\n[api]\nruns-dir = {:?}\n", src.text(), runs);
    periscope_daemon::service::Service::open(TomlSource::from_text(src.path().to_owned(), text), None)
        .unwrap()
}

/// A service case: one at a time (see [`ONE_AT_A_TIME`]), on a fresh runs directory.
fn fresh_service() -> (
    std::sync::MutexGuard<'static, ()>,
    tempfile::TempDir,
    Arc<periscope_daemon::service::Service>,
) {
    let serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let runs = tempfile::tempdir().unwrap();
    let svc = service(runs.path());
    (serial, runs, svc)
}

/// Waits until run `id` captures with the laser on.
fn wait_capturing(svc: &periscope_daemon::service::Service, id: &str, rig: &Rig) {
    let start = Instant::now();
    while !(svc.status(id).unwrap().stage == "capture" && rig.emission()) {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "run {id} never captured"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

#[test]
fn an_idle_estop_reaches_the_laser_with_the_tdc_unplugged_and_the_disk_refusing_writes() {
    use periscope_drivers::galvo::Connector;
    use periscope_drivers::galvo::protocol::encode_line;
    use periscope_sim::devices::Arm;

    let (_serial, runs, svc) = fresh_service();
    let rig = rig_of(svc.backend()).unwrap().clone();
    // A queued run whose run.json cannot be rewritten (the disk refuses writes in its
    // directory), so holding it fails.
    let queued = svc.submit(plan()).unwrap().id;
    let _refused = periscope_daemon::store::refuse_writes_in(&runs.path().join(&queued));
    // The laser left on by something else, and the histogrammer unplugged.
    let mut link = rig.galvo_connector(Arm::Laser).connect().unwrap();
    link.send(encode_line(0x01, "LASER ON").as_bytes()).unwrap();
    let mut buf = [0u8; 64];
    link.receive(&mut buf, Duration::from_secs(1)).unwrap();
    assert!(rig.emission());
    rig.unplug_tdc(1_000);
    let t = Instant::now();
    let report = svc.estop().unwrap();
    let off = rig.off_since(t).expect("the e-stop left the laser on");
    assert!(off - t < Duration::from_millis(50), "{:?}: {report:?}", off - t);
    assert!(report.laser.contains("opened for the e-stop"), "{report:?}");
    assert!(report.parked, "{report:?}");
    assert!(
        report.warnings.iter().any(|w| w.contains(&queued)),
        "the failed write is reported: {report:?}"
    );
    let (laser, spad) = rig.pointing();
    assert_eq!((laser.x, laser.y, spad.x, spad.y), (0.0, 0.0, 0.0, 0.0));
    // The hold holds though its run.json still reads queued: the worker does not start
    // the run (it had, and switched the laser on, once the disk took writes again).
    assert_eq!(report.held, std::slice::from_ref(&queued), "{report:?}");
    // A resume the disk refuses fails, and leaves the hold in place (it was dropped
    // before the write, and the run then started by itself once writes came back).
    assert!(svc.resume(&queued).is_err());
    drop(_refused);
    rig.plug_tdc();
    let worker = svc.start_worker();
    std::thread::sleep(Duration::from_millis(400));
    assert_eq!(svc.status(&queued).unwrap().state, RunState::Queued);
    assert!(!svc.instrument_status().busy);
    assert!(rig.off_since(t).is_some() && !rig.emission());
    // An operator's resume releases it; it runs to the end.
    svc.resume(&queued).unwrap();
    let start = Instant::now();
    while svc.status(&queued).unwrap().state != RunState::Completed {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "{queued} never completed"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    svc.shutdown();
    worker.join().unwrap();
}

#[test]
fn a_panicking_run_fails_resumably_and_the_queue_goes_on() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    periscope_daemon::signals::install_panic_hook();
    let runs = tempfile::tempdir().unwrap();
    let svc = service(runs.path());
    let worker = svc.start_worker();
    let rig = rig_of(svc.backend()).unwrap().clone();
    let a = svc.submit(plan()).unwrap().id;
    let b = svc.submit(plan()).unwrap().id;
    let start = Instant::now();
    wait_capturing(&svc, &a, &rig);
    let t = Instant::now();
    assert!(svc.inject_panic(Stage::Capture));
    let wait = |id: &str, state: RunState| {
        while svc.status(id).unwrap().state != state {
            assert!(start.elapsed() < Duration::from_secs(60), "{id} never {state:?}");
            std::thread::sleep(Duration::from_millis(5));
        }
    };
    wait(&a, RunState::Failed);
    // The next run may already have switched the laser on again: read the log.
    let off = rig
        .emission_changes()
        .into_iter()
        .find(|c| !c.on && c.at >= t)
        .expect("the panicking run left the laser on")
        .at;
    assert!(off - t <= EMISSION_BOUND, "{:?}", off - t);
    let err = svc.status(&a).unwrap().error.unwrap();
    assert!(err.contains("internal error in stage capture"), "{err}");
    // The queue goes on: the next run completes, on the same instrument.
    wait(&b, RunState::Completed);
    // And the failed one resumes to completion.
    svc.resume(&a).unwrap();
    wait(&a, RunState::Completed);
    assert_each_pair_once(&runs.path().join(&a));
    assert!(!rig.emission());
    svc.shutdown();
    worker.join().unwrap();
}

#[test]
fn an_estop_reaches_the_laser_and_parks_while_the_worker_hangs() {
    let (_serial, _runs, svc) = fresh_service();
    let worker = svc.start_worker();
    let rig = rig_of(svc.backend()).unwrap().clone();
    let a = svc.submit(plan()).unwrap().id;
    let start = Instant::now();
    wait_capturing(&svc, &a, &rig);
    // The worker gets stuck at its next checkpoint for 4 s, with the laser on.
    assert!(svc.inject_hang(Stage::Capture, Duration::from_secs(4)));
    std::thread::sleep(Duration::from_millis(100));
    assert!(
        rig.emission(),
        "the keepalive holds emission while the worker hangs"
    );
    let t = Instant::now();
    let report = svc.estop().unwrap();
    let off = rig.off_since(t).expect("the laser is on after the e-stop");
    assert!(off - t <= EMISSION_BOUND, "{:?}: {report:?}", off - t);
    assert!(report.laser.contains("out-of-band"), "{report:?}");
    // It waited 2 s for the run, then parked both arms itself.
    assert!(report.parked, "{report:?}");
    assert!(
        report.warnings.iter().any(|w| w.contains("checkpoint")),
        "{report:?}"
    );
    assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    // Through the run's own links, out of band: the controllers act on the PARK as
    // they read it.
    let parked = Instant::now();
    loop {
        let (laser, spad) = rig.pointing();
        if (laser.x, laser.y, spad.x, spad.y) == (0.0, 0.0, 0.0, 0.0) {
            break;
        }
        assert!(
            parked.elapsed() < Duration::from_millis(500),
            "{:?}",
            rig.pointing()
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    // The keepalive stopped with the e-stop, so nothing switches the laser back on, and
    // the run ends aborted once the worker comes back.
    while svc.status(&a).unwrap().state != RunState::Aborted {
        assert!(start.elapsed() < Duration::from_secs(60), "{a} never aborted");
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(rig.emission_changes().iter().all(|c| !c.on || c.at < t));
    svc.shutdown();
    worker.join().unwrap();
}

/// A worker stuck with the laser on and nobody at the e-stop: once the run has shown no
/// progress (no checkpoint, no stop poll) for `[laser] stall-ms`, the keepalive stops
/// feeding the controller's watchdog, and the watchdog switches the laser off.
#[test]
fn a_worker_stuck_with_the_laser_on_loses_it_to_the_watchdog_without_an_estop() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let runs = tempfile::tempdir().unwrap();
    let src = instrument();
    let stall = Duration::from_millis(1000);
    let text = src.text().replacen("[laser]\n", "[laser]\nstall-ms = 1000\n", 1);
    assert!(
        text.contains("stall-ms"),
        "the instrument config has no [laser] table"
    );
    let text = format!("{text}\n[api]\nruns-dir = {:?}\n", runs.path());
    let svc =
        periscope_daemon::service::Service::open(TomlSource::from_text(src.path().to_owned(), text), None)
            .unwrap();
    let worker = svc.start_worker();
    let rig = rig_of(svc.backend()).unwrap().clone();
    let a = svc.submit(plan()).unwrap().id;
    wait_capturing(&svc, &a, &rig);
    // Stuck at its next checkpoint for 4 s, with the laser on.
    let t = Instant::now();
    assert!(svc.inject_hang(Stage::Capture, Duration::from_secs(4)));
    let off = loop {
        if let Some(off) = rig.off_since(t) {
            break off - t;
        }
        assert!(
            t.elapsed() < Duration::from_secs(4),
            "the laser stayed on while the run hung"
        );
        std::thread::sleep(Duration::from_millis(2));
    };
    eprintln!(
        "stuck worker: laser off {:.0} ms after the hang began",
        off.as_secs_f64() * 1e3
    );
    let (watchdog, trips) = rig.watchdog();
    assert_eq!(trips, 1, "switched off by the watchdog");
    assert_eq!(
        rig.emission_changes().last().unwrap().cause,
        EmissionCause::Watchdog
    );
    assert!(
        off >= stall - Duration::from_millis(50) && off <= stall + watchdog + Duration::from_millis(500),
        "off {off:?} after the hang began (stall limit {stall:?}, watchdog {watchdog:?})"
    );
    svc.shutdown();
    worker.join().unwrap();
    assert!(!rig.emission());
}

/// The e-stop believes a run that stopped only if the run made the instrument safe.
/// Here the SPAD arm is unplugged for good during a capture, so the run's park fails
/// on its way out; the e-stop then opens the controllers itself and reports the arm it
/// could not park, where it had reported the instrument parked.
#[test]
fn an_estop_does_not_take_a_failed_make_safe_for_parked() {
    use periscope_sim::devices::{Arm, Fault, GalvoFault};

    let (_serial, _runs, svc) = fresh_service();
    let worker = svc.start_worker();
    let rig = rig_of(svc.backend()).unwrap().clone();
    let a = svc.submit(plan()).unwrap().id;
    wait_capturing(&svc, &a, &rig);
    rig.inject(Fault::Galvo(
        Arm::Spad,
        GalvoFault::Disconnect {
            refused_connects: 1_000_000,
        },
    ));
    let t = Instant::now();
    let report = svc.estop().unwrap();
    let off = rig.off_since(t).expect("the e-stop left the laser on");
    assert!(off - t <= EMISSION_BOUND, "{:?}: {report:?}", off - t);
    assert!(!report.parked, "the SPAD arm could not be parked: {report:?}");
    assert!(
        report.warnings.iter().any(|w| w.contains("SPAD arm")),
        "{report:?}"
    );
    assert!(
        !svc.instrument_status()
            .last_safe
            .is_some_and(|s| s.contains(&format!("end of run {a}"))),
        "the worker claimed the run parked the arms"
    );
    svc.shutdown();
    worker.join().unwrap();
}

/// A run that fails before it can record anything (its stored plan no longer loads) is
/// recorded as failed with the reason by the worker, instead of staying `queued` out of
/// the queue, never to run and not resumable.
#[test]
fn a_run_that_cannot_start_is_recorded_failed_not_left_queued() {
    let (_serial, runs, svc) = fresh_service();
    let a = svc.submit(plan()).unwrap().id;
    std::fs::write(runs.path().join(&a).join("plan.toml"), "[los\n").unwrap();
    let worker = svc.start_worker();
    let start = Instant::now();
    let status = loop {
        let s = svc.status(&a).unwrap();
        if s.state != RunState::Queued {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(30), "{a} stayed queued");
        std::thread::sleep(Duration::from_millis(5));
    };
    assert_eq!(status.state, RunState::Failed, "{status:?}");
    let error = status.error.unwrap_or_default();
    assert!(error.contains("plan.toml"), "{error}");
    assert!(!svc.instrument_status().busy);
    svc.shutdown();
    worker.join().unwrap();
}

/// A submission whose queue.json cannot be rewritten (the disk refuses writes in the
/// runs directory) is still queued and answered as such, rather than answered with an
/// error while it sits in the queue (a client would submit it again: a duplicate run);
/// the next start finds it from its run.json and queues it again.
#[test]
fn a_submission_the_queue_file_misses_is_queued_and_survives_a_restart() {
    let (_serial, runs, svc) = fresh_service();
    let refused = periscope_daemon::store::refuse_writes_in(runs.path());
    let status = svc.submit(plan()).unwrap();
    assert_eq!(status.state, RunState::Queued);
    assert_eq!(status.queue_position, Some(0));
    let listed = std::fs::read_to_string(runs.path().join("queue.json")).unwrap();
    assert!(!listed.contains(&status.id), "{listed}");
    drop(refused);
    drop(svc);
    let again = service(runs.path());
    assert_eq!(again.status(&status.id).unwrap().queue_position, Some(0));
}

/// A run the disk refuses to write (full, as `refuse_writes_in` makes it) fails
/// naming the file it could not write and what to do: free space, then resume; the
/// laser is off. Until 2026-12-07 it named the run's directory only, with the bare
/// "No space left on device".
#[test]
fn a_full_disk_names_the_file_and_the_remedy() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let refused = periscope_daemon::store::refuse_writes_in(&dir);
    let e = execute(&dir, &rig, Control::new(), |_| {})
        .expect_err("a run whose files cannot be written")
        .to_string();
    drop(refused);
    assert!(e.contains("run.json"), "{e}");
    assert!(
        e.contains("the disk is full: free space on it, then resume the run"),
        "{e}"
    );
    assert!(!rig.emission());
}

/// A run whose end neither its pipeline nor the worker could record (the disk refused
/// every write in its directory) still reads `queued` with nothing working on it: once
/// the disk takes writes again it can be resumed (and runs), where it was refused as
/// neither paused nor failed. A `running` run.json the service never worked on (a
/// `periscope run` of another process in the same directory) is still left alone.
#[test]
fn a_run_whose_end_could_not_be_recorded_can_be_resumed() {
    let (_serial, runs, svc) = fresh_service();
    let a = svc.submit(plan()).unwrap().id;
    let refused = periscope_daemon::store::refuse_writes_in(&runs.path().join(&a));
    let worker = svc.start_worker();
    let start = Instant::now();
    while svc.status(&a).unwrap().queue_position.is_some() || svc.instrument_status().busy {
        assert!(start.elapsed() < Duration::from_secs(30), "{a} was never taken");
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(svc.status(&a).unwrap().state, RunState::Queued);
    drop(refused);
    let resumed = svc.resume(&a).unwrap();
    assert!(
        matches!(resumed.state, RunState::Queued | RunState::Running),
        "{resumed:?}"
    );
    while svc.status(&a).unwrap().state != RunState::Completed {
        assert!(start.elapsed() < Duration::from_secs(90), "{a} never completed");
        std::thread::sleep(Duration::from_millis(10));
    }
    // Another process's run, running as far as anyone here knows.
    let b = svc.submit(plan()).unwrap().id;
    svc.shutdown();
    worker.join().unwrap();
    let dir = runs.path().join(&b);
    let mut info = RunInfo::load(&dir).unwrap();
    info.state = RunState::Running;
    info.save(&dir).unwrap();
    assert!(svc.resume(&b).is_err());
    assert!(svc.abort(&b).is_err());
}

/// A run killed between writing a temporary file and renaming it (`kill -9` in the
/// outputs stage) left `volume.npy.<pid>-<n>.tmp` behind, which resume never removed;
/// and a run that completed after a pause kept the pause's error text. A resume removes
/// the first, and completion clears the second.
#[test]
fn a_completed_resume_leaves_no_stale_temporaries_and_no_old_error() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let (dir, rig) = prepare(tmp.path(), &plan());
    let stale = dir.join("volume.npy.4000000000-3.tmp");
    std::fs::write(&stale, b"half a volume").unwrap();
    let mut info = RunInfo::load(&dir).unwrap();
    info.error = Some("the interlock opened: the laser is off and the run paused after 3 pairs".into());
    info.save(&dir).unwrap();
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    assert!(
        !stale.exists(),
        "the interrupted write's temporary is still there"
    );
    let info = RunInfo::load(&dir).unwrap();
    assert_eq!(info.state, RunState::Completed);
    assert_eq!(info.error, None, "a completed run kept an earlier stop's error");
}

/// A 3D-GTR plan whose detection points no plane can fit (a fixed laser and a 2 × 1
/// detection grid) is refused when it is read, naming `fbp` as the way to reconstruct
/// it: no run is made, and nothing measured for a fit that could never render. (Until
/// 2026-12-06 it was refused only once the LOS scan had found the relay, with the laser
/// on; three or more points in a line still are, there.)
#[test]
fn a_gtr_capture_no_plane_fits_is_refused_before_its_pairs_are_measured() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = SmallPlan::named("line")
        .set("los.grid", [8, 8])
        .set("los.dwell-ms", 10.0)
        .set("pairs.mode", "fixed-laser")
        .unset("pairs.offset-mm")
        .set("pairs.laser", [0.0, 0.0, 0.0])
        .set("pairs.grid", [2, 1])
        .set("acquisition.dwell-ms", 30.0)
        .set("recon.method", "gtr")
        .set("recon.volume.shape", [16, 16, 16])
        .toml();
    let plan_src = TomlSource::from_text(tmp.path().join("plan.toml"), plan);
    let out = tmp.path().join("run");
    let e = pipeline::prepare(&plan_src, &instrument_on(Devices::InProcess), Some(&out), "test")
        .map(drop)
        .unwrap_err()
        .to_string();
    assert!(e.contains("pairs.mode") && e.contains("at least three"), "{e}");
    assert!(e.contains("fbp"), "{e}");
    assert!(!out.join("run.json").exists(), "a run was made");
    // So is an adaptive capture whose budget measures fewer than three points.
    let plan = SmallPlan::named("two")
        .set("pairs.mode", "adaptive")
        .set("pairs.candidates", "confocal")
        .set("pairs.grid", [4, 4])
        .set("recon.method", "gtr")
        .set("recon.adaptive.pairs", 2)
        .toml();
    let plan_src = TomlSource::from_text(tmp.path().join("plan.toml"), plan);
    let e = pipeline::prepare(&plan_src, &instrument_on(Devices::InProcess), Some(&out), "test")
        .map(drop)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("recon.adaptive.pairs") && e.contains("a budget of 2 pair(s)"),
        "{e}"
    );
    assert!(!out.join("run.json").exists(), "a run was made");
}

/// A pairs grid finer than the relay the LOS scan found: the run measures what the
/// relay gives, and says how many of the grid's pairs it could not plan (the `planned`
/// event's `requested` against its `pairs`), rather than a smaller layout passed off as
/// the plan's.
#[test]
fn a_pairs_grid_finer_than_the_relay_is_planned_short_and_says_so() {
    let _serial = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let plan = SmallPlan::named("sparse")
        .set("los.grid", [6, 6])
        .set("los.dwell-ms", 10.0)
        .set("relay.neighbours", 8)
        .set("pairs.grid", [16, 16])
        .set("acquisition.dwell-ms", 5.0)
        .toml();
    let (dir, rig) = prepare_on(tmp.path(), &plan, Devices::InProcess);
    execute(&dir, &rig, Control::new(), |_| {}).unwrap();
    let planned = std::fs::read_to_string(dir.join("events.jsonl"))
        .unwrap()
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .find(|v| v["event"] == "planned")
        .expect("a planned event");
    let (pairs, requested) = (
        planned["pairs"].as_u64().unwrap(),
        planned["requested"].as_u64().unwrap(),
    );
    assert_eq!(requested, 256, "{planned}");
    assert!(pairs > 0 && pairs <= 36, "{planned}");
    assert_each_pair_once(&dir);
}

/// A run paused or aborted while it opens its devices (an e-stop's hold lands there:
/// the worker has just taken the run) names who stopped it in its state history, as a
/// stop at any later checkpoint does. Until 2026-12-07 such a stop recorded nobody.
#[test]
fn a_run_stopped_while_opening_names_who_stopped_it() {
    for (ask, state) in [("pause", RunState::Paused), ("abort", RunState::Aborted)] {
        let tmp = tempfile::tempdir().unwrap();
        let (dir, rig) = prepare(tmp.path(), &plan());
        let control = Control::new();
        match ask {
            "pause" => assert!(control.pause_by("estop")),
            _ => assert!(control.abort_by("alice")),
        }
        let r = Run::open(&dir, control, None, Some(&rig));
        assert!(
            matches!(r, Err(PipelineError::Paused(_) | PipelineError::Aborted(_))),
            "{ask}: {:?}",
            r.err()
        );
        let info = RunInfo::load(&dir).unwrap();
        assert_eq!(info.state, state);
        let last = info.history.last().unwrap();
        assert_eq!(last.state, state);
        let want = if ask == "pause" { "estop" } else { "alice" };
        assert_eq!(last.by.as_deref(), Some(want), "{ask}: {:?}", info.history);
        assert!(!rig.emission());
    }
}

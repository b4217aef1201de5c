//! The stage × event stop matrix on a stand-in vendor library (`periscope-standins`):
//! the measuring stages (LOS scan, capture) × pause, abort, e-stop, a stop signal, the
//! counter vanishing for good, and a panic, each fired 7 ms into a dwell from another
//! thread, checked on the stand-in rig's own emission log. Shared by the PicoQuant and
//! the DAQmx tests, which differ only in the bench they set up.
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock, mpsc};
use std::time::{Duration, Instant};

use periscope_daemon::config::TomlSource;
use periscope_daemon::events::{EventSink, RunEvent, Stage};
use periscope_daemon::pipeline::{Control, Run};
use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_daemon::service::Service;
use periscope_daemon::store::read_log;
use periscope_drivers::EmergencyOff;
use periscope_drivers::picoquant::Family;
use periscope_standins::client::{Standin, exclusive};

/// The safety matrix's plan: 64 LOS points of 10 ms, 25 pairs of 30 ms, a tiny fit.
pub(crate) const PLAN: &str = r#"
name = "standin"
[los]
angles-deg = { x = [-12.0, 12.0], y = [-12.0, 12.0] }
grid = [8, 8]
dwell-ms = 10.0
[relay]
depth-m = [1.7, 3.0]
neighbours = 8
detection = { min = [-0.4, -0.4, -0.1], max = [0.4, 0.4, 0.1] }
[pairs]
mode = "confocal"
grid = [5, 5]
offset-mm = 5.0
[acquisition]
dwell-ms = 30.0
[recon]
method = "gtr"
[recon.volume]
x = [-0.4, 0.4]
y = [-0.4, 0.4]
z = [0.3, 0.9]
shape = [16, 16, 16]
[recon.gtr]
primitives = 200
epochs = 40
virtual-grid = [16, 16]
"#;

/// Longest the laser may stay on after an event (the docs' 50 ms).
const EMISSION_BOUND: Duration = Duration::from_millis(50);

/// Longest the run may take to return after an event.
const RETURN_BOUND: Duration = Duration::from_secs(2);

#[derive(Clone, Copy, Debug, PartialEq)]
enum Event {
    Pause,
    Abort,
    Estop,
    Signal,
    /// The counter vanishes from the bus for good.
    CounterGone,
    Panic,
}

/// Fires `event`, as the service, the signal handlers or the bench would.
fn fire(event: Event, stage: Stage, control: &Control, s: &Standin, laser: &OnceLock<EmergencyOff>) {
    match event {
        Event::Pause => control.pause(),
        Event::Abort => control.abort(),
        Event::Estop => {
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
        Event::CounterGone => s.vanish(Family::MultiHarp, 0, u32::MAX),
        Event::Panic => control.inject_panic(stage),
    }
}

fn expected_state(event: Event) -> RunState {
    match event {
        Event::Pause | Event::Signal => RunState::Paused,
        Event::Abort | Event::Estop => RunState::Aborted,
        Event::CounterGone | Event::Panic => RunState::Failed,
    }
}

/// Runs the plan in real time and fires `event` 7 ms into the first dwell of `stage`
/// (LOS scan or capture), from another thread; checks the rig's laser and arms.
fn run_case(stage: Stage, event: Event, setup: &dyn Fn(&Path) -> (Standin, PathBuf)) -> String {
    let tmp = tempfile::tempdir().unwrap();
    let (s, dir) = setup(tmp.path());
    let control = Control::new();
    let laser: Arc<OnceLock<EmergencyOff>> = Arc::new(OnceLock::new());
    let fired: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let events = EventSink::open(&dir).unwrap();
    let (tx, rx) = mpsc::channel::<()>();
    let mut armed = true;
    events.listen(move |e| {
        let first = matches!(
            (stage, e),
            (Stage::LosScan, RunEvent::LosPoint { .. }) | (Stage::Capture, RunEvent::Pair { .. })
        );
        if armed && first {
            armed = false;
            let _ = tx.send(());
        }
    });
    let trigger = {
        let (control, laser, fired) = (control.clone(), laser.clone(), fired.clone());
        std::thread::spawn(move || {
            if rx.recv().is_ok() {
                std::thread::sleep(Duration::from_millis(7));
                *fired.lock().unwrap() = Some(Instant::now());
                fire(event, stage, &control, &s, &laser);
            }
        })
    };
    let result = match Run::open(&dir, control, Some(events), None) {
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
        !s.emission(),
        "{event:?} in {stage:?}: the laser is on after the run returned"
    );
    let log = s.emission_log();
    let off_at = log
        .iter()
        .rev()
        .find(|(_, on, _)| !on)
        .map_or(t, |(at, _, _)| (*at).max(t));
    let on_after: Vec<_> = log.iter().filter(|(at, on, _)| *on && *at > t).collect();
    assert!(
        on_after.is_empty(),
        "{event:?} in {stage:?}: emission went on again: {on_after:?}"
    );
    let off_after = off_at.saturating_duration_since(t);
    assert!(
        off_after <= EMISSION_BOUND,
        "{event:?} in {stage:?}: emission lasted {off_after:?} after the event"
    );
    assert!(
        returned.saturating_duration_since(t) <= RETURN_BOUND,
        "{event:?} in {stage:?}: slow to return"
    );
    assert_eq!(
        s.parked(),
        (true, true),
        "{event:?} in {stage:?}: both arms parked"
    );
    let state = RunInfo::load(&dir).unwrap().state;
    assert_eq!(state, expected_state(event), "{event:?} in {stage:?}: {result:?}");
    if event == Event::CounterGone {
        let e = result.as_ref().unwrap_err().to_string();
        assert!(
            e.contains("MultiHarp") && e.contains("MH_ERROR_USB_VCMD_FAIL"),
            "{e}"
        );
    }
    format!(
        "{:<10} {:<12} off after {:>5.1} ms, state {state:?}\n",
        stage.name(),
        format!("{event:?}"),
        off_after.as_secs_f64() * 1e3
    )
}

/// The stop matrix's row for `stage`: every event, each on a fresh bench from `setup`
/// (the stand-in and a prepared run directory).
pub(crate) fn check_stage(stage: Stage, setup: &dyn Fn(&Path) -> (Standin, PathBuf)) {
    let _one = exclusive();
    periscope_daemon::signals::install_panic_hook();
    let mut table = String::new();
    for event in [
        Event::Pause,
        Event::Abort,
        Event::Estop,
        Event::Signal,
        Event::CounterGone,
        Event::Panic,
    ] {
        table.push_str(&run_case(stage, event, setup));
    }
    eprint!("{table}");
}

/// Runs the prepared run in `dir` to completion and checks what every backend must
/// give: completed, every planned pair stored once as a 1024-bin histogram, and light
/// reaching the counter. Returns the number of planned pairs.
pub(crate) fn whole_capture(dir: &Path) -> usize {
    let run = Run::open(dir, Control::new(), None, None).unwrap();
    run.execute().unwrap();
    let info = RunInfo::load(dir).unwrap();
    assert_eq!(info.state, RunState::Completed);
    // Every planned pair stored once, each a 1024-bin histogram from the counter.
    let planned: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(dir.join("pairs.json")).unwrap()).unwrap();
    let planned = planned.len();
    assert!(
        planned > 10,
        "{planned} pairs planned on the relay found by the LOS scan"
    );
    let log = read_log(dir).unwrap();
    let mut pairs: Vec<u32> = log.records.iter().map(|r| r.pair).collect();
    pairs.sort_unstable();
    assert_eq!(pairs, (0..planned as u32).collect::<Vec<_>>());
    assert!(log.records.iter().all(|r| r.counts.len() == 1024));
    let total: u64 = log
        .records
        .iter()
        .flat_map(|r| &r.counts)
        .map(|&c| u64::from(c))
        .sum();
    assert!(total > 0, "the third bounce and the background reach the counter");
    planned
}

/// A service on the lab config `lab` (the stand-in `s` behind it): a run stuck in its
/// capture with the laser on and its devices held, then an e-stop. The laser goes off
/// through the run's own laser driver, and both arms park through its own galvo
/// drivers, within the e-stop's wait; the run ends aborted once it comes back, with
/// nothing moved again. `confirmed`: the drivers can confirm the park (a DAQ's writes
/// return; a serial controller's answers are on the link the stuck run reads, so the
/// report says the arms were sent to park, unconfirmed, and not that they parked).
pub(crate) fn estop_while_the_run_hangs(tmp: &Path, s: &Standin, lab: &TomlSource, confirmed: bool) {
    let runs = tmp.join("runs");
    std::fs::create_dir(&runs).unwrap();
    let text = format!("{}\n[api]\nruns-dir = {:?}\n", lab.text(), runs);
    let svc = Service::open(TomlSource::from_text(lab.path().to_owned(), text), None).unwrap();
    let worker = svc.start_worker();
    let id = svc.submit(PLAN.to_owned()).unwrap().id;
    let start = Instant::now();
    while !(svc.status(&id).unwrap().stage == "capture" && s.emission()) {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "run {id} never captured"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    // During the capture the arms point at the relay, away from the park position
    // (the laser arm may be at its centre).
    let ((lx, ly), (sx, sy)) = s.pointing();
    assert!(
        lx.abs() + ly.abs() + sx.abs() + sy.abs() > 0.1,
        "{:?}",
        s.pointing()
    );
    assert!(svc.inject_hang(Stage::Capture, Duration::from_secs(5)));
    std::thread::sleep(Duration::from_millis(100));
    let t = Instant::now();
    let report = svc.estop().unwrap();
    assert!(!s.emission(), "{report:?}");
    assert!(report.laser_off_s.is_some_and(|s| s < 0.05), "{report:?}");
    let said = |text: &str| report.warnings.iter().any(|w| w.contains(text));
    if confirmed {
        assert!(report.parked, "{report:?}");
        assert!(
            said("both arms were parked through its own drivers"),
            "{report:?}"
        );
    } else {
        assert!(!report.parked, "{report:?}");
        assert!(said("PARK sent on run") && said("unconfirmed"), "{report:?}");
        assert!(said("sent to park through its own drivers"), "{report:?}");
    }
    assert!(t.elapsed() < Duration::from_secs(4), "{:?}", t.elapsed());
    // The controller takes its settling time to get there.
    let parked = Instant::now();
    while s.parked() != (true, true) {
        assert!(
            parked.elapsed() < Duration::from_secs(1),
            "{:?}: {report:?}",
            s.pointing()
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    let ((lx, ly), (sx, sy)) = s.pointing();
    assert!(
        lx.abs() + ly.abs() + sx.abs() + sy.abs() < 1e-9,
        "{:?}",
        s.pointing()
    );
    // The run ends aborted once it comes back, and nothing moved the arms again.
    while svc.status(&id).unwrap().state != RunState::Aborted {
        assert!(start.elapsed() < Duration::from_secs(90), "{id} never aborted");
        std::thread::sleep(Duration::from_millis(10));
    }
    assert_eq!(s.parked(), (true, true));
    assert!(!s.emission());
    svc.shutdown();
    worker.join().unwrap();
}

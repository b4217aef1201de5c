//! The DAQmx drivers through the real FFI path against the stand-in library: NI's
//! "Write Voltage Update" call sequence for a galvo pair (create, channels, start,
//! on-demand writes) with the slew limit and the limits checked on the voltages the
//! stand-in received; NI's "Watchdog Timer" sequence for the laser (watchdog task with
//! the gate's expiration state low, started before the gate goes high, reset by the
//! guard's keepalive); a stalled keepalive whose hardware watchdog switches the laser
//! off with nobody pressing the e-stop (the rig's log says watchdog); a device with no
//! watchdog, refused unless a heartbeat or the config's acceptance; the interlock; the
//! emergency off's latch; every class of error code with the library's words.
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use periscope_daemon::config::{GalvoLink, InstrumentConfig};
use periscope_drivers::daqmx::defin::error;
use periscope_drivers::daqmx::{AoGalvoSettings, DaqGalvo, DaqLaser, DaqLaserSettings};
use periscope_drivers::{Error, ErrorKind, GalvoPair, Laser, OpticalAngles, Parked, Progress};
use periscope_standins::client::{Standin, exclusive};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn sim_text() -> String {
    let scene = root().join("configs/scenes/wall-letter.toml");
    std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("../scenes/wall-letter.toml", &scene.to_string_lossy())
        .replace("[sim]\n", "[sim]\ntime-scale = 0.0\n")
}

/// The shipped instrument as a lab config with both pairs and the laser on `Dev1`
/// through `library`, `laser_extra` added to `[laser]`.
fn lab_text(library: &Path, laser_extra: &str) -> String {
    let text = sim_text();
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
                 volts-per-deg = [0.4, 0.4]\noffsets-v = [0.1, -0.1]\nmax-slew-deg-per-ms = 2.0\n"
            ));
        } else if line.starts_with("[galvo.spad]") {
            out.push_str(&format!(
                "scanner = \"pivot\"\ndriver = \"daqmx\"\nlibrary = \"{lib}\"\nchannels = [\"Dev1/ao2\", \"Dev1/ao3\"]\n\
                 volts-per-deg = [0.4, -0.4]\nmax-slew-deg-per-ms = 2.0\n"
            ));
        } else if line.starts_with("[laser]") {
            out.push_str(&format!(
                "laser-line = \"Dev1/port0/line0\"\ninterlock-line = \"Dev1/port0/line1\"\n\
                 diffuser-line = \"Dev1/port0/line2\"\nwatchdog-ms = 200\n{laser_extra}"
            ));
        } else if line.starts_with("[tdc]") {
            out.push_str(&format!("driver = \"multiharp\"\nlibrary = \"{lib}\"\n"));
        }
    }
    out
}

/// A fresh stand-in with its DAQ wired by the lab config; that config, loaded.
fn bench(dir: &Path, laser_extra: &str) -> (Standin, InstrumentConfig) {
    let s = Standin::load();
    let rig = dir.join("rig.toml");
    std::fs::write(&rig, sim_text()).unwrap();
    s.setup(&rig);
    let lab = dir.join("lab.toml");
    std::fs::write(&lab, lab_text(&s.path(), laser_extra)).unwrap();
    s.daq_setup(&lab);
    let config = InstrumentConfig::load(&lab).unwrap();
    (s, config)
}

fn galvo_settings(config: &InstrumentConfig) -> AoGalvoSettings {
    match &config.laser_arm.link {
        Some(GalvoLink::Daqmx(s)) => s.clone(),
        other => panic!("not a DAQmx arm: {other:?}"),
    }
}

fn laser_settings(config: &InstrumentConfig) -> DaqLaserSettings {
    config.laser.daqmx.clone().expect("DAQmx laser lines")
}

/// The calls whose names start with `prefix`.
fn named<'a>(calls: &'a [String], prefix: &str) -> Vec<&'a str> {
    calls
        .iter()
        .filter(|c| c.starts_with(prefix))
        .map(String::as_str)
        .collect()
}

/// The voltages of each `DAQmxWriteAnalogF64` on task `task`.
fn writes(calls: &[String], task: &str) -> Vec<Vec<f64>> {
    let head = format!("DAQmxWriteAnalogF64({task}, [");
    calls
        .iter()
        .filter_map(|c| c.strip_prefix(&head))
        .map(|rest| {
            rest.trim_end_matches("])")
                .split(", ")
                .map(|v| v.parse().unwrap())
                .collect()
        })
        .collect()
}

fn deg(x: f64, y: f64) -> OpticalAngles {
    OpticalAngles {
        x: x.to_radians(),
        y: y.to_radians(),
    }
}

#[test]
fn a_galvo_pair_follows_the_write_voltage_update_sequence_with_slew_limited_moves() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    s.clear_calls();
    let settings = galvo_settings(&config);
    let mut g = DaqGalvo::open(settings.clone()).unwrap();
    let calls = s.calls();
    assert_eq!(
        calls[..4],
        [
            "DAQmxCreateTask(\"periscope-galvo-laser\")".to_owned(),
            // ±20° at 0.4 V/° around offsets 0.1 and -0.1: the range the limits need.
            "DAQmxCreateAOVoltageChan(Dev1/ao0,Dev1/ao1, -8.1, 8.1, 10348)".to_owned(),
            "DAQmxStartTask(periscope-galvo-laser)".to_owned(),
            "DAQmxWriteAnalogF64(periscope-galvo-laser, [0.100000, -0.100000])".to_owned(),
        ],
        "{calls:#?}"
    );
    assert!(s.parked().0, "open writes the park position");
    let info = g.identify().unwrap();
    assert!(info.model.starts_with("PCIe-6363 (Dev1"), "{info:?}");
    assert_eq!(info.serial, "1A2B3C4");

    // A 15° move at 2°/ms: 8 writes, 1 ms apart, none more than 2° from the last.
    s.clear_calls();
    let t = Instant::now();
    g.move_to(deg(15.0, -5.0)).unwrap();
    let took = t.elapsed();
    let w = writes(&s.calls(), "periscope-galvo-laser");
    assert_eq!(w.len(), 8, "{w:?}");
    assert!(took >= Duration::from_millis(7), "the ramp took {took:?}");
    let mut last = [0.1, -0.1];
    for v in &w {
        for axis in 0..2 {
            let step_deg = (v[axis] - last[axis]).abs() / 0.4;
            assert!(step_deg <= 2.0 + 1e-6, "a {step_deg}° step in {w:?}");
        }
        last = [v[0], v[1]];
    }
    assert!((last[0] - (0.1 + 0.4 * 15.0)).abs() < 1e-6 && (last[1] - (-0.1 - 0.4 * 5.0)).abs() < 1e-6);
    // The rig's mirrors went where the voltages say, through the config's scale.
    let (laser, _) = s.pointing();
    assert!(
        (laser.0 - 15.0).abs() < 1e-6 && (laser.1 + 5.0).abs() < 1e-6,
        "{laser:?}"
    );
    assert_eq!(g.wait_settled(Duration::from_secs(1)).unwrap(), deg(15.0, -5.0));

    // Out of the limits: refused, nothing written.
    s.clear_calls();
    let e = g.move_to(deg(25.0, 0.0)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutOfRange);
    assert!(named(&s.calls(), "DAQmxWriteAnalogF64").is_empty());
    g.park().unwrap();
    assert!(s.parked().0);
    assert_eq!(
        s.daq_counters().0,
        0,
        "no write drove an arm past the rig's hard limits"
    );
    drop(g);
    let calls = s.calls();
    assert!(
        calls.ends_with(&[
            "DAQmxStopTask(periscope-galvo-laser)".to_owned(),
            "DAQmxClearTask(periscope-galvo-laser)".to_owned()
        ]),
        "{:?}",
        &calls[calls.len().saturating_sub(4)..]
    );
}

#[test]
fn the_laser_follows_the_watchdog_timer_sequence_and_the_keepalive_holds_it() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    s.clear_calls();
    laser.set_diffuser(true).unwrap();
    laser.set_emission(true).unwrap();
    let calls = s.calls();
    assert_eq!(
        calls,
        [
            "DAQmxWriteDigitalLines(periscope-diffuser, [1])",
            "DAQmxReadDigitalLines(periscope-interlock)",
            "DAQmxCreateWatchdogTimerTaskEx(Dev1, 0.2)",
            "DAQmxCfgWatchdogDOExpirStates(Dev1/port0/line0, [10214])",
            "DAQmxStartTask(watchdog)",
            "DAQmxWriteDigitalLines(periscope-laser-gate, [1])",
        ],
        "{calls:#?}"
    );
    assert!(s.emission());
    // Held by the keepalive for five timeouts.
    std::thread::sleep(Duration::from_millis(1000));
    assert!(
        s.emission(),
        "the watchdog tripped while the keepalive fed it: {:?}",
        s.emission_log()
    );
    let resets = named(&s.calls(), "DAQmxControlWatchdogTask(0)").len();
    assert!(resets >= 10, "{resets} resets in 1 s with a 200 ms watchdog");
    let state = laser.laser_state().unwrap();
    assert!(state.emission && state.interlock_closed && state.diffuser_in);
    s.clear_calls();
    laser.set_emission(false).unwrap();
    assert!(!s.emission());
    // A keepalive feed (its watchdog reset and interlock read) may land among them.
    let calls: Vec<String> = s
        .calls()
        .into_iter()
        .filter(|c| c != "DAQmxControlWatchdogTask(0)" && c != "DAQmxReadDigitalLines(periscope-interlock)")
        .collect();
    assert_eq!(
        calls,
        [
            "DAQmxWriteDigitalLines(periscope-laser-gate, [0])",
            "DAQmxStopTask(watchdog)",
            "DAQmxClearTask(watchdog)"
        ]
    );
    let log = s.emission_log();
    assert!(
        log.iter().all(|(_, _, cause)| *cause == 0),
        "host switched: {log:?}"
    );
}

#[test]
fn a_stalled_run_loses_the_laser_to_the_hardware_watchdog_without_an_estop() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    let progress = Progress::new(Duration::from_millis(150));
    laser.watch_progress(progress.clone());
    laser.set_emission(true).unwrap();
    let t = Instant::now();
    // Beating: held past several timeouts.
    while t.elapsed() < Duration::from_millis(600) {
        progress.beat();
        std::thread::sleep(Duration::from_millis(5));
    }
    assert!(s.emission(), "switched off while the run made progress");
    // Stalled: the keepalive stops after 150 ms, the device's timer after 200 more.
    let stalled = Instant::now();
    let off = loop {
        if !s.emission() {
            break stalled.elapsed();
        }
        assert!(stalled.elapsed() < Duration::from_secs(2), "the laser stayed on");
        std::thread::sleep(Duration::from_millis(2));
    };
    assert!(
        off >= Duration::from_millis(150) && off <= Duration::from_millis(150 + 200 + 120),
        "off {off:?} after the last beat"
    );
    let (_, on, cause) = *s.emission_log().last().unwrap();
    assert!(!on);
    assert_eq!(cause, 1, "the watchdog switched it off, not the host");
    assert!(
        !laser.laser_state().unwrap().emission,
        "the driver sees the expiry"
    );
    // The run comes back and switches off: the expired line counts as off.
    laser.set_emission(false).unwrap();
    // And a later switch-on arms a fresh watchdog.
    laser.watch_progress(Progress::new(Duration::from_secs(60)));
    laser.set_emission(true).unwrap();
    assert!(s.emission());
    laser.set_emission(false).unwrap();
}

/// A watchdog that expired keeps the gate line at its expiration state after its task
/// is cleared, as NI-DAQmx keeps a device's expiration: a later program that drives
/// the line without a watchdog of its own is refused with what to do, and one that
/// starts a watchdog (which clears the expiration) switches on.
#[test]
fn an_expired_watchdog_holds_the_line_after_its_task_is_gone() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    laser.watch_progress(Progress::new(Duration::from_millis(50)));
    laser.set_emission(true).unwrap();
    let t = Instant::now();
    while s.emission() {
        assert!(t.elapsed() < Duration::from_secs(2), "the watchdog never expired");
        std::thread::sleep(Duration::from_millis(5));
    }
    // The program ends without clearing the expiration: its tasks are cleared.
    drop(laser);
    // Another program, configured without the hardware watchdog, on the same device.
    let unguarded = tmp.path().join("unguarded.toml");
    std::fs::write(
        &unguarded,
        lab_text(&s.path(), "daq-watchdog = false\naccept-no-watchdog = true\n"),
    )
    .unwrap();
    let unguarded = InstrumentConfig::load(&unguarded).unwrap();
    let mut laser = DaqLaser::open(laser_settings(&unguarded)).unwrap();
    let e = laser.set_emission(true).unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("DAQmxErrorWriteFailedBecauseWatchdogExpired")
            && text.contains("daq-watchdog = true")
            && text.contains("Reset Device"),
        "{text}"
    );
    assert!(!s.emission(), "the expired line went high");
    drop(laser);
    // With the watchdog, starting its task clears the expiration: on.
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    laser.watch_progress(Progress::new(Duration::from_secs(60)));
    laser.set_emission(true).unwrap();
    assert!(s.emission());
    laser.set_emission(false).unwrap();
}

#[test]
fn without_a_hardware_watchdog_emission_needs_a_heartbeat_or_the_configs_acceptance() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    // Refused: the device says it has no watchdog, and nothing else is configured.
    let (s, config) = bench(tmp.path(), "");
    s.daq_watchdog_supported(false);
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    let e = laser.set_emission(true).unwrap_err();
    assert!(
        e.to_string().contains("no hardware watchdog") && e.to_string().contains("heartbeat-line"),
        "{e}"
    );
    assert!(
        !s.emission() && s.emission_log().is_empty(),
        "emitted without a watchdog"
    );
    drop(laser);

    // With a heartbeat line: on, and each keepalive toggles it.
    let (s, config) = bench(tmp.path(), "heartbeat-line = \"Dev1/port0/line3\"\n");
    s.daq_watchdog_supported(false);
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    laser.set_emission(true).unwrap();
    assert!(s.emission());
    let before = s.daq_counters().1;
    std::thread::sleep(Duration::from_millis(300));
    let beats = s.daq_counters().1 - before;
    assert!(beats >= 4, "{beats} heartbeats in 300 ms (a feed every 50 ms)");
    laser.set_emission(false).unwrap();
    drop(laser);

    // Accepted by the config: on, with no watchdog at all.
    let (s, config) = bench(tmp.path(), "daq-watchdog = false\naccept-no-watchdog = true\n");
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    s.clear_calls();
    laser.set_emission(true).unwrap();
    assert!(s.emission());
    assert!(named(&s.calls(), "DAQmxCreateWatchdogTimerTaskEx").is_empty());
    laser.set_emission(false).unwrap();
}

/// A pair's emergency park from another thread, while its owner ramps a move: the park
/// takes the task between two of the owner's writes, ramps to 0 at the slew limit
/// (no write more than 2° from the one before, whoever wrote it), and latches: the
/// owner's move ends with `Interrupted` at its next write, and every later move is
/// refused with nothing written; the owner's own park still works. Once the driver is
/// closed, the handle reaches nothing, and the channels are free to open again.
#[test]
fn an_emergency_park_takes_the_pair_from_its_owner_and_latches() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    // 0.1° a write: a 30° move takes 300 writes, 1 ms apart.
    let settings = AoGalvoSettings {
        max_slew_deg_per_ms: 0.1,
        ..galvo_settings(&config)
    };
    let mut g = DaqGalvo::open(settings.clone()).unwrap();
    let park = g.emergency_park();
    g.park().unwrap();
    g.move_to(deg(-15.0, 10.0)).unwrap();
    s.clear_calls();
    let mover = std::thread::spawn(move || {
        let e = g.move_to(deg(15.0, -5.0)).unwrap_err();
        (g, e)
    });
    // The park comes in once the move is under way.
    let t = Instant::now();
    while writes(&s.calls(), "periscope-galvo-laser").len() < 5 {
        assert!(t.elapsed() < Duration::from_secs(2), "the move never started");
        std::thread::sleep(Duration::from_micros(200));
    }
    assert_eq!(park.park().unwrap(), Parked::Done);
    let (mut g, e) = mover.join().unwrap();
    assert_eq!(e.kind(), ErrorKind::Interrupted, "{e}");
    assert!(s.parked().0, "{:?}", s.pointing());
    let w = writes(&s.calls(), "periscope-galvo-laser");
    assert!(w.len() >= 10 && w.len() < 2 * 300, "{}", w.len());
    let mut last = [0.1 + 0.4 * -15.0, -0.1 + 0.4 * 10.0];
    for v in &w {
        for axis in 0..2 {
            let step_deg = (v[axis] - last[axis]).abs() / 0.4;
            assert!(step_deg <= 0.1 + 1e-6, "a {step_deg}° step in {w:?}");
        }
        last = [v[0], v[1]];
    }
    assert_eq!(last, [0.1, -0.1], "{w:?}");
    // Latched: refused with nothing written; its own park still answers.
    s.clear_calls();
    assert_eq!(
        g.move_to(deg(1.0, 1.0)).unwrap_err().kind(),
        ErrorKind::Interrupted
    );
    assert!(named(&s.calls(), "DAQmxWriteAnalogF64").is_empty());
    g.park().unwrap();
    assert!(s.parked().0);
    drop(g);
    assert_eq!(park.park().unwrap_err().kind(), ErrorKind::Disconnected);
    drop(DaqGalvo::open(settings).unwrap());
}

#[test]
fn the_interlock_and_an_emergency_off_keep_the_laser_off() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    s.set_interlock(false);
    let e = laser.set_emission(true).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Interlock);
    assert!(!s.emission());
    s.set_interlock(true);
    laser.set_emission(true).unwrap();
    let off = laser.emergency_off();
    off.laser_off().unwrap();
    assert!(!s.emission());
    assert_eq!(
        laser.set_emission(true).unwrap_err().kind(),
        ErrorKind::Interrupted
    );
    assert!(!s.emission());
    // Dropping the driver leaves the gate low and clears every task, even while its
    // emergency off is still held (the panic hook keeps the handles of a process's
    // runs): the line is free for the next open, which NI-DAQmx would refuse as
    // reserved while the old gate task lived.
    s.clear_calls();
    drop(laser);
    assert!(!s.emission());
    assert!(!off.is_open());
    let calls = s.calls();
    let cleared = named(&calls, "DAQmxClearTask");
    assert!(
        cleared.iter().any(|c| c.contains("periscope-laser-gate")),
        "the gate's task was not cleared: {cleared:?}"
    );
    let again = DaqLaser::open(laser_settings(&config)).unwrap_or_else(|e| panic!("reopening the line: {e}"));
    // The closed driver's switch says it cannot reach the line, as the serial one does.
    assert_eq!(off.laser_off().unwrap_err().kind(), ErrorKind::Disconnected);
    drop(again);
}

#[test]
fn error_codes_become_kinds_with_the_librarys_words() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let settings = galvo_settings(&config);
    let mut g = DaqGalvo::open(settings.clone()).unwrap();
    for (code, kind, words) in [
        (
            error::DEVICE_REMOVED,
            ErrorKind::Disconnected,
            "DAQmxErrorDeviceRemoved",
        ),
        (
            error::RESOURCE_ALREADY_RESERVED,
            ErrorKind::Busy,
            "DAQmxErrorResourceAlreadyReserved",
        ),
        (
            error::SAMPLE_VALUE_OUT_OF_RANGE,
            ErrorKind::OutOfRange,
            "DAQmxErrorSampleValueOutOfRange",
        ),
        (
            error::INVALID_AO_DATA_WRITE,
            ErrorKind::OutOfRange,
            "DAQmxErrorInvalidAODataWrite",
        ),
        (
            error::OPERATION_TIMED_OUT,
            ErrorKind::Timeout,
            "DAQmxErrorOperationTimedOut",
        ),
        (error::INVALID_TASK, ErrorKind::Device, "DAQmxErrorInvalidTask"),
    ] {
        s.daq_fail_next("DAQmxWriteAnalogF64", code);
        let e = g.move_to(deg(1.0, 1.0)).unwrap_err();
        assert_eq!(e.kind(), kind, "{e}");
        let text = e.to_string();
        assert!(
            text.contains(words)
                && text.contains(&format!("error {code}"))
                && text.contains("galvo pair `laser`"),
            "{text}"
        );
        let d: periscope_drivers::DeviceError = e.into();
        assert_eq!(d.kind(), kind);
    }
    // A second driver on the same pair while the first holds it: its task's name is
    // taken, as NI-DAQmx refuses a duplicate task (another daemon on the device).
    let e = DaqGalvo::open(settings.clone()).err().unwrap();
    assert_eq!(e.kind(), ErrorKind::Busy, "{e}");
    assert!(
        e.to_string().contains("DAQmxErrorDuplicateTask")
            && e.to_string().contains("another Periscope daemon"),
        "{e}"
    );
    // A channel the device does not have: refused when the task is made (a pair of
    // another name: this one's task is still open).
    let mut bad = settings.clone();
    bad.name = "spare".into();
    bad.channels[1] = "Dev1/ao7".into();
    let e = DaqGalvo::open(bad).err().unwrap();
    assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
    assert!(
        e.to_string().contains("DAQmxErrorPhysicalChanDoesNotExist"),
        "{e}"
    );
    // The device vanishes: writes fail `disconnected`, and its gate drops.
    let mut laser = DaqLaser::open(laser_settings(&config)).unwrap();
    laser.set_emission(true).unwrap();
    s.daq_vanish();
    assert!(!s.emission());
    assert_eq!(s.emission_log().last().unwrap().2, 3, "a power loss");
    assert_eq!(
        g.move_to(deg(1.0, 1.0)).unwrap_err().kind(),
        ErrorKind::Disconnected
    );
    // No library there.
    let mut missing = settings;
    missing.library = "/nonexistent/libnidaqmx.so".into();
    let e = DaqGalvo::open(missing).err().unwrap();
    assert_eq!(e.kind(), ErrorKind::Disconnected);
    assert!(
        e.to_string().contains("cannot load /nonexistent/libnidaqmx.so")
            && e.to_string().contains("install NI-DAQmx")
    );
}

/// `DAQmxWriteAnalogF64` and `DAQmxWriteDigitalLines` take no array size: the library
/// reads one value a channel (a byte a line) of the task. A galvo axis named by a list
/// (`Dev1/ao0,Dev1/ao2`: three channels for the driver's two values) or a laser line
/// naming two lines is refused by the driver's own check of the task's width, naming
/// the fix, with nothing written; until 2026-12-06 the library read past the driver's
/// values (the stand-in read a third voltage from beyond the array).
#[test]
fn a_task_wider_than_the_drivers_values_is_refused_before_any_write() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let (s, config) = bench(tmp.path(), "");
    let mut settings = galvo_settings(&config);
    settings.channels[0] = "Dev1/ao0,Dev1/ao2".into();
    s.clear_calls();
    let e = DaqGalvo::open(settings)
        .err()
        .expect("a three-channel task opened");
    assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
    assert!(e.to_string().contains("one analog output"), "{e}");
    assert!(
        named(&s.calls(), "DAQmxWriteAnalogF64").is_empty(),
        "{:?}",
        s.calls()
    );

    let mut laser = laser_settings(&config);
    laser.laser_line = "Dev1/port0/line0,Dev1/port0/line3".into();
    s.clear_calls();
    let e = DaqLaser::open(laser).err().expect("a two-line gate opened");
    assert!(e.to_string().contains("one digital line"), "{e}");
    assert!(
        named(&s.calls(), "DAQmxWriteDigitalLines").is_empty(),
        "{:?}",
        s.calls()
    );
}

//! The laser when the `periscope` process itself goes: `kill -9`, SIGTERM, a second
//! signal, and SIGTERM to `periscope serve` with event-stream clients attached.
//!
//! The laser controller here runs in the test process, on a pseudo-terminal the
//! `periscope` child opens by path (`galvo.laser.serial` in its instrument config), as
//! it would a real controller on `/dev/ttyUSB0`: so the controller outlives the child,
//! and the test reads the simulated laser's own emission log. The rest of the child's
//! instrument is simulated in the child.
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use periscope_daemon::config::{InstrumentConfig, TomlSource};
use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_sim::devices::{Arm, EmissionCause, Rig, ServedPort};
use periscope_tests::{SmallPlan, periscope_bin, repo_root};

/// A long LOS scan (16 × 16 points of 50 ms, about 13 s): the laser is on throughout.
fn plan_toml() -> String {
    SmallPlan::named("process-safety")
        .set("los.grid", [16, 16])
        .set("los.dwell-ms", 50.0)
        .set("relay.neighbours", 16)
        .set("pairs.offset-mm", 0.0)
        .set("recon.volume.shape", [16, 16, 16])
        .toml()
}

/// The default controller watchdog.
const WATCHDOG: Duration = Duration::from_millis(500);

/// Scheduling slack on top of a bound (the test polls every millisecond or so).
const SLACK: Duration = Duration::from_millis(60);

/// A simulated instrument whose two galvo controllers (the laser arm's with the laser)
/// the test hosts.
struct Bench {
    rig: Rig,
    _ports: [ServedPort; 2],
    dir: tempfile::TempDir,
    instrument: PathBuf,
    plan: PathBuf,
}

/// `extra` adds to the instrument config, given the bench's directory.
fn bench(extra: impl FnOnce(&Path) -> String) -> Bench {
    let dir = tempfile::tempdir().unwrap();
    let extra = extra(dir.path());
    let text = periscope_tests::real_time_sim_instrument();
    let path = dir.path().join("instrument.toml");
    let config = InstrumentConfig::from_source(&TomlSource::from_text(path.clone(), text.clone())).unwrap();
    let rig = periscope_daemon::devices::sim::SimBackend::from_config(&config)
        .unwrap()
        .unwrap()
        .rig()
        .clone();
    let port = rig.serve_galvo_port(Arm::Laser).unwrap();
    let spad = rig.serve_galvo_port(Arm::Spad).unwrap();
    let text = text
        .replacen(
            "[galvo.spad]",
            &format!("serial = {{ port = {:?} }}\n\n[galvo.spad]", port.path()),
            1,
        )
        .replacen(
            "\n[laser]",
            &format!("serial = {{ port = {:?} }}\n\n[laser]", spad.path()),
            1,
        );
    std::fs::write(&path, format!("{text}\n{extra}")).unwrap();
    let plan = dir.path().join("plan.toml");
    std::fs::write(&plan, plan_toml()).unwrap();
    Bench {
        rig,
        _ports: [port, spad],
        dir,
        instrument: path,
        plan,
    }
}

impl Bench {
    fn spawn(&self, args: &[&str]) -> Child {
        Command::new(periscope_bin())
            .args(args)
            .current_dir(repo_root())
            .env("RUST_LOG", "warn")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("periscope starts")
    }

    fn run(&self) -> Child {
        let out = self.dir.path().join("run");
        self.spawn(&[
            "run",
            self.plan.to_str().unwrap(),
            "--instrument",
            self.instrument.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
    }

    /// Waits until the child has switched the laser on (and a little longer, so a
    /// dwell is under way).
    fn wait_emitting(&self, child: &mut Child) {
        let start = Instant::now();
        while !self.rig.emission() {
            if let Some(status) = child.try_wait().unwrap() {
                let mut err = String::new();
                child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
                panic!("periscope exited ({status}) before switching the laser on:\n{err}");
            }
            assert!(
                start.elapsed() < Duration::from_secs(30),
                "the laser never went on"
            );
            std::thread::sleep(Duration::from_millis(2));
        }
        std::thread::sleep(Duration::from_millis(120));
        assert!(self.rig.emission());
    }

    /// When emission went off after `t`, waiting up to `limit`.
    fn off_after(&self, t: Instant, limit: Duration) -> Duration {
        loop {
            if let Some(off) = self.rig.off_since(t) {
                return off - t;
            }
            assert!(t.elapsed() < limit, "the laser was still on {limit:?} later");
            std::thread::sleep(Duration::from_millis(1));
        }
    }
}

fn signal(child: &Child, name: &str) {
    let ok = Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{name} failed");
}

/// Waits for the child to exit, up to `limit`; returns its exit code and how long.
fn exit_within(child: &mut Child, since: Instant, limit: Duration) -> (Option<i32>, Duration) {
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return (status.code(), since.elapsed());
        }
        if since.elapsed() > limit {
            let _ = child.kill();
            panic!("periscope was still running {limit:?} after the signal");
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn a_killed_run_leaves_the_laser_off_within_the_watchdog_timeout() {
    let b = bench(|_| String::new());
    let mut child = b.run();
    b.wait_emitting(&mut child);
    let t = Instant::now();
    child.kill().unwrap(); // SIGKILL: no handler, no unwinding, no drop.
    child.wait().unwrap();
    let off = b.off_after(t, Duration::from_secs(3));
    let last = *b.rig.emission_changes().last().unwrap();
    eprintln!(
        "kill -9: laser off {:.0} ms later ({:?})",
        off.as_secs_f64() * 1e3,
        last.cause
    );
    assert_eq!(last.cause, EmissionCause::Watchdog);
    assert!(off <= WATCHDOG + SLACK, "{off:?}");
    assert_eq!(b.rig.watchdog().1, 1);
}

/// A laser left emitting by a process that died, with a watchdog longer than the
/// restart takes, is switched off by the next process that opens the instrument (here
/// `periscope devices`; `serve`'s first reading and every run open it the same way):
/// its requests feed the controller's watchdog, so it must not leave the laser on.
#[test]
fn opening_the_instrument_switches_off_a_laser_a_killed_run_left_on() {
    let b = bench(|_| String::new());
    let stderr = open_after_a_killed_run_left_the_laser_on(&b, |text| text, true);
    assert!(
        stderr.contains("the laser was emitting when Periscope opened its controller"),
        "{stderr}"
    );
}

/// The same, with the instrument config changed after the kill so that opening the
/// laser arm is refused (its angle limits now reach past the controller's own): the
/// laser is switched off before the refusal. Before 2026-12-07 the limits were checked
/// first, and every refused open (`serve` retries every `status-interval-s`) fed the
/// watchdog of a laser it never switched off.
#[test]
fn opening_the_instrument_switches_the_laser_off_before_it_refuses_the_config() {
    let b = bench(|_| String::new());
    let widen = |text: String| {
        let (head, tail) = text.split_once("[galvo.laser]").unwrap();
        let from = "angle-limits-deg = { x = [-20.0, 20.0], y = [-20.0, 20.0] }";
        assert!(tail.contains(from), "the sim's laser arm limits");
        let to = "angle-limits-deg = { x = [-25.0, 25.0], y = [-20.0, 20.0] }";
        format!("{head}[galvo.laser]{}", tail.replacen(from, to, 1))
    };
    let stderr = open_after_a_killed_run_left_the_laser_on(&b, widen, false);
    assert!(stderr.contains("galvo.laser.angle-limits-deg"), "{stderr}");
}

/// Kills a run on bench `b` (its laser's watchdog set to 30 s) while the laser is on,
/// rewrites the instrument config through `edit`, then runs `periscope devices`, which
/// must succeed or fail as `opens` says, and asserts the laser went off by the host's
/// command within 10 s of it. Returns what `periscope devices` wrote to stderr.
fn open_after_a_killed_run_left_the_laser_on(
    b: &Bench,
    edit: impl FnOnce(String) -> String,
    opens: bool,
) -> String {
    let text = std::fs::read_to_string(&b.instrument).unwrap();
    assert!(text.contains("[laser]\n"));
    std::fs::write(
        &b.instrument,
        text.replacen("[laser]\n", "[laser]\nwatchdog-ms = 30000\n", 1),
    )
    .unwrap();
    let mut child = b.run();
    b.wait_emitting(&mut child);
    child.kill().unwrap(); // SIGKILL: no handler, no unwinding, no drop.
    child.wait().unwrap();
    assert!(b.rig.emission(), "the 30 s watchdog cannot have tripped yet");
    let text = std::fs::read_to_string(&b.instrument).unwrap();
    std::fs::write(&b.instrument, edit(text)).unwrap();
    let t = Instant::now();
    let devices = b.spawn(&["devices", "--instrument", b.instrument.to_str().unwrap()]);
    let out = devices.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.success(), opens, "periscope devices: {stderr}");
    let off = b
        .rig
        .off_since(t)
        .expect("the laser is still on after `periscope devices`")
        - t;
    let last = *b.rig.emission_changes().last().unwrap();
    eprintln!(
        "laser left on by kill -9: off {:.0} ms after `periscope devices` started",
        off.as_secs_f64() * 1e3
    );
    assert_eq!(
        last.cause,
        EmissionCause::Host,
        "switched off by a command, not the watchdog"
    );
    assert!(!b.rig.emission());
    assert!(off < Duration::from_secs(10), "{off:?}");
    stderr
}

#[test]
fn sigterm_switches_the_laser_off_at_once_and_the_run_pauses_resumably() {
    let b = bench(|_| String::new());
    let mut child = b.run();
    b.wait_emitting(&mut child);
    let t = Instant::now();
    signal(&child, "TERM");
    let (code, exited) = exit_within(&mut child, t, Duration::from_secs(5));
    let off = b.off_after(t, Duration::from_secs(1));
    eprintln!(
        "SIGTERM: laser off {:.1} ms later, exit after {:.0} ms",
        off.as_secs_f64() * 1e3,
        exited.as_secs_f64() * 1e3
    );
    assert_eq!(
        b.rig.emission_changes().last().unwrap().cause,
        EmissionCause::Host
    );
    assert!(off <= Duration::from_millis(50), "{off:?}");
    assert!(exited <= Duration::from_secs(2), "{exited:?}");
    assert_eq!(code, Some(128 + 15));
    let info = RunInfo::load(&b.dir.path().join("run")).unwrap();
    assert_eq!(info.state, RunState::Paused, "{info:?}");
    assert_eq!(info.stage, "los-scan");
    assert_eq!(b.rig.watchdog().1, 0, "the watchdog had nothing to do");
}

#[test]
fn a_second_signal_exits_at_once_with_the_laser_off() {
    let b = bench(|_| String::new());
    let mut child = b.run();
    b.wait_emitting(&mut child);
    // The LOS scan points the SPAD arm (on the other port this rig serves) away from
    // its park position.
    let scanning = Instant::now();
    while b.rig.parked().1 {
        assert!(
            scanning.elapsed() < Duration::from_secs(5),
            "the SPAD arm never moved"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(b.rig.emission());
    let t = Instant::now();
    // The second at once, while the first is being handled: the signals are
    // listened for from the start, so it is not lost between two registrations.
    signal(&child, "INT");
    signal(&child, "HUP");
    let (code, exited) = exit_within(&mut child, t, Duration::from_secs(5));
    let off = b.off_after(t, Duration::from_secs(1));
    assert!(off <= Duration::from_millis(50), "{off:?}");
    assert!(exited <= Duration::from_millis(500), "{exited:?}");
    assert_eq!(code, Some(128 + 2));
    // Exiting without waiting for the run, it parked the arms through the run's own
    // drivers.
    let parked = Instant::now();
    while b.rig.parked() != (true, true) {
        assert!(
            parked.elapsed() < Duration::from_millis(500),
            "the arms were left at {:?}",
            b.rig.pointing()
        );
        std::thread::sleep(Duration::from_millis(2));
    }
}

/// Opens an event stream and reads its response head; returns the connection.
fn open_stream(addr: &str, id: &str) -> TcpStream {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    write!(
        s,
        "GET /api/v1/runs/{id}/events HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        assert_eq!(s.read(&mut byte).unwrap(), 1, "the stream closed before its head");
        head.push(byte[0]);
    }
    assert!(
        head.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&head)
    );
    s
}

/// Reads until the server closes the stream (true) or the timeout (false).
fn closed(mut s: TcpStream, within: Duration) -> bool {
    s.set_read_timeout(Some(within)).unwrap();
    let mut buf = [0u8; 4096];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return true,
            Ok(_) => {}
            Err(_) => return false,
        }
    }
}

#[test]
fn sigterm_on_serve_with_ten_event_streams_exits_within_2_s_with_the_laser_off() {
    let b = bench(|dir| format!("[api]\nruns-dir = {:?}\n", dir.join("runs")));
    let runs = b.dir.path().join("runs");
    let mut child = Command::new(periscope_bin())
        .args([
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--instrument",
            b.instrument.to_str().unwrap(),
        ])
        .current_dir(repo_root())
        .env("RUST_LOG", "warn")
        .env("PERISCOPE_TOKEN", "safety-token")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // The address it listens on, from its first line.
    let mut stderr = child.stderr.take().unwrap();
    let mut line = Vec::new();
    let mut byte = [0u8; 1];
    while !line.ends_with(b"\n") {
        assert_eq!(stderr.read(&mut byte).unwrap(), 1, "serve exited early");
        line.push(byte[0]);
    }
    let line = String::from_utf8(line).unwrap();
    let addr = line
        .split("http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
        .unwrap_or_else(|| panic!("no address in {line:?}"))
        .to_owned();
    std::thread::spawn(move || std::io::copy(&mut stderr, &mut std::io::sink()));
    // Submit the plan.
    let plan = plan_toml();
    let mut s = TcpStream::connect(&addr).unwrap();
    write!(
        s,
        "POST /api/v1/runs HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer safety-token\r\n\
         Content-Type: application/toml\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{plan}",
        plan.len()
    )
    .unwrap();
    let mut reply = String::new();
    s.read_to_string(&mut reply).unwrap();
    assert!(reply.starts_with("HTTP/1.1 201"), "{reply}");
    let id = reply
        .split("\"id\":\"")
        .nth(1)
        .and_then(|r| r.split('"').next())
        .unwrap()
        .to_owned();
    b.wait_emitting(&mut child);
    let streams: Vec<TcpStream> = (0..10).map(|_| open_stream(&addr, &id)).collect();
    let t = Instant::now();
    signal(&child, "TERM");
    let (_, exited) = exit_within(&mut child, t, Duration::from_secs(5));
    let off = b.off_after(t, Duration::from_secs(1));
    eprintln!(
        "serve SIGTERM with 10 streams: laser off {:.1} ms later, exit after {:.0} ms",
        off.as_secs_f64() * 1e3,
        exited.as_secs_f64() * 1e3
    );
    assert!(off <= Duration::from_millis(50), "{off:?}");
    assert!(exited < Duration::from_secs(2), "{exited:?}");
    for s in streams {
        assert!(closed(s, Duration::from_secs(1)), "an event stream was left open");
    }
    let info = RunInfo::load(&runs.join(&id)).unwrap();
    assert_eq!(info.state, RunState::Paused, "{info:?}");
}

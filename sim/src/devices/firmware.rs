//! Galvo controller firmware on a pseudo-terminal: reads tagged lines, answers them
//! as `docs/protocols/galvo-serial.md` specifies, and models settling and limits.
use std::io::{self, Read, Write};
use std::sync::Weak;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use periscope_drivers::galvo::protocol::{self, ErrorCode, LineError, MotionState, Request};
use periscope_drivers::galvo::{Connector, Link};
use serialport::{SerialPort, TTYPort};
use tracing::debug;

use super::rig::{Arm, EmissionCause, GalvoFault, Rig, Shared};

/// Firmware version the simulated controllers report.
pub(crate) const FIRMWARE: &str = "1.0.0-sim";

/// Opens a pseudo-terminal pair per connection and runs the firmware on the master.
pub struct PtyConnector {
    rig: Rig,
    arm: Arm,
    last_path: String,
}

impl PtyConnector {
    pub(crate) fn new(rig: Rig, arm: Arm) -> PtyConnector {
        PtyConnector {
            rig,
            arm,
            last_path: String::from("(simulated pty, not yet opened)"),
        }
    }
}

impl Connector for PtyConnector {
    fn connect(&mut self) -> io::Result<Box<dyn Link>> {
        let generation = {
            let mut s = self.rig.shared.lock();
            let arm = &mut s.arms[self.arm.index()];
            if arm.refused_connects > 0 {
                arm.refused_connects -= 1;
                return Err(io::Error::new(
                    io::ErrorKind::NotFound,
                    "simulated controller unplugged",
                ));
            }
            arm.generation += 1;
            arm.generation
        };
        let (master, slave) = TTYPort::pair().map_err(io::Error::from)?;
        self.last_path = slave.name().unwrap_or_else(|| "simulated pty".into());
        let firmware = Firmware {
            shared: std::sync::Arc::downgrade(&self.rig.shared),
            arm: self.arm,
            end: End::Generation(generation),
        };
        std::thread::Builder::new()
            .name(format!("sim-galvo-{:?}", self.arm).to_lowercase())
            .spawn(move || firmware.run(master))?;
        Ok(Box::new(Box::new(slave)))
    }

    fn describe(&self) -> String {
        format!(
            "simulated {} controller ({})",
            format!("{:?}", self.arm).to_lowercase(),
            self.last_path
        )
    }
}

/// A simulated controller on a pseudo-terminal that any process can open by path, as
/// it would open `/dev/ttyUSB0`: the firmware keeps running while hosts connect and
/// go (or die), so a test can kill a `periscope` process and watch the controller's
/// watchdog switch the laser off. Dropping it stops the firmware.
pub struct ServedPort {
    path: String,
    stop: std::sync::Arc<AtomicBool>,
    /// Held open so the master side never sees a hang-up between hosts.
    _slave: TTYPort,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl ServedPort {
    pub(crate) fn new(rig: &Rig, arm: Arm) -> io::Result<ServedPort> {
        let (master, slave) = TTYPort::pair().map_err(io::Error::from)?;
        let path = slave
            .name()
            .ok_or_else(|| io::Error::other("the pseudo-terminal has no path"))?;
        let stop = std::sync::Arc::new(AtomicBool::new(false));
        let firmware = Firmware {
            shared: std::sync::Arc::downgrade(&rig.shared),
            arm,
            end: End::Stop(stop.clone()),
        };
        let thread = std::thread::Builder::new()
            .name(format!("sim-galvo-{arm:?}-served").to_lowercase())
            .spawn(move || firmware.run(master))?;
        Ok(ServedPort {
            path,
            stop,
            _slave: slave,
            thread: Some(thread),
        })
    }

    /// The port's path (`/dev/pts/N`).
    pub fn path(&self) -> &str {
        &self.path
    }
}

impl Drop for ServedPort {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// When a firmware thread ends.
enum End {
    /// When its connection is replaced by a newer one (a reconnect), or the host hangs up.
    Generation(u64),
    /// When told to (a served port); it outlives its hosts.
    Stop(std::sync::Arc<AtomicBool>),
}

/// The longest the firmware sleeps in a read, so it notices the end conditions.
const POLL: Duration = Duration::from_millis(10);

struct Firmware {
    shared: Weak<Shared>,
    arm: Arm,
    end: End,
}

impl Firmware {
    fn ended(&self, rig: &Shared) -> bool {
        match &self.end {
            End::Generation(g) => rig.lock().arms[self.arm.index()].generation != *g,
            End::Stop(stop) => stop.load(Ordering::SeqCst),
        }
    }

    /// The firmware loop: reads lines and answers them. A move's reply waits until the
    /// pair has settled, but the loop goes on reading meanwhile, so an out-of-band
    /// `LASER OFF` is acted on at once whatever is outstanding.
    fn run(self, port: TTYPort) {
        self.quiet(Instant::now());
        self.serve(port);
        if self.arm == Arm::Laser
            && let Some(rig) = self.shared.upgrade()
        {
            rig.lock().line_quiet(None);
        }
    }

    /// The laser arm's firmware has looked at its line at `now` and found no complete
    /// line waiting (the watchdog's view of time, [`super::rig::Watchdog`]).
    fn quiet(&self, now: Instant) {
        if self.arm == Arm::Laser
            && let Some(rig) = self.shared.upgrade()
        {
            rig.lock().line_quiet(Some(now));
        }
    }

    fn serve(&self, mut port: TTYPort) {
        let mut rx: Vec<u8> = Vec::with_capacity(protocol::MAX_LINE);
        let mut chunk = [0u8; 256];
        // Replies waiting for their time (a settling move, an injected stall); a move's
        // carries its tag, so that a move a `PARK` overrode meanwhile is answered so.
        let mut due: Vec<(Instant, Vec<u8>, Option<u8>)> = Vec::new();
        loop {
            {
                let Some(rig) = self.shared.upgrade() else { return };
                if self.ended(&rig) {
                    return;
                }
            }
            let now = Instant::now();
            let (ready, later): (Vec<_>, Vec<_>) = due.drain(..).partition(|(t, _, _)| *t <= now);
            due = later;
            for (_, bytes, move_tag) in ready {
                let bytes = match move_tag {
                    Some(tag) if self.shared.upgrade().is_some_and(|rig| rig.parked(self.arm)) => {
                        protocol::encode_line(tag, &ErrorCode::Interrupted.reply()).into_bytes()
                    }
                    _ => bytes,
                };
                if port.write_all(&bytes).and_then(|()| port.flush()).is_err() {
                    return;
                }
            }
            let wait = due
                .iter()
                .map(|(t, _, _)| t.saturating_duration_since(now))
                .fold(POLL, Duration::min)
                .max(Duration::from_micros(20));
            let _ = port.set_timeout(wait);
            match port.read(&mut chunk) {
                Ok(0) => match self.end {
                    End::Generation(_) => return,
                    End::Stop(_) => {
                        self.quiet(Instant::now());
                        continue;
                    }
                },
                Ok(n) => rx.extend_from_slice(&chunk[..n]),
                Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock => {
                    self.quiet(Instant::now());
                    continue;
                }
                Err(_) => match self.end {
                    End::Generation(_) => return,
                    // No host on the other end just now: wait for the next one.
                    End::Stop(_) => {
                        self.quiet(Instant::now());
                        std::thread::sleep(POLL);
                        continue;
                    }
                },
            }
            // Bytes but no correctly framed line (a partial line, line noise): the
            // watchdog's line was quiet up to this read.
            let read_at = Instant::now();
            let mut framed = false;
            while let Some(end) = rx.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = rx.drain(..=end).collect();
                framed |= protocol::decode_line(&line[..line.len() - 1]).is_ok();
                let Some(rig) = self.shared.upgrade() else { return };
                let outcome = answer(&rig, self.arm, &line[..line.len() - 1]);
                drop(rig);
                match outcome {
                    Outcome::Reply(bytes, delay) if delay.is_zero() => {
                        if port.write_all(&bytes).and_then(|()| port.flush()).is_err() {
                            return;
                        }
                    }
                    Outcome::Reply(bytes, delay) => due.push((Instant::now() + delay, bytes, None)),
                    Outcome::Move { reply, settle, tag } => {
                        due.push((Instant::now() + settle, reply, Some(tag)))
                    }
                    Outcome::Starve(bytes, pause) => {
                        if port.write_all(&bytes).and_then(|()| port.flush()).is_err() {
                            return;
                        }
                        std::thread::sleep(pause);
                    }
                    Outcome::Silent => {}
                    Outcome::Unplug => match self.end {
                        End::Generation(_) => return,
                        End::Stop(_) => due.clear(),
                    },
                }
            }
            if !framed {
                self.quiet(read_at);
            }
            if rx.len() > protocol::MAX_LINE {
                rx.clear();
            }
        }
    }
}

enum Outcome {
    /// Send these bytes after this long.
    Reply(Vec<u8>, Duration),
    /// A `MOVE`'s `OK SETTLED`, sent once it has settled, unless an out-of-band `PARK`
    /// overrode it meanwhile: then `ERR 9` with its tag.
    Move {
        reply: Vec<u8>,
        settle: Duration,
        tag: u8,
    },
    /// Send these bytes now, then read nothing for this long.
    Starve(Vec<u8>, Duration),
    Silent,
    Unplug,
}

fn answer(rig: &Shared, arm: Arm, line: &[u8]) -> Outcome {
    let decoded = protocol::decode_line(line);
    // Injected faults are one-shot and meant for the host's ordinary requests; the
    // out-of-band keepalives a driver sends from its own thread do not consume them.
    let out_of_band = matches!(decoded, Ok((tag, _)) if tag == protocol::OUT_OF_BAND_TAG);
    let fault = if out_of_band {
        None
    } else {
        rig.lock().arms[arm.index()].faults.pop_front()
    };
    let (tag, body, mut delay, moving) = match decoded {
        Ok((tag, body)) => {
            if arm == Arm::Laser {
                // Every correctly framed line feeds the laser watchdog.
                rig.lock().heard_host(Instant::now());
            }
            let (reply, settle) = handle(rig, arm, body);
            let moving = reply.starts_with("OK ") && matches!(Request::parse(body), Ok(Request::Move(_)));
            (tag, reply, settle, moving)
        }
        Err(LineError::Checksum(Some(tag))) => (tag, ErrorCode::BadChecksum.reply(), Duration::ZERO, false),
        Err(_) => {
            debug!(?arm, "firmware ignoring garbage");
            return Outcome::Silent;
        }
    };
    let mut reply = protocol::encode_line(tag, &body).into_bytes();
    // A move's answer is decided when it is sent, unless a fault garbles or drops it.
    let deferred = moving && matches!(fault, None | Some(GalvoFault::Stall(_)));
    match fault {
        None => {}
        Some(GalvoFault::DropReply) => return Outcome::Silent,
        Some(GalvoFault::CorruptChecksum) => {
            // Flip a bit in the body, past the tag, so the CRC no longer matches.
            let i = 3.min(reply.len() - 2);
            reply[i] ^= 0x02;
        }
        Some(GalvoFault::Stall(d)) => delay += d,
        Some(GalvoFault::Starve(pause)) => return Outcome::Starve(reply, pause),
        Some(GalvoFault::Garbage) => {
            let mut noisy = b"\x00\xff~~ line noise 17*ZZ\n".to_vec();
            noisy.extend_from_slice(&reply);
            reply = noisy;
        }
        Some(GalvoFault::Disconnect { refused_connects }) => {
            let mut s = rig.lock();
            s.arms[arm.index()].refused_connects = refused_connects;
            // A controller that loses power forgets its laser state (fail-safe off)
            // and comes back with its power-up watchdog: the 500 ms timeout, and no
            // trips (`WDOG` counts them since power-up).
            if arm == Arm::Laser {
                s.set_emission(false, EmissionCause::PowerLoss, Instant::now());
                s.watchdog.timeout = Duration::from_millis(u64::from(protocol::WATCHDOG_DEFAULT_MS));
                s.watchdog.trips = 0;
            }
            return Outcome::Unplug;
        }
    }
    if deferred {
        return Outcome::Move {
            reply,
            settle: delay,
            tag,
        };
    }
    Outcome::Reply(reply, delay)
}

/// The reply to a request, and how long to wait before sending it.
fn handle(rig: &Shared, arm: Arm, body: &str) -> (String, Duration) {
    let req = match Request::parse(body) {
        Ok(r) => r,
        Err(code) => return (code.reply(), Duration::ZERO),
    };
    if let Request::Move(target) = req {
        return match rig.start_move(arm, target) {
            Ok(settle) => (
                format!(
                    "OK {} {}",
                    MotionState::Settled.word(),
                    protocol::fmt_angles(target)
                ),
                settle,
            ),
            Err(code) => (code.reply(), Duration::ZERO),
        };
    }
    (handle_immediate(rig, arm, req), Duration::ZERO)
}

fn handle_immediate(rig: &Shared, arm: Arm, req: Request) -> String {
    let settings = &rig.settings;
    let is_laser = arm == Arm::Laser;
    match req {
        Request::Identify => format!(
            "OK PGC-2 {FIRMWARE} {} SIM-{}-0001 {}",
            protocol::PROTOCOL_VERSION,
            if is_laser { "L" } else { "S" },
            if is_laser { "LASER" } else { "NOLASER" }
        ),
        Request::Limits => format!("OK {}", protocol::fmt_limits(settings.limits[arm.index()])),
        Request::Move(_) => unreachable!("moves are answered by `handle`"),
        Request::Position => format!("OK {}", protocol::fmt_angles(rig.motion(arm).1)),
        Request::Status => {
            let (state, target, _) = rig.motion(arm);
            format!("OK {} {}", state.word(), protocol::fmt_angles(target))
        }
        Request::Park => {
            rig.park(arm);
            "OK".into()
        }
        Request::KeepAlive => "OK".into(),
        Request::Laser(_)
        | Request::LaserStatus
        | Request::Interlock
        | Request::Diffuser(_)
        | Request::Watchdog(_)
            if !is_laser =>
        {
            ErrorCode::NoLaser.reply()
        }
        Request::Laser(on) => match rig.switch_laser(on) {
            Ok(()) => "OK".into(),
            Err(code) => code.reply(),
        },
        Request::Watchdog(set) => {
            let (timeout, trips) = rig.laser_watchdog(set.map(|ms| Duration::from_millis(u64::from(ms))));
            format!("OK {} {trips}", timeout.as_millis())
        }
        Request::LaserStatus => {
            let (emission, closed, diffuser_in) = rig.laser_state();
            format!(
                "OK {} {} {}",
                if emission { "ON" } else { "OFF" },
                if closed { "CLOSED" } else { "OPEN" },
                if diffuser_in { "IN" } else { "OUT" }
            )
        }
        Request::Interlock => format!("OK {}", if rig.laser_state().1 { "CLOSED" } else { "OPEN" }),
        Request::Diffuser(inserted) => {
            rig.set_diffuser(inserted);
            "OK".into()
        }
    }
}

//! Galvo controller firmware on a pseudo-terminal: reads tagged lines, answers them
//! as `docs/protocols/galvo-serial.md` specifies, and models settling and limits.
use std::io::{self, Read, Write};
use std::sync::Weak;
use std::time::{Duration, Instant};

use periscope_drivers::galvo::protocol::{self, ErrorCode, LineError, MotionState, Request};
use periscope_drivers::galvo::{Connector, Link};
use serialport::{SerialPort, TTYPort};
use tracing::debug;

use super::rig::{Arm, GalvoFault, Rig, Shared};

/// Firmware version the simulated controllers report.
const FIRMWARE: &str = "1.0.0-sim";

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
        let (mut master, slave) = TTYPort::pair().map_err(io::Error::from)?;
        master
            .set_timeout(Duration::from_millis(50))
            .map_err(io::Error::from)?;
        self.last_path = slave.name().unwrap_or_else(|| "simulated pty".into());
        let shared = std::sync::Arc::downgrade(&self.rig.shared);
        let arm = self.arm;
        std::thread::Builder::new()
            .name(format!("sim-galvo-{arm:?}").to_lowercase())
            .spawn(move || run(master, shared, arm, generation))?;
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

/// The firmware loop: one line in, one line out, until the link is replaced, the rig
/// is dropped or the host side closes.
fn run(mut port: TTYPort, shared: Weak<Shared>, arm: Arm, generation: u64) {
    let mut rx: Vec<u8> = Vec::with_capacity(protocol::MAX_LINE);
    let mut chunk = [0u8; 256];
    loop {
        let Some(rig) = shared.upgrade() else { return };
        if rig.lock().arms[arm.index()].generation != generation {
            return;
        }
        drop(rig);
        match port.read(&mut chunk) {
            Ok(0) => return,
            Ok(n) => rx.extend_from_slice(&chunk[..n]),
            Err(e) if e.kind() == io::ErrorKind::TimedOut || e.kind() == io::ErrorKind::WouldBlock => {
                continue;
            }
            Err(_) => return,
        }
        while let Some(end) = rx.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = rx.drain(..=end).collect();
            let Some(rig) = shared.upgrade() else { return };
            let outcome = answer(&rig, arm, &line[..line.len() - 1]);
            drop(rig);
            match outcome {
                Outcome::Reply(bytes) => {
                    if port.write_all(&bytes).and_then(|()| port.flush()).is_err() {
                        return;
                    }
                }
                Outcome::Silent => {}
                Outcome::Unplug => return,
            }
        }
        if rx.len() > protocol::MAX_LINE {
            rx.clear();
        }
    }
}

enum Outcome {
    Reply(Vec<u8>),
    Silent,
    Unplug,
}

fn answer(rig: &Shared, arm: Arm, line: &[u8]) -> Outcome {
    let fault = rig.lock().arms[arm.index()].faults.pop_front();
    let (tag, body) = match protocol::decode_line(line) {
        Ok((tag, body)) => {
            let (reply, settle) = handle(rig, arm, body);
            // A move is answered once the pair has settled.
            if !settle.is_zero() {
                std::thread::sleep(settle);
            }
            (tag, reply)
        }
        Err(LineError::Checksum(Some(tag))) => (tag, ErrorCode::BadChecksum.reply()),
        Err(_) => {
            debug!(?arm, "firmware ignoring garbage");
            return Outcome::Silent;
        }
    };
    let mut reply = protocol::encode_line(tag, &body).into_bytes();
    match fault {
        None => {}
        Some(GalvoFault::DropReply) => return Outcome::Silent,
        Some(GalvoFault::CorruptChecksum) => {
            // Flip a bit in the body, past the tag, so the CRC no longer matches.
            let i = 3.min(reply.len() - 2);
            reply[i] ^= 0x02;
        }
        Some(GalvoFault::Stall(d)) => std::thread::sleep(d),
        Some(GalvoFault::Garbage) => {
            let mut noisy = b"\x00\xff~~ line noise 17*ZZ\n".to_vec();
            noisy.extend_from_slice(&reply);
            reply = noisy;
        }
        Some(GalvoFault::Disconnect { refused_connects }) => {
            let mut s = rig.lock();
            s.arms[arm.index()].refused_connects = refused_connects;
            // A controller that loses power forgets its laser state (fail-safe off).
            if arm == Arm::Laser {
                s.emission = false;
            }
            return Outcome::Unplug;
        }
    }
    Outcome::Reply(reply)
}

/// The reply to a request, and how long to wait before sending it.
fn handle(rig: &Shared, arm: Arm, body: &str) -> (String, Duration) {
    let req = match Request::parse(body) {
        Ok(r) => r,
        Err(code) => return (code.reply(), Duration::ZERO),
    };
    if let Request::Move(target) = req {
        if !rig.settings.limits[arm.index()].contains(target) {
            return (ErrorCode::OutOfRange.reply(), Duration::ZERO);
        }
        let settle = rig.scaled(rig.settings.settle[arm.index()]);
        let mut s = rig.lock();
        let a = &mut s.arms[arm.index()];
        a.target = target;
        a.parked = false;
        a.settled_at = Instant::now() + settle;
        let reply = format!(
            "OK {} {}",
            MotionState::Settled.word(),
            protocol::fmt_angles(target)
        );
        return (reply, settle);
    }
    (handle_immediate(rig, arm, req), Duration::ZERO)
}

fn handle_immediate(rig: &Shared, arm: Arm, req: Request) -> String {
    let settings = &rig.settings;
    let mut s = rig.lock();
    let now = Instant::now();
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
        Request::Position => format!("OK {}", protocol::fmt_angles(s.arms[arm.index()].target)),
        Request::Status => {
            let a = &s.arms[arm.index()];
            let state = if now < a.settled_at {
                MotionState::Moving
            } else if a.parked {
                MotionState::Parked
            } else {
                MotionState::Settled
            };
            format!("OK {} {}", state.word(), protocol::fmt_angles(a.target))
        }
        Request::Park => {
            let settle = rig.scaled(settings.settle[arm.index()]);
            let a = &mut s.arms[arm.index()];
            a.target = periscope_drivers::OpticalAngles { x: 0.0, y: 0.0 };
            a.parked = true;
            a.settled_at = now + settle;
            "OK".into()
        }
        Request::Laser(_) | Request::LaserStatus | Request::Interlock | Request::Diffuser(_) if !is_laser => {
            ErrorCode::NoLaser.reply()
        }
        Request::Laser(on) => {
            if on && !s.interlock_closed {
                return ErrorCode::InterlockOpen.reply();
            }
            s.emission = on;
            "OK".into()
        }
        Request::LaserStatus => format!(
            "OK {} {} {}",
            if s.emission { "ON" } else { "OFF" },
            if s.interlock_closed { "CLOSED" } else { "OPEN" },
            if s.diffuser_in { "IN" } else { "OUT" }
        ),
        Request::Interlock => format!("OK {}", if s.interlock_closed { "CLOSED" } else { "OPEN" }),
        Request::Diffuser(inserted) => {
            s.diffuser_in = inserted;
            "OK".into()
        }
    }
}

//! The serial galvo driver: one request, one reply, checked and retried.
//!
//! Every exchange discards stale input, sends a tagged, checksummed line and reads
//! lines until the reply with its tag arrives. Lines with a bad checksum or another
//! tag (noise, a late reply to an earlier request) are dropped, which is how the
//! driver re-synchronises after garbage. All commands set absolute states (a target
//! angle, emission on or off), so repeating one is harmless: a timed-out or corrupted
//! exchange is retried once, and a broken link is reopened once before the retry.
//! A second failure is reported with its kind.
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use tracing::{debug, instrument, warn};

use super::error::GalvoError;
use super::link::{Connector, Link};
use super::protocol::{self, LineError, MotionState, Reply, Request};
use crate::error::{DeviceError, Error, ErrorKind, ErrorType};
use crate::geometry::{AngleLimits, OpticalAngles};
use crate::laser_guard::{EmergencyOff, GuardedLaser, LaserGuard, LaserLine, Progress};
use crate::park::{EmergencyPark, ParkLine, Parked};
use crate::traits::{DeviceInfo, GalvoPair, GalvoStatus, Laser, LaserState};

/// How far the settled position may be from the target before the driver refuses it,
/// radians (10 µrad: 20 µm at 2 m, a tenth of a typical spot).
pub const POSITION_TOLERANCE: f64 = 1e-5;

/// Driver settings.
#[derive(Clone, Debug)]
pub struct SerialGalvoSettings {
    /// The arm's name for messages (`laser`, `spad`).
    pub name: String,
    /// Limits from the instrument config, enforced before anything is sent.
    pub limits: AngleLimits,
    /// How long to wait for a reply.
    pub timeout: Duration,
    /// Nominal settling time after a move (the controller also reports its own).
    pub settle: Duration,
    /// The laser watchdog timeout to set on the controller before every `LASER ON`
    /// (laser arm; `None` leaves the controller's own, 500 ms from power-up). While
    /// emission is wanted the driver feeds the watchdog from its own thread.
    pub watchdog: Option<Duration>,
}

/// The write side shared by the driver and its out-of-band senders: the link's second
/// handle, replaced on every reconnect. Holding the lock is holding the right to
/// write a line, so lines from different threads never interleave.
type OobWriter = Arc<Mutex<Option<Box<dyn Write + Send>>>>;

fn lock_writer(w: &Mutex<Option<Box<dyn Write + Send>>>) -> MutexGuard<'_, Option<Box<dyn Write + Send>>> {
    w.lock().unwrap_or_else(|p| p.into_inner())
}

/// Writes one out-of-band line (tag `00`, reply not awaited).
fn write_out_of_band(w: &Mutex<Option<Box<dyn Write + Send>>>, req: Request) -> std::io::Result<()> {
    let line = protocol::encode_line(protocol::OUT_OF_BAND_TAG, &req.body());
    let mut guard = lock_writer(w);
    let writer = guard.as_mut().ok_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::NotConnected,
            "the controller is not connected",
        )
    })?;
    // Written, not drained: the kernel sends what is queued at the line's rate, and
    // a drain (`tcdrain`, which has no timeout) would hold this lock, and with it the
    // e-stop's off and park, behind a controller that stopped reading its input.
    writer.write_all(line.as_bytes())
}

/// The serial controller's out-of-band path for the [`LaserGuard`]: `KEEP` and
/// `LASER OFF` lines with tag `00` through the link, which the controller acts on at
/// once even while a move is outstanding, without waiting for anything else the driver
/// is doing. It holds the writer weakly: once the driver is closed it reaches nothing,
/// and the controller's watchdog ends emission.
struct SerialLine {
    writer: Weak<Mutex<Option<Box<dyn Write + Send>>>>,
    name: String,
    port: String,
}

impl SerialLine {
    fn write_off(writer: &mut Option<Box<dyn Write + Send>>, line: &str) -> bool {
        writer
            .as_mut()
            .is_some_and(|w| w.write_all(line.as_bytes()).is_ok())
    }
}

impl LaserLine for SerialLine {
    fn feed(&self) -> std::io::Result<()> {
        let writer = self
            .writer
            .upgrade()
            .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::NotConnected, "the driver is closed"))?;
        write_out_of_band(&writer, Request::KeepAlive)
    }

    fn describe(&self) -> String {
        format!("laser on `{}` ({})", self.name, self.port)
    }

    fn try_off(&self) -> bool {
        let Some(writer) = self.writer.upgrade() else {
            return false;
        };
        let line = protocol::encode_line(protocol::OUT_OF_BAND_TAG, &Request::Laser(false).body());
        for _ in 0..50 {
            match writer.try_lock() {
                Ok(mut guard) => return SerialLine::write_off(&mut guard, &line),
                Err(std::sync::TryLockError::Poisoned(p)) => {
                    return SerialLine::write_off(&mut p.into_inner(), &line);
                }
                Err(std::sync::TryLockError::WouldBlock) => std::thread::sleep(Duration::from_micros(100)),
            }
        }
        false
    }

    fn off(&self) -> Result<(), DeviceError> {
        let err = |kind, message: String| GalvoError::new(&self.name, &self.port, kind, message);
        let writer = self.writer.upgrade().ok_or_else(|| {
            err(
                ErrorKind::Disconnected,
                "the driver is closed; the controller's watchdog switches emission off".into(),
            )
        })?;
        write_out_of_band(&writer, Request::Laser(false)).map_err(|e| {
            err(
                ErrorKind::Disconnected,
                "could not write the emergency LASER OFF; the controller's watchdog switches emission off within its timeout".into(),
            )
            .with_source(e)
            .into()
        })
    }
}

/// A galvo pair (and, on the laser arm, the laser) behind a serial controller.
pub struct SerialGalvo {
    settings: SerialGalvoSettings,
    connector: Box<dyn Connector>,
    port: String,
    link: Option<Box<dyn Link>>,
    tag: u8,
    rx: Vec<u8>,
    /// Target of the last park, for the settled check of a STAT poll.
    target: Option<OpticalAngles>,
    /// A `MOVE` sent whose reply (sent by the controller once settled) is not yet read:
    /// its tag and target.
    pending: Option<(u8, OpticalAngles)>,
    /// The link's out-of-band writer (shared with the guard's keepalive and off
    /// switches).
    oob: OobWriter,
    /// The laser's host-side safety (laser arm): watchdog, keepalive, latch.
    guard: LaserGuard,
    /// Set (under the writer's lock) once an [`EmergencyPark`] has parked the pair:
    /// no `MOVE` is sent from then on.
    park_latch: Arc<AtomicBool>,
}

impl ErrorType for SerialGalvo {
    type Error = GalvoError;
}

impl SerialGalvo {
    /// A driver that connects on first use.
    pub fn new(settings: SerialGalvoSettings, connector: Box<dyn Connector>) -> SerialGalvo {
        let port = connector.describe();
        let oob: OobWriter = Arc::new(Mutex::new(None));
        let guard = LaserGuard::new(
            &settings.name,
            settings.watchdog,
            Duration::from_millis(u64::from(protocol::WATCHDOG_DEFAULT_MS)),
            SerialLine {
                writer: Arc::downgrade(&oob),
                name: settings.name.clone(),
                port: port.clone(),
            },
        );
        SerialGalvo {
            settings,
            connector,
            port,
            link: None,
            tag: 0,
            rx: Vec::with_capacity(protocol::MAX_LINE),
            target: None,
            pending: None,
            oob,
            guard,
            park_latch: Arc::new(AtomicBool::new(false)),
        }
    }

    /// The watchdog timeout and the trips since power-up, as the controller reports
    /// them (laser arm).
    pub fn watchdog(&mut self) -> Result<(Duration, u32), GalvoError> {
        let req = Request::Watchdog(None);
        let fields = self.request(req)?;
        self.parse_watchdog(req, &fields)
    }

    fn parse_watchdog(&self, req: Request, fields: &[String]) -> Result<(Duration, u32), GalvoError> {
        match fields {
            [ms, trips] => match (ms.parse::<u64>(), trips.parse::<u32>()) {
                (Ok(ms), Ok(trips)) => Ok((Duration::from_millis(ms), trips)),
                _ => Err(self.malformed(req, fields)),
            },
            _ => Err(self.malformed(req, fields)),
        }
    }

    /// Connects now (and identifies the controller), instead of on first use.
    pub fn open(
        settings: SerialGalvoSettings,
        connector: Box<dyn Connector>,
    ) -> Result<SerialGalvo, GalvoError> {
        let mut galvo = SerialGalvo::new(settings, connector);
        galvo.identify()?;
        Ok(galvo)
    }

    /// The arm's name.
    pub fn name(&self) -> &str {
        &self.settings.name
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> GalvoError {
        GalvoError::new(&self.settings.name, &self.port, kind, message)
    }

    /// One request, its reply fields; retried once where that is safe (always: every
    /// command is idempotent).
    fn request(&mut self, req: Request) -> Result<Vec<String>, GalvoError> {
        if self.pending.is_some() {
            if self.park_latch.load(Ordering::SeqCst) {
                // An emergency park overrode the move: its reply, whenever it comes,
                // is dropped as stale, and nothing waits for it.
                self.pending = None;
            } else {
                self.finish_move(self.settings.settle * 4)?;
            }
        }
        match self.exchange(req) {
            Ok(fields) => Ok(fields),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Disconnected
                ) =>
            {
                warn!(arm = %self.settings.name, error = %e, "retrying galvo exchange once");
                self.exchange(req)
            }
            Err(e) => Err(e),
        }
    }

    fn connect(&mut self) -> Result<(), GalvoError> {
        if self.link.is_none() {
            let link = self.connector.connect().map_err(|e| {
                let why = if e.kind() == std::io::ErrorKind::ResourceBusy {
                    "cannot open the port: another program or process holds it (a port is opened by one at a time): \
                     close it, or stop the other Periscope process (`periscope serve`, `run` or `calibrate`)"
                } else {
                    "cannot open the port: check that the controller is plugged in and powered, and the port path in the instrument config"
                };
                self.err(ErrorKind::Disconnected, why).with_source(e)
            })?;
            debug!(arm = %self.settings.name, port = %self.port, "connected");
            *lock_writer(&self.oob) = link.out_of_band_writer().ok();
            self.link = Some(link);
            self.rx.clear();
        }
        Ok(())
    }

    fn parked_by_estop(&self) -> GalvoError {
        self.err(
            ErrorKind::Interrupted,
            "an emergency stop parked this pair, and it stays parked on this connection: open the devices again to move it",
        )
    }

    fn emergency_stopped(&self) -> GalvoError {
        self.err(
            ErrorKind::Interrupted,
            "emission was switched off by an emergency stop and stays off on this connection: open the devices again to switch it on",
        )
    }

    fn broken(&mut self, e: std::io::Error) -> GalvoError {
        self.link = None;
        *lock_writer(&self.oob) = None;
        self.err(
            ErrorKind::Disconnected,
            "the link broke (unplugged or powered off?); the driver reconnects on the next command",
        )
        .with_source(e)
    }

    #[instrument(level = "trace", skip(self), fields(arm = %self.settings.name))]
    fn exchange(&mut self, req: Request) -> Result<Vec<String>, GalvoError> {
        let tag = self.send(req)?;
        self.receive(req, tag, self.settings.timeout)
    }

    /// Sends `req` with a fresh tag after dropping stale input; returns the tag.
    fn send(&mut self, req: Request) -> Result<u8, GalvoError> {
        self.connect()?;
        // Tag 00 is reserved for out-of-band lines.
        self.tag = self.tag.wrapping_add(1).max(1);
        let tag = self.tag;
        let line = protocol::encode_line(tag, &req.body());
        let link = self.link.as_mut().expect("connected above");
        let sent = {
            let _writing = lock_writer(&self.oob);
            // Checked holding the write lock: an emergency off either latched before
            // this (refused here) or writes its LASER OFF after this line; an
            // emergency park likewise with its PARK and a move.
            if req == Request::Laser(true) && self.guard.latched() {
                None
            } else if matches!(req, Request::Move(_)) && self.park_latch.load(Ordering::SeqCst) {
                return Err(self.parked_by_estop());
            } else {
                Some(link.discard_input().and_then(|()| link.send(line.as_bytes())))
            }
        };
        match sent {
            None => return Err(self.emergency_stopped()),
            Some(Err(e)) => return Err(self.broken(e)),
            Some(Ok(())) => {}
        }
        self.rx.clear();
        Ok(tag)
    }

    /// Reads lines until the reply tagged `tag` arrives, within `timeout`.
    fn receive(&mut self, req: Request, tag: u8, timeout: Duration) -> Result<Vec<String>, GalvoError> {
        self.connect()?;
        let deadline = Instant::now() + timeout;
        let mut corrupted = false;
        let mut chunk = [0u8; 128];
        loop {
            // Complete lines first.
            while let Some(end) = self.rx.iter().position(|&b| b == b'\n') {
                let raw: Vec<u8> = self.rx.drain(..=end).collect();
                match protocol::decode_line(&raw[..raw.len() - 1]) {
                    Ok((t, body)) if t == tag => return self.interpret(req, body),
                    Ok((t, _)) => debug!(tag = t, expected = tag, "dropping a stale reply"),
                    // Our reply, corrupted: no point waiting out the timeout.
                    Err(LineError::Checksum(Some(t))) if t == tag => return Err(self.corrupted(req)),
                    Err(LineError::Checksum(_)) => corrupted = true,
                    Err(LineError::Malformed) => {
                        debug!(line = ?String::from_utf8_lossy(&raw), "dropping garbage")
                    }
                }
            }
            if self.rx.len() > protocol::MAX_LINE {
                self.rx.clear();
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(if corrupted {
                    self.corrupted(req)
                } else {
                    self.err(
                        ErrorKind::Timeout,
                        format!(
                            "no reply to `{}` within {} ms: check the cable, the baud rate and that the controller is powered",
                            req.body(),
                            timeout.as_millis()
                        ),
                    )
                });
            }
            let link = self.link.as_mut().expect("connected above");
            match link.receive(&mut chunk, deadline - now) {
                Ok(n) => self.rx.extend_from_slice(&chunk[..n]),
                Err(e) => return Err(self.broken(e)),
            }
        }
    }

    /// Collects the reply to an outstanding `MOVE` (sent by `move_to`), retrying the
    /// move once on a timeout, a corrupted reply or a broken link, and checks that the
    /// pair settled where it was sent.
    fn finish_move(&mut self, timeout: Duration) -> Result<OpticalAngles, GalvoError> {
        let Some((tag, target)) = self.pending.take() else {
            return Err(self.err(ErrorKind::Device, "no move is outstanding"));
        };
        if self.park_latch.load(Ordering::SeqCst) {
            return Err(self.parked_by_estop());
        }
        let req = Request::Move(target);
        let wait = timeout + self.settings.timeout;
        let fields = match self.receive(req, tag, wait) {
            Ok(f) => f,
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::Timeout | ErrorKind::Protocol | ErrorKind::Disconnected
                ) =>
            {
                warn!(arm = %self.settings.name, error = %e, "repeating the move once");
                let tag = self.send(req)?;
                self.receive(req, tag, wait)?
            }
            Err(e) => return Err(e),
        };
        // An emergency park that came while the move settled overrode it, whatever
        // its answer says.
        if self.park_latch.load(Ordering::SeqCst) {
            return Err(self.parked_by_estop());
        }
        let status = self.parse_status(req, &fields)?;
        self.check_settled(status, target)
    }

    fn parse_status(&self, req: Request, fields: &[String]) -> Result<GalvoStatus, GalvoError> {
        let refs: Vec<&str> = fields.iter().map(String::as_str).collect();
        match refs.as_slice() {
            [state, rest @ ..] => match (MotionState::from_word(state), protocol::parse_angles(rest)) {
                (Some(state), Some(position)) => Ok(GalvoStatus { state, position }),
                _ => Err(self.malformed(req, fields)),
            },
            _ => Err(self.malformed(req, fields)),
        }
    }

    /// Accepts a settled status only at the target.
    fn check_settled(&self, status: GalvoStatus, target: OpticalAngles) -> Result<OpticalAngles, GalvoError> {
        match status.state {
            MotionState::Fault => Err(self.err(
                ErrorKind::Device,
                "servo fault while settling: power-cycle the controller",
            )),
            MotionState::Moving => Err(self.err(
                ErrorKind::Device,
                "the controller reported a move done while still moving",
            )),
            MotionState::Settled | MotionState::Parked => {
                let off = (status.position.x - target.x)
                    .abs()
                    .max((status.position.y - target.y).abs());
                if !(off <= POSITION_TOLERANCE) {
                    return Err(self.err(
                        ErrorKind::Device,
                        format!(
                            "settled at ({:.7}, {:.7}) rad instead of the target ({:.7}, {:.7}): the position was not accepted; check the servo tuning",
                            status.position.x, status.position.y, target.x, target.y
                        ),
                    ));
                }
                Ok(status.position)
            }
        }
    }

    fn corrupted(&self, req: Request) -> GalvoError {
        self.err(
            ErrorKind::Protocol,
            format!(
                "the reply to `{}` failed its checksum: check the cable and its shielding",
                req.body()
            ),
        )
    }

    fn interpret(&self, req: Request, body: &str) -> Result<Vec<String>, GalvoError> {
        match Reply::parse(body) {
            Some(Reply::Ok(fields)) => Ok(fields.into_iter().map(str::to_owned).collect()),
            Some(Reply::Err(code, text)) => {
                let (kind, hint) = protocol::refusal(code);
                Err(self.err(kind, format!("`{}` refused (ERR {text}): {hint}", req.body())))
            }
            None => Err(self.err(
                ErrorKind::Protocol,
                format!("malformed reply `{body}` to `{}`", req.body()),
            )),
        }
    }

    fn malformed(&self, req: Request, fields: &[String]) -> GalvoError {
        self.err(
            ErrorKind::Protocol,
            format!("unexpected reply fields {fields:?} to `{}`", req.body()),
        )
    }

    /// The controller's hard limits.
    pub fn hard_limits(&mut self) -> Result<AngleLimits, GalvoError> {
        let fields = self.request(Request::Limits)?;
        let refs: Vec<&str> = fields.iter().map(String::as_str).collect();
        protocol::parse_limits(&refs).ok_or_else(|| self.malformed(Request::Limits, &fields))
    }

    fn on_off(
        &mut self,
        req: Request,
        i: usize,
        yes: &str,
        no: &str,
        fields: &[String],
    ) -> Result<bool, GalvoError> {
        match fields.get(i).map(String::as_str) {
            Some(w) if w == yes => Ok(true),
            Some(w) if w == no => Ok(false),
            _ => Err(self.malformed(req, fields)),
        }
    }
}

impl SerialGalvo {
    /// `LASER OFF` out of band, then waits (up to the reply timeout) for the
    /// controller's tag-00 answer before the link closes: a port closed at once may
    /// lose the line still in its buffer (a pseudo-terminal does).
    fn off_before_closing(&mut self) {
        let line = protocol::encode_line(protocol::OUT_OF_BAND_TAG, &Request::Laser(false).body());
        let Some(link) = self.link.as_mut() else { return };
        {
            let _writing = lock_writer(&self.oob);
            if link
                .discard_input()
                .and_then(|()| link.send(line.as_bytes()))
                .is_err()
            {
                return;
            }
        }
        let deadline = Instant::now() + self.settings.timeout;
        let mut rx = Vec::new();
        let mut chunk = [0u8; 128];
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            match link.receive(&mut chunk, left) {
                Ok(n) => rx.extend_from_slice(&chunk[..n.min(chunk.len())]),
                Err(_) => return,
            }
            // Keep the tail only: a controller that babbles cannot grow this.
            if rx.len() > 4096 {
                rx.drain(..rx.len() - 1024);
            }
            let answered = rx
                .split(|&b| b == b'\n')
                .any(|l| matches!(protocol::decode_line(l), Ok((t, _)) if t == protocol::OUT_OF_BAND_TAG));
            if answered {
                return;
            }
        }
        warn!(arm = %self.settings.name, "no answer to LASER OFF while closing; the controller's watchdog ends emission");
    }
}

impl Drop for SerialGalvo {
    /// A driver dropped while emission is wanted (a panic unwinding, a run abandoned)
    /// switches the laser off on its way out; its keepalive stops with it, so the
    /// controller's watchdog ends emission even if this line is lost.
    fn drop(&mut self) {
        if self.guard.release() {
            self.off_before_closing();
        }
    }
}

impl GalvoPair for SerialGalvo {
    fn identify(&mut self) -> Result<DeviceInfo, GalvoError> {
        let fields = self.request(Request::Identify)?;
        match fields.as_slice() {
            [model, firmware, protocol, serial, ..] => {
                let protocol: u32 = protocol
                    .parse()
                    .map_err(|_| self.malformed(Request::Identify, &fields))?;
                if protocol != protocol::PROTOCOL_VERSION {
                    return Err(self.err(
                        ErrorKind::Protocol,
                        format!(
                            "controller speaks protocol {protocol}, this driver speaks {}: update the firmware or Periscope",
                            protocol::PROTOCOL_VERSION
                        ),
                    ));
                }
                Ok(DeviceInfo {
                    model: model.clone(),
                    firmware: firmware.clone(),
                    serial: serial.clone(),
                    protocol,
                })
            }
            _ => Err(self.malformed(Request::Identify, &fields)),
        }
    }

    fn limits(&self) -> AngleLimits {
        self.settings.limits
    }

    fn hard_limits(&mut self) -> Result<Option<AngleLimits>, GalvoError> {
        SerialGalvo::hard_limits(self).map(Some)
    }

    fn move_to(&mut self, target: OpticalAngles) -> Result<(), GalvoError> {
        if !self.settings.limits.contains(target) {
            let l = self.settings.limits;
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!(
                    "target ({:.3}°, {:.3}°) is outside the limits x [{:.3}°, {:.3}°], y [{:.3}°, {:.3}°]; nothing was moved",
                    target.x.to_degrees(),
                    target.y.to_degrees(),
                    l.x[0].to_degrees(),
                    l.x[1].to_degrees(),
                    l.y[0].to_degrees(),
                    l.y[1].to_degrees()
                ),
            ));
        }
        if self.pending.is_some() {
            self.finish_move(self.settings.settle * 4)?;
        }
        let req = Request::Move(target);
        let tag = match self.send(req) {
            Ok(tag) => tag,
            Err(e) if e.kind() == ErrorKind::Disconnected => {
                warn!(arm = %self.settings.name, error = %e, "reconnecting to send the move again");
                self.send(req)?
            }
            Err(e) => return Err(e),
        };
        self.pending = Some((tag, target));
        // What `wait_settled` checks a polled position against when the move's reply
        // is no longer awaited (it held the last park's target, or none).
        self.target = Some(target);
        Ok(())
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<OpticalAngles, GalvoError> {
        if self.pending.is_some() {
            return self.finish_move(timeout);
        }
        // After a park (or with nothing commanded): poll.
        let start = Instant::now();
        loop {
            let status = self.status()?;
            if status.state != MotionState::Moving {
                return match self.target {
                    Some(target) => self.check_settled(status, target),
                    None => Ok(status.position),
                };
            }
            if start.elapsed() >= timeout {
                return Err(self.err(
                    ErrorKind::Timeout,
                    format!(
                        "still moving after {} ms: raise settle-us in the instrument config or check the mirrors",
                        timeout.as_millis()
                    ),
                ));
            }
            std::thread::sleep(
                (self.settings.settle / 10).clamp(Duration::from_micros(20), Duration::from_millis(5)),
            );
        }
    }

    fn position(&mut self) -> Result<OpticalAngles, GalvoError> {
        let fields = self.request(Request::Position)?;
        let refs: Vec<&str> = fields.iter().map(String::as_str).collect();
        protocol::parse_angles(&refs).ok_or_else(|| self.malformed(Request::Position, &fields))
    }

    fn status(&mut self) -> Result<GalvoStatus, GalvoError> {
        let fields = self.request(Request::Status)?;
        self.parse_status(Request::Status, &fields)
    }

    /// `PARK`, sent at once: a move still outstanding neither holds it up nor, if it
    /// failed, keeps it from being sent (as for `LASER OFF`); its reply is dropped as
    /// stale when it comes, and the controller, taking requests in order, parks after
    /// the move. Until 2026-12-07 the move was finished first (settle × 4 and a
    /// repeat), and a fault returned before the park was sent.
    fn park(&mut self) -> Result<(), GalvoError> {
        if self.pending.take().is_some() {
            debug!(arm = %self.settings.name, "parking without waiting for the outstanding move");
        }
        self.request(Request::Park)?;
        self.target = Some(OpticalAngles { x: 0.0, y: 0.0 });
        Ok(())
    }

    fn emergency_park(&self) -> EmergencyPark {
        EmergencyPark::new(SerialPark {
            writer: Arc::downgrade(&self.oob),
            latch: self.park_latch.clone(),
            name: self.settings.name.clone(),
            port: self.port.clone(),
        })
    }
}

/// The serial controller's [`ParkLine`]: `PARK` out of band (tag `00`), which the
/// controller acts on at once, even with a `MOVE` settling, through the link's write
/// side and without the driver. The latch is set holding the writer's lock, so no
/// `MOVE` of the driver's follows the `PARK`.
struct SerialPark {
    writer: Weak<Mutex<Option<Box<dyn Write + Send>>>>,
    latch: Arc<AtomicBool>,
    name: String,
    port: String,
}

impl ParkLine for SerialPark {
    fn park(&self) -> Result<Parked, DeviceError> {
        let err = |message: &str| GalvoError::new(&self.name, &self.port, ErrorKind::Disconnected, message);
        let writer = self
            .writer
            .upgrade()
            .ok_or_else(|| err("the driver is closed; open the controller again to park it"))?;
        let line = protocol::encode_line(protocol::OUT_OF_BAND_TAG, &Request::Park.body());
        let mut guard = lock_writer(&writer);
        self.latch.store(true, Ordering::SeqCst);
        let w = guard
            .as_mut()
            .ok_or_else(|| err("the controller is not connected; open it again to park it"))?;
        w.write_all(line.as_bytes())
            .and_then(|()| w.flush())
            .map_err(|e| err("could not write the out-of-band PARK: the link broke").with_source(e))?;
        warn!(arm = %self.name, port = %self.port, "PARK sent by an emergency stop; the pair refuses moves from now on");
        // Its answer comes on the link's read side, which the driver's own thread holds.
        Ok(Parked::Sent)
    }

    fn describe(&self) -> String {
        format!("galvo pair `{}` ({})", self.name, self.port)
    }
}

impl Laser for SerialGalvo {
    /// On: sets the controller's watchdog (if configured), starts feeding it, then
    /// `LASER ON`. Off: stops feeding, sends `LASER OFF` out of band at once (nothing
    /// outstanding can hold it up), then again as an ordinary, confirmed request.
    /// After an emergency off through this driver's [`Laser::emergency_off`] handle,
    /// on is refused (kind `Interrupted`) for the driver's life, however the two race.
    fn set_emission(&mut self, on: bool) -> Result<(), GalvoError> {
        if on {
            return self.switch_on();
        }
        self.guard.switching_off();
        if let Err(e) = write_out_of_band(&self.oob, Request::Laser(false)) {
            debug!(error = %e, "no out-of-band LASER OFF; sending it in band");
        }
        // A move still outstanding neither holds up the confirmed LASER OFF nor, if
        // it failed, keeps it from being sent (until 2026-12-06 `request` finished the
        // move first: settle × 4 and a repeat, and a servo fault returned before the
        // laser went off). Its reply is dropped as stale when it comes; a later
        // `wait_settled` polls the status against its target.
        if self.pending.take().is_some() {
            debug!(arm = %self.settings.name, "switching the laser off without waiting for the outstanding move");
        }
        self.request(Request::Laser(false)).map(drop)
    }

    fn laser_state(&mut self) -> Result<LaserState, GalvoError> {
        let req = Request::LaserStatus;
        let fields = self.request(req)?;
        Ok(LaserState {
            emission: self.on_off(req, 0, "ON", "OFF", &fields)?,
            interlock_closed: self.on_off(req, 1, "CLOSED", "OPEN", &fields)?,
            diffuser_in: self.on_off(req, 2, "IN", "OUT", &fields)?,
        })
    }

    fn interlock_closed(&mut self) -> Result<bool, GalvoError> {
        let req = Request::Interlock;
        let fields = self.request(req)?;
        self.on_off(req, 0, "CLOSED", "OPEN", &fields)
    }

    fn set_diffuser(&mut self, inserted: bool) -> Result<(), GalvoError> {
        self.request(Request::Diffuser(inserted)).map(drop)
    }

    fn watch_progress(&mut self, progress: Progress) {
        self.guard.watch_progress(progress);
    }

    /// `LASER OFF` out of band through the link, whatever this driver is waiting for.
    fn emergency_off(&self) -> EmergencyOff {
        self.guard.emergency_off()
    }
}

impl GuardedLaser for SerialGalvo {
    type Error = GalvoError;

    fn guard(&mut self) -> &mut LaserGuard {
        &mut self.guard
    }

    /// `WDOG ms`, and a refusal unless the controller reports the same timeout back.
    fn arm_watchdog(&mut self, timeout: Duration) -> Result<(), GalvoError> {
        let ms = u32::try_from(timeout.as_millis()).unwrap_or(u32::MAX);
        let req = Request::Watchdog(Some(ms));
        let fields = self.request(req)?;
        let (set, _) = self.parse_watchdog(req, &fields)?;
        if set != timeout {
            return Err(self.err(
                ErrorKind::Device,
                format!(
                    "the controller set its laser watchdog to {} ms, not {ms} ms; emission was not switched on",
                    set.as_millis()
                ),
            ));
        }
        Ok(())
    }

    /// `LASER ON`, refused in `send` (holding the write lock) once an emergency off
    /// has latched, so the two are ordered on the wire.
    fn send_on(&mut self) -> Result<(), GalvoError> {
        self.request(Request::Laser(true)).map(drop)
    }

    fn latched_error(&self) -> GalvoError {
        self.emergency_stopped()
    }
}

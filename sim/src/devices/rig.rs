//! The shared state of the simulated instrument: mirror positions, laser and
//! interlock, pending faults, and the physics that turns a pointing into counts.
use std::collections::VecDeque;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use glam::DVec3;
use periscope_drivers::galvo::protocol::{self, ErrorCode, MotionState};
use periscope_drivers::{AngleLimits, GalvoPose, OpticalAngles};

use crate::detector::Detector;
use crate::transport::{Instrument, World};

/// Which galvo controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Arm {
    /// The laser arm (its controller also switches the laser and the diffuser).
    Laser,
    /// The SPAD arm.
    Spad,
}

impl Arm {
    pub(crate) fn index(self) -> usize {
        match self {
            Arm::Laser => 0,
            Arm::Spad => 1,
        }
    }

    /// `laser` or `spad`.
    pub fn name(self) -> &'static str {
        match self {
            Arm::Laser => "laser",
            Arm::Spad => "spad",
        }
    }
}

/// A one-shot galvo controller fault, applied to the next request it receives.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum GalvoFault {
    /// Read the request, never answer.
    DropReply,
    /// Answer with one character flipped (so the checksum fails).
    CorruptChecksum,
    /// Answer after this long.
    Stall(Duration),
    /// Send a line of noise before the answer.
    Garbage,
    /// Answer, then read nothing for this long: the firmware thread starved by a
    /// loaded host, while a real controller's UART would go on taking bytes. The
    /// host's keepalives wait in the line, and the watchdog must not count them late.
    Starve(Duration),
    /// Drop the link without answering (an unplug); refuse this many reconnects.
    Disconnect {
        /// Connection attempts refused before the device is back.
        refused_connects: u32,
    },
}

/// A one-shot histogrammer fault, applied to the next acquisition.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TdcFault {
    /// Accept `START`, never send the frame.
    Stall,
    /// Send the frame with one bit flipped.
    CorruptCrc,
    /// Deliver the frame in small pieces over several bulk transfers.
    ShortRead,
    /// Deliver only the first half of the frame; the rest is lost.
    Truncated,
    /// Set the overflow flag.
    Overflow,
    /// Send a frame with an old sequence number first.
    StaleFrame,
    /// Vanish from the bus (every transfer fails); refuse this many reopens.
    Disconnect {
        /// Reopen attempts refused before the device is back.
        refused_reopens: u32,
    },
}

/// A fault for one device.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Fault {
    /// For a galvo controller.
    Galvo(Arm, GalvoFault),
    /// For the histogrammer.
    Tdc(TdcFault),
}

/// What the simulated devices are built from.
#[derive(Clone, Debug)]
pub struct RigSettings {
    /// Laser arm pose (calibration model shared with the driver side).
    pub laser_pose: GalvoPose,
    /// SPAD arm pose.
    pub spad_pose: GalvoPose,
    /// Firmware hard limits, laser arm then SPAD arm.
    pub limits: [AngleLimits; 2],
    /// Settling time after a move, per arm.
    pub settle: [Duration; 2],
    /// Detector model; the TDC's bins, bin width and offset replace its own.
    pub detector: Detector,
    /// Real seconds per simulated second for settling and dwell (0 = instant).
    pub time_scale: f64,
    /// Seed of the Poisson draws.
    pub seed: u64,
    /// Whether the interlock starts closed.
    pub interlock_closed: bool,
    /// Poisson noise on the counts (the default); `false` reports the expected counts,
    /// rounded, so a test can tell a model error from photon noise.
    pub noise: bool,
}

#[derive(Debug)]
pub(crate) struct ArmState {
    pub target: OpticalAngles,
    pub settled_at: Instant,
    pub parked: bool,
    /// Bumped on every (re)connection; firmware threads of older generations exit.
    pub generation: u64,
    pub refused_connects: u32,
    pub faults: VecDeque<GalvoFault>,
}

/// Why the simulated laser's emission changed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EmissionCause {
    /// The host sent `LASER ON` or `LASER OFF` (an ordinary or an out-of-band request).
    Host,
    /// The watchdog expired: nothing heard from the host for its timeout.
    Watchdog,
    /// The interlock loop opened.
    Interlock,
    /// The controller lost power (an injected unplug).
    PowerLoss,
}

/// One change of the simulated laser's emission, with when it happened.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EmissionChange {
    /// When (for a watchdog trip: the moment the timeout ran out).
    pub at: Instant,
    /// Emission after the change.
    pub on: bool,
    /// Why.
    pub cause: EmissionCause,
}

/// The laser controller's watchdog, as its firmware keeps it.
#[derive(Debug)]
pub(crate) struct Watchdog {
    pub timeout: Duration,
    /// The last correctly framed line from the host.
    pub last_heard: Instant,
    /// While a wire firmware thread serves the laser arm: the latest instant it has
    /// looked at its line and found no complete line waiting. A real controller stamps
    /// a line when its bytes arrive; the simulated one only when its thread reads
    /// them, which a loaded host may delay past the timeout although the keepalives
    /// were sent on time. So the watchdog expires only once the firmware has seen its
    /// line silent past the deadline. `None` (in-process devices, or no firmware
    /// thread): by the wall clock.
    pub quiet_until: Option<Instant>,
    /// Times it switched emission off since power-up.
    pub trips: u32,
}

#[derive(Debug)]
pub(crate) struct RigState {
    pub arms: [ArmState; 2],
    emission: bool,
    pub watchdog: Watchdog,
    emission_log: Vec<EmissionChange>,
    pub interlock_closed: bool,
    pub diffuser_in: bool,
    pub tdc_faults: VecDeque<TdcFault>,
    pub tdc_refused_reopens: u32,
    /// Unplugged now (not at the next acquisition): every transfer fails.
    pub tdc_unplugged: bool,
    /// The laser is gated by a line from outside (a DAQ's digital output): the
    /// controller's own watchdog plays no part ([`Rig::gate_externally`]).
    pub external_gate: bool,
    /// How fast the laser pulses now, hertz: the detector's rate until
    /// [`Rig::set_repetition_rate`] changes it.
    pub repetition_rate: f64,
}

/// Emission changes remembered for [`Rig::emission_changes`].
const EMISSION_LOG: usize = 4096;

impl RigState {
    /// Whether the laser emits.
    pub(crate) fn emission(&self) -> bool {
        self.emission
    }

    /// Switches emission, remembering when and why.
    pub(crate) fn set_emission(&mut self, on: bool, cause: EmissionCause, at: Instant) {
        if self.emission == on {
            return;
        }
        self.emission = on;
        if self.emission_log.len() == EMISSION_LOG {
            self.emission_log.remove(0);
        }
        self.emission_log.push(EmissionChange { at, on, cause });
    }

    /// The watchdog, evaluated at `now`: emission is switched off at the moment the
    /// timeout ran out if nothing was heard from the host since. Evaluating it on every
    /// look at the state is exactly equivalent to a timer interrupt in the firmware,
    /// since nothing can observe emission in between.
    fn expire_watchdog(&mut self, now: Instant) {
        if self.external_gate {
            return;
        }
        let due = self.watchdog.last_heard + self.watchdog.timeout;
        let seen = self.watchdog.quiet_until.map_or(now, |q| q.min(now));
        if self.emission && seen >= due {
            self.watchdog.trips += 1;
            self.set_emission(false, EmissionCause::Watchdog, due);
        }
    }

    /// The host was heard (a correctly framed line): the watchdog restarts. The
    /// expiry is evaluated first, so a line that arrives too late does not undo a trip.
    pub(crate) fn heard_host(&mut self, now: Instant) {
        self.expire_watchdog(now);
        self.watchdog.last_heard = now;
    }

    /// The laser arm's wire firmware looked at its line at `now` and found no complete
    /// line waiting (`Some`), or stopped serving it (`None`).
    pub(crate) fn line_quiet(&mut self, now: Option<Instant>) {
        self.watchdog.quiet_until = now;
        self.expire_watchdog(now.unwrap_or_else(Instant::now));
    }
}

/// Hard limits as the firmware reports them in `LIM` and holds moves to: seven
/// decimals of a radian, what the wire carries. A host that moves to the limit it read
/// (`MOVE 0.3490659` for ±20°), or to its own limit of the same angle, which the wire
/// rounds onto it, is not refused for a digit it was never shown; one a reported digit
/// beyond is. Until 2026-12-07 moves were checked against the unrounded limits, and
/// both were refused with `ERR 4` wherever the rounding went outward.
pub(crate) fn as_reported(limits: AngleLimits) -> AngleLimits {
    let wire = |a: f64| protocol::parse_angle(&protocol::fmt_angle(a)).unwrap_or(a);
    AngleLimits {
        x: limits.x.map(wire),
        y: limits.y.map(wire),
    }
}

pub(crate) struct Shared {
    pub settings: RigSettings,
    pub world: Option<World>,
    pub state: Mutex<RigState>,
}

impl Shared {
    pub(crate) fn lock(&self) -> MutexGuard<'_, RigState> {
        // A panicking firmware thread must not take the whole rig down with it.
        let mut s = self.state.lock().unwrap_or_else(|p| p.into_inner());
        s.expire_watchdog(Instant::now());
        s
    }

    pub(crate) fn instrument(&self) -> Instrument {
        Instrument {
            laser: self.settings.laser_pose.origin,
            spad: self.settings.spad_pose.origin,
        }
    }

    pub(crate) fn scaled(&self, d: Duration) -> Duration {
        d.mul_f64(self.settings.time_scale.max(0.0))
    }

    // The controllers' behaviour, typed: the firmware answers its protocol lines with
    // these, and the in-process devices call them directly.

    /// Starts a move to `target`; returns how long the pair takes to settle. A target
    /// outside the firmware's hard limits, as `LIM` reports them ([`as_reported`]), is
    /// refused.
    pub(crate) fn start_move(&self, arm: Arm, target: OpticalAngles) -> Result<Duration, ErrorCode> {
        if !as_reported(self.settings.limits[arm.index()]).contains(target) {
            return Err(ErrorCode::OutOfRange);
        }
        let settle = self.scaled(self.settings.settle[arm.index()]);
        let mut s = self.lock();
        let a = &mut s.arms[arm.index()];
        a.target = target;
        a.parked = false;
        a.settled_at = Instant::now() + settle;
        Ok(settle)
    }

    /// Moves to the park position.
    pub(crate) fn park(&self, arm: Arm) {
        let settle = self.scaled(self.settings.settle[arm.index()]);
        let mut s = self.lock();
        let a = &mut s.arms[arm.index()];
        a.target = OpticalAngles { x: 0.0, y: 0.0 };
        a.parked = true;
        a.settled_at = Instant::now() + settle;
    }

    /// Whether an arm's last command was `PARK`.
    pub(crate) fn parked(&self, arm: Arm) -> bool {
        self.lock().arms[arm.index()].parked
    }

    /// Motion state and position of an arm, and when it settles.
    pub(crate) fn motion(&self, arm: Arm) -> (MotionState, OpticalAngles, Instant) {
        let s = self.lock();
        let a = &s.arms[arm.index()];
        let state = if Instant::now() < a.settled_at {
            MotionState::Moving
        } else if a.parked {
            MotionState::Parked
        } else {
            MotionState::Settled
        };
        (state, a.target, a.settled_at)
    }

    /// Switches emission; on is refused while the interlock is open.
    pub(crate) fn switch_laser(&self, on: bool) -> Result<(), ErrorCode> {
        let mut s = self.lock();
        if on && !s.interlock_closed {
            return Err(ErrorCode::InterlockOpen);
        }
        s.set_emission(on, EmissionCause::Host, Instant::now());
        Ok(())
    }

    /// Sets the watchdog timeout (if given); returns it with the trips since power-up.
    pub(crate) fn laser_watchdog(&self, set: Option<Duration>) -> (Duration, u32) {
        let mut s = self.lock();
        if let Some(t) = set {
            s.watchdog.timeout = t;
        }
        (s.watchdog.timeout, s.watchdog.trips)
    }

    /// Emission off without waiting more than a few milliseconds for the state (for
    /// a panic hook, which may run on a thread that holds it); whether it went off.
    pub(crate) fn try_laser_off(&self) -> bool {
        for _ in 0..50 {
            match self.state.try_lock() {
                Ok(mut s) => {
                    s.set_emission(false, EmissionCause::Host, Instant::now());
                    return true;
                }
                Err(std::sync::TryLockError::Poisoned(p)) => {
                    p.into_inner()
                        .set_emission(false, EmissionCause::Host, Instant::now());
                    return true;
                }
                Err(std::sync::TryLockError::WouldBlock) => std::thread::sleep(Duration::from_micros(100)),
            }
        }
        false
    }

    /// Emission, interlock and diffuser.
    pub(crate) fn laser_state(&self) -> (bool, bool, bool) {
        let s = self.lock();
        (s.emission(), s.interlock_closed, s.diffuser_in)
    }

    /// Puts the diffuser in or takes it out.
    pub(crate) fn set_diffuser(&self, inserted: bool) {
        self.lock().diffuser_in = inserted;
    }
}

/// The simulated instrument. Cheap to clone; all clones share one state.
#[derive(Clone)]
pub struct Rig {
    pub(crate) shared: Arc<Shared>,
}

impl Rig {
    /// A rig over a scene (`None`: the histogrammer reports dark and ambient counts
    /// only, which costs nothing to compute; benchmarks use it to time the software).
    pub fn new(world: Option<World>, settings: RigSettings) -> Rig {
        let now = Instant::now();
        let arm = || ArmState {
            target: OpticalAngles { x: 0.0, y: 0.0 },
            settled_at: now,
            parked: true,
            generation: 0,
            refused_connects: 0,
            faults: VecDeque::new(),
        };
        let state = RigState {
            arms: [arm(), arm()],
            emission: false,
            watchdog: Watchdog {
                timeout: Duration::from_millis(u64::from(
                    periscope_drivers::galvo::protocol::WATCHDOG_DEFAULT_MS,
                )),
                last_heard: now,
                quiet_until: None,
                trips: 0,
            },
            emission_log: Vec::new(),
            interlock_closed: settings.interlock_closed,
            diffuser_in: false,
            tdc_faults: VecDeque::new(),
            tdc_refused_reopens: 0,
            tdc_unplugged: false,
            external_gate: false,
            repetition_rate: settings.detector.repetition_rate,
        };
        Rig {
            shared: Arc::new(Shared {
                settings,
                world,
                state: Mutex::new(state),
            }),
        }
    }

    /// Queues a one-shot fault.
    pub fn inject(&self, fault: Fault) {
        let mut s = self.shared.lock();
        match fault {
            Fault::Galvo(arm, f) => s.arms[arm.index()].faults.push_back(f),
            Fault::Tdc(f) => s.tdc_faults.push_back(f),
        }
    }

    /// The laser pulses at `hz` from now on (another preset, another laser): the
    /// photons per pulse and the counter's sync rate follow.
    pub fn set_repetition_rate(&self, hz: f64) {
        self.shared.lock().repetition_rate = hz;
    }

    /// Pulls the histogrammer's cable now: the transfer in progress and every later one
    /// fail, and this many reopens are refused before it is back.
    pub fn unplug_tdc(&self, refused_reopens: u32) {
        let mut s = self.shared.lock();
        s.tdc_unplugged = true;
        s.tdc_refused_reopens = refused_reopens;
    }

    /// Plugs the histogrammer's cable back in: the next reopen succeeds (the transfers
    /// of a handle opened before the unplug keep failing, as on a real bus).
    pub fn plug_tdc(&self) {
        let mut s = self.shared.lock();
        s.tdc_unplugged = false;
        s.tdc_refused_reopens = 0;
    }

    /// Opens or closes the interlock loop; opening it stops emission at once.
    pub fn set_interlock(&self, closed: bool) {
        let mut s = self.shared.lock();
        s.interlock_closed = closed;
        if !closed {
            s.set_emission(false, EmissionCause::Interlock, Instant::now());
        }
    }

    /// From now on the laser is gated by a line driven from outside the galvo
    /// controllers (a DAQ device's digital output, in the DAQmx stand-in): the serial
    /// controller's watchdog no longer switches it off; whatever drives the gate
    /// (and that driver's own watchdog) does, through [`Rig::gate_laser`].
    pub fn gate_externally(&self) {
        self.shared.lock().external_gate = true;
    }

    /// Drives the laser's gate input: emission follows it while the interlock is
    /// closed (a gate high with the loop open leaves the laser off). `cause` is what
    /// the emission log records (the host's write, a watchdog's expiry, a power loss).
    pub fn gate_laser(&self, high: bool, cause: EmissionCause) {
        let mut s = self.shared.lock();
        let on = high && s.interlock_closed;
        s.set_emission(on, cause, Instant::now());
    }

    /// Whether the interlock loop is closed (what a line reading it sees).
    pub fn interlock_closed(&self) -> bool {
        self.shared.lock().interlock_closed
    }

    /// Puts the LOS diffuser in or takes it out (a digital line driving its actuator).
    pub fn drive_diffuser(&self, inserted: bool) {
        self.shared.set_diffuser(inserted);
    }

    /// Drives an arm's mirrors straight to `target` (analog inputs: the servo follows
    /// the voltage; nothing refuses it), settling after the arm's settle time; `park`
    /// marks the park position. Returns whether `target` lay within the firmware's
    /// hard limits, which an analog servo does not enforce.
    pub fn drive_galvo(&self, arm: Arm, target: OpticalAngles, park: bool) -> bool {
        let within = self.shared.settings.limits[arm.index()].contains(target);
        let settle = self.shared.scaled(self.shared.settings.settle[arm.index()]);
        let mut s = self.shared.lock();
        let a = &mut s.arms[arm.index()];
        a.target = target;
        a.parked = park;
        a.settled_at = Instant::now() + settle;
        within
    }

    /// How many times a host has connected to either galvo controller (each `open` of
    /// a driver is one): tests use it to prove a request touched no hardware.
    pub fn galvo_connects(&self) -> u64 {
        let s = self.shared.lock();
        s.arms.iter().map(|a| a.generation).sum()
    }

    /// Every change of emission so far (the last 4,096), oldest first.
    pub fn emission_changes(&self) -> Vec<EmissionChange> {
        self.shared.lock().emission_log.clone()
    }

    /// When emission last went off at or after `since`, if it is off now; `None` while
    /// it is on. A laser that was already off at `since` reports `since`.
    pub fn off_since(&self, since: Instant) -> Option<Instant> {
        let s = self.shared.lock();
        if s.emission {
            return None;
        }
        let last_off = s.emission_log.iter().rev().find(|c| !c.on).map(|c| c.at);
        Some(last_off.map_or(since, |t| t.max(since)))
    }

    /// The laser watchdog's timeout and the number of times it has tripped.
    pub fn watchdog(&self) -> (Duration, u32) {
        let s = self.shared.lock();
        (s.watchdog.timeout, s.watchdog.trips)
    }

    /// Where each arm is commanded to point (laser, SPAD).
    pub fn pointing(&self) -> (OpticalAngles, OpticalAngles) {
        let s = self.shared.lock();
        (s.arms[0].target, s.arms[1].target)
    }

    /// Whether each arm is parked (laser, SPAD): its last command was `PARK`, not a move.
    pub fn parked(&self) -> (bool, bool) {
        let s = self.shared.lock();
        (s.arms[0].parked, s.arms[1].parked)
    }

    /// Whether the laser is emitting.
    pub fn emission(&self) -> bool {
        self.shared.lock().emission()
    }

    /// The galvo origins.
    pub fn origins(&self) -> (DVec3, DVec3) {
        (
            self.shared.settings.laser_pose.origin,
            self.shared.settings.spad_pose.origin,
        )
    }

    /// The scene physics, if any.
    pub fn world(&self) -> Option<&World> {
        self.shared.world.as_ref()
    }

    /// A connector that hands out pseudo-terminals with this arm's firmware on the far
    /// end (what the driver opens in place of `/dev/ttyUSB0`).
    pub fn galvo_connector(&self, arm: Arm) -> crate::devices::PtyConnector {
        crate::devices::PtyConnector::new(self.clone(), arm)
    }

    /// This arm's firmware on a pseudo-terminal that another process opens by path (see
    /// [`crate::devices::ServedPort`]).
    pub fn serve_galvo_port(&self, arm: Arm) -> std::io::Result<crate::devices::ServedPort> {
        crate::devices::ServedPort::new(self, arm)
    }

    /// This arm's controller in process, without a wire (see
    /// [`crate::devices::InProcessGalvo`]).
    pub fn in_process_galvo(
        &self,
        arm: Arm,
        limits: AngleLimits,
        watchdog: Option<Duration>,
    ) -> crate::devices::InProcessGalvo {
        crate::devices::InProcessGalvo::new(self.clone(), arm, arm.name(), limits, watchdog)
    }

    /// The histogrammer in process, without a wire (see
    /// [`crate::devices::InProcessTdc`]).
    pub fn in_process_tdc(&self) -> crate::devices::InProcessTdc {
        crate::devices::InProcessTdc::new(self.clone())
    }

    /// The histogrammer behind a USB transport.
    pub fn tdc_transport(&self) -> crate::devices::SimTdcTransport {
        crate::devices::SimTdcTransport::new(self.clone())
    }
}

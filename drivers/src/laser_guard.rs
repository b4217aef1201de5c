//! The laser's host-side guard, written once for every laser driver.
//!
//! Whatever talks to the laser (the serial controller's driver, the simulator's
//! in-process controller, a DAQ's digital line), the host must do the same four
//! things around emission, and do them the same way:
//!
//! - **arm the watchdog** before every switch-on (the controller ends emission by
//!   itself when the host goes quiet for its timeout);
//! - **keep it fed** from a thread of its own while emission is wanted, and only while
//!   the run it serves shows progress ([`Progress`]): a run stuck with the laser on
//!   loses it to the watchdog with nobody there to press the e-stop;
//! - **latch an emergency off**: once an [`EmergencyOff`] handle has switched the
//!   laser off, the driver refuses to switch it on again for the rest of its life,
//!   however the two calls race;
//! - **switch off from any thread** without waiting for the driver, which may be
//!   blocked in a move or a dwell (the e-stop's and the signal handlers' path).
//!
//! [`LaserGuard`] does these; a driver supplies only its [`LaserLine`], the
//! out-of-band path to its laser (a tagged line on the serial link, a call into the
//! simulated controller), implements [`GuardedLaser`] (how it arms the watchdog and
//! sends the switch-on), and calls [`GuardedLaser::switch_on`] and
//! [`LaserGuard::switching_off`] from its `set_emission`. The safety tests therefore
//! prove this one copy, on every backend that uses it.
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use crate::error::DeviceError;

/// A run's sign of life for a laser's keepalive ([`crate::Laser::watch_progress`]).
/// The run calls [`Progress::beat`] at each of its checkpoints and stop polls (every
/// 5 ms inside a dwell); it is alive while the last beat is younger than its limit.
/// Clones share the beat.
#[derive(Clone, Debug)]
pub struct Progress(Arc<ProgressInner>);

#[derive(Debug)]
struct ProgressInner {
    epoch: Instant,
    /// Nanoseconds from `epoch` to the last beat.
    last: AtomicU64,
    limit: Duration,
}

impl Progress {
    /// A progress that has just beaten, alive for `limit` after each beat.
    pub fn new(limit: Duration) -> Progress {
        Progress(Arc::new(ProgressInner {
            epoch: Instant::now(),
            last: AtomicU64::new(0),
            limit,
        }))
    }

    fn now_ns(&self) -> u64 {
        u64::try_from(self.0.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }

    /// The run is making progress.
    pub fn beat(&self) {
        self.0.last.fetch_max(self.now_ns(), Ordering::Relaxed);
    }

    /// Whether the last beat is at most the limit old.
    pub fn alive(&self) -> bool {
        self.since_beat() <= self.0.limit
    }

    /// How long ago the last beat was.
    pub fn since_beat(&self) -> Duration {
        let last = self.0.last.load(Ordering::Relaxed);
        Duration::from_nanos(self.now_ns().saturating_sub(last))
    }

    /// How long it stays alive after a beat.
    pub fn limit(&self) -> Duration {
        self.0.limit
    }
}

/// A laser's out-of-band path, which its driver hands the [`LaserGuard`]: what only
/// the driver knows how to say to its laser. Every method is called from threads
/// other than the driver's (the keepalive thread, an e-stop, a signal handler, a panic
/// hook) while the driver may be blocked in a call of its own.
pub trait LaserLine: Send + Sync + 'static {
    /// Feeds the controller's watchdog once. A failure is logged and the next period
    /// tries again; the watchdog ends emission if none gets through.
    fn feed(&self) -> std::io::Result<()>;
    /// Switches emission off now. An error means the command could not be delivered;
    /// the keepalive has stopped regardless, so the controller's watchdog ends
    /// emission within its timeout.
    fn off(&self) -> Result<(), DeviceError>;
    /// Like [`LaserLine::off`], but never blocks for more than a few milliseconds (for
    /// a panic hook, which may run on the very thread that holds a lock the driver
    /// needs). Returns whether the command was delivered.
    fn try_off(&self) -> bool;
    /// Which laser, for logs: ``laser on `laser` (/dev/ttyUSB0)``.
    fn describe(&self) -> String;
}

/// What the guard, its keepalive thread and its off switches share.
#[derive(Debug, Default)]
struct GuardState {
    /// Whether emission is wanted: the keepalive feeds the watchdog only then.
    wanted: AtomicBool,
    /// Set by an emergency off: emission stays off for the driver's life.
    latched: AtomicBool,
    /// The run the keepalive watches.
    progress: Mutex<Option<Progress>>,
}

impl GuardState {
    /// `None` while the keepalive may feed (nothing watched, or alive); otherwise how
    /// long the watched run has shown no progress.
    fn stalled_for(&self) -> Option<Duration> {
        let p = self.progress.lock().unwrap_or_else(|p| p.into_inner());
        p.as_ref().filter(|p| !p.alive()).map(Progress::since_beat)
    }

    fn latch(&self) {
        self.latched.store(true, Ordering::SeqCst);
        self.wanted.store(false, Ordering::SeqCst);
    }
}

/// The host side of one laser's safety: watchdog arming, the progress-fed keepalive,
/// the emergency-off latch and the off switch (see the module docs). A laser driver
/// owns one; dropping it (with the driver) stops the keepalive.
pub struct LaserGuard {
    name: String,
    /// The watchdog timeout armed before each switch-on; `None` leaves the
    /// controller's own.
    watchdog: Option<Duration>,
    /// Time between keepalives: a quarter of the watchdog's timeout, so one lost or
    /// late feed never trips it.
    period: Duration,
    line: Arc<dyn LaserLine>,
    state: Arc<GuardState>,
    /// Dropped with the guard: the keepalive thread and the off switches see it go.
    alive: Arc<()>,
    keepalive: bool,
}

impl std::fmt::Debug for LaserGuard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LaserGuard")
            .field("laser", &self.line.describe())
            .field("watchdog", &self.watchdog)
            .field("state", &self.state)
            .finish_non_exhaustive()
    }
}

impl LaserGuard {
    /// The guard of the laser `name` reached through `line`. `watchdog` is the timeout
    /// to arm before every switch-on (`None`: the controller keeps its own, which is
    /// `default_watchdog`); the keepalive feeds four times per timeout.
    pub fn new(
        name: &str,
        watchdog: Option<Duration>,
        default_watchdog: Duration,
        line: impl LaserLine,
    ) -> LaserGuard {
        let timeout = watchdog.unwrap_or(default_watchdog);
        LaserGuard {
            name: name.to_owned(),
            watchdog,
            period: (timeout / 4).max(Duration::from_millis(2)),
            line: Arc::new(line),
            state: Arc::default(),
            alive: Arc::new(()),
            keepalive: false,
        }
    }

    /// Whether an emergency off has latched: the driver must refuse to switch on.
    /// A driver whose switch-on command can race the off switch checks this where it
    /// orders the two (the serial driver: holding the link's write lock).
    pub fn latched(&self) -> bool {
        self.state.latched.load(Ordering::SeqCst)
    }

    /// Whether emission is wanted (switched on and not since off).
    pub fn wanted(&self) -> bool {
        self.state.wanted.load(Ordering::SeqCst)
    }

    /// The watchdog timeout armed before each switch-on, if one is configured.
    pub fn watchdog(&self) -> Option<Duration> {
        self.watchdog
    }

    /// Emission is no longer wanted: the keepalive stops feeding. Call before sending
    /// the switch-off.
    pub fn switching_off(&self) {
        self.state.wanted.store(false, Ordering::SeqCst);
    }

    /// Emission is no longer wanted, for a driver being dropped; returns whether it
    /// was, so the driver switches the laser off on its way out.
    pub fn release(&self) -> bool {
        self.state.wanted.swap(false, Ordering::SeqCst)
    }

    /// From now on the keepalive feeds only while `progress` is alive.
    pub fn watch_progress(&self, progress: Progress) {
        *self.state.progress.lock().unwrap_or_else(|p| p.into_inner()) = Some(progress);
    }

    /// A handle that switches this laser off from any thread and latches the guard.
    pub fn emergency_off(&self) -> EmergencyOff {
        EmergencyOff(Arc::new(GuardSwitch {
            line: self.line.clone(),
            state: self.state.clone(),
            alive: Arc::downgrade(&self.alive),
        }))
    }

    fn start_keepalive(&mut self) {
        if self.keepalive {
            return;
        }
        let (line, state, alive) = (self.line.clone(), self.state.clone(), Arc::downgrade(&self.alive));
        let (name, period) = (self.name.clone(), self.period);
        match std::thread::Builder::new()
            .name(format!("laser-{name}-keepalive"))
            .spawn(move || keepalive(&line, &state, &alive, &name, period))
        {
            Ok(_) => self.keepalive = true,
            Err(e) => tracing::warn!(
                error = %e,
                "cannot start the laser keepalive; emission stops at the watchdog timeout"
            ),
        }
    }
}

/// A laser driver that keeps a [`LaserGuard`]: what the guard needs from it to
/// switch the laser on the one way every driver must ([`GuardedLaser::switch_on`]).
pub trait GuardedLaser {
    /// The driver's error.
    type Error;
    /// The driver's guard.
    fn guard(&mut self) -> &mut LaserGuard;
    /// Sets the controller's watchdog to `timeout`, checking that it took.
    fn arm_watchdog(&mut self, timeout: Duration) -> Result<(), Self::Error>;
    /// Sends the switch-on itself.
    fn send_on(&mut self) -> Result<(), Self::Error>;
    /// The error a switch-on gets after an emergency off latched (kind
    /// `Interrupted`).
    fn latched_error(&self) -> Self::Error;

    /// Switches the laser on: refused with [`GuardedLaser::latched_error`] after an
    /// emergency off; then the watchdog is armed (when one is configured), the
    /// keepalive starts feeding it, and the switch-on is sent. If that fails, emission
    /// is no longer wanted and the laser is switched off through the line (the
    /// switch-on may have got through unanswered). If an emergency off latched while the switch-on was on its
    /// way, the laser is switched off again and the call fails with
    /// [`GuardedLaser::latched_error`], whichever of the two reached the laser first.
    fn switch_on(&mut self) -> Result<(), Self::Error>
    where
        Self: Sized,
    {
        if self.guard().latched() {
            return Err(self.latched_error());
        }
        if let Some(timeout) = self.guard().watchdog {
            self.arm_watchdog(timeout)?;
        }
        let guard = self.guard();
        guard.state.wanted.store(true, Ordering::SeqCst);
        guard.start_keepalive();
        let mut result = self.send_on();
        let guard = self.guard();
        if result.is_ok() && guard.latched() {
            if let Err(e) = guard.line.off() {
                tracing::warn!(error = %e, "switching the laser off again after a racing emergency off failed");
            }
            result = Err(self.latched_error());
        } else if result.is_err() {
            // A switch-on that failed may still have reached the laser (its line went
            // out, and both answers to it and to its repeat were lost): it is switched
            // off, or only the controller's watchdog (up to `watchdog-ms`) or the
            // caller's make-safe would end it.
            if let Err(e) = guard.line.off() {
                tracing::warn!(error = %e, "switching the laser off after a failed switch-on failed");
            }
        }
        if result.is_err() {
            self.guard().state.wanted.store(false, Ordering::SeqCst);
        }
        result
    }
}

/// Feeds the watchdog every `period` while emission is wanted and the watched run
/// shows progress, until the guard is dropped. Warns once per stall.
fn keepalive(line: &Arc<dyn LaserLine>, state: &GuardState, alive: &Weak<()>, name: &str, period: Duration) {
    let mut stalled = false;
    loop {
        std::thread::sleep(period);
        if alive.strong_count() == 0 {
            return;
        }
        if !state.wanted.load(Ordering::SeqCst) {
            stalled = false;
            continue;
        }
        match state.stalled_for() {
            None => {
                stalled = false;
                if let Err(e) = line.feed() {
                    tracing::debug!(error = %e, "keepalive not sent");
                }
            }
            Some(since) => {
                if !stalled {
                    tracing::warn!(
                        arm = %name,
                        "the run has shown no progress for {:.1} s with the laser on; the keepalive stops, \
                         and the controller's watchdog switches the laser off",
                        since.as_secs_f64()
                    );
                    stalled = true;
                }
            }
        }
    }
}

/// What an [`EmergencyOff`] handle does: latch the guard, then the line's off.
struct GuardSwitch {
    line: Arc<dyn LaserLine>,
    state: Arc<GuardState>,
    alive: Weak<()>,
}

/// Switches a laser off from any thread without waiting for its driver. Cheap to
/// clone; [`crate::Laser::emergency_off`] hands one out (from the driver's
/// [`LaserGuard`]). Using it latches: the driver refuses to switch on again.
#[derive(Clone)]
pub struct EmergencyOff(Arc<GuardSwitch>);

impl EmergencyOff {
    /// Switches emission off now (see [`LaserLine::off`]).
    pub fn laser_off(&self) -> Result<(), DeviceError> {
        self.0.state.latch();
        self.0.line.off()
    }

    /// Switches emission off without blocking for more than a few milliseconds (see
    /// [`LaserLine::try_off`]). Returns whether the command was delivered.
    pub fn try_laser_off(&self) -> bool {
        self.0.state.latch();
        self.0.line.try_off()
    }

    /// Whether the driver it belongs to is still open.
    pub fn is_open(&self) -> bool {
        self.0.alive.strong_count() > 0
    }
}

impl std::fmt::Debug for EmergencyOff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("EmergencyOff")
            .field(&self.0.line.describe())
            .finish()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicUsize;

    use super::*;
    use crate::error::{Error, ErrorKind};

    /// A line that counts what it was asked to do.
    #[derive(Clone, Default)]
    struct Counting {
        feeds: Arc<AtomicUsize>,
        offs: Arc<AtomicUsize>,
    }

    impl LaserLine for Counting {
        fn feed(&self) -> std::io::Result<()> {
            self.feeds.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
        fn off(&self) -> Result<(), DeviceError> {
            self.offs.fetch_add(1, Ordering::SeqCst);
            Ok(())
        }
        fn try_off(&self) -> bool {
            self.offs.fetch_add(1, Ordering::SeqCst);
            true
        }
        fn describe(&self) -> String {
            "counting laser".into()
        }
    }

    #[derive(Debug, PartialEq)]
    enum Refused {
        Latched,
        Arm,
        On,
    }

    const WATCHDOG: Duration = Duration::from_millis(40);

    /// A driver around a guard whose arming and switch-on can be made to fail, and
    /// whose switch-on can run an e-stop as it goes.
    struct Driver {
        guard: LaserGuard,
        armed: usize,
        fail_arm: bool,
        fail_on: bool,
        during_on: Option<EmergencyOff>,
    }

    impl GuardedLaser for Driver {
        type Error = Refused;
        fn guard(&mut self) -> &mut LaserGuard {
            &mut self.guard
        }
        fn arm_watchdog(&mut self, timeout: Duration) -> Result<(), Refused> {
            assert_eq!(timeout, WATCHDOG);
            self.armed += 1;
            if self.fail_arm { Err(Refused::Arm) } else { Ok(()) }
        }
        fn send_on(&mut self) -> Result<(), Refused> {
            if let Some(off) = &self.during_on {
                off.try_laser_off();
            }
            if self.fail_on { Err(Refused::On) } else { Ok(()) }
        }
        fn latched_error(&self) -> Refused {
            Refused::Latched
        }
    }

    fn driver() -> (Driver, Counting) {
        let line = Counting::default();
        let guard = LaserGuard::new("test", Some(WATCHDOG), WATCHDOG, line.clone());
        let d = Driver {
            guard,
            armed: 0,
            fail_arm: false,
            fail_on: false,
            during_on: None,
        };
        (d, line)
    }

    #[test]
    fn the_keepalive_feeds_only_while_emission_is_wanted_and_the_run_beats() {
        let (mut d, line) = driver();
        d.switch_on().unwrap();
        assert_eq!(d.armed, 1);
        std::thread::sleep(WATCHDOG * 2);
        let fed = line.feeds.load(Ordering::SeqCst);
        assert!(fed >= 3, "fed {fed} times in two watchdog periods");

        // A run that stops beating: the feeds stop.
        d.guard.watch_progress(Progress::new(Duration::from_millis(5)));
        std::thread::sleep(Duration::from_millis(30));
        let before = line.feeds.load(Ordering::SeqCst);
        std::thread::sleep(WATCHDOG * 2);
        assert_eq!(line.feeds.load(Ordering::SeqCst), before, "fed a stalled run");

        // Switched off: no feeds either, even with a live run.
        d.guard.watch_progress(Progress::new(Duration::from_secs(60)));
        d.guard.switching_off();
        std::thread::sleep(WATCHDOG);
        let before = line.feeds.load(Ordering::SeqCst);
        std::thread::sleep(WATCHDOG * 2);
        assert_eq!(line.feeds.load(Ordering::SeqCst), before, "fed with emission off");
    }

    #[test]
    fn an_emergency_off_latches_and_reaches_the_line() {
        let (mut d, line) = driver();
        let off = d.guard.emergency_off();
        assert!(off.is_open());
        off.laser_off().unwrap();
        assert_eq!(line.offs.load(Ordering::SeqCst), 1);
        assert!(d.guard.latched() && !d.guard.wanted());
        assert_eq!(d.switch_on(), Err(Refused::Latched));
        assert_eq!(d.armed, 0, "armed the watchdog of a latched laser");
        drop(d);
        assert!(!off.is_open());
    }

    #[test]
    fn an_emergency_off_racing_the_switch_on_wins() {
        let (mut d, line) = driver();
        d.during_on = Some(d.guard.emergency_off());
        assert_eq!(d.switch_on(), Err(Refused::Latched));
        assert_eq!(
            line.offs.load(Ordering::SeqCst),
            2,
            "the guard did not switch off again"
        );
        assert!(!d.guard.wanted());
    }

    #[test]
    fn a_failed_arm_or_switch_on_leaves_emission_unwanted() {
        let (mut d, line) = driver();
        d.fail_arm = true;
        assert_eq!(d.switch_on(), Err(Refused::Arm));
        assert!(!d.guard.wanted());
        assert_eq!(line.offs.load(Ordering::SeqCst), 0, "nothing was switched on");
        d.fail_arm = false;
        d.fail_on = true;
        assert_eq!(d.switch_on(), Err(Refused::On));
        assert!(!d.guard.wanted());
        // The switch-on may have got through unanswered: it is switched off.
        assert_eq!(line.offs.load(Ordering::SeqCst), 1);
        assert!(!d.guard.release());
        d.fail_on = false;
        d.switch_on().unwrap();
        assert!(
            d.guard.release(),
            "a switched-on laser is not reported wanted on release"
        );
    }

    #[test]
    fn the_off_switch_reports_the_lines_failure() {
        struct Broken;
        impl LaserLine for Broken {
            fn feed(&self) -> std::io::Result<()> {
                Err(std::io::Error::other("gone"))
            }
            fn off(&self) -> Result<(), DeviceError> {
                Err(DeviceError::new(
                    "laser",
                    crate::galvo::GalvoError::new("laser", "nowhere", ErrorKind::Disconnected, "gone"),
                ))
            }
            fn try_off(&self) -> bool {
                false
            }
            fn describe(&self) -> String {
                "broken".into()
            }
        }
        let g = LaserGuard::new("b", None, WATCHDOG, Broken);
        let off = g.emergency_off();
        assert_eq!(off.laser_off().unwrap_err().kind(), ErrorKind::Disconnected);
        assert!(!off.try_laser_off());
        assert!(g.latched());
    }
}

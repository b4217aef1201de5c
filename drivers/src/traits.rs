//! The device traits the daemon drives: a galvo pair, the laser (on the laser arm's
//! controller) and a histogrammer. Small traits with one associated error type each,
//! so the pipeline is written once against them and runs the real drivers, whatever
//! transport sits under those drivers (a serial port or the simulator's
//! pseudo-terminal; libusb or the simulator's USB transport).
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use serde::Serialize;

use crate::error::ErrorType;
use crate::galvo::GalvoError;
use crate::galvo::protocol::MotionState;
use crate::geometry::{AngleLimits, OpticalAngles};

/// What a device says about itself.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct DeviceInfo {
    /// Model name.
    pub model: String,
    /// Firmware version.
    pub firmware: String,
    /// Serial number.
    pub serial: String,
    /// Protocol revision the device speaks.
    pub protocol: u32,
}

/// A galvo pair's motion state and measured position.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct GalvoStatus {
    /// Settled, moving, parked or faulted.
    pub state: MotionState,
    /// Measured optical angles.
    pub position: OpticalAngles,
}

/// A two-axis galvo scanner.
pub trait GalvoPair: ErrorType {
    /// Model, firmware and serial number.
    fn identify(&mut self) -> Result<DeviceInfo, Self::Error>;
    /// The optical-angle range this driver lets through; targets outside it are
    /// refused before anything is sent.
    fn limits(&self) -> AngleLimits;
    /// Starts a move to `target` and returns without waiting for it, so that two pairs
    /// can move at once. A target outside [`GalvoPair::limits`] is refused here; the
    /// controller's own answer (settled, or a refusal) is collected by
    /// [`GalvoPair::wait_settled`] or, failing that, by the next command.
    fn move_to(&mut self, target: OpticalAngles) -> Result<(), Self::Error>;
    /// Waits until the pair is settled at the last commanded target (never accepting
    /// another position) and returns the measured position.
    fn wait_settled(&mut self, timeout: Duration) -> Result<OpticalAngles, Self::Error>;
    /// The measured position.
    fn position(&mut self) -> Result<OpticalAngles, Self::Error>;
    /// Motion state and position.
    fn status(&mut self) -> Result<GalvoStatus, Self::Error>;
    /// Moves to the park position and holds there.
    fn park(&mut self) -> Result<(), Self::Error>;

    /// Moves to `target` and waits until settled there.
    fn move_settled(
        &mut self,
        target: OpticalAngles,
        timeout: Duration,
    ) -> Result<OpticalAngles, Self::Error> {
        self.move_to(target)?;
        self.wait_settled(timeout)
    }
}

/// Laser emission state, as the laser arm's controller reports it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct LaserState {
    /// Whether the laser is emitting.
    pub emission: bool,
    /// Whether the interlock loop is closed (emission allowed).
    pub interlock_closed: bool,
    /// Whether the LOS diffuser is in the beam.
    pub diffuser_in: bool,
}

/// Laser emission control with interlock, and the LOS diffuser.
pub trait Laser: ErrorType {
    /// Turns emission on or off. Turning on fails with kind `Interlock` while the
    /// interlock loop is open; turning off always reaches the controller.
    fn set_emission(&mut self, on: bool) -> Result<(), Self::Error>;
    /// Emission, interlock and diffuser state.
    fn laser_state(&mut self) -> Result<LaserState, Self::Error>;
    /// Whether the interlock loop is closed.
    fn interlock_closed(&mut self) -> Result<bool, Self::Error> {
        Ok(self.laser_state()?.interlock_closed)
    }
    /// Puts the LOS diffuser into the beam (first-bounce scan) or takes it out.
    fn set_diffuser(&mut self, inserted: bool) -> Result<(), Self::Error>;
    /// A handle that switches emission off from any thread, whatever this driver is
    /// doing or waiting for (the e-stop's and the signal handlers' path). It latches:
    /// once used, this driver refuses to switch emission on (kind `Interrupted`) for
    /// the rest of its life, so a `set_emission(true)` racing the stop cannot undo it.
    fn emergency_off(&self) -> EmergencyOff;
    /// From now on, feeds the controller's watchdog only while `progress` is alive: a
    /// run that stops making progress with the laser on (a call that never returns, a
    /// deadlock) has its laser switched off by the controller's watchdog within the
    /// progress limit plus the watchdog's timeout, with nobody there to press the
    /// e-stop. Without a progress the keepalive feeds while emission is wanted.
    fn watch_progress(&mut self, progress: Progress);
}

/// A run's sign of life for a laser's keepalive ([`Laser::watch_progress`]). The run
/// calls [`Progress::beat`] at each of its checkpoints and stop polls (every 5 ms
/// inside a dwell); it is alive while the last beat is younger than its limit. Clones
/// share the beat.
#[derive(Clone, Debug)]
pub struct Progress(Arc<ProgressInner>);

#[derive(Debug)]
struct ProgressInner {
    epoch: std::time::Instant,
    /// Nanoseconds from `epoch` to the last beat.
    last: std::sync::atomic::AtomicU64,
    limit: Duration,
}

impl Progress {
    /// A progress that has just beaten, alive for `limit` after each beat.
    pub fn new(limit: Duration) -> Progress {
        Progress(Arc::new(ProgressInner {
            epoch: std::time::Instant::now(),
            last: std::sync::atomic::AtomicU64::new(0),
            limit,
        }))
    }

    fn now_ns(&self) -> u64 {
        u64::try_from(self.0.epoch.elapsed().as_nanos()).unwrap_or(u64::MAX)
    }

    /// The run is making progress.
    pub fn beat(&self) {
        self.0
            .last
            .fetch_max(self.now_ns(), std::sync::atomic::Ordering::Relaxed);
    }

    /// Whether the last beat is at most the limit old.
    pub fn alive(&self) -> bool {
        self.since_beat() <= self.0.limit
    }

    /// How long ago the last beat was.
    pub fn since_beat(&self) -> Duration {
        let last = self.0.last.load(std::sync::atomic::Ordering::Relaxed);
        Duration::from_nanos(self.now_ns().saturating_sub(last))
    }

    /// How long it stays alive after a beat.
    pub fn limit(&self) -> Duration {
        self.0.limit
    }
}

/// The progress a laser driver's keepalive consults, shared between the driver (which
/// [`Laser::watch_progress`] sets) and its keepalive thread. For laser drivers.
#[derive(Clone, Debug, Default)]
pub struct ProgressWatch(Arc<Mutex<Option<Progress>>>);

impl ProgressWatch {
    /// Watches `progress` from now on.
    pub fn set(&self, progress: Progress) {
        *self.0.lock().unwrap_or_else(|p| p.into_inner()) = Some(progress);
    }

    /// `None` while the keepalive may feed (nothing watched, or alive); otherwise how
    /// long the watched run has shown no progress.
    pub fn stalled_for(&self) -> Option<Duration> {
        let p = self.0.lock().unwrap_or_else(|p| p.into_inner());
        p.as_ref().filter(|p| !p.alive()).map(Progress::since_beat)
    }
}

/// A keepalive loop's view of a stall, so it warns once per stall. For laser drivers.
#[derive(Debug, Default)]
pub struct Stall(bool);

impl Stall {
    /// Whether a keepalive of the laser `name` feeds the watchdog now: emission is
    /// `wanted` and the run it watches shows progress. Warns when a stall begins.
    pub fn feeds(&mut self, progress: &ProgressWatch, wanted: bool, name: &str) -> bool {
        if !wanted {
            self.0 = false;
            return false;
        }
        match progress.stalled_for() {
            None => {
                self.0 = false;
                true
            }
            Some(since) => {
                if !self.0 {
                    tracing::warn!(
                        arm = %name,
                        "the run has shown no progress for {:.1} s with the laser on; the keepalive stops, \
                         and the controller's watchdog switches the laser off",
                        since.as_secs_f64()
                    );
                    self.0 = true;
                }
                false
            }
        }
    }
}

/// What an [`EmergencyOff`] handle does; each laser driver implements it over its own
/// out-of-band path to the laser.
pub trait OffSwitch: Send + Sync {
    /// Switches emission off now. An error means the command could not be delivered;
    /// the driver's keepalive has stopped regardless, so the controller's watchdog
    /// ends emission within its timeout.
    fn laser_off(&self) -> Result<(), GalvoError>;
    /// Like [`OffSwitch::laser_off`], but never blocks for more than a few
    /// milliseconds (for a panic hook, which may run on the very thread that holds a
    /// lock the driver needs). Returns whether the command was delivered.
    fn try_laser_off(&self) -> bool;
    /// Whether the driver it belongs to is still open.
    fn is_open(&self) -> bool;
    /// Which laser, for logs.
    fn describe(&self) -> String;
}

/// Switches a laser off from any thread without waiting for its driver. Cheap to
/// clone; [`Laser::emergency_off`] hands one out.
#[derive(Clone)]
pub struct EmergencyOff(Arc<dyn OffSwitch>);

impl EmergencyOff {
    /// A handle over a driver's off switch.
    pub fn new(switch: impl OffSwitch + 'static) -> EmergencyOff {
        EmergencyOff(Arc::new(switch))
    }

    /// Switches emission off now (see [`OffSwitch::laser_off`]).
    pub fn laser_off(&self) -> Result<(), GalvoError> {
        self.0.laser_off()
    }

    /// Switches emission off without blocking (see [`OffSwitch::try_laser_off`]).
    pub fn try_laser_off(&self) -> bool {
        self.0.try_laser_off()
    }

    /// Whether the driver it belongs to is still open.
    pub fn is_open(&self) -> bool {
        self.0.is_open()
    }
}

impl std::fmt::Debug for EmergencyOff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("EmergencyOff").field(&self.0.describe()).finish()
    }
}

/// One controller behind two of its traits at once: the laser arm's controller is
/// both a [`GalvoPair`] and the [`Laser`], and the daemon holds each as its own trait
/// object. Clones share the driver; each call holds it for that call only.
pub struct Shared<T>(Arc<Mutex<T>>);

impl<T> Shared<T> {
    /// Shares `driver`.
    pub fn new(driver: T) -> Shared<T> {
        Shared(Arc::new(Mutex::new(driver)))
    }

    fn lock(&self) -> MutexGuard<'_, T> {
        // A panic in one call must not leave the laser unreachable.
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }
}

impl<T> Clone for Shared<T> {
    fn clone(&self) -> Self {
        Shared(self.0.clone())
    }
}

impl<T: ErrorType> ErrorType for Shared<T> {
    type Error = T::Error;
}

impl<T: GalvoPair> GalvoPair for Shared<T> {
    fn identify(&mut self) -> Result<DeviceInfo, Self::Error> {
        self.lock().identify()
    }
    fn limits(&self) -> AngleLimits {
        self.lock().limits()
    }
    fn move_to(&mut self, target: OpticalAngles) -> Result<(), Self::Error> {
        self.lock().move_to(target)
    }
    fn wait_settled(&mut self, timeout: Duration) -> Result<OpticalAngles, Self::Error> {
        self.lock().wait_settled(timeout)
    }
    fn position(&mut self) -> Result<OpticalAngles, Self::Error> {
        self.lock().position()
    }
    fn status(&mut self) -> Result<GalvoStatus, Self::Error> {
        self.lock().status()
    }
    fn park(&mut self) -> Result<(), Self::Error> {
        self.lock().park()
    }
}

impl<T: Laser> Laser for Shared<T> {
    fn set_emission(&mut self, on: bool) -> Result<(), Self::Error> {
        self.lock().set_emission(on)
    }
    fn laser_state(&mut self) -> Result<LaserState, Self::Error> {
        self.lock().laser_state()
    }
    fn interlock_closed(&mut self) -> Result<bool, Self::Error> {
        self.lock().interlock_closed()
    }
    fn set_diffuser(&mut self, inserted: bool) -> Result<(), Self::Error> {
        self.lock().set_diffuser(inserted)
    }
    fn emergency_off(&self) -> EmergencyOff {
        self.lock().emergency_off()
    }
    fn watch_progress(&mut self, progress: Progress) {
        self.lock().watch_progress(progress)
    }
}

/// Histogrammer settings, SI units.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TdcConfig {
    /// Bin width, seconds.
    pub bin_width: f64,
    /// Number of bins.
    pub bins: u32,
    /// TDC time of bin 0's start after the sync, seconds.
    pub offset: f64,
    /// Sync divider (1 = every laser pulse starts a cycle).
    pub sync_divider: u32,
    /// Acquisition time per histogram.
    pub acquisition: Duration,
}

/// Flags a histogram frame carries.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct HistogramFlags {
    /// A bin counter or the device FIFO overflowed: counts are a lower bound.
    pub overflow: bool,
    /// The detector count rate was above the pile-up threshold during acquisition.
    pub saturated: bool,
}

/// One acquired histogram.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Histogram {
    /// Device sequence number of the acquisition.
    pub sequence: u32,
    /// Photon counts per bin.
    pub counts: Vec<u32>,
    /// Frame flags.
    pub flags: HistogramFlags,
    /// The settings it was acquired with.
    pub config: TdcConfig,
}

/// Count rates, Hz.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct CountRates {
    /// Sync (laser) rate after the divider.
    pub sync: f64,
    /// Detector input rate.
    pub detector: f64,
}

/// Histogrammer state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum TdcState {
    /// Ready for an acquisition.
    Idle,
    /// Acquiring.
    Acquiring,
    /// Reporting an internal error.
    Error,
}

/// Histogrammer status.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TdcStatus {
    /// State.
    pub state: TdcState,
    /// Count rates.
    pub rates: CountRates,
    /// Histograms acquired since power-up.
    pub acquisitions: u32,
}

/// A time-correlated histogrammer (TDC + SPAD).
pub trait Histogrammer: ErrorType {
    /// Model, firmware and serial number.
    fn identify(&mut self) -> Result<DeviceInfo, Self::Error>;
    /// Applies settings; they stay in force (and are restored after a reconnect).
    fn configure(&mut self, config: &TdcConfig) -> Result<(), Self::Error>;
    /// The settings in force, if configured.
    fn config(&self) -> Option<TdcConfig>;
    /// Acquires one histogram with the settings in force.
    fn acquire(&mut self) -> Result<Histogram, Self::Error>;
    /// Acquires one histogram, asking `stop` every few milliseconds while the dwell
    /// runs; when it says stop, the acquisition is aborted on the device and the
    /// error's kind is [`crate::ErrorKind::Interrupted`]. However long the dwell, a
    /// stop lands within the driver's poll interval.
    fn acquire_until(&mut self, stop: &dyn Fn() -> bool) -> Result<Histogram, Self::Error>;
    /// Aborts an acquisition in progress and drops frames not yet read.
    fn abort(&mut self) -> Result<(), Self::Error>;
    /// State, rates and counters.
    fn status(&mut self) -> Result<TdcStatus, Self::Error>;
}

//! The device traits the daemon drives: a galvo pair, the laser (on the laser arm's
//! controller) and a histogrammer. Small traits with one associated error type each,
//! so the pipeline is written once against them and runs the real drivers, whatever
//! transport sits under those drivers (a serial port or the simulator's
//! pseudo-terminal; libusb or the simulator's USB transport).
//!
//! Each driver keeps its own error type (embedded-hal's shape: an associated error
//! whose `kind()` the caller decides on). Where a caller picks the driver at run time
//! it holds the device as a trait object with the one [`DeviceError`]
//! ([`GalvoBox`], [`LaserBox`], [`HistogrammerBox`]), made by [`Erased`] from any
//! driver: it never learns which driver it holds.
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use serde::Serialize;

use crate::error::{DeviceError, ErrorType};
use crate::geometry::{AngleLimits, OpticalAngles};
use crate::laser_guard::{EmergencyOff, Progress};
use crate::park::EmergencyPark;

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

/// Motion state a galvo pair reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MotionState {
    /// At the commanded position and within the settling band.
    Settled,
    /// Moving or still settling.
    Moving,
    /// Holding the park position.
    Parked,
    /// Servo fault; the controller needs attention.
    Fault,
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
    /// The controller's own hard limits, where it reports them (`None` where it does
    /// not, or where [`GalvoPair::limits`] are the only ones there are).
    fn hard_limits(&mut self) -> Result<Option<AngleLimits>, Self::Error> {
        Ok(None)
    }
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
    /// A handle that parks this pair from any thread, whatever this driver is doing
    /// or waiting for (the e-stop's path while a run is stuck holding the driver). It
    /// latches: once used, this driver refuses every move (kind `Interrupted`) for the
    /// rest of its life; [`GalvoPair::park`] still works. Take it when the driver is
    /// opened, not when it is needed: a driver behind [`Shared`] hands it out under
    /// the lock the stuck thread may hold.
    fn emergency_park(&self) -> EmergencyPark;

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
    fn hard_limits(&mut self) -> Result<Option<AngleLimits>, Self::Error> {
        self.lock().hard_limits()
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
    fn emergency_park(&self) -> EmergencyPark {
        self.lock().emergency_park()
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
    /// How long after the sync changes (the laser starts pulsing, a divider is set)
    /// [`Histogrammer::status`] reads the new rate: a counter with a gated rate meter
    /// answers the last gate's count until then. Zero (the default) where the status
    /// reads the rate as it is.
    fn rate_latency(&self) -> Duration {
        Duration::ZERO
    }
    /// Whether [`Histogrammer::status`]'s sync rate is counted after the sync divider
    /// (`Some(true)`, the default: Periscope's counter and the simulator), before it
    /// (`Some(false)`), or `None` where the vendor's documents do not settle which.
    fn sync_after_divider(&self) -> Option<bool> {
        Some(true)
    }
}

/// A galvo pair, whatever drives it.
pub type GalvoBox = Box<dyn GalvoPair<Error = DeviceError> + Send>;
/// A laser, whatever drives it.
pub type LaserBox = Box<dyn Laser<Error = DeviceError> + Send>;
/// A histogrammer, whatever drives it.
pub type HistogrammerBox = Box<dyn Histogrammer<Error = DeviceError> + Send>;

/// A driver behind the device traits with its errors turned into the one
/// [`DeviceError`], so that callers who choose the driver at run time hold every
/// driver as the same trait object.
pub struct Erased<T>(pub T);

impl<T> Erased<T> {
    /// `driver` as a [`GalvoBox`].
    pub fn galvo(driver: T) -> GalvoBox
    where
        T: GalvoPair + Send + 'static,
        T::Error: Into<DeviceError>,
    {
        Box::new(Erased(driver))
    }

    /// `driver` as a [`LaserBox`].
    pub fn laser(driver: T) -> LaserBox
    where
        T: Laser + Send + 'static,
        T::Error: Into<DeviceError>,
    {
        Box::new(Erased(driver))
    }

    /// `driver` as a [`HistogrammerBox`].
    pub fn histogrammer(driver: T) -> HistogrammerBox
    where
        T: Histogrammer + Send + 'static,
        T::Error: Into<DeviceError>,
    {
        Box::new(Erased(driver))
    }
}

impl<T> ErrorType for Erased<T> {
    type Error = DeviceError;
}

impl<T: GalvoPair> GalvoPair for Erased<T>
where
    T::Error: Into<DeviceError>,
{
    fn identify(&mut self) -> Result<DeviceInfo, DeviceError> {
        self.0.identify().map_err(Into::into)
    }
    fn limits(&self) -> AngleLimits {
        self.0.limits()
    }
    fn hard_limits(&mut self) -> Result<Option<AngleLimits>, DeviceError> {
        self.0.hard_limits().map_err(Into::into)
    }
    fn move_to(&mut self, target: OpticalAngles) -> Result<(), DeviceError> {
        self.0.move_to(target).map_err(Into::into)
    }
    fn wait_settled(&mut self, timeout: Duration) -> Result<OpticalAngles, DeviceError> {
        self.0.wait_settled(timeout).map_err(Into::into)
    }
    fn position(&mut self) -> Result<OpticalAngles, DeviceError> {
        self.0.position().map_err(Into::into)
    }
    fn status(&mut self) -> Result<GalvoStatus, DeviceError> {
        self.0.status().map_err(Into::into)
    }
    fn park(&mut self) -> Result<(), DeviceError> {
        self.0.park().map_err(Into::into)
    }
    fn emergency_park(&self) -> EmergencyPark {
        self.0.emergency_park()
    }
    fn move_settled(
        &mut self,
        target: OpticalAngles,
        timeout: Duration,
    ) -> Result<OpticalAngles, DeviceError> {
        self.0.move_settled(target, timeout).map_err(Into::into)
    }
}

impl<T: Laser> Laser for Erased<T>
where
    T::Error: Into<DeviceError>,
{
    fn set_emission(&mut self, on: bool) -> Result<(), DeviceError> {
        self.0.set_emission(on).map_err(Into::into)
    }
    fn laser_state(&mut self) -> Result<LaserState, DeviceError> {
        self.0.laser_state().map_err(Into::into)
    }
    fn interlock_closed(&mut self) -> Result<bool, DeviceError> {
        self.0.interlock_closed().map_err(Into::into)
    }
    fn set_diffuser(&mut self, inserted: bool) -> Result<(), DeviceError> {
        self.0.set_diffuser(inserted).map_err(Into::into)
    }
    fn emergency_off(&self) -> EmergencyOff {
        self.0.emergency_off()
    }
    fn watch_progress(&mut self, progress: Progress) {
        self.0.watch_progress(progress)
    }
}

impl<T: Histogrammer> Histogrammer for Erased<T>
where
    T::Error: Into<DeviceError>,
{
    fn identify(&mut self) -> Result<DeviceInfo, DeviceError> {
        self.0.identify().map_err(Into::into)
    }
    fn configure(&mut self, config: &TdcConfig) -> Result<(), DeviceError> {
        self.0.configure(config).map_err(Into::into)
    }
    fn config(&self) -> Option<TdcConfig> {
        self.0.config()
    }
    fn acquire(&mut self) -> Result<Histogram, DeviceError> {
        self.0.acquire().map_err(Into::into)
    }
    fn acquire_until(&mut self, stop: &dyn Fn() -> bool) -> Result<Histogram, DeviceError> {
        self.0.acquire_until(stop).map_err(Into::into)
    }
    fn abort(&mut self) -> Result<(), DeviceError> {
        self.0.abort().map_err(Into::into)
    }
    fn status(&mut self) -> Result<TdcStatus, DeviceError> {
        self.0.status().map_err(Into::into)
    }
    fn rate_latency(&self) -> Duration {
        self.0.rate_latency()
    }
    fn sync_after_divider(&self) -> Option<bool> {
        self.0.sync_after_divider()
    }
}

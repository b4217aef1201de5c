//! The simulated devices in process: the device traits implemented straight over the
//! [`Rig`]'s controller model (the one the wire-level devices answer their protocols
//! with), with no pseudo-terminal, USB framing or driver in between.
//!
//! What they model is the instrument: settling times, the firmware's hard limits, the
//! interlock, the laser watchdog (fed from a keepalive thread while emission is wanted,
//! as the serial driver feeds it, and by every call), the diffuser, an unplugged
//! histogrammer, and the same Poisson counts, draw for draw, as the wire-level
//! histogrammer gives the same acquisitions. What they do not model is the wire:
//! [`crate::devices::GalvoFault`]s and the wire faults among the
//! [`crate::devices::TdcFault`]s are left queued for the wire-level devices (an
//! overflow and an unplug do reach these). Tests that are about the pipeline, the API
//! or the safety logic rather than the drivers use them (`sim.devices =
//! "in-process"`); the wire-level devices keep testing the real drivers.
use std::sync::{Arc, Mutex, Weak};
use std::time::{Duration, Instant};

use periscope_drivers::galvo::GalvoError;
use periscope_drivers::galvo::protocol::{self as galvo_protocol, ErrorCode};
use periscope_drivers::laser_guard::GuardedLaser;
use periscope_drivers::tdc::TdcError;
use periscope_drivers::tdc::protocol::{self as tdc_protocol, WireConfig, flag};
use periscope_drivers::{
    AngleLimits, CountRates, DeviceError, DeviceInfo, EmergencyOff, EmergencyPark, ErrorKind, ErrorType,
    GalvoPair, GalvoStatus, Histogram, HistogramFlags, Histogrammer, Laser, LaserGuard, LaserLine,
    LaserState, ParkLine, Parked, Progress, TdcConfig, TdcState, TdcStatus,
};

use super::rig::{Arm, Rig, Shared};
use super::tdc::{Measurement, measure, sync_rate};

/// A galvo controller in process (on the laser arm, with its laser and diffuser).
pub struct InProcessGalvo {
    rig: Rig,
    arm: Arm,
    name: String,
    limits: AngleLimits,
    /// The laser's host-side safety, the same guard the serial driver keeps: the
    /// watchdog armed before each switch-on, the keepalive (here a call into the
    /// controller model), the emergency-off latch.
    guard: LaserGuard,
    /// Set once an [`EmergencyPark`] has parked the pair; held while a move starts,
    /// so no move follows the park.
    park_latch: Arc<Mutex<bool>>,
}

impl InProcessGalvo {
    /// The controller of `arm`, named `name` in errors, refusing targets outside
    /// `limits` before they reach the controller (as the serial driver does) and,
    /// on the laser arm, setting `watchdog` before every `LASER ON`.
    pub fn new(
        rig: Rig,
        arm: Arm,
        name: &str,
        limits: AngleLimits,
        watchdog: Option<Duration>,
    ) -> InProcessGalvo {
        let guard = LaserGuard::new(
            name,
            watchdog,
            Duration::from_millis(u64::from(galvo_protocol::WATCHDOG_DEFAULT_MS)),
            InProcessLine {
                shared: Arc::downgrade(&rig.shared),
                name: name.to_owned(),
            },
        );
        InProcessGalvo {
            rig,
            arm,
            name: name.to_owned(),
            limits,
            guard,
            park_latch: Arc::new(Mutex::new(false)),
        }
    }

    fn port(&self) -> String {
        format!("simulated {} controller (in process)", self.arm.name())
    }

    fn emergency_stopped(&self) -> GalvoError {
        GalvoError::new(
            &self.name,
            &self.port(),
            ErrorKind::Interrupted,
            "emission was switched off by an emergency stop and stays off on this connection: open the devices again to switch it on",
        )
    }

    fn refused(&self, what: &str, code: ErrorCode) -> GalvoError {
        let (kind, hint) = galvo_protocol::refusal(Some(code));
        GalvoError::new(
            &self.name,
            &self.port(),
            kind,
            format!("`{what}` refused: {hint}"),
        )
    }

    /// A call reaches the controller: on the laser arm it feeds the watchdog, as every
    /// correctly framed line does.
    fn heard(&self) {
        if self.arm == Arm::Laser {
            self.rig.shared.lock().heard_host(Instant::now());
        }
    }

    fn laser_only(&self, what: &str) -> Result<(), GalvoError> {
        self.heard();
        if self.arm == Arm::Laser {
            Ok(())
        } else {
            Err(self.refused(what, ErrorCode::NoLaser))
        }
    }
}

impl Drop for InProcessGalvo {
    /// Dropped while emission is wanted (a panic unwinding, a run abandoned): the laser
    /// goes off on the way out, as with the serial driver.
    fn drop(&mut self) {
        if self.guard.release() {
            let _ = self.rig.shared.switch_laser(false);
        }
    }
}

impl ErrorType for InProcessGalvo {
    type Error = GalvoError;
}

impl GalvoPair for InProcessGalvo {
    fn identify(&mut self) -> Result<DeviceInfo, GalvoError> {
        self.heard();
        let letter = if self.arm == Arm::Laser { "L" } else { "S" };
        Ok(DeviceInfo {
            model: "PGC-2 (in process)".into(),
            firmware: super::firmware::FIRMWARE.into(),
            serial: format!("SIM-{letter}-0001"),
            protocol: galvo_protocol::PROTOCOL_VERSION,
        })
    }

    fn limits(&self) -> AngleLimits {
        self.limits
    }

    fn move_to(&mut self, target: periscope_drivers::OpticalAngles) -> Result<(), GalvoError> {
        self.heard();
        if !self.limits.contains(target) {
            return Err(GalvoError::new(
                &self.name,
                &self.port(),
                ErrorKind::OutOfRange,
                format!(
                    "target ({:.4}, {:.4}) rad is outside the configured limits",
                    target.x, target.y
                ),
            ));
        }
        // The wire carries seven decimals of a radian: the controller moves to what it
        // would have been sent.
        let wire = |a: f64| galvo_protocol::parse_angle(&galvo_protocol::fmt_angle(a)).unwrap_or(a);
        let target = periscope_drivers::OpticalAngles {
            x: wire(target.x),
            y: wire(target.y),
        };
        let latch = self.park_latch.lock().unwrap_or_else(|p| p.into_inner());
        if *latch {
            return Err(GalvoError::new(
                &self.name,
                &self.port(),
                ErrorKind::Interrupted,
                "an emergency stop parked this pair, and it stays parked on this connection: open the devices again to move it",
            ));
        }
        self.rig
            .shared
            .start_move(self.arm, target)
            .map(drop)
            .map_err(|code| self.refused("MOVE", code))
    }

    fn wait_settled(&mut self, timeout: Duration) -> Result<periscope_drivers::OpticalAngles, GalvoError> {
        self.heard();
        let (_, target, settled_at) = self.rig.shared.motion(self.arm);
        let wait = settled_at.saturating_duration_since(Instant::now());
        if wait > timeout {
            std::thread::sleep(timeout);
            return Err(GalvoError::new(
                &self.name,
                &self.port(),
                ErrorKind::Timeout,
                format!(
                    "still moving after {} ms: raise settle-us in the instrument config",
                    timeout.as_millis()
                ),
            ));
        }
        std::thread::sleep(wait);
        Ok(target)
    }

    fn position(&mut self) -> Result<periscope_drivers::OpticalAngles, GalvoError> {
        self.heard();
        Ok(self.rig.shared.motion(self.arm).1)
    }

    fn status(&mut self) -> Result<GalvoStatus, GalvoError> {
        self.heard();
        let (state, position, _) = self.rig.shared.motion(self.arm);
        Ok(GalvoStatus { state, position })
    }

    fn park(&mut self) -> Result<(), GalvoError> {
        self.heard();
        self.rig.shared.park(self.arm);
        Ok(())
    }

    fn emergency_park(&self) -> EmergencyPark {
        EmergencyPark::new(InProcessPark {
            shared: Arc::downgrade(&self.rig.shared),
            latch: self.park_latch.clone(),
            arm: self.arm,
            name: self.name.clone(),
        })
    }
}

/// The in-process controller's [`ParkLine`]: a call into the controller model, the
/// latch set first.
struct InProcessPark {
    shared: Weak<Shared>,
    latch: Arc<Mutex<bool>>,
    arm: Arm,
    name: String,
}

impl ParkLine for InProcessPark {
    fn park(&self) -> Result<Parked, DeviceError> {
        let mut latch = self.latch.lock().unwrap_or_else(|p| p.into_inner());
        *latch = true;
        let shared = self.shared.upgrade().ok_or_else(|| {
            GalvoError::new(
                &self.name,
                &self.describe(),
                ErrorKind::Disconnected,
                "the simulated instrument is gone",
            )
        })?;
        shared.park(self.arm);
        Ok(Parked::Done)
    }

    fn describe(&self) -> String {
        format!("simulated {} controller (in process)", self.arm.name())
    }
}

impl Laser for InProcessGalvo {
    fn set_emission(&mut self, on: bool) -> Result<(), GalvoError> {
        self.laser_only(if on { "LASER ON" } else { "LASER OFF" })?;
        if on {
            return self.switch_on();
        }
        self.guard.switching_off();
        self.rig
            .shared
            .switch_laser(false)
            .map_err(|code| self.refused("LASER OFF", code))
    }

    fn laser_state(&mut self) -> Result<LaserState, GalvoError> {
        self.laser_only("LSTAT")?;
        let (emission, interlock_closed, diffuser_in) = self.rig.shared.laser_state();
        Ok(LaserState {
            emission,
            interlock_closed,
            diffuser_in,
        })
    }

    fn set_diffuser(&mut self, inserted: bool) -> Result<(), GalvoError> {
        self.laser_only("DIFF")?;
        self.rig.shared.set_diffuser(inserted);
        Ok(())
    }

    fn watch_progress(&mut self, progress: Progress) {
        self.guard.watch_progress(progress);
    }

    fn emergency_off(&self) -> EmergencyOff {
        self.guard.emergency_off()
    }
}

impl GuardedLaser for InProcessGalvo {
    type Error = GalvoError;

    fn guard(&mut self) -> &mut LaserGuard {
        &mut self.guard
    }

    fn arm_watchdog(&mut self, timeout: Duration) -> Result<(), GalvoError> {
        self.rig.shared.laser_watchdog(Some(timeout));
        Ok(())
    }

    fn send_on(&mut self) -> Result<(), GalvoError> {
        self.rig
            .shared
            .switch_laser(true)
            .map_err(|code| self.refused("LASER ON", code))
    }

    fn latched_error(&self) -> GalvoError {
        self.emergency_stopped()
    }
}

/// The in-process laser's out-of-band path: calls into the controller model, which
/// hears a keepalive as the firmware hears a `KEEP` line and switches emission off at
/// once. It outlives the device (the rig keeps the controller), as a controller
/// outlives its host's driver.
struct InProcessLine {
    shared: Weak<Shared>,
    name: String,
}

impl LaserLine for InProcessLine {
    fn feed(&self) -> std::io::Result<()> {
        let shared = self.shared.upgrade().ok_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::NotConnected,
                "the simulated instrument is gone",
            )
        })?;
        shared.lock().heard_host(Instant::now());
        Ok(())
    }

    fn off(&self) -> Result<(), DeviceError> {
        let gone = || {
            GalvoError::new(
                &self.name,
                "simulated controller (in process)",
                ErrorKind::Disconnected,
                "the simulated instrument is gone",
            )
        };
        let shared = self.shared.upgrade().ok_or_else(gone)?;
        shared.switch_laser(false).map_err(|_| gone().into())
    }

    fn try_off(&self) -> bool {
        self.shared.upgrade().is_some_and(|s| s.try_laser_off())
    }

    fn describe(&self) -> String {
        format!("laser on `{}` (in process)", self.name)
    }
}

/// The histogrammer in process.
pub struct InProcessTdc {
    rig: Rig,
    config: Option<(TdcConfig, WireConfig)>,
    /// Acquisitions started (numbers the Poisson draws, as the wire device does).
    acquisitions: u64,
    frames: u32,
    sequence: u32,
    last_rate: f64,
    absent: bool,
}

const TDC_NAME: &str = "simulated histogrammer (in process)";

impl InProcessTdc {
    /// The rig's histogrammer. With its cable out it is absent until the rig lets a
    /// reopen through, as on the wire.
    pub fn new(rig: Rig) -> InProcessTdc {
        InProcessTdc {
            rig,
            config: None,
            acquisitions: 0,
            frames: 0,
            sequence: 0,
            last_rate: 0.0,
            absent: false,
        }
    }

    fn err(kind: ErrorKind, message: impl Into<String>) -> TdcError {
        TdcError::new(TDC_NAME, kind, message)
    }

    /// Fails while the cable is out; a device that was unplugged comes back (with its
    /// settings restored, as the driver restores them) once the rig allows a reopen.
    fn present(&mut self) -> Result<(), TdcError> {
        let mut s = self.rig.shared.lock();
        if std::mem::take(&mut s.tdc_unplugged) {
            self.absent = true;
        }
        if self.absent {
            if s.tdc_unplugged || s.tdc_refused_reopens > 0 {
                s.tdc_refused_reopens = s.tdc_refused_reopens.saturating_sub(1);
                return Err(Self::err(
                    ErrorKind::Disconnected,
                    "unplugged: plug the histogrammer back in",
                ));
            }
            self.absent = false;
        }
        Ok(())
    }
}

impl ErrorType for InProcessTdc {
    type Error = TdcError;
}

impl Histogrammer for InProcessTdc {
    fn identify(&mut self) -> Result<DeviceInfo, TdcError> {
        self.present()?;
        Ok(DeviceInfo {
            model: "PTDC-SIM (in process)".into(),
            firmware: "1.0".into(),
            serial: format!("SIM{:04}", self.rig.shared.settings.seed % 10_000),
            protocol: u32::from(tdc_protocol::PROTOCOL_VERSION),
        })
    }

    fn configure(&mut self, config: &TdcConfig) -> Result<(), TdcError> {
        self.present()?;
        let wire = WireConfig::from_config(config)
            .filter(|w| (1..=tdc_protocol::MAX_BINS).contains(&w.bins) && w.sync_divider >= 1)
            .ok_or_else(|| {
                Self::err(
                    ErrorKind::OutOfRange,
                    format!("the device refused the settings {config:?} (bins, bin width or acquisition time outside its range)"),
                )
            })?;
        self.config = Some((*config, wire));
        Ok(())
    }

    fn config(&self) -> Option<TdcConfig> {
        self.config.map(|(c, _)| c)
    }

    fn acquire(&mut self) -> Result<Histogram, TdcError> {
        self.acquire_until(&|| false)
    }

    fn acquire_until(&mut self, stop: &dyn Fn() -> bool) -> Result<Histogram, TdcError> {
        let (config, wire) = self.config.ok_or_else(|| {
            Self::err(
                ErrorKind::Device,
                "acquire called before configure: the driver has no settings to acquire with",
            )
        })?;
        self.present()?;
        self.acquisitions += 1;
        self.sequence = self.sequence.wrapping_add(1);
        let overflow_fault = {
            let mut s = self.rig.shared.lock();
            let hit = s.tdc_faults.front() == Some(&super::rig::TdcFault::Overflow);
            if hit {
                s.tdc_faults.pop_front();
            }
            hit
        };
        let Measurement { counts, flags, rate } = measure(&self.rig.shared, wire, self.acquisitions);
        // The dwell, in slices a stop interrupts.
        let end = Instant::now() + self.rig.shared.scaled(config.acquisition);
        loop {
            if stop() {
                return Err(Self::err(
                    ErrorKind::Interrupted,
                    format!(
                        "acquisition {} was stopped and aborted on the device",
                        self.sequence
                    ),
                ));
            }
            let left = end.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            std::thread::sleep(left.min(periscope_drivers::tdc::POLL));
        }
        self.present()?;
        self.last_rate = rate;
        self.frames = self.frames.wrapping_add(1);
        Ok(Histogram {
            sequence: self.sequence,
            counts,
            flags: HistogramFlags {
                overflow: flags & flag::OVERFLOW != 0 || overflow_fault,
                saturated: flags & flag::SATURATED != 0,
            },
            config,
        })
    }

    fn abort(&mut self) -> Result<(), TdcError> {
        Ok(())
    }

    fn status(&mut self) -> Result<TdcStatus, TdcError> {
        self.present()?;
        // Whole hertz, as the device reports them on the wire.
        let hz = |r: f64| f64::from(r.min(f64::from(u32::MAX)) as u32);
        Ok(TdcStatus {
            state: TdcState::Idle,
            rates: CountRates {
                sync: self
                    .config
                    .map_or(0.0, |(_, w)| hz(sync_rate(&self.rig.shared, w))),
                detector: hz(self.last_rate),
            },
            acquisitions: self.frames,
        })
    }
}

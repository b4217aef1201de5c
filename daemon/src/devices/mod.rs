//! The device boundary: the instrument's devices opened from its config, as trait
//! objects the pipeline, the run service and the API drive without knowing what is
//! behind them (probe-rs's factory shape: the config picks a [`DeviceBackend`], the
//! rest of the daemon sees the traits and the one [`DeviceError`]):
//!
//! | config | backend | galvo pairs and laser | histogrammer |
//! |---|---|---|---|
//! | `backend = "hardware"` | [`hardware::HardwareBackend`] | serial driver on the configured ports, or a DAQ device's analog outputs and digital lines through NI-DAQmx (`galvo.<arm>.driver = "daqmx"`, [`daqmx`]) | USB driver over libusb, or a PicoQuant counter through its library (`tdc.driver`, [`picoquant`]) |
//! | `backend = "sim"` (`sim.devices = "wire"`) | [`sim::SimBackend`] | serial driver on the simulator's pseudo-terminals | USB driver over the simulator's transport |
//! | `backend = "sim"`, `sim.devices = "in-process"` | [`sim::SimBackend`] | the simulator's controller model, no wire | the simulator's histogrammer, no wire |
//!
//! The first two run the same drivers, so CI runs the code the lab runs. Every laser
//! driver keeps the one `periscope_drivers::LaserGuard`. A new backend is a type that
//! implements [`DeviceBackend`] in a file of its own here, and one more arm of
//! [`backend`]; nothing past this module names a driver type or the simulator (a
//! test in `daemon/tests/architecture.rs` holds that).
use std::any::Any;
use std::sync::Arc;

pub use periscope_drivers::{DeviceError, GalvoBox, HistogrammerBox, LaserBox};
use periscope_drivers::{DeviceInfo, LaserState, TdcStatus};
use serde::Serialize;

use crate::config::{Backend, ConfigError, InstrumentConfig};

pub mod daqmx;
pub mod hardware;
pub mod picoquant;
pub mod sim;

/// A way to the instrument's devices, chosen from the config: one per backend. It
/// opens each device on its own, not yet identified ([`Devices::open`] opens them
/// all); the run service keeps one for the daemon's life, so that runs, e-stops and
/// status readings all reach the same devices.
pub trait DeviceBackend: Any + Send + Sync {
    /// The backend, for logs: `hardware`, `simulated (wire)`, `simulated (in process)`.
    fn name(&self) -> &'static str;
    /// Opens the laser arm's controller: one driver behind its galvo pair and its
    /// laser.
    fn laser_arm(&self) -> Result<LaserArm, OpenError>;
    /// Opens the SPAD arm's galvo pair.
    fn spad_arm(&self) -> Result<GalvoBox, OpenError>;
    /// Opens the histogrammer.
    fn histogrammer(&self) -> Result<HistogrammerBox, OpenError>;
}

/// The backend the instrument config names: [`hardware::HardwareBackend`] for
/// `backend = "hardware"`, a fresh simulated instrument ([`sim::SimBackend`]) for
/// `backend = "sim"`.
pub fn backend(config: &InstrumentConfig) -> Result<Arc<dyn DeviceBackend>, ConfigError> {
    Ok(match &config.backend {
        Backend::Hardware => Arc::new(hardware::HardwareBackend::new(config)),
        Backend::Sim(sim) => Arc::new(sim::SimBackend::new(config, sim)?),
    })
}

/// Why the devices could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The config is missing something the back-end needs.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A key the hardware back-end needs is missing.
    #[error("{0}")]
    Missing(String),
    /// A device failed or did not answer.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// A step of making the instrument safe failed ([`Devices::make_safe`]).
    #[error("{step}: {source}; {remedy}")]
    Unsafe {
        /// Which step, in words.
        step: &'static str,
        /// What the operator should do.
        remedy: &'static str,
        /// The device's error.
        source: DeviceError,
    },
    /// Opening was interrupted (pause, abort or e-stop) before every device was open.
    #[error("opening the devices was interrupted")]
    Interrupted,
    /// The TDC's USB device was not found.
    #[error(
        "histogrammer {selector}: {why}; plug it in and check `periscope devices` and `tdc.usb` in the instrument config"
    )]
    Usb {
        /// The configured selector.
        selector: String,
        /// What libusb said.
        why: String,
    },
}

/// Refuses a pair whose configured limits reach past its controller's own: every
/// target there would be refused by the controller mid-run (its `ERR`), hours into a
/// capture, naming the controller rather than the key.
fn within_hard_limits(name: &str, arm: &mut GalvoBox) -> Result<(), OpenError> {
    let Some(hard) = arm.hard_limits()? else {
        return Ok(());
    };
    let conf = arm.limits();
    // The protocol gives limits to 10⁻⁷ rad; a thousandth of a degree of slack.
    let slack = 1e-3f64.to_radians();
    let within = |c: [f64; 2], h: [f64; 2]| c[0] >= h[0] - slack && c[1] <= h[1] + slack;
    if within(conf.x, hard.x) && within(conf.y, hard.y) {
        return Ok(());
    }
    let deg = |r: [f64; 2]| format!("[{:.3}, {:.3}]", r[0].to_degrees(), r[1].to_degrees());
    Err(OpenError::Missing(format!(
        "galvo.{name}.angle-limits-deg (x {}, y {}) reach past the controller's own hard limits (x {}, y {}): narrow them to within the controller's",
        deg(conf.x),
        deg(conf.y),
        deg(hard.x),
        deg(hard.y)
    )))
}

/// What to do about an arm that did not park as the instrument was made safe.
const PARK_BY_HAND: &str = "the laser is off; park the arm with the e-stop (`POST /api/v1/estop`, the dashboard's button) or at its controller";

/// The instrument's devices, opened.
pub struct Devices {
    /// Laser arm galvo pair.
    pub laser_arm: GalvoBox,
    /// The laser and the LOS diffuser (on the laser arm's controller: the two share
    /// it).
    pub laser: LaserBox,
    /// SPAD arm galvo pair.
    pub spad: GalvoBox,
    /// The histogrammer.
    pub tdc: HistogrammerBox,
}

/// The laser arm's controller opened on its own: its galvo pair and its laser.
pub struct LaserArm {
    /// The galvo pair.
    pub arm: GalvoBox,
    /// The laser.
    pub laser: LaserBox,
}

impl Devices {
    /// Opens every device the config names and identifies each (a fresh simulated
    /// instrument for `sim`).
    pub fn open_config(config: &InstrumentConfig) -> Result<Devices, OpenError> {
        Devices::open(backend(config)?.as_ref(), &|| false)
    }

    /// Opens every device of `backend`, identifying each, and switches off a laser it
    /// finds emitting (with a warning); `stop` is asked between devices and opening
    /// gives up with [`OpenError::Interrupted`] when it says so.
    pub fn open(backend: &dyn DeviceBackend, stop: &dyn Fn() -> bool) -> Result<Devices, OpenError> {
        let interrupted = || {
            if stop() {
                Err(OpenError::Interrupted)
            } else {
                Ok(())
            }
        };
        interrupted()?;
        let LaserArm {
            arm: mut laser_arm,
            mut laser,
        } = backend.laser_arm()?;
        // Opening the instrument leaves the laser off, and sees to it before anything
        // that can refuse the controller. A laser found emitting was left on by a
        // process that ended without switching it off (a crash or `kill -9` with a
        // watchdog longer than the restart took, or another program); every request
        // feeds the controller's watchdog, so without this the idle worker's readings
        // (or its retries of an open the config's limits refuse) would keep such a
        // laser on for as long as the daemon runs. A state that cannot be read is
        // switched off all the same.
        let found = laser.laser_state();
        if !matches!(found, Ok(ref s) if !s.emission) {
            if found.is_ok() {
                tracing::warn!(
                    "the laser was emitting when Periscope opened its controller, with no run of \
                     this process measuring (left on by a process that ended without switching \
                     it off?); switching it off"
                );
            }
            let off = laser.set_emission(false);
            if found.is_err() || off.is_err() {
                // A controller that does not answer as this protocol expects is most
                // often one of another version: identifying it says so, with what to
                // do, where the state's parse error would not.
                laser_arm.identify()?;
            }
            found?;
            off?;
        }
        laser_arm.identify()?;
        within_hard_limits("laser", &mut laser_arm)?;
        interrupted()?;
        let mut spad = backend.spad_arm()?;
        spad.identify()?;
        within_hard_limits("spad", &mut spad)?;
        interrupted()?;
        let mut tdc = backend.histogrammer()?;
        tdc.identify()?;
        interrupted()?;
        Ok(Devices {
            laser_arm,
            laser,
            spad,
            tdc,
        })
    }

    /// Everything the devices report about themselves.
    pub fn report(&mut self) -> Result<DeviceReport, OpenError> {
        Ok(DeviceReport {
            laser_arm: self.laser_arm.identify()?,
            laser_position: self.laser_arm.position()?,
            laser: self.laser.laser_state()?,
            spad_arm: self.spad.identify()?,
            spad_position: self.spad.position()?,
            tdc: self.tdc.identify()?,
            tdc_status: self.tdc.status()?,
        })
    }

    /// Laser off and both pairs parked: the safe state. The laser goes first (out of
    /// band, then confirmed), every step is tried even if an earlier one fails, and the
    /// first failure is returned, naming the step and what to do. The histogrammer's
    /// measurement is stopped last and is not part of the safe state: a counter gone
    /// from the bus (whose abort waits out its timeout) neither delays the parks nor
    /// makes a laser that is off and arms that are parked read as unsafe; its failure
    /// is a warning.
    pub fn make_safe(&mut self) -> Result<(), OpenError> {
        let off = self.laser.set_emission(false);
        let lp = self.laser_arm.park();
        let sp = self.spad.park();
        if let Err(e) = self.tdc.abort() {
            tracing::warn!(
                error = %e,
                "the histogrammer was not told to stop measuring as the instrument was made safe \
                 (the laser and the arms do not depend on it); check it with `periscope devices`"
            );
        }
        let unsafe_at = |step: &'static str, remedy: &'static str| {
            move |source| OpenError::Unsafe { step, remedy, source }
        };
        off.map_err(unsafe_at(
            "the laser did not confirm it switched off",
            "switch it off by hand (its key switch or the interlock) and check its controller",
        ))?;
        lp.map_err(unsafe_at("the laser arm did not park", PARK_BY_HAND))?;
        sp.map_err(unsafe_at("the SPAD arm did not park", PARK_BY_HAND))?;
        Ok(())
    }
}

/// What `periscope devices` prints for the configured instrument.
#[derive(Clone, Debug, Serialize)]
pub struct DeviceReport {
    /// Laser arm controller.
    pub laser_arm: DeviceInfo,
    /// Its position.
    pub laser_position: periscope_drivers::OpticalAngles,
    /// Laser, interlock and diffuser.
    pub laser: LaserState,
    /// SPAD arm controller.
    pub spad_arm: DeviceInfo,
    /// Its position.
    pub spad_position: periscope_drivers::OpticalAngles,
    /// Histogrammer.
    pub tdc: DeviceInfo,
    /// Its state and count rates.
    pub tdc_status: TdcStatus,
}

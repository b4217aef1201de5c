//! Opening the instrument's devices from its config, as trait objects the pipeline
//! drives without knowing what is behind them (probe-rs's factory shape: the config
//! picks the implementation, the rest of the daemon sees the traits):
//!
//! | config | galvo pairs and laser | histogrammer |
//! |---|---|---|
//! | `backend = "hardware"` | serial driver on the configured ports | USB driver over libusb |
//! | `backend = "sim"` (`sim.devices = "wire"`) | serial driver on the simulator's pseudo-terminals | USB driver over the simulator's transport |
//! | `backend = "sim"`, `sim.devices = "in-process"` | the simulator's controller model, no wire | the simulator's histogrammer, no wire |
//!
//! The first two run the same drivers, so CI runs the code the lab runs. A new driver
//! is one more arm of `open_galvo`, `open_laser_arm` or `open_histogrammer`.
use std::time::Duration;

use periscope_drivers::galvo::{GalvoError, PortConnector, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::{RusbTransport, TdcError, UsbTdc, UsbTransport};
use periscope_drivers::{DeviceInfo, GalvoPair, Histogrammer, Laser, LaserState, Shared, TdcStatus};
use periscope_sim::World;
use periscope_sim::devices::{Arm, Rig, RigSettings};
use serde::Serialize;

use crate::config::{Backend, ConfigError, GalvoArm, InstrumentConfig, SimDevices, TomlSource, sim_scene};

/// A galvo pair, whatever drives it.
pub type GalvoBox = Box<dyn GalvoPair<Error = GalvoError> + Send>;
/// A laser, whatever drives it.
pub type LaserBox = Box<dyn Laser<Error = GalvoError> + Send>;
/// A histogrammer, whatever drives it.
pub type HistogrammerBox = Box<dyn Histogrammer<Error = TdcError> + Send>;

/// Reply timeout of the simulated controllers' links.
const SIM_TIMEOUT: Duration = Duration::from_millis(500);

/// Slack the histogrammer driver allows beyond the acquisition time.
const TDC_TIMEOUT: Duration = Duration::from_millis(1000);

/// Why the devices could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The config is missing something the back-end needs.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// A key the hardware back-end needs is missing.
    #[error("{0}")]
    Missing(String),
    /// A galvo controller did not answer.
    #[error(transparent)]
    Galvo(#[from] GalvoError),
    /// The histogrammer could not be opened.
    #[error(transparent)]
    Tdc(#[from] TdcError),
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
    /// The simulated instrument behind them, when the back-end is `sim`.
    pub rig: Option<Rig>,
}

/// The laser arm's controller opened on its own: its galvo pair and its laser.
pub struct LaserArm {
    /// The galvo pair.
    pub arm: GalvoBox,
    /// The laser.
    pub laser: LaserBox,
}

fn galvo_settings(
    name: &str,
    arm: &GalvoArm,
    timeout: Duration,
    watchdog: Option<Duration>,
) -> SerialGalvoSettings {
    SerialGalvoSettings {
        name: name.into(),
        limits: arm.limits,
        timeout,
        settle: arm.settle,
        watchdog,
    }
}

/// Most hidden-surface samples a simulated scene may need (about 1.5 GB of samples).
const MAX_HIDDEN_SAMPLES: f64 = 2e7;

/// Builds the simulated instrument for a `sim` config: scene physics and devices.
pub fn sim_rig(config: &InstrumentConfig) -> Result<Option<Rig>, ConfigError> {
    let Backend::Sim(sim) = &config.backend else {
        return Ok(None);
    };
    let scene = sim_scene(sim)?;
    // The third bounce samples hidden surfaces every `sample-spacing`: bound the count
    // before anything is allocated (a scene file is a file from someone else).
    let area: f64 = scene.hidden.iter().map(|s| s.mesh.total_area()).sum();
    let samples = area / (sim.sample_spacing * sim.sample_spacing);
    if !(samples <= MAX_HIDDEN_SAMPLES) {
        let path = sim.scene.clone().unwrap_or_else(|| "<built-in scene>".into());
        return Err(TomlSource::from_text(path, "").invalid(
            "sim.sample-spacing-mm",
            format!(
                "the hidden surfaces ({area:.3e} m²) need {samples:.3e} samples at {} mm, more than {MAX_HIDDEN_SAMPLES:.0e}: \
                 use a coarser spacing or smaller hidden objects",
                sim.sample_spacing * 1e3
            ),
        ));
    }
    let world = World::new(scene, sim.sample_spacing, sim.seed);
    Ok(Some(Rig::new(
        Some(world),
        RigSettings {
            laser_pose: config.laser_arm.pose,
            spad_pose: config.spad_arm.pose,
            limits: [config.laser_arm.limits, config.spad_arm.limits],
            settle: [config.laser_arm.settle, config.spad_arm.settle],
            detector: config.sim_detector(sim),
            time_scale: sim.time_scale,
            seed: sim.seed,
            interlock_closed: sim.interlock_closed,
        },
    )))
}

/// Whether the simulated arm is reached in process: `sim.devices = "in-process"` and
/// no `serial` table of its own.
fn in_process_arm(config: &InstrumentConfig, arm: Arm, rig: Option<&Rig>) -> Option<Rig> {
    let a = match arm {
        Arm::Laser => &config.laser_arm,
        Arm::Spad => &config.spad_arm,
    };
    match (&config.backend, rig) {
        (Backend::Sim(sim), Some(rig)) if sim.devices == SimDevices::InProcess && a.serial.is_none() => {
            Some(rig.clone())
        }
        _ => None,
    }
}

/// Opens the SPAD arm's (or any plain) galvo pair, not yet identified.
fn open_galvo(config: &InstrumentConfig, arm: Arm, rig: Option<&Rig>) -> Result<GalvoBox, OpenError> {
    let limits = match arm {
        Arm::Laser => config.laser_arm.limits,
        Arm::Spad => config.spad_arm.limits,
    };
    Ok(match in_process_arm(config, arm, rig) {
        Some(rig) => Box::new(rig.in_process_galvo(arm, limits, None)),
        None => Box::new(serial_galvo(config, arm, rig)?),
    })
}

/// Opens the laser arm's controller, not yet identified: one driver behind both its
/// galvo pair and its laser.
fn open_laser_arm(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<LaserArm, OpenError> {
    Ok(match in_process_arm(config, Arm::Laser, rig) {
        Some(rig) => {
            let shared = Shared::new(rig.in_process_galvo(
                Arm::Laser,
                config.laser_arm.limits,
                Some(config.laser.watchdog),
            ));
            LaserArm {
                arm: Box::new(shared.clone()),
                laser: Box::new(shared),
            }
        }
        None => {
            let shared = Shared::new(serial_galvo(config, Arm::Laser, rig)?);
            LaserArm {
                arm: Box::new(shared.clone()),
                laser: Box::new(shared),
            }
        }
    })
}

/// Opens one galvo controller's serial driver (not yet connected). In the simulator
/// an arm with a `serial` table talks to that port (a real controller, or one
/// simulated in another process) instead of the built-in firmware.
fn serial_galvo(config: &InstrumentConfig, arm: Arm, rig: Option<&Rig>) -> Result<SerialGalvo, OpenError> {
    let (name, a, watchdog) = match arm {
        Arm::Laser => ("laser", &config.laser_arm, Some(config.laser.watchdog)),
        Arm::Spad => ("spad", &config.spad_arm, None),
    };
    let connector: Box<dyn periscope_drivers::galvo::Connector> = match (&a.serial, rig) {
        (Some(link), _) => Box::new(PortConnector {
            path: link.port.clone(),
            baud: link.baud,
        }),
        (None, Some(rig)) => Box::new(rig.galvo_connector(arm)),
        (None, None) => {
            return Err(OpenError::Missing(format!(
                "galvo.{name}.serial is required with backend = \"hardware\": give the port, e.g. serial = {{ port = \"/dev/ttyUSB0\", baud = 115200, timeout-ms = 200 }}"
            )));
        }
    };
    let timeout = a.serial.as_ref().map_or(SIM_TIMEOUT, |l| l.timeout);
    Ok(SerialGalvo::new(
        galvo_settings(name, a, timeout, watchdog),
        connector,
    ))
}

/// Opens the histogrammer.
fn open_histogrammer(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<HistogrammerBox, OpenError> {
    if let (Backend::Sim(sim), Some(rig)) = (&config.backend, rig)
        && sim.devices == SimDevices::InProcess
    {
        return Ok(Box::new(rig.in_process_tdc()));
    }
    let transport: Box<dyn UsbTransport> = match rig {
        Some(rig) => Box::new(rig.tdc_transport()),
        None => {
            let selector = config.tdc.usb.clone().ok_or_else(|| {
                OpenError::Missing(
                    "tdc.usb is required with backend = \"hardware\": give the histogrammer's VID:PID".into(),
                )
            })?;
            Box::new(RusbTransport::open(selector.clone()).map_err(|e| OpenError::Usb {
                selector: selector.to_string(),
                why: e.to_string(),
            })?)
        }
    };
    Ok(Box::new(UsbTdc::open(transport, TDC_TIMEOUT)?))
}

impl Devices {
    /// Opens every device and identifies it (a fresh simulated instrument for `sim`).
    pub fn open(config: &InstrumentConfig) -> Result<Devices, OpenError> {
        Devices::open_on(config, sim_rig(config)?, &|| false)
    }

    /// Opens every device on `rig` (the simulated instrument a caller keeps across
    /// runs; `None` for hardware), identifying each, and switches off a laser it finds
    /// emitting (with a warning); `stop` is asked between devices and opening gives up
    /// with [`OpenError::Interrupted`] when it says so.
    pub fn open_on(
        config: &InstrumentConfig,
        rig: Option<Rig>,
        stop: &dyn Fn() -> bool,
    ) -> Result<Devices, OpenError> {
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
        } = open_laser_arm(config, rig.as_ref())?;
        laser_arm.identify()?;
        // Opening the instrument leaves the laser off. A laser found emitting was left
        // on by a process that ended without switching it off (a crash or `kill -9`
        // with a watchdog longer than the restart took, or another program); every
        // request feeds the controller's watchdog, so without this the idle worker's
        // readings would keep such a laser on for as long as the daemon runs.
        if laser.laser_state()?.emission {
            tracing::warn!(
                "the laser was emitting when Periscope opened its controller, with no run of this \
                 process measuring (left on by a process that ended without switching it off?); \
                 switching it off"
            );
            laser.set_emission(false)?;
        }
        interrupted()?;
        let mut spad = open_galvo(config, Arm::Spad, rig.as_ref())?;
        spad.identify()?;
        interrupted()?;
        let mut tdc = open_histogrammer(config, rig.as_ref())?;
        tdc.identify()?;
        interrupted()?;
        Ok(Devices {
            laser_arm,
            laser,
            spad,
            tdc,
            rig,
        })
    }

    /// Opens the laser arm's controller alone (the e-stop's way to the laser when no
    /// run holds the devices: it needs neither the SPAD arm nor the histogrammer).
    pub fn laser_controller(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<LaserArm, OpenError> {
        open_laser_arm(config, rig)
    }

    /// Opens the SPAD arm's controller alone (to park it).
    pub fn spad_controller(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<GalvoBox, OpenError> {
        open_galvo(config, Arm::Spad, rig)
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
    /// first failure is returned.
    pub fn make_safe(&mut self) -> Result<(), OpenError> {
        let off = self.laser.set_emission(false);
        let abort = self.tdc.abort();
        let lp = self.laser_arm.park();
        let sp = self.spad.park();
        off?;
        lp?;
        sp?;
        abort?;
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

//! Opening the instrument's devices from its config: the real drivers, over real
//! ports and libusb for `backend = "hardware"`, or over the simulator's
//! pseudo-terminals and USB transport for `backend = "sim"`. Either way the daemon
//! gets the same driver types, so the pipeline runs the same code in the lab and in CI.
use std::time::Duration;

use periscope_drivers::galvo::{GalvoError, PortConnector, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::{RusbTransport, TdcError, UsbTdc, UsbTransport};
use periscope_drivers::{DeviceInfo, GalvoPair, Histogrammer, Laser, LaserState, TdcStatus};
use periscope_sim::World;
use periscope_sim::devices::{Arm, Rig, RigSettings};
use serde::Serialize;

use crate::config::{Backend, ConfigError, GalvoArm, InstrumentConfig, TomlSource, sim_scene};

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
    /// Laser arm: its galvo pair, the laser and the LOS diffuser.
    pub laser: SerialGalvo,
    /// SPAD arm galvo pair.
    pub spad: SerialGalvo,
    /// The histogrammer.
    pub tdc: UsbTdc<Box<dyn UsbTransport>>,
    /// The simulated instrument behind them, when the back-end is `sim`.
    pub rig: Option<Rig>,
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

/// Opens one galvo controller's driver (not yet connected). In the simulator an arm
/// with a `serial` table talks to that port (a real controller, or one simulated in
/// another process) instead of the built-in firmware.
fn galvo(config: &InstrumentConfig, arm: Arm, rig: Option<&Rig>) -> Result<SerialGalvo, OpenError> {
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

/// Opens the histogrammer's driver.
fn tdc(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<UsbTdc<Box<dyn UsbTransport>>, OpenError> {
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
    Ok(UsbTdc::open(transport, TDC_TIMEOUT)?)
}

impl Devices {
    /// Opens every device and identifies it (a fresh simulated instrument for `sim`).
    pub fn open(config: &InstrumentConfig) -> Result<Devices, OpenError> {
        Devices::open_on(config, sim_rig(config)?, &|| false)
    }

    /// Opens every device on `rig` (the simulated instrument a caller keeps across
    /// runs; `None` for hardware), identifying each; `stop` is asked between devices
    /// and opening gives up with [`OpenError::Interrupted`] when it says so.
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
        let mut laser = galvo(config, Arm::Laser, rig.as_ref())?;
        laser.identify()?;
        interrupted()?;
        let mut spad = galvo(config, Arm::Spad, rig.as_ref())?;
        spad.identify()?;
        interrupted()?;
        let mut tdc = tdc(config, rig.as_ref())?;
        tdc.identify()?;
        interrupted()?;
        Ok(Devices {
            laser,
            spad,
            tdc,
            rig,
        })
    }

    /// Opens the laser arm's controller alone (the e-stop's way to the laser when no
    /// run holds the devices: it needs neither the SPAD arm nor the histogrammer).
    pub fn laser_controller(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<SerialGalvo, OpenError> {
        galvo(config, Arm::Laser, rig)
    }

    /// Opens the SPAD arm's controller alone (to park it).
    pub fn spad_controller(config: &InstrumentConfig, rig: Option<&Rig>) -> Result<SerialGalvo, OpenError> {
        galvo(config, Arm::Spad, rig)
    }

    /// Everything the devices report about themselves.
    pub fn report(&mut self) -> Result<DeviceReport, OpenError> {
        Ok(DeviceReport {
            laser_arm: self.laser.identify()?,
            laser_position: self.laser.position()?,
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
        let lp = self.laser.park();
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

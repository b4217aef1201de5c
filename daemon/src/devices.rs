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

use crate::config::{Backend, ConfigError, GalvoArm, InstrumentConfig, sim_scene};

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

fn galvo_settings(name: &str, arm: &GalvoArm, timeout: Duration) -> SerialGalvoSettings {
    SerialGalvoSettings {
        name: name.into(),
        limits: arm.limits,
        timeout,
        settle: arm.settle,
    }
}

/// Builds the simulated instrument for a `sim` config: scene physics and devices.
pub fn sim_rig(config: &InstrumentConfig) -> Result<Option<Rig>, ConfigError> {
    let Backend::Sim(sim) = &config.backend else {
        return Ok(None);
    };
    let scene = sim_scene(sim)?;
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

impl Devices {
    /// Opens every device and identifies it.
    pub fn open(config: &InstrumentConfig) -> Result<Devices, OpenError> {
        let mut devices = match sim_rig(config)? {
            Some(rig) => Devices {
                laser: SerialGalvo::new(
                    galvo_settings("laser", &config.laser_arm, SIM_TIMEOUT),
                    Box::new(rig.galvo_connector(Arm::Laser)),
                ),
                spad: SerialGalvo::new(
                    galvo_settings("spad", &config.spad_arm, SIM_TIMEOUT),
                    Box::new(rig.galvo_connector(Arm::Spad)),
                ),
                tdc: UsbTdc::new(Box::new(rig.tdc_transport()), TDC_TIMEOUT),
                rig: Some(rig),
            },
            None => {
                let port = |arm: &GalvoArm, key: &str| {
                    arm.serial.clone().ok_or_else(|| {
                        OpenError::Missing(format!(
                            "galvo.{key}.serial is required with backend = \"hardware\": give the port, e.g. serial = {{ port = \"/dev/ttyUSB0\", baud = 115200, timeout-ms = 200 }}"
                        ))
                    })
                };
                let (lp, sp) = (port(&config.laser_arm, "laser")?, port(&config.spad_arm, "spad")?);
                let selector = config.tdc.usb.clone().ok_or_else(|| {
                    OpenError::Missing(
                        "tdc.usb is required with backend = \"hardware\": give the histogrammer's VID:PID"
                            .into(),
                    )
                })?;
                let transport = RusbTransport::open(selector.clone()).map_err(|e| OpenError::Usb {
                    selector: selector.to_string(),
                    why: e.to_string(),
                })?;
                Devices {
                    laser: SerialGalvo::new(
                        galvo_settings("laser", &config.laser_arm, lp.timeout),
                        Box::new(PortConnector {
                            path: lp.port,
                            baud: lp.baud,
                        }),
                    ),
                    spad: SerialGalvo::new(
                        galvo_settings("spad", &config.spad_arm, sp.timeout),
                        Box::new(PortConnector {
                            path: sp.port,
                            baud: sp.baud,
                        }),
                    ),
                    tdc: UsbTdc::new(Box::new(transport), TDC_TIMEOUT),
                    rig: None,
                }
            }
        };
        devices.laser.identify()?;
        devices.spad.identify()?;
        devices.tdc.identify()?;
        Ok(devices)
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

    /// Laser off and both pairs parked: the safe state. Tries every step even if one
    /// fails, and returns the first failure.
    pub fn make_safe(&mut self) -> Result<(), OpenError> {
        let off = self.laser.set_emission(false);
        let lp = self.laser.park();
        let sp = self.spad.park();
        off?;
        lp?;
        sp?;
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

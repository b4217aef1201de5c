//! The lab backend: each galvo pair on what its `driver` names (the serial galvo
//! driver on the configured port, or two analog outputs of an NI DAQ device through
//! NI-DAQmx, `daqmx.rs`, with the laser's lines on the same device), and the
//! histogrammer `tdc.driver` picks: the USB histogrammer driver over libusb, or a
//! PicoQuant counter through its vendor library (`picoquant.rs`). The simulated backend reuses the pieces here
//! that build these drivers, so that it runs the very drivers the lab runs.
use std::time::Duration;

use periscope_drivers::galvo::{Connector, PortConnector, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::{RusbTransport, UsbTdc, UsbTransport};
use periscope_drivers::{DeviceError, Erased, GalvoBox, GalvoPair, HistogrammerBox, Laser, Shared};

use super::{DeviceBackend, LaserArm, OpenError};
use crate::config::{GalvoArm, GalvoLink, InstrumentConfig, TdcDriver};

/// Reply timeout of a controller link with no `serial` table of its own (the
/// simulator's pseudo-terminals).
const DEFAULT_TIMEOUT: Duration = Duration::from_millis(500);

/// Slack the histogrammer driver allows beyond the acquisition time.
const TDC_TIMEOUT: Duration = Duration::from_millis(1000);

/// Which of the two galvo arms.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Role {
    /// The laser arm (its controller also drives the laser and the diffuser).
    Laser,
    /// The SPAD arm.
    Spad,
}

impl Role {
    /// The arm's name in messages and its table in the config; on the laser arm, the
    /// watchdog to arm before each switch-on.
    fn of(self, config: &InstrumentConfig) -> (&'static str, &GalvoArm, Option<Duration>) {
        match self {
            Role::Laser => ("laser", &config.laser_arm, Some(config.laser.watchdog)),
            Role::Spad => ("spad", &config.spad_arm, None),
        }
    }

    /// The arm's table in the config.
    pub(super) fn arm(self, config: &InstrumentConfig) -> &GalvoArm {
        self.of(config).1
    }
}

/// The lab's devices: every one on the port or USB selector its config names.
pub struct HardwareBackend {
    config: InstrumentConfig,
}

impl HardwareBackend {
    /// The devices of `config` (opened when asked for, not now).
    pub fn new(config: &InstrumentConfig) -> HardwareBackend {
        HardwareBackend {
            config: config.clone(),
        }
    }
}

impl DeviceBackend for HardwareBackend {
    fn name(&self) -> &'static str {
        "hardware"
    }

    fn laser_arm(&self) -> Result<LaserArm, OpenError> {
        if let Some(GalvoLink::Daqmx(arm)) = &self.config.laser_arm.link {
            return super::daqmx::laser_arm(&self.config, arm);
        }
        Ok(laser_arm(serial_galvo(&self.config, Role::Laser, None)?))
    }

    fn spad_arm(&self) -> Result<GalvoBox, OpenError> {
        if let Some(GalvoLink::Daqmx(arm)) = &self.config.spad_arm.link {
            return super::daqmx::galvo(arm);
        }
        Ok(Erased::galvo(serial_galvo(&self.config, Role::Spad, None)?))
    }

    fn histogrammer(&self) -> Result<HistogrammerBox, OpenError> {
        if let TdcDriver::PicoQuant(counter) = &self.config.tdc.driver {
            return super::picoquant::histogrammer(counter);
        }
        let selector = self.config.tdc.usb.clone().ok_or_else(|| {
            OpenError::Missing(
                "tdc.usb is required with backend = \"hardware\": give the histogrammer's VID:PID".into(),
            )
        })?;
        let transport = RusbTransport::open(selector.clone()).map_err(|e| OpenError::Usb {
            selector: selector.to_string(),
            why: e.to_string(),
        })?;
        usb_histogrammer(Box::new(transport))
    }
}

/// The laser arm's one controller behind both its traits.
pub(super) fn laser_arm<T>(driver: T) -> LaserArm
where
    T: GalvoPair + Laser + Send + 'static,
    <T as periscope_drivers::ErrorType>::Error: Into<DeviceError>,
{
    let shared = Shared::new(driver);
    LaserArm {
        arm: Erased::galvo(shared.clone()),
        laser: Erased::laser(shared),
    }
}

/// One galvo controller's serial driver (not yet connected): on the arm's `serial`
/// port when the config gives one, else on `fallback` (the simulator's
/// pseudo-terminal).
pub(super) fn serial_galvo(
    config: &InstrumentConfig,
    role: Role,
    fallback: Option<Box<dyn Connector>>,
) -> Result<SerialGalvo, OpenError> {
    let (name, arm, watchdog) = role.of(config);
    let connector: Box<dyn Connector> = match (arm.serial(), fallback) {
        (Some(link), _) => Box::new(PortConnector {
            path: link.port.clone(),
            baud: link.baud,
        }),
        (None, Some(connector)) => connector,
        (None, None) => {
            return Err(OpenError::Missing(format!(
                "galvo.{name}.serial is required with backend = \"hardware\": give the port, e.g. serial = {{ port = \"/dev/ttyUSB0\", baud = 115200, timeout-ms = 200 }}"
            )));
        }
    };
    let timeout = arm.serial().map_or(DEFAULT_TIMEOUT, |l| l.timeout);
    Ok(SerialGalvo::new(
        SerialGalvoSettings {
            name: name.into(),
            limits: arm.limits,
            timeout,
            settle: arm.settle,
            watchdog,
        },
        connector,
    ))
}

/// The USB histogrammer driver over `transport`.
pub(super) fn usb_histogrammer(transport: Box<dyn UsbTransport>) -> Result<HistogrammerBox, OpenError> {
    let tdc = UsbTdc::open(transport, TDC_TIMEOUT).map_err(DeviceError::from)?;
    Ok(Erased::histogrammer(tdc))
}

//! Galvo pairs and the laser on an NI DAQ device (`galvo.<arm>.driver = "daqmx"`):
//! the drivers opened from the config's galvo tables and `[laser]` lines, and the
//! survey `periscope devices` prints (which devices NI-DAQmx sees, what the configured
//! lines do, or plainly that the library is not there).
use std::path::PathBuf;

use periscope_drivers::daqmx::{self, AoGalvoSettings, DaqGalvo, DaqLaser};
use periscope_drivers::{DeviceError, Erased, GalvoBox};

use super::{LaserArm, OpenError};
use crate::config::{GalvoLink, InstrumentConfig};

/// Opens a galvo pair on two analog outputs.
pub(super) fn galvo(settings: &AoGalvoSettings) -> Result<GalvoBox, OpenError> {
    let galvo = DaqGalvo::open(settings.clone()).map_err(DeviceError::from)?;
    Ok(Erased::galvo(galvo))
}

/// Opens the laser arm on a DAQ device: its pair and the laser's lines (two drivers on
/// one device, unlike the serial controller which is one driver behind both traits).
pub(super) fn laser_arm(config: &InstrumentConfig, arm: &AoGalvoSettings) -> Result<LaserArm, OpenError> {
    let lines = config.laser.daqmx.clone().ok_or_else(|| {
        OpenError::Missing("the laser arm is on a DAQ device but [laser] names no laser-line".into())
    })?;
    let laser = DaqLaser::open(lines).map_err(DeviceError::from)?;
    Ok(LaserArm {
        arm: galvo(arm)?,
        laser: Erased::laser(laser),
    })
}

/// The libraries the config's DAQmx pairs name (one, as a rule).
fn libraries(config: &InstrumentConfig) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = Vec::new();
    for arm in [&config.laser_arm, &config.spad_arm] {
        if let Some(GalvoLink::Daqmx(s)) = &arm.link
            && !out.contains(&s.library)
        {
            out.push(s.library.clone());
        }
    }
    out
}

/// What `periscope devices` says about NI-DAQmx, when the config uses it: per library,
/// the devices it knows, or why it could not be used; then the configured lines, and
/// whether the interlock is read.
pub fn survey(config: &InstrumentConfig) -> Vec<String> {
    let mut lines = Vec::new();
    for library in libraries(config) {
        match daqmx::survey(&library) {
            Err(e) => lines.push(e.to_string()),
            Ok(found) => {
                lines.push(format!(
                    "NI-DAQmx at {}: {} device{}",
                    library.display(),
                    found.devices.len(),
                    if found.devices.len() == 1 { "" } else { "s" }
                ));
                for (name, model, serial) in found.devices {
                    lines.push(format!("  {name}  {model}  serial {serial}"));
                }
            }
        }
    }
    for (name, arm) in [("laser", &config.laser_arm), ("spad", &config.spad_arm)] {
        if let Some(GalvoLink::Daqmx(s)) = &arm.link {
            lines.push(format!(
                "galvo.{name}: x on {}, y on {}",
                s.channels[0], s.channels[1]
            ));
        }
    }
    if let Some(l) = &config.laser.daqmx {
        lines.push(format!("laser gate on {}", l.laser_line));
        lines.push(match &l.interlock_line {
            Some(i) => format!("interlock read on {i}"),
            None => "interlock: no interlock-line, so it is not read and counts as closed".into(),
        });
        lines.push(match (l.hardware_watchdog, &l.heartbeat_line) {
            (true, _) => format!(
                "watchdog: the device's hardware watchdog timer, {} ms, drives the gate low",
                l.watchdog.as_millis()
            ),
            (false, Some(h)) => format!("watchdog: an external relay fed by toggling {h}"),
            (false, None) => "watchdog: NONE (accept-no-watchdog = true)".into(),
        });
    }
    lines
}

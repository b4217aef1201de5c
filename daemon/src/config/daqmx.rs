//! The instrument config's NI-DAQmx keys: a galvo pair on two analog outputs
//! (`[galvo.laser]`/`[galvo.spad]` with `driver = "daqmx"`) and the laser's digital
//! lines (`[laser]`), validated into types the driver takes as they are. Kept apart
//! from `instrument.rs`, which calls these with the raw keys it parsed.
use std::path::PathBuf;

use periscope_drivers::AngleLimits;
use periscope_drivers::daqmx::{AoGalvoSettings, DEFAULT_LIBRARY, DaqLaserSettings};
use serde::Deserialize;

use super::{ConfigError, TomlSource};

/// A galvo table's `driver`.
#[derive(Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
#[serde(rename_all = "kebab-case")]
pub(super) enum RawGalvoDriver {
    /// A galvo controller on a serial port (the default).
    #[default]
    Serial,
    /// Two analog outputs of an NI DAQ device.
    Daqmx,
}

/// A galvo table's DAQmx keys, as parsed.
#[derive(Default)]
pub(super) struct RawDaqGalvo {
    pub channels: Option<[String; 2]>,
    pub volts_per_deg: Option<[f64; 2]>,
    pub offsets_v: Option<[f64; 2]>,
    pub max_slew_deg_per_ms: Option<f64>,
    pub library: Option<PathBuf>,
}

impl RawDaqGalvo {
    /// The keys given, by name (for refusing them with the serial driver).
    pub(super) fn given(&self) -> Vec<&'static str> {
        [
            ("channels", self.channels.is_some()),
            ("volts-per-deg", self.volts_per_deg.is_some()),
            ("offsets-v", self.offsets_v.is_some()),
            ("max-slew-deg-per-ms", self.max_slew_deg_per_ms.is_some()),
            ("library", self.library.is_some()),
        ]
        .into_iter()
        .filter_map(|(k, g)| g.then_some(k))
        .collect()
    }
}

/// `[laser]`'s DAQmx keys, as parsed.
#[derive(Default)]
pub(super) struct RawDaqLaser {
    pub laser_line: Option<String>,
    pub interlock_line: Option<String>,
    pub diffuser_line: Option<String>,
    pub heartbeat_line: Option<String>,
    pub daq_watchdog: Option<bool>,
    pub accept_no_watchdog: Option<bool>,
}

impl RawDaqLaser {
    pub(super) fn given(&self) -> Vec<&'static str> {
        [
            ("laser-line", self.laser_line.is_some()),
            ("interlock-line", self.interlock_line.is_some()),
            ("diffuser-line", self.diffuser_line.is_some()),
            ("heartbeat-line", self.heartbeat_line.is_some()),
            ("daq-watchdog", self.daq_watchdog.is_some()),
            ("accept-no-watchdog", self.accept_no_watchdog.is_some()),
        ]
        .into_iter()
        .filter_map(|(k, g)| g.then_some(k))
        .collect()
    }
}

/// Refuses the DAQmx keys of a table whose driver is not DAQmx.
pub(super) fn refuse_keys(
    src: &TomlSource,
    table: &str,
    given: &[&str],
    why: &str,
) -> Result<(), ConfigError> {
    match given.first() {
        Some(k) => Err(src.invalid(&format!("{table}.{k}"), why.to_owned())),
        None => Ok(()),
    }
}

/// Refuses the galvo table's DAQmx keys unless its driver is DAQmx.
pub(super) fn refuse_galvo_keys(src: &TomlSource, key: &str, raw: &RawDaqGalvo) -> Result<(), ConfigError> {
    refuse_keys(
        src,
        key,
        &raw.given(),
        "is a DAQmx galvo setting: add `driver = \"daqmx\"` to the table, or remove it",
    )
}

/// A physical channel or line name: `Dev1/ao0`, `Dev1/port0/line0`. Exactly one: a
/// digital line is a device, a port and a line (a whole port, `Dev1/port0`, would make
/// one channel of eight lines, which the driver's one-byte writes do not fill).
fn channel(src: &TomlSource, key: &str, name: &str, kind: &str) -> Result<String, ConfigError> {
    let name = name.trim();
    let parts: Vec<&str> = name.split('/').collect();
    // `prefix` followed by a number.
    let numbered = |part: &str, prefix: &str| {
        part.len() > prefix.len()
            && part.is_char_boundary(prefix.len())
            && part[..prefix.len()].eq_ignore_ascii_case(prefix)
            && part[prefix.len()..].bytes().all(|b| b.is_ascii_digit())
    };
    let ok = !name.contains([',', ':', ' '])
        && match (kind, parts.as_slice()) {
            ("digital line", [device, port, line]) => {
                !device.is_empty() && numbered(port, "port") && numbered(line, "line")
            }
            ("analog output", [device, ao]) => !device.is_empty() && numbered(ao, "ao"),
            _ => false,
        };
    if ok {
        Ok(name.to_owned())
    } else {
        Err(src.invalid(
            key,
            format!(
                "`{name}` is not one {kind} (write it as NI-DAQmx names it, e.g. {})",
                match kind {
                    "analog output" => "Dev1/ao0",
                    _ => "Dev1/port0/line0",
                }
            ),
        ))
    }
}

/// `[galvo.<arm>]` with `driver = "daqmx"`: the channels, the volts per optical degree
/// and offsets (every angle within the limits must need no more than ±10 V), the slew
/// limit and the library.
pub(super) fn galvo(
    src: &TomlSource,
    key: &str,
    name: &str,
    raw: RawDaqGalvo,
    limits: AngleLimits,
    settle: std::time::Duration,
) -> Result<AoGalvoSettings, ConfigError> {
    let k = |s: &str| format!("{key}.{s}");
    let channels = raw.channels.ok_or_else(|| {
        src.invalid(
            key,
            "driver = \"daqmx\" needs `channels = [\"Dev1/ao0\", \"Dev1/ao1\"]`: the x and y axes' analog outputs",
        )
    })?;
    let channels = [
        channel(src, &k("channels[0]"), &channels[0], "analog output")?,
        channel(src, &k("channels[1]"), &channels[1], "analog output")?,
    ];
    if channels[0].eq_ignore_ascii_case(&channels[1]) {
        return Err(src.invalid(&k("channels"), "x and y must be two different analog outputs"));
    }
    let volts_per_deg = raw.volts_per_deg.ok_or_else(|| {
        src.invalid(
            key,
            "driver = \"daqmx\" needs `volts-per-deg = [x, y]`: the servo driver's input scale, volts per optical degree",
        )
    })?;
    for (i, v) in volts_per_deg.iter().enumerate() {
        if !v.is_finite() || *v == 0.0 || v.abs() > 10.0 {
            return Err(src.invalid(
                &k(&format!("volts-per-deg[{i}]")),
                format!("{v} is not a scale: give a non-zero number of volts per optical degree, at most 10"),
            ));
        }
    }
    let offsets_v = raw.offsets_v.unwrap_or([0.0, 0.0]);
    for (i, v) in offsets_v.iter().enumerate() {
        if !(v.is_finite() && v.abs() <= 10.0) {
            return Err(src.invalid(&k(&format!("offsets-v[{i}]")), format!("{v} V is outside ±10 V")));
        }
    }
    let slew = raw.max_slew_deg_per_ms.ok_or_else(|| {
        src.invalid(
            key,
            "driver = \"daqmx\" needs `max-slew-deg-per-ms`: the largest optical step the galvo follows in a millisecond (its data sheet's small-step response)",
        )
    })?;
    if !(slew > 0.0 && slew <= 100.0) {
        return Err(src.invalid(
            &k("max-slew-deg-per-ms"),
            format!("{slew} is out of range: it must be above 0 and at most 100 optical degrees per ms"),
        ));
    }
    let settings = AoGalvoSettings {
        name: name.to_owned(),
        library: raw.library.unwrap_or_else(|| PathBuf::from(DEFAULT_LIBRARY)),
        channels,
        volts_per_deg,
        offsets_v,
        limits,
        max_slew_deg_per_ms: slew,
        settle,
    };
    if settings.volt_range().is_none() {
        return Err(src.invalid(
            &k("volts-per-deg"),
            "with these offsets-v, the angle limits need voltages outside the card's ±10 V: narrow angle-limits-deg or lower the scale",
        ));
    }
    Ok(settings)
}

/// `[laser]`'s lines, required when the laser arm is on a DAQ device.
pub(super) fn laser(
    src: &TomlSource,
    raw: RawDaqLaser,
    library: PathBuf,
    watchdog: std::time::Duration,
) -> Result<DaqLaserSettings, ConfigError> {
    let laser_line = raw.laser_line.ok_or_else(|| {
        src.invalid(
            "laser",
            "the laser arm is on a DAQ device (galvo.laser.driver = \"daqmx\"), so [laser] needs `laser-line = \"Dev1/port0/line0\"`: the digital output wired to the laser's gate input",
        )
    })?;
    let line = |key: &str, v: Option<String>| -> Result<Option<String>, ConfigError> {
        v.map(|v| channel(src, &format!("laser.{key}"), &v, "digital line"))
            .transpose()
    };
    let laser_line = channel(src, "laser.laser-line", &laser_line, "digital line")?;
    let interlock_line = line("interlock-line", raw.interlock_line)?;
    let diffuser_line = line("diffuser-line", raw.diffuser_line)?;
    let heartbeat_line = line("heartbeat-line", raw.heartbeat_line)?;
    let mut seen = vec![("laser-line", laser_line.clone())];
    for (key, l) in [
        ("interlock-line", &interlock_line),
        ("diffuser-line", &diffuser_line),
        ("heartbeat-line", &heartbeat_line),
    ] {
        if let Some(l) = l {
            if let Some((other, _)) = seen.iter().find(|(_, s)| s == l) {
                return Err(src.invalid(&format!("laser.{key}"), format!("`{l}` is already laser.{other}")));
            }
            seen.push((key, l.clone()));
        }
    }
    let hardware_watchdog = raw.daq_watchdog.unwrap_or(true);
    let accept_no_watchdog = raw.accept_no_watchdog.unwrap_or(false);
    if !hardware_watchdog && heartbeat_line.is_none() && !accept_no_watchdog {
        return Err(src.invalid(
            "laser.daq-watchdog",
            "with the DAQ's watchdog off, nothing ends emission if the host dies: set heartbeat-line to feed an external watchdog relay in series with the gate, or accept-no-watchdog = true to accept the risk (docs/safety.md)",
        ));
    }
    Ok(DaqLaserSettings {
        library,
        laser_line,
        interlock_line,
        diffuser_line,
        heartbeat_line,
        hardware_watchdog,
        accept_no_watchdog,
        watchdog,
    })
}

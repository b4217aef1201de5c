//! PicoQuant counters (`tdc.driver = "multiharp"` or `"hydraharp"`): the driver opened
//! from the config's `[tdc]` table, and the survey `periscope devices` prints (which
//! counters the vendor library sees, or plainly that the library is not there).
use std::time::Duration;

use periscope_drivers::picoquant::{self, PicoQuantSettings, PicoQuantTdc};
use periscope_drivers::{DeviceError, Erased, HistogrammerBox};

use super::OpenError;
use crate::config::PicoQuantCounter;

/// Slack the counter's driver allows beyond the acquisition time.
const TIMEOUT: Duration = Duration::from_millis(1000);

/// The driver's settings for the configured counter.
fn settings(counter: &PicoQuantCounter) -> PicoQuantSettings {
    PicoQuantSettings {
        family: counter.family,
        library: counter.library.clone(),
        serial: counter.serial.clone(),
        channel: counter.channel,
        sync_trigger: counter.sync_trigger,
        input_trigger: counter.input_trigger,
        input_offset_ps: counter.input_offset_ps,
        timeout: TIMEOUT,
    }
}

/// Opens the configured counter.
pub(super) fn histogrammer(counter: &PicoQuantCounter) -> Result<HistogrammerBox, OpenError> {
    let tdc = PicoQuantTdc::open(settings(counter)).map_err(DeviceError::from)?;
    Ok(Erased::histogrammer(tdc))
}

/// What `periscope devices` says about the configured counter's library: each counter
/// it sees, one line each, or why the library could not be used (the path tried and
/// what to install).
pub fn survey(counter: &PicoQuantCounter) -> Vec<String> {
    let family = counter.family;
    match picoquant::list_counters(family, &counter.library) {
        Err(e) => vec![format!("{e}")],
        Ok((version, found)) => {
            let mut lines = vec![format!(
                "{} {version} at {}: {} {family}{} found",
                family.library_name(),
                counter.library.display(),
                found.len(),
                if found.len() == 1 { "" } else { "s" },
            )];
            for f in found {
                let wanted = counter.serial.as_ref().is_some_and(|s| *s == f.serial);
                lines.push(format!(
                    "  index {}  serial {}  {}{}{}",
                    f.index,
                    if f.serial.is_empty() { "?" } else { &f.serial },
                    f.model.as_deref().unwrap_or("(model unknown)"),
                    f.problem.map(|p| format!("  [{p}]")).unwrap_or_default(),
                    if wanted { "  <- tdc.serial" } else { "" },
                ));
            }
            lines
        }
    }
}

//! The PicoQuant counter behind the [`Histogrammer`] trait, in histogram mode, following
//! the call sequence of the vendor's histogram-mode demos: open by index (looking for
//! the configured serial number), initialise, read the hardware info, calibrate
//! (HydraHarp), set the sync divider, triggers and channel offsets; then per setting
//! the histogram length, binning and offset, checked against the resolution the device
//! reports; per acquisition clear, start, poll `CTCStatus` (asking `stop`), stop, read
//! the SPAD channel's histogram and the flags.
//!
//! A setting the device cannot express exactly (a bin width that is not its base
//! resolution times a power of two, an offset of a fraction of a nanosecond, an
//! acquisition time of a fraction of a millisecond) is refused with kind `OutOfRange`,
//! never rounded: the histogram says which settings it was acquired with. A device that
//! vanishes is reopened once (by serial number), its settings restored and the call
//! repeated, as the USB driver does; a lost sync fails the acquisition.
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use tracing::{debug, instrument, warn};

use super::defin::{self, MAX_DEV_NUM, MODE_HIST, REFSRC_INTERNAL, error as code, flag, warning};
use super::error::PicoQuantError;
use super::family::{Family, Settings, Trigger};
use super::ffi::{Lib, LoadError};
use crate::error::{Error, ErrorKind, ErrorType};
use crate::traits::{
    CountRates, DeviceInfo, Histogram, HistogramFlags, Histogrammer, TdcConfig, TdcState, TdcStatus,
};

/// How often an acquisition asks the device whether it is done and the caller whether
/// to stop: the bound on how long a stop waits, whatever the dwell.
pub const POLL: Duration = Duration::from_millis(2);

/// How the counter is reached and wired.
#[derive(Clone, Debug, PartialEq)]
pub struct PicoQuantSettings {
    /// Which library and instruments.
    pub family: Family,
    /// The library to load.
    pub library: PathBuf,
    /// The counter's serial number; `None` takes the first one found.
    pub serial: Option<String>,
    /// The SPAD's input, 0-based (the library's numbering).
    pub channel: u32,
    /// The sync input's trigger.
    pub sync_trigger: Trigger,
    /// The SPAD input's trigger.
    pub input_trigger: Trigger,
    /// The SPAD input's channel offset, ps (like a cable delay; the sync channel's
    /// stays 0, as only the difference matters in histogram mode).
    pub input_offset_ps: i32,
    /// Slack beyond the acquisition time before an acquisition counts as timed out.
    pub timeout: Duration,
}

/// A counter the library can see.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FoundCounter {
    /// Device index.
    pub index: i32,
    /// Serial number.
    pub serial: String,
    /// Model, part number and version, when the device could be initialised.
    pub model: Option<String>,
    /// Why it could not be opened or initialised (another program holds it...).
    pub problem: Option<String>,
}

/// The settings in force on the device, as the device takes them.
#[derive(Clone, Copy, Debug)]
struct Applied {
    config: TdcConfig,
    acquisition_ms: i32,
}

/// A PicoQuant counter in histogram mode.
pub struct PicoQuantTdc {
    lib: Lib,
    settings: PicoQuantSettings,
    index: i32,
    serial: String,
    info: DeviceInfo,
    device: String,
    applied: Option<Applied>,
    sequence: u32,
    acquisitions: u32,
    counts: Vec<u32>,
    last_warnings: i32,
    /// The rate meter's readings, and the warnings the library makes from them, are
    /// valid from this instant: [`RATE_SETTLE`] after the last `Initialize` or
    /// `SetSyncDiv`.
    rates_from: Instant,
    /// The sync divider the device holds since it was last initialised: set again only
    /// when it changes, since each `SetSyncDiv` blinds the rate meters for
    /// [`RATE_SETTLE`].
    sync_div_set: Option<u32>,
}

/// How long after `Initialize` or `SetSyncDiv` the rate meters read true: the vendor's
/// demos say "you must allow > 400 ms for valid new count rate readings; otherwise you
/// get new values after every 100 ms".
const RATE_SETTLE: Duration = Duration::from_millis(400);

impl ErrorType for PicoQuantTdc {
    type Error = PicoQuantError;
}

/// The library of `family` at `path`, or an error that says what is missing.
fn load(family: Family, path: &Path) -> Result<Lib, PicoQuantError> {
    let who = format!("{family} library");
    Lib::load(family, path).map_err(|e| match e {
        LoadError::Open(why) => PicoQuantError::new(
            &who,
            ErrorKind::Disconnected,
            format!(
                "cannot load {}: {why}; install PicoQuant's {} for Linux (its demos load it from {}) \
                 or set tdc.library in the instrument config to where it is",
                path.display(),
                family.library_name(),
                family.default_library()
            ),
        ),
        LoadError::Missing(name, why) => PicoQuantError::new(
            &who,
            ErrorKind::Protocol,
            format!(
                "{} has no function {name} ({why}): it is not {} 3.x; check tdc.library and tdc.driver",
                path.display(),
                family.library_name()
            ),
        ),
    })
}

/// Every counter `library` of `family` can see: index, serial number and model (each
/// is opened, initialised for its hardware info and closed again). Also the library's
/// version.
pub fn list_counters(family: Family, library: &Path) -> Result<(String, Vec<FoundCounter>), PicoQuantError> {
    let lib = load(family, library)?;
    let version = lib.library_version().unwrap_or_else(|c| lib.error_string(c));
    let mut found = Vec::new();
    for index in 0..MAX_DEV_NUM {
        match lib.open_device(index) {
            Ok(serial) => {
                let info = lib
                    .initialize(index, MODE_HIST, REFSRC_INTERNAL)
                    .and_then(|()| lib.hardware_info(index));
                let (model, problem) = match info {
                    Ok((model, part, version)) => {
                        (Some(format!("{model} (part {part}, version {version})")), None)
                    }
                    Err(c) => (None, Some(lib.error_string(c))),
                };
                let _ = lib.close_device(index);
                found.push(FoundCounter {
                    index,
                    serial,
                    model,
                    problem,
                });
            }
            Err(code::DEVICE_OPEN_FAIL) => {}
            Err(c) => found.push(FoundCounter {
                index,
                serial: String::new(),
                model: None,
                problem: Some(lib.error_string(c)),
            }),
        }
    }
    Ok((version, found))
}

impl PicoQuantTdc {
    /// Loads the library, opens the counter with the configured serial number (the
    /// first one found without one), initialises it in histogram mode and applies the
    /// triggers and channel settings.
    pub fn open(settings: PicoQuantSettings) -> Result<PicoQuantTdc, PicoQuantError> {
        let lib = load(settings.family, &settings.library)?;
        if let Ok(v) = lib.library_version() {
            debug!(library = %settings.library.display(), version = %v, "loaded {}", settings.family.library_name());
        }
        let (index, serial) = find(&lib, &settings)?;
        let device = format!("{} {serial}", settings.family);
        let mut tdc = PicoQuantTdc {
            lib,
            settings,
            index,
            serial: serial.clone(),
            info: DeviceInfo {
                model: String::new(),
                firmware: String::new(),
                serial,
                protocol: 0,
            },
            device,
            applied: None,
            sequence: 0,
            acquisitions: 0,
            counts: Vec::new(),
            last_warnings: 0,
            rates_from: Instant::now() + RATE_SETTLE,
            sync_div_set: None,
        };
        if let Err(e) = tdc.initialise() {
            let _ = tdc.lib.close_device(tdc.index);
            return Err(e);
        }
        Ok(tdc)
    }

    /// The library's answer `r` to `call`, as our error.
    fn call<T>(&self, call: &str, r: Result<T, i32>) -> Result<T, PicoQuantError> {
        r.map_err(|c| {
            let name = format!("{}{call}", self.settings.family.prefix());
            PicoQuantError::library(&self.device, &name, c, &self.lib.error_string(c))
        })
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> PicoQuantError {
        PicoQuantError::new(&self.device, kind, message)
    }

    /// Initialise, identify, calibrate and apply the static settings.
    fn initialise(&mut self) -> Result<(), PicoQuantError> {
        self.sync_div_set = None;
        self.info = self.identify_device()?;
        self.rates_from = Instant::now() + RATE_SETTLE;
        let (dev, lib) = (self.index, &self.lib);
        let channels = self.call("GetNumOfInputChannels", lib.input_channels(dev))?;
        let ch = self.settings.channel as i32;
        if ch >= channels {
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!(
                    "the SPAD is configured on input {} but this {} has {channels} inputs: check tdc.channel (1 to {channels})",
                    ch + 1,
                    self.info.model
                ),
            ));
        }
        self.call("Calibrate", lib.calibrate(dev))?;
        let (level, edge) = self.trigger_args(self.settings.sync_trigger)?;
        self.call(self.sync_trigger_name(), lib.set_sync_trigger(dev, level, edge))?;
        self.call("SetSyncChannelOffset", lib.set_sync_channel_offset(dev, 0))?;
        let (level, edge) = self.trigger_args(self.settings.input_trigger)?;
        for c in 0..channels {
            // Only the SPAD's input counts: the others stay quiet (and off the USB).
            if c == ch {
                self.call(
                    self.input_trigger_name(),
                    lib.set_input_trigger(dev, c, level, edge),
                )?;
                self.call(
                    "SetInputChannelOffset",
                    lib.set_input_channel_offset(dev, c, self.settings.input_offset_ps),
                )?;
            }
            self.call(
                "SetInputChannelEnable",
                lib.set_input_channel_enable(dev, c, c == ch),
            )?;
        }
        debug!(device = %self.device, model = %self.info.model, index = dev, "opened");
        Ok(())
    }

    /// `Initialize` in histogram mode, then what the device says about itself.
    fn identify_device(&self) -> Result<DeviceInfo, PicoQuantError> {
        let (dev, lib) = (self.index, &self.lib);
        self.call("Initialize", lib.initialize(dev, MODE_HIST, REFSRC_INTERNAL))?;
        let (model, part, version) = self.call("GetHardwareInfo", lib.hardware_info(dev))?;
        let serial = self.call("GetSerialNumber", lib.serial_number(dev))?;
        let library = lib.library_version().unwrap_or_default();
        Ok(DeviceInfo {
            model,
            firmware: format!(
                "{version} (part {part}, {} {library})",
                self.settings.family.library_name()
            ),
            serial,
            protocol: library
                .split('.')
                .next()
                .and_then(|m| m.parse().ok())
                .unwrap_or(0),
        })
    }

    fn sync_trigger_name(&self) -> &'static str {
        if self.settings.family.uses_cfd() {
            "SetSyncCFD"
        } else {
            "SetSyncEdgeTrg"
        }
    }

    fn input_trigger_name(&self) -> &'static str {
        if self.settings.family.uses_cfd() {
            "SetInputCFD"
        } else {
            "SetInputEdgeTrg"
        }
    }

    /// The library's two trigger arguments for `t`, refused if the family does not take it.
    fn trigger_args(&self, t: Trigger) -> Result<(i32, i32), PicoQuantError> {
        if !self.settings.family.accepts(t) {
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!("the {} does not take the trigger {t:?}", self.settings.family),
            ));
        }
        Ok(match t {
            Trigger::Edge { level_mv, rising } => (
                level_mv,
                if rising {
                    defin::EDGE_RISING
                } else {
                    defin::EDGE_FALLING
                },
            ),
            Trigger::Cfd {
                level_mv,
                zero_cross_mv,
            } => (level_mv, zero_cross_mv),
        })
    }

    /// Applies `config`: sync divider, histogram length, binning and offset, each
    /// checked against what the device can do exactly.
    fn apply(&mut self, config: &TdcConfig) -> Result<Applied, PicoQuantError> {
        let family = self.settings.family;
        let Settings {
            acquisition_ms,
            offset_ns,
            len_code,
        } = family
            .settings(config)
            .map_err(|what| self.err(ErrorKind::OutOfRange, what))?;
        let (dev, lib) = (self.index, &self.lib);
        if self.sync_div_set != Some(config.sync_divider) {
            // Unknown until the call answers.
            self.sync_div_set = None;
            self.call("SetSyncDiv", lib.set_sync_div(dev, config.sync_divider as i32))?;
            self.sync_div_set = Some(config.sync_divider);
            self.rates_from = Instant::now() + RATE_SETTLE;
        }
        let len = self.call("SetHistoLen", lib.set_histo_len(dev, len_code))?;
        if len < config.bins as i32 {
            return Err(self.err(
                ErrorKind::Protocol,
                format!(
                    "length code {len_code} gave {len} bins, fewer than the {} asked for",
                    config.bins
                ),
            ));
        }
        // The base resolution is the bin width at binning 0; binning b doubles it b times.
        self.call("SetBinning", lib.set_binning(dev, 0))?;
        let base_ps = self.call("GetResolution", lib.resolution(dev))?;
        let want_ps = config.bin_width * 1e12;
        let binning = (want_ps / base_ps).log2().round();
        let exact = binning >= 0.0 && (base_ps * binning.exp2() - want_ps).abs() <= 1e-3 * want_ps;
        if !exact || binning > 30.0 {
            let options: Vec<String> = (0..6)
                .map(|b| format!("{}", base_ps * f64::from(1 << b)))
                .collect();
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!(
                    "this {family}'s bins are {base_ps} ps × 2^n wide, so {want_ps} ps is not available: \
                 set bin-width-ps to one of {}, ... ps",
                    options.join(", ")
                ),
            ));
        }
        self.call("SetBinning", lib.set_binning(dev, binning as i32))?;
        self.call("SetOffset", lib.set_offset(dev, offset_ns))?;
        let got_ps = self.call("GetResolution", lib.resolution(dev))?;
        if (got_ps - want_ps).abs() > 1e-3 * want_ps {
            return Err(self.err(
                ErrorKind::Protocol,
                format!("binning {binning} gave {got_ps} ps bins, not the {want_ps} ps asked for"),
            ));
        }
        Ok(Applied {
            config: *config,
            acquisition_ms,
        })
    }

    /// Closes the device and opens it again by serial number, restoring the settings.
    fn reconnect(&mut self) -> Result<(), PicoQuantError> {
        let _ = self.lib.close_device(self.index);
        let wanted = PicoQuantSettings {
            serial: Some(self.serial.clone()),
            ..self.settings.clone()
        };
        let (index, _) = find(&self.lib, &wanted)?;
        self.index = index;
        self.initialise()?;
        if let Some(a) = self.applied {
            self.apply(&a.config)?;
        }
        Ok(())
    }

    /// Runs `f`; when the device is gone, reopens it, restores the settings and runs
    /// `f` once more.
    fn with_recovery<R>(
        &mut self,
        mut f: impl FnMut(&mut Self) -> Result<R, PicoQuantError>,
    ) -> Result<R, PicoQuantError> {
        match f(self) {
            Err(e) if e.kind() == ErrorKind::Disconnected => {
                warn!(device = %self.device, error = %e, "reopening the counter");
                self.reconnect().map_err(|again| {
                    self.err(
                        ErrorKind::Disconnected,
                        format!(
                            "{} (and it could not be reopened: {})",
                            e.message(),
                            again.message()
                        ),
                    )
                })?;
                f(self)
            }
            r => r,
        }
    }

    /// One acquisition: clear, start, poll until the acquisition time has run out (or
    /// `stop` says stop), stop, read the histogram and the flags.
    #[instrument(level = "trace", skip(self, stop))]
    fn acquire_once(
        &mut self,
        applied: Applied,
        stop: &dyn Fn() -> bool,
    ) -> Result<Histogram, PicoQuantError> {
        let (dev, ch) = (self.index, self.settings.channel as i32);
        let config = applied.config;
        self.call("ClearHistMem", self.lib.clear_hist_mem(dev))?;
        self.call("StartMeas", self.lib.start_meas(dev, applied.acquisition_ms))?;
        if let Err(e) = self.wait(applied, stop) {
            // Whatever went wrong, the measurement does not run on: the next one could
            // not start, and a stop must end it on the device.
            if let Err(c) = self.lib.stop_meas(dev) {
                debug!(device = %self.device, code = c, "StopMeas after a failed acquisition failed too");
            }
            return Err(e);
        }
        self.call("StopMeas", self.lib.stop_meas(dev))?;
        let mut counts = std::mem::take(&mut self.counts);
        let read = self.call("GetHistogram", self.lib.histogram(dev, ch, &mut counts));
        let histogram = counts[..config.bins as usize].to_vec();
        self.counts = counts;
        read?;
        let flags = self.call("GetFlags", self.lib.flags(dev))?;
        if flags & flag::SYNC_LOST != 0 {
            return Err(self.err(
                ErrorKind::Device,
                "the sync signal was lost during the acquisition (flag SYNC_LOST): check the laser's sync cable \
                 and that the laser is pulsing; the histogram was discarded",
            ));
        }
        if flags & (flag::SYSERROR | flag::REF_LOST) != 0 {
            return Err(self.err(
                ErrorKind::Device,
                format!(
                    "the counter reports a {} (flags {flags:#06x}): power-cycle it; if it stays, contact PicoQuant support",
                    if flags & flag::SYSERROR != 0 {
                        "hardware error"
                    } else {
                        "lost reference clock"
                    }
                ),
            ));
        }
        let elapsed = self.call("GetElapsedMeasTime", self.lib.elapsed_ms(dev))?;
        if elapsed + 1.0 < f64::from(applied.acquisition_ms) {
            return Err(self.err(
                ErrorKind::Device,
                format!(
                    "the measurement ended after {elapsed:.1} of {} ms; the histogram was discarded",
                    applied.acquisition_ms
                ),
            ));
        }
        // Warnings come from the rate meters, which read nothing true for a while after
        // the counter was (re)initialised or its divider set: a sync of 0 then would
        // flag every histogram as piled up.
        let warnings = if Instant::now() >= self.rates_from {
            self.warnings()?
        } else {
            0
        };
        // A sync that stopped once the measurement had ended (no SYNC_LOST above: the
        // histogram had its sync throughout, and is kept) makes the detector's rate over
        // the sync's infinite: that is no pile-up, so it is not judged; the next
        // acquisition fails on the lost sync, naming it.
        let sync_gone = warnings & warning::SYNC_RATE_ZERO != 0;
        if sync_gone {
            warn!(
                device = %self.device,
                "the sync input reads 0 Hz since the last acquisition: the laser has stopped pulsing or its sync \
                 cable is out; that histogram is kept, unjudged for pile-up"
            );
        }
        let saturated =
            !sync_gone && warnings & (warning::INPT_RATE_RATIO | warning::INPT_RATE_TOO_HIGH) != 0;
        self.sequence = self.sequence.wrapping_add(1);
        self.acquisitions = self.acquisitions.wrapping_add(1);
        Ok(Histogram {
            sequence: self.sequence,
            counts: histogram,
            flags: HistogramFlags {
                overflow: flags & (flag::OVERFLOW | flag::FIFOFULL | flag::CNTS_DROPPED) != 0,
                saturated,
            },
            config,
        })
    }

    /// Polls until the acquisition time has run out, asking `stop` every [`POLL`].
    fn wait(&self, applied: Applied, stop: &dyn Fn() -> bool) -> Result<(), PicoQuantError> {
        let dev = self.index;
        let deadline = Instant::now() + applied.config.acquisition + self.settings.timeout;
        loop {
            if stop() {
                return Err(self.err(
                    ErrorKind::Interrupted,
                    "the acquisition was stopped and ended on the device",
                ));
            }
            if self.call("CTCStatus", self.lib.ctc_done(dev))? {
                return Ok(());
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(self.err(
                    ErrorKind::Timeout,
                    format!(
                        "the {} ms acquisition had not ended {} ms after its time: check the counter",
                        applied.acquisition_ms,
                        self.settings.timeout.as_millis()
                    ),
                ));
            }
            std::thread::sleep((deadline - now).min(POLL));
        }
    }

    /// Reads the rates (the library computes its warnings from them), then the
    /// warnings; logs their text when they change.
    fn warnings(&mut self) -> Result<i32, PicoQuantError> {
        let dev = self.index;
        self.call("GetSyncRate", self.lib.sync_rate(dev))?;
        self.call(
            "GetCountRate",
            self.lib.count_rate(dev, self.settings.channel as i32),
        )?;
        let w = self.call("GetWarnings", self.lib.warnings(dev))?;
        if w != self.last_warnings {
            self.last_warnings = w;
            if w != 0 {
                let text = self.lib.warnings_text(dev, w).unwrap_or_default();
                warn!(device = %self.device, warnings = w, "{}", text.trim());
            }
        }
        Ok(w)
    }

    /// The device index the library uses for this counter.
    pub fn index(&self) -> i32 {
        self.index
    }
}

/// The index and serial number of the counter `settings` asks for, left open; every
/// other device opened on the way is closed again.
fn find(lib: &Lib, settings: &PicoQuantSettings) -> Result<(i32, String), PicoQuantError> {
    let family = settings.family;
    let mut seen = Vec::new();
    let mut refused = Vec::new();
    for index in 0..MAX_DEV_NUM {
        match lib.open_device(index) {
            Ok(serial) => {
                if settings.serial.as_ref().is_none_or(|s| s == &serial) {
                    return Ok((index, serial));
                }
                let _ = lib.close_device(index);
                seen.push(serial);
            }
            Err(code::DEVICE_OPEN_FAIL) => {}
            Err(c) => refused.push(format!("index {index}: {} (error {c})", lib.error_string(c))),
        }
    }
    let wanted = settings.serial.as_ref().map_or_else(
        || format!("no {family} found"),
        |s| format!("no {family} with serial {s} found"),
    );
    let seen = if seen.is_empty() {
        String::new()
    } else {
        format!(" (found serials {}: check tdc.serial)", seen.join(", "))
    };
    let refused_text = if refused.is_empty() {
        String::new()
    } else {
        format!("; could not open {}", refused.join(", "))
    };
    let kind = if !refused.is_empty() && seen.is_empty() {
        ErrorKind::Busy
    } else {
        ErrorKind::Disconnected
    };
    Err(PicoQuantError::new(
        &format!("{family} {}", settings.serial.as_deref().unwrap_or("(any)")),
        kind,
        format!(
            "{wanted} through {}{seen}{refused_text}; plug it in and check `periscope devices`",
            settings.library.display()
        ),
    ))
}

impl Drop for PicoQuantTdc {
    fn drop(&mut self) {
        let _ = self.lib.stop_meas(self.index);
        let _ = self.lib.close_device(self.index);
    }
}

impl Histogrammer for PicoQuantTdc {
    fn identify(&mut self) -> Result<DeviceInfo, PicoQuantError> {
        self.with_recovery(|d| {
            let serial = d.call("GetSerialNumber", d.lib.serial_number(d.index))?;
            if serial != d.serial {
                return Err(d.err(
                    ErrorKind::Protocol,
                    format!("the device at index {} now reports serial {serial}", d.index),
                ));
            }
            Ok(d.info.clone())
        })
    }

    fn configure(&mut self, config: &TdcConfig) -> Result<(), PicoQuantError> {
        let c = *config;
        let applied = self.with_recovery(|d| d.apply(&c))?;
        self.applied = Some(applied);
        Ok(())
    }

    fn config(&self) -> Option<TdcConfig> {
        self.applied.map(|a| a.config)
    }

    fn acquire(&mut self) -> Result<Histogram, PicoQuantError> {
        self.acquire_until(&|| false)
    }

    fn acquire_until(&mut self, stop: &dyn Fn() -> bool) -> Result<Histogram, PicoQuantError> {
        let Some(applied) = self.applied else {
            return Err(self.err(
                ErrorKind::Device,
                "acquire called before configure: the driver has no settings to acquire with",
            ));
        };
        self.with_recovery(|d| d.acquire_once(applied, stop))
    }

    fn abort(&mut self) -> Result<(), PicoQuantError> {
        let r = self.lib.stop_meas(self.index);
        self.call("StopMeas", r)
    }

    fn status(&mut self) -> Result<TdcStatus, PicoQuantError> {
        self.with_recovery(|d| {
            let sync = d.call("GetSyncRate", d.lib.sync_rate(d.index))?;
            let detector = d.call(
                "GetCountRate",
                d.lib.count_rate(d.index, d.settings.channel as i32),
            )?;
            Ok(TdcStatus {
                state: TdcState::Idle,
                rates: CountRates {
                    sync: f64::from(sync),
                    detector: f64::from(detector),
                },
                acquisitions: d.acquisitions,
            })
        })
    }

    /// The vendor's demos: "after Init or SetSyncDiv you must allow > 400 ms for valid
    /// new count rate readings; otherwise you get new values after every 100 ms".
    fn rate_latency(&self) -> Duration {
        RATE_SETTLE
    }

    /// Before: "the readings obtained with GetCountRate are internally corrected for
    /// the divider setting and deliver the external (undivided) rate" (the
    /// `SetSyncDiv` entries of MHLib's, HHLib's, PHLib's and TH260Lib's manuals, as
    /// QuTech's QMI and Ulm's qudi quote them; the sync's reading is the one a
    /// divider acts on).
    fn sync_after_divider(&self) -> Option<bool> {
        Some(false)
    }
}

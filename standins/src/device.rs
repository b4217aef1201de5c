//! One simulated counter: the state a MultiHarp or HydraHarp keeps between library
//! calls (open, initialised, settings, histogram memory, flags), and a measurement
//! running on a thread of its own while the host polls, as on the device. The counts
//! come from the rig's histogrammer model (`InProcessTdc`): the same physics and
//! Poisson draws as the simulator's other histogrammers, for the rig's current pointing.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use periscope_drivers::picoquant::Family;
use periscope_drivers::picoquant::defin::{self, error, flag, warning};
use periscope_drivers::tdc::TdcError;
use periscope_drivers::{Histogram, Histogrammer, TdcConfig};
use periscope_sim::devices::InProcessTdc;

/// A library return code: 0 or a negative `*_ERROR_*`.
pub(crate) type Code = i32;

/// A measurement in progress.
struct Running {
    stop: Arc<AtomicBool>,
    done: Arc<AtomicBool>,
    thread: JoinHandle<(InProcessTdc, Result<Histogram, TdcError>)>,
    started: Instant,
    acquisition_ms: i32,
}

/// A counter plugged into an index.
pub(crate) struct Device {
    pub family: Family,
    pub serial: String,
    pub model: String,
    pub channels: i32,
    /// Base resolution, ps (bin width at binning 0).
    pub base_ps: f64,
    /// The input the SPAD is wired to (0-based); the other inputs see nothing.
    pub spad_channel: i32,
    pub open: bool,
    initialised: bool,
    calibrated: bool,
    sync_div: i32,
    len_code: i32,
    binning: i32,
    offset_ns: i32,
    enabled: Vec<bool>,
    tdc: Option<InProcessTdc>,
    running: Option<Running>,
    memory: Vec<u32>,
    flags: i32,
    elapsed_ms: f64,
    /// Flags the next measurement ends with (test control).
    pub next_flags: i32,
    /// The laser's sync stops once the next measurement has ended (test control): its
    /// histogram and flags are whole, the rate meter then reads 0.
    pub sync_stops_after_next: bool,
    /// Rates the library last measured, Hz.
    rates: (i32, i32),
    /// Rates last read by the host (`GetSyncRate`, `GetCountRate`): warnings come
    /// from these, as the vendor's manual says.
    read_rates: (Option<i32>, Option<i32>),
    /// Gone from the bus: every call fails until it is plugged back in.
    pub vanished: bool,
    /// Opens refused before a vanished device is back.
    pub refused_reopens: u32,
    /// The laser's repetition rate, Hz (the sync input's rate before the divider).
    repetition_rate: f64,
    /// The sync rate meter: until the instant, `GetSyncRate` still answers the rate
    /// (Hz) it showed before the last `Initialize` or `SetSyncDiv`.
    meter: (Instant, i32),
}

/// How long after `Initialize` or `SetSyncDiv` the rate meter shows the new sync rate:
/// the vendor's demos say to allow more than 400 ms ("otherwise you get new values
/// after every 100 ms").
pub(crate) const RATE_SETTLE: Duration = Duration::from_millis(400);

impl Device {
    /// A counter of `family` with `channels` inputs, its SPAD on input `spad_channel`.
    pub(crate) fn new(
        family: Family,
        serial: &str,
        channels: i32,
        spad_channel: i32,
        tdc: InProcessTdc,
        repetition_rate: f64,
    ) -> Device {
        let (model, base_ps) = match family {
            Family::MultiHarp => ("MultiHarp 150 4P", 5.0),
            Family::HydraHarp => ("HydraHarp 400", 1.0),
        };
        Device {
            family,
            serial: serial.to_owned(),
            model: model.to_owned(),
            channels,
            base_ps,
            spad_channel,
            open: false,
            initialised: false,
            calibrated: false,
            sync_div: 1,
            len_code: defin::MAX_LEN_CODE,
            binning: 0,
            offset_ns: 0,
            enabled: vec![true; channels as usize],
            tdc: Some(tdc),
            running: None,
            memory: vec![0; 1024 << defin::MAX_LEN_CODE],
            flags: 0,
            elapsed_ms: 0.0,
            next_flags: 0,
            sync_stops_after_next: false,
            rates: (0, 0),
            read_rates: (None, None),
            vanished: false,
            refused_reopens: 0,
            repetition_rate,
            meter: (Instant::now(), 0),
        }
    }

    /// The error every call of a vanished device gets: a USB command that failed.
    fn present(&self) -> Result<(), Code> {
        if self.vanished {
            Err(error::USB_VCMD_FAIL)
        } else if !self.open {
            Err(error::DEVICE_NOT_OPEN)
        } else {
            Ok(())
        }
    }

    /// Open and initialised (and, on a HydraHarp, calibrated when `calibrated`).
    pub(crate) fn ready(&self, calibrated: bool) -> Result<(), Code> {
        self.present()?;
        if !self.initialised {
            return Err(error::NOT_INITIALIZED);
        }
        if calibrated && self.family == Family::HydraHarp && !self.calibrated {
            return Err(error::NOT_CALIBRATED);
        }
        Ok(())
    }

    /// `OpenDevice` on this index.
    pub(crate) fn open(&mut self) -> Result<(), Code> {
        if self.vanished {
            if self.refused_reopens > 0 {
                self.refused_reopens = self.refused_reopens.saturating_sub(1);
                return Err(error::DEVICE_OPEN_FAIL);
            }
            // Plugged back in: a fresh device.
            self.vanished = false;
            self.open = false;
        }
        if self.open {
            return Err(error::DEVICE_BUSY);
        }
        self.open = true;
        self.initialised = false;
        self.calibrated = false;
        Ok(())
    }

    /// `CloseDevice`.
    pub(crate) fn close(&mut self) {
        self.finish(true);
        self.open = false;
        self.initialised = false;
    }

    /// `Initialize(mode, refsource)`.
    pub(crate) fn initialise(&mut self, mode: i32, refsource: i32) -> Result<(), Code> {
        self.present()?;
        if mode != defin::MODE_HIST {
            // The stand-in models histogramming only.
            return Err(error::INVALID_MODE);
        }
        if refsource != defin::REFSRC_INTERNAL {
            return Err(error::INVALID_OPTION);
        }
        self.finish(true);
        self.meter = (Instant::now() + RATE_SETTLE, 0);
        self.initialised = true;
        self.calibrated = false;
        self.sync_div = 1;
        self.len_code = defin::MAX_LEN_CODE;
        self.binning = 0;
        self.offset_ns = 0;
        Ok(())
    }

    pub(crate) fn calibrate(&mut self) -> Result<(), Code> {
        self.ready(false)?;
        self.calibrated = true;
        Ok(())
    }

    pub(crate) fn set_sync_div(&mut self, div: i32) -> Result<(), Code> {
        self.ready(false)?;
        if !self.family.sync_divider_ok(div.max(0) as u32) {
            return Err(error::INVALID_ARGUMENT);
        }
        let shown = self.shown_sync_rate();
        self.sync_div = div;
        self.meter = (Instant::now() + RATE_SETTLE, shown);
        Ok(())
    }

    pub(crate) fn channel(&self, ch: i32) -> Result<usize, Code> {
        if (0..self.channels).contains(&ch) {
            Ok(ch as usize)
        } else {
            Err(error::INVALID_ARGUMENT)
        }
    }

    pub(crate) fn set_enable(&mut self, ch: i32, on: i32) -> Result<(), Code> {
        self.ready(false)?;
        let ch = self.channel(ch)?;
        if !(0..=1).contains(&on) {
            return Err(error::INVALID_ARGUMENT);
        }
        self.enabled[ch] = on == 1;
        Ok(())
    }

    pub(crate) fn set_histo_len(&mut self, code: i32) -> Result<i32, Code> {
        self.ready(false)?;
        if !(0..=defin::MAX_LEN_CODE).contains(&code) {
            return Err(error::INVALID_ARGUMENT);
        }
        self.len_code = code;
        Ok(self.histo_len() as i32)
    }

    fn histo_len(&self) -> usize {
        1024 << self.len_code
    }

    pub(crate) fn set_binning(&mut self, binning: i32) -> Result<(), Code> {
        self.ready(false)?;
        let steps = match self.family {
            Family::MultiHarp => 24,
            Family::HydraHarp => 26,
        };
        if !(0..steps).contains(&binning) {
            return Err(error::INVALID_ARGUMENT);
        }
        self.binning = binning;
        Ok(())
    }

    pub(crate) fn set_offset(&mut self, ns: i32) -> Result<(), Code> {
        self.ready(false)?;
        if !(0..=self.family.max_offset_ns()).contains(&i64::from(ns)) {
            return Err(error::INVALID_ARGUMENT);
        }
        self.offset_ns = ns;
        Ok(())
    }

    /// The bin width in force, ps.
    pub(crate) fn resolution(&self) -> Result<f64, Code> {
        self.ready(false)?;
        Ok(self.base_ps * f64::from(1u32 << self.binning))
    }

    pub(crate) fn clear(&mut self) -> Result<(), Code> {
        self.ready(true)?;
        self.memory.iter_mut().for_each(|c| *c = 0);
        self.flags = 0;
        Ok(())
    }

    /// `StartMeas`: the rig's histogrammer measures for `ms` (scaled by the rig's time
    /// scale) on a thread; the host polls `CTCStatus`.
    pub(crate) fn start(&mut self, ms: i32) -> Result<(), Code> {
        self.ready(true)?;
        if !defin::ACQ_MS.contains(&i64::from(ms)) {
            return Err(error::INVALID_ARGUMENT);
        }
        if self.running.is_some() {
            return Err(error::INSTANCE_RUNNING);
        }
        let config = TdcConfig {
            bin_width: self.resolution()? * 1e-12,
            bins: self.histo_len() as u32,
            offset: f64::from(self.offset_ns) * 1e-9,
            sync_divider: self.sync_div as u32,
            acquisition: Duration::from_millis(ms as u64),
        };
        let mut tdc = self.tdc.take().expect("the histogrammer model is home when idle");
        if tdc.configure(&config).is_err() {
            self.tdc = Some(tdc);
            return Err(error::INVALID_ARGUMENT);
        }
        let stop = Arc::new(AtomicBool::new(false));
        let done = Arc::new(AtomicBool::new(false));
        let (s, d) = (stop.clone(), done.clone());
        let thread = std::thread::Builder::new()
            .name("standin-measure".into())
            .spawn(move || {
                let r = tdc.acquire_until(&|| s.load(Ordering::SeqCst));
                d.store(true, Ordering::SeqCst);
                (tdc, r)
            })
            .map_err(|_| error::INVALID_MEMORY)?;
        self.running = Some(Running {
            stop,
            done,
            thread,
            started: Instant::now(),
            acquisition_ms: ms,
        });
        Ok(())
    }

    /// Collects a measurement that has ended (or, with `force`, ends it first): its
    /// counts go to the histogram memory, its flags and rates are kept.
    fn finish(&mut self, force: bool) {
        let Some(run) = self.running.as_ref() else { return };
        if !force && !run.done.load(Ordering::SeqCst) {
            return;
        }
        let run = self.running.take().expect("checked");
        run.stop.store(true, Ordering::SeqCst);
        let (mut tdc, result) = run.thread.join().expect("the measurement thread does not panic");
        match result {
            Ok(h) => {
                let spad = &mut self.memory;
                spad.iter_mut().for_each(|c| *c = 0);
                spad[..h.counts.len()].copy_from_slice(&h.counts);
                if h.flags.overflow {
                    self.flags |= flag::OVERFLOW;
                }
                self.elapsed_ms = f64::from(run.acquisition_ms);
                if let Ok(s) = tdc.status() {
                    self.rates = (s.rates.sync as i32, s.rates.detector as i32);
                }
            }
            Err(_) => {
                // Stopped early: the counts so far are not modelled; the memory stays clear.
                self.elapsed_ms = run.started.elapsed().as_secs_f64() * 1e3;
            }
        }
        self.flags |= std::mem::take(&mut self.next_flags);
        if self.repetition_rate == 0.0 {
            // No sync for the whole measurement: nothing to time photons against.
            self.flags |= flag::SYNC_LOST;
            self.memory.iter_mut().for_each(|c| *c = 0);
        }
        if std::mem::take(&mut self.sync_stops_after_next) {
            self.repetition_rate = 0.0;
        }
        self.tdc = Some(tdc);
    }

    pub(crate) fn stop(&mut self) -> Result<(), Code> {
        self.present()?;
        self.finish(true);
        Ok(())
    }

    /// `CTCStatus`: 1 once the acquisition time has run out.
    pub(crate) fn ctc_status(&mut self) -> Result<i32, Code> {
        self.ready(true)?;
        match &self.running {
            Some(run) if !run.done.load(Ordering::SeqCst) => Ok(0),
            _ => {
                self.finish(false);
                Ok(1)
            }
        }
    }

    /// `GetHistogram` of input `ch`: the memory's first `histo_len` bins.
    pub(crate) fn histogram(&mut self, ch: i32) -> Result<Vec<u32>, Code> {
        self.ready(true)?;
        let ch = self.channel(ch)?;
        if self.family == Family::MultiHarp && self.len_code < self.family.min_len_code() {
            // mhdefin.h: length codes 0 and 1 do not work with MH_GetHistogram.
            return Err(error::INVALID_ARGUMENT);
        }
        self.finish(false);
        let n = self.histo_len();
        if ch as i32 == self.spad_channel && self.enabled[ch] {
            Ok(self.memory[..n].to_vec())
        } else {
            Ok(vec![0; n])
        }
    }

    pub(crate) fn flags(&mut self) -> Result<i32, Code> {
        self.ready(false)?;
        self.finish(false);
        let active = if self.running.is_some() { flag::ACTIVE } else { 0 };
        Ok(self.flags | active)
    }

    pub(crate) fn elapsed(&mut self) -> Result<f64, Code> {
        self.ready(false)?;
        Ok(match &self.running {
            Some(run) => run.started.elapsed().as_secs_f64() * 1e3,
            None => self.elapsed_ms,
        })
    }

    /// The sync rate after the divider, Hz, as the rate meter shows it: the rate
    /// before the last `Initialize` or `SetSyncDiv` until [`RATE_SETTLE`] has passed.
    pub(crate) fn sync_rate(&mut self) -> Result<i32, Code> {
        self.ready(false)?;
        let rate = self.shown_sync_rate();
        self.read_rates.0 = Some(rate);
        Ok(rate)
    }

    /// The sync's reading: the laser's rate, undivided, as the libraries' manuals say
    /// theirs is ("corrected for the divider setting").
    fn shown_sync_rate(&self) -> i32 {
        if Instant::now() < self.meter.0 {
            self.meter.1
        } else {
            self.repetition_rate as i32
        }
    }

    /// Input `ch`'s rate, Hz: the SPAD's during the last measurement, 0 elsewhere.
    pub(crate) fn count_rate(&mut self, ch: i32) -> Result<i32, Code> {
        self.ready(false)?;
        let ch = self.channel(ch)?;
        let rate = if ch as i32 == self.spad_channel && self.enabled[ch] {
            self.rates.1
        } else {
            0
        };
        self.read_rates.1 = Some(rate);
        Ok(rate)
    }

    /// `GetWarnings`, from the rates the host last read.
    pub(crate) fn warnings(&self) -> Result<i32, Code> {
        self.ready(false)?;
        let mut w = 0;
        if let Some(sync) = self.read_rates.0 {
            if sync == 0 {
                w |= warning::SYNC_RATE_ZERO;
            }
            if self.sync_div > 1 {
                w |= warning::DIVIDER_GREATER_ONE;
            }
            if f64::from(sync) / f64::from(self.sync_div) > self.family.max_sync_rate_hz() {
                w |= warning::SYNC_RATE_TOO_HIGH;
            }
            if let Some(input) = self.read_rates.1
                && f64::from(input) > 0.05 * f64::from(sync)
            {
                w |= warning::INPT_RATE_RATIO;
            }
        }
        Ok(w)
    }
}

/// The vendor's error string for `code`, as the stand-in words it: the symbolic name.
pub(crate) fn error_name(code: Code) -> Option<&'static str> {
    Some(match code {
        0 => "ERROR_NONE",
        error::DEVICE_OPEN_FAIL => "ERROR_DEVICE_OPEN_FAIL",
        error::DEVICE_BUSY => "ERROR_DEVICE_BUSY",
        error::DEVICE_VERSION_MISMATCH => "ERROR_DEVICE_VERSION_MISMATCH",
        error::DEVICE_NOT_OPEN => "ERROR_DEVICE_NOT_OPEN",
        error::DEVICE_LOCKED => "ERROR_DEVICE_LOCKED",
        error::INSTANCE_RUNNING => "ERROR_INSTANCE_RUNNING",
        error::INVALID_ARGUMENT => "ERROR_INVALID_ARGUMENT",
        error::INVALID_MODE => "ERROR_INVALID_MODE",
        error::INVALID_OPTION => "ERROR_INVALID_OPTION",
        error::INVALID_MEMORY => "ERROR_INVALID_MEMORY",
        error::NOT_INITIALIZED => "ERROR_NOT_INITIALIZED",
        error::NOT_CALIBRATED => "ERROR_NOT_CALIBRATED",
        error::USB_DRIVERVER_MISMATCH => "ERROR_USB_DRIVERVER_MISMATCH",
        error::USB_VCMD_FAIL => "ERROR_USB_VCMD_FAIL",
        error::USB_BULKRD_FAIL => "ERROR_USB_BULKRD_FAIL",
        -41 => "ERROR_DONEALL_TIMEOUT",
        -46 => "ERROR_CALIB_FAIL",
        _ => return None,
    })
}

//! The library as the DAQmx drivers share it (loading, error words, the device
//! survey), and a galvo pair on two analog outputs.
//!
//! An analog galvo pair is open loop: its servo follows the voltage, and nothing
//! reports where the mirrors are. So the pair's position is the last commanded one,
//! and "settled" means the configured settling time has passed since the last write
//! (the settle time from the galvo's data sheet for the largest step a move makes,
//! which the slew limit bounds). Each axis's voltage is `offset + volts-per-degree ×
//! optical angle` (the configured calibration of the servo driver's input); targets
//! outside the configured limits, or whose voltage lies outside the card's ±10 V, are
//! refused before anything is written.
//!
//! A move is slew-limited: the driver writes intermediate positions at most
//! `max-slew-deg-per-ms` apart on either axis, one per millisecond ([`STEP_PERIOD`],
//! software-timed on-demand writes as in NI's "Write Voltage Update" example), so a
//! large step never asks the servo for more than it can follow. `move_to` returns once
//! the last step is written (a 30° move at 1°/ms takes 30 ms); the settling time runs
//! from then, so two pairs settle together.
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::{Duration, Instant};

use tracing::{debug, instrument, warn};

use super::defin::MAX_AO_VOLTS;
use super::error::DaqError;
use super::ffi::{Lib, LoadError, Task};
use crate::error::{DeviceError, ErrorKind, ErrorType};
use crate::geometry::{AngleLimits, OpticalAngles};
use crate::park::{EmergencyPark, ParkLine, Parked};
use crate::traits::{DeviceInfo, GalvoPair, GalvoStatus, MotionState};

/// Where NI's Linux installer puts the library (Debian and Ubuntu packages; NI's own
/// documentation and many published programs load it from here).
pub const DEFAULT_LIBRARY: &str = "/usr/lib/x86_64-linux-gnu/libnidaqmx.so";

/// Time between the intermediate writes of a slew-limited move.
pub const STEP_PERIOD: Duration = Duration::from_millis(1);

/// How long one on-demand write may take before the library gives up.
pub(crate) const WRITE_TIMEOUT_S: f64 = 1.0;

/// The library at `path`, or an error that says what is missing.
pub(crate) fn load(path: &Path) -> Result<Arc<Lib>, DaqError> {
    Lib::load(path).map(Arc::new).map_err(|e| match e {
        LoadError::Open(why) => DaqError::new(
            "NI-DAQmx library",
            ErrorKind::Disconnected,
            format!(
                "cannot load {}: {why}; install NI-DAQmx for Linux (its packages put the library at {DEFAULT_LIBRARY}) \
                 or set `library` in the galvo table of the instrument config to where it is",
                path.display()
            ),
        ),
        LoadError::Missing(name, why) => DaqError::new(
            "NI-DAQmx library",
            ErrorKind::Protocol,
            format!(
                "{} has no function {name} ({why}): it is not NI-DAQmx's C library, or one too old \
                 (the driver needs the watchdog functions of NI-DAQmx 9.x or later)",
                path.display()
            ),
        ),
    })
}

/// The library's answer `code` to `call`, as an error of `device` with the extended
/// error information.
pub(crate) fn failed(lib: &Lib, device: &str, call: &str, code: i32) -> DaqError {
    // Refused before the library was called (`Lib::write_*`): its extended
    // information is of some earlier call, if any.
    if code == super::defin::error::WRITE_NUM_CHANS_MISMATCH {
        return DaqError::library(
            device,
            call,
            code,
            "the task has another number of channels or lines than Periscope writes, so nothing was written: \
             each galvo axis must name one analog output (Dev1/ao0), and the laser's lines one digital line \
             each (Dev1/port0/line0), not a list or a whole port",
        );
    }
    let mut text = lib.extended_error_info();
    if text.is_empty() {
        text = lib.error_string(code);
    }
    DaqError::library(device, call, code, &text)
}

/// Logs a warning the last call left, if any.
pub(crate) fn warn_of(lib: &Lib, device: &str, call: &str) {
    if let Some(w) = lib.take_warning() {
        warn!(device, call, warning = w, "{}", lib.error_string(w));
    }
}

/// The device part of a physical channel or line: `Dev1` of `Dev1/ao0`.
pub fn device_of(channel: &str) -> &str {
    channel.split('/').next().unwrap_or(channel).trim()
}

/// What `periscope devices` says about NI-DAQmx.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DaqSurvey {
    /// Each device NI-DAQmx knows: name, model, serial number (hex, as NI prints it).
    pub devices: Vec<(String, String, String)>,
}

/// The devices the library at `library` knows (`DAQmxGetSysDevNames`), each with its
/// model and serial number.
pub fn survey(library: &Path) -> Result<DaqSurvey, DaqError> {
    let lib = load(library)?;
    let names = lib
        .sys_dev_names()
        .map_err(|c| failed(&lib, "NI-DAQmx library", "DAQmxGetSysDevNames", c))?;
    let devices = names
        .into_iter()
        .map(|name| {
            let model = lib
                .dev_product_type(&name)
                .unwrap_or_else(|c| lib.error_string(c));
            let serial = lib
                .dev_serial_num(&name)
                .map_or_else(|c| lib.error_string(c), |s| format!("{s:X}"));
            (name, model, serial)
        })
        .collect();
    Ok(DaqSurvey { devices })
}

/// A galvo pair on two analog outputs, as the instrument config describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct AoGalvoSettings {
    /// The arm's name (`laser`, `spad`).
    pub name: String,
    /// NI-DAQmx's library.
    pub library: PathBuf,
    /// The x and y axes' physical channels (`Dev1/ao0`, `Dev1/ao1`).
    pub channels: [String; 2],
    /// Volts per optical degree, x and y (negative flips an axis).
    pub volts_per_deg: [f64; 2],
    /// Volts at optical angle 0, x and y.
    pub offsets_v: [f64; 2],
    /// The optical angles this pair may be sent to.
    pub limits: AngleLimits,
    /// Largest step between two writes, optical degrees (one write per [`STEP_PERIOD`]).
    pub max_slew_deg_per_ms: f64,
    /// Settling time after the last write of a move.
    pub settle: Duration,
}

impl AoGalvoSettings {
    /// The voltages for `angles`, x then y.
    pub fn volts(&self, angles: OpticalAngles) -> [f64; 2] {
        [
            self.offsets_v[0] + self.volts_per_deg[0] * angles.x.to_degrees(),
            self.offsets_v[1] + self.volts_per_deg[1] * angles.y.to_degrees(),
        ]
    }

    /// The lowest and highest voltage any angle within the limits or the park
    /// position needs (the range the channels are created with: NI-DAQmx refuses a
    /// write outside it, and the pair parks at (0°, 0°) whatever the limits), or
    /// `None` if it leaves the card's ±10 V.
    pub fn volt_range(&self) -> Option<(f64, f64)> {
        let mut lo = f64::INFINITY;
        let mut hi = f64::NEG_INFINITY;
        let corners = self
            .limits
            .x
            .into_iter()
            .flat_map(|x| self.limits.y.map(|y| OpticalAngles { x, y }));
        for angles in corners.chain([PARK]) {
            for v in self.volts(angles) {
                lo = lo.min(v);
                hi = hi.max(v);
            }
        }
        (lo >= -MAX_AO_VOLTS && hi <= MAX_AO_VOLTS && lo < hi).then_some((lo, hi))
    }
}

/// A galvo pair driven by two analog outputs of a DAQ device.
pub struct DaqGalvo {
    out: Arc<AoOut>,
}

/// What the driver and its [`EmergencyPark`] share: the library, the task and where
/// the mirrors were last sent. Every write holds the state's lock, so the two never
/// interleave. NI-DAQmx is multithread-safe (NI's documentation, "Multithreading in
/// NI-DAQmx"), so the e-stop's thread may write to the task the run's thread opened.
struct AoOut {
    lib: Arc<Lib>,
    settings: AoGalvoSettings,
    device: String,
    state: Mutex<AoState>,
}

struct AoState {
    /// The task; `None` once the driver has cleared it (a park handle then reaches
    /// nothing).
    task: Option<Task>,
    /// Where the mirrors were last sent (open loop: the only position there is).
    commanded: OpticalAngles,
    parked: bool,
    /// When the last write of the last move went out.
    last_write: Instant,
    /// An emergency park has taken the pair: every move is refused from then on.
    latched: bool,
}

impl ErrorType for DaqGalvo {
    type Error = DaqError;
}

/// The park position: both axes at optical angle 0.
const PARK: OpticalAngles = OpticalAngles { x: 0.0, y: 0.0 };

/// How long an emergency park waits for a write of the driver's own to return: the
/// library's write timeout, and a margin.
const PARK_LOCK_WAIT: Duration = Duration::from_millis((WRITE_TIMEOUT_S * 1000.0) as u64 + 500);

impl DaqGalvo {
    /// Loads the library and opens the pair: one task with both channels, created
    /// with the voltage range the limits need, started, and the park position
    /// written. The output's previous value is unknown to a new task, so this first
    /// write is the one that is not slew-limited.
    pub fn open(settings: AoGalvoSettings) -> Result<DaqGalvo, DaqError> {
        let device = format!(
            "galvo pair `{}` on {},{}",
            settings.name, settings.channels[0], settings.channels[1]
        );
        let (lo, hi) = settings.volt_range().ok_or_else(|| {
            DaqError::new(
                &device,
                ErrorKind::OutOfRange,
                "the angle limits need voltages outside the card's ±10 V with the configured volts-per-deg and offsets",
            )
        })?;
        let lib = load(&settings.library)?;
        let task = lib
            .create_task(&format!("periscope-galvo-{}", settings.name))
            .map_err(|c| failed(&lib, &device, "DAQmxCreateTask", c))?;
        let galvo = DaqGalvo {
            out: Arc::new(AoOut {
                lib,
                device,
                settings,
                state: Mutex::new(AoState {
                    task: Some(task),
                    commanded: PARK,
                    parked: true,
                    last_write: Instant::now(),
                    latched: false,
                }),
            }),
        };
        let out = &galvo.out;
        let channels = out.settings.channels.join(",");
        out.call(task, "DAQmxCreateAOVoltageChan", |lib, t| {
            lib.create_ao_voltage_chan(t, &channels, lo, hi)
        })?;
        out.call(task, "DAQmxStartTask", Lib::start_task)?;
        out.write(&mut out.lock(), PARK)?;
        Ok(galvo)
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> DaqError {
        self.out.err(kind, message)
    }

    /// The configured settings.
    pub fn settings(&self) -> &AoGalvoSettings {
        &self.out.settings
    }
}

impl AoOut {
    fn lock(&self) -> MutexGuard<'_, AoState> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn call<T>(
        &self,
        task: Task,
        name: &str,
        f: impl FnOnce(&Lib, Task) -> Result<T, i32>,
    ) -> Result<T, DaqError> {
        let r = f(&self.lib, task).map_err(|c| failed(&self.lib, &self.device, name, c));
        warn_of(&self.lib, &self.device, name);
        r
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> DaqError {
        DaqError::new(&self.device, kind, message)
    }

    /// Writes the voltages for `angles` (checked against ±10 V once more), holding
    /// the state's lock.
    fn write(&self, state: &mut AoState, angles: OpticalAngles) -> Result<(), DaqError> {
        let task = state.task.ok_or_else(|| {
            self.err(
                ErrorKind::Disconnected,
                "the driver has closed its task; nothing was written",
            )
        })?;
        let volts = self.settings.volts(angles);
        if volts.iter().any(|v| !(v.abs() <= MAX_AO_VOLTS)) {
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!("{volts:?} V is outside the card's ±10 V; nothing was written"),
            ));
        }
        self.call(task, "DAQmxWriteAnalogF64", |lib, t| {
            lib.write_analog_f64(t, &volts, WRITE_TIMEOUT_S)
        })?;
        state.commanded = angles;
        state.last_write = Instant::now();
        Ok(())
    }

    /// The `k`th of `steps` positions of the straight ramp from `from` to `target`.
    fn ramp_step(from: OpticalAngles, target: OpticalAngles, k: u64, steps: u64) -> OpticalAngles {
        if k == steps {
            return target;
        }
        let f = k as f64 / steps as f64;
        OpticalAngles {
            x: from.x + (target.x - from.x) * f,
            y: from.y + (target.y - from.y) * f,
        }
    }

    /// How many writes a ramp from `from` to `target` takes at the slew limit.
    fn ramp_steps(&self, from: OpticalAngles, target: OpticalAngles) -> u64 {
        let step = self.settings.max_slew_deg_per_ms.to_radians();
        let span = (target.x - from.x).abs().max((target.y - from.y).abs());
        ((span / step).ceil() as u64).max(1)
    }

    /// Ramps from the commanded position to `target`, one write per [`STEP_PERIOD`],
    /// each at most the slew limit from the one before, taking the lock for each
    /// write only. Once an emergency park has latched the pair a move is refused; a
    /// park (`to_park`) whose ramp an emergency park overtook starts again from where
    /// that left the mirrors.
    fn ramp(&self, target: OpticalAngles, to_park: bool) -> Result<(), DaqError> {
        'again: loop {
            let mut last = self.lock().commanded;
            let (from, steps) = (last, self.ramp_steps(last, target));
            let start = Instant::now();
            for k in 1..=steps {
                if k > 1 {
                    let due = start + STEP_PERIOD * (k - 1) as u32;
                    std::thread::sleep(due.saturating_duration_since(Instant::now()));
                }
                let mut state = self.lock();
                if state.latched && !to_park {
                    return Err(self.err(
                        ErrorKind::Interrupted,
                        "an emergency stop parked this pair, and it stays parked: open the devices again to move it",
                    ));
                }
                if state.commanded != last {
                    continue 'again;
                }
                let at = Self::ramp_step(from, target, k, steps);
                self.write(&mut state, at)?;
                last = at;
            }
            debug!(steps, "move written");
            return Ok(());
        }
    }

    /// The emergency park: the pair latched, then ramped to the park position with
    /// the lock held throughout, so no write of the driver's comes between.
    fn emergency_park(&self) -> Result<(), DaqError> {
        let deadline = Instant::now() + PARK_LOCK_WAIT;
        let mut state = loop {
            match self.state.try_lock() {
                Ok(s) => break s,
                Err(std::sync::TryLockError::Poisoned(p)) => break p.into_inner(),
                Err(std::sync::TryLockError::WouldBlock) if Instant::now() < deadline => {
                    std::thread::sleep(Duration::from_micros(200));
                }
                Err(std::sync::TryLockError::WouldBlock) => {
                    return Err(self.err(
                        ErrorKind::Timeout,
                        format!(
                            "a write of the run's has not returned for {:.1} s, so the pair could not be parked: \
                             the DAQ may be hung; switch the galvo drivers off",
                            PARK_LOCK_WAIT.as_secs_f64()
                        ),
                    ));
                }
            }
        };
        state.latched = true;
        let from = state.commanded;
        let steps = self.ramp_steps(from, PARK);
        // A step period after the driver's last write, as the ramp it may have been in
        // would have: the slew limit holds across the two.
        std::thread::sleep((state.last_write + STEP_PERIOD).saturating_duration_since(Instant::now()));
        let start = Instant::now();
        for k in 1..=steps {
            if k > 1 {
                let due = start + STEP_PERIOD * (k - 1) as u32;
                std::thread::sleep(due.saturating_duration_since(Instant::now()));
            }
            self.write(&mut state, Self::ramp_step(from, PARK, k, steps))?;
        }
        state.parked = true;
        warn!(device = %self.device, steps, "parked by an emergency stop; the pair refuses moves from now on");
        Ok(())
    }
}

/// A [`DaqGalvo`]'s [`ParkLine`]: its task, reached without its owner.
struct DaqPark(Weak<AoOut>, String);

impl ParkLine for DaqPark {
    fn park(&self) -> Result<Parked, DeviceError> {
        let out = self.0.upgrade().ok_or_else(|| {
            DaqError::new(
                &self.1,
                ErrorKind::Disconnected,
                "the driver is closed; open the pair again to park it",
            )
        })?;
        out.emergency_park().map(|()| Parked::Done).map_err(Into::into)
    }

    fn describe(&self) -> String {
        self.1.clone()
    }
}

impl Drop for DaqGalvo {
    fn drop(&mut self) {
        // The outputs keep their last voltage after the task is cleared. Cleared under
        // the lock, so a park handle writes before it or finds it gone.
        let mut state = self.out.lock();
        if let Some(task) = state.task.take() {
            let _ = self.out.lib.stop_task(task);
            let _ = self.out.lib.clear_task(task);
        }
    }
}

impl GalvoPair for DaqGalvo {
    fn identify(&mut self) -> Result<DeviceInfo, DaqError> {
        let out = &self.out;
        let dev = device_of(&out.settings.channels[0]).to_owned();
        let model = out
            .lib
            .dev_product_type(&dev)
            .map_err(|c| failed(&out.lib, &out.device, "DAQmxGetDevProductType", c))?;
        let serial = out
            .lib
            .dev_serial_num(&dev)
            .map_err(|c| failed(&out.lib, &out.device, "DAQmxGetDevSerialNum", c))?;
        Ok(DeviceInfo {
            model: format!("{model} ({dev}, analog outputs)"),
            firmware: "NI-DAQmx".into(),
            serial: format!("{serial:X}"),
            protocol: 0,
        })
    }

    fn limits(&self) -> AngleLimits {
        self.out.settings.limits
    }

    /// Checks the target against the limits and the card's range, then writes the
    /// slew-limited ramp to it.
    #[instrument(skip(self), fields(arm = %self.out.settings.name))]
    fn move_to(&mut self, target: OpticalAngles) -> Result<(), DaqError> {
        let settings = &self.out.settings;
        if !target.x.is_finite() || !target.y.is_finite() || !settings.limits.contains(target) {
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!(
                    "({:.3}°, {:.3}°) is outside the configured angle limits; nothing was written",
                    target.x.to_degrees(),
                    target.y.to_degrees()
                ),
            ));
        }
        let volts = settings.volts(target);
        if volts.iter().any(|v| v.abs() > MAX_AO_VOLTS) {
            return Err(self.err(
                ErrorKind::OutOfRange,
                format!("{volts:?} V is outside the card's ±10 V; nothing was written"),
            ));
        }
        {
            let mut state = self.out.lock();
            if !state.latched {
                state.parked = false;
            }
        }
        self.out.ramp(target, false)
    }

    /// Waits out the settling time after the last write and returns the commanded
    /// position (an open-loop galvo reports none of its own).
    fn wait_settled(&mut self, timeout: Duration) -> Result<OpticalAngles, DaqError> {
        let settle = self.out.settings.settle;
        let (last_write, commanded) = {
            let state = self.out.lock();
            (state.last_write, state.commanded)
        };
        let left = (last_write + settle).saturating_duration_since(Instant::now());
        if left > timeout {
            std::thread::sleep(timeout);
            return Err(self.err(
                ErrorKind::Timeout,
                format!("still settling after {timeout:?} (settle time {settle:?}): raise the timeout or lower settle-us"),
            ));
        }
        std::thread::sleep(left);
        Ok(commanded)
    }

    fn position(&mut self) -> Result<OpticalAngles, DaqError> {
        Ok(self.out.lock().commanded)
    }

    fn status(&mut self) -> Result<GalvoStatus, DaqError> {
        let settle = self.out.settings.settle;
        let s = self.out.lock();
        let state = if Instant::now() < s.last_write + settle {
            MotionState::Moving
        } else if s.parked {
            MotionState::Parked
        } else {
            MotionState::Settled
        };
        Ok(GalvoStatus {
            state,
            position: s.commanded,
        })
    }

    /// Ramps to optical angle 0 on both axes.
    fn park(&mut self) -> Result<(), DaqError> {
        self.out.ramp(PARK, true)?;
        self.out.lock().parked = true;
        Ok(())
    }

    fn emergency_park(&self) -> EmergencyPark {
        EmergencyPark::new(DaqPark(Arc::downgrade(&self.out), self.out.device.clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Limits that leave out 0° still give channels that can park: NI-DAQmx refuses a
    /// write outside the range a channel was created with, and the pair parks at 0°.
    #[test]
    fn the_channels_range_holds_the_park_position_whatever_the_limits() {
        let settings = |x: [f64; 2]| AoGalvoSettings {
            name: "laser".into(),
            library: PathBuf::new(),
            channels: ["Dev1/ao0".into(), "Dev1/ao1".into()],
            volts_per_deg: [0.4, 0.4],
            offsets_v: [0.1, -0.1],
            limits: AngleLimits {
                x: x.map(f64::to_radians),
                y: [-5f64.to_radians(), 5f64.to_radians()],
            },
            max_slew_deg_per_ms: 2.0,
            settle: Duration::from_millis(1),
        };
        let (lo, hi) = settings([5.0, 20.0]).volt_range().unwrap();
        let park = settings([5.0, 20.0]).volts(PARK);
        for v in park {
            assert!((lo..=hi).contains(&v), "park at {v} V outside {lo}..{hi} V");
        }
        assert!((hi - (0.1 + 0.4 * 20.0)).abs() < 1e-9, "{hi}");
        // Limits around 0°: the corners alone, as before (x's −10° and +10°).
        let (lo, hi) = settings([-10.0, 10.0]).volt_range().unwrap();
        assert!((lo - (0.1 - 0.4 * 10.0)).abs() < 1e-9 && (hi - (0.1 + 0.4 * 10.0)).abs() < 1e-9);
    }
}

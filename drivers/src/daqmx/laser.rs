//! The laser on a DAQ device's digital lines: its gate input on a digital output
//! (high: emission allowed), the interlock loop read on a digital input (high:
//! closed), the LOS diffuser on another digital output, and the laser guard's
//! watchdog on the device's hardware watchdog timer.
//!
//! The watchdog mapping (NI's "Watchdog Timer" example's sequence): before every
//! switch-on the guard arms the watchdog, which here creates a watchdog timer task on
//! the gate line's device (`DAQmxCreateWatchdogTimerTaskEx`) with the gate line's
//! expiration state low (`DAQmxCfgWatchdogDOExpirStates`) and starts it; the guard's
//! keepalive feeds it (`DAQmxControlWatchdogTask(…, DAQmx_Val_ResetTimer)`), so when
//! the process dies or the run stalls, the device itself drives the gate low within
//! the timeout. Switching off writes the gate low and then stops and clears the
//! watchdog task, so an idle laser leaves no timer to expire.
//!
//! A device without a hardware watchdog (the library answers
//! `DAQmxErrorWatchdogTimerNotSupported`, or the config says `daq-watchdog = false`)
//! leaves two ways: a heartbeat line (`heartbeat-line`), toggled on every feed, which
//! the lab wires to an external watchdog relay in series with the gate; or the
//! config's explicit `accept-no-watchdog = true`. Without either, the laser is not
//! switched on (docs/safety.md says what to wire).
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, Weak};
use std::time::Duration;

use tracing::warn;

use super::defin::{VAL_LOW, VAL_RESET_TIMER, error as code};
use super::driver::{WRITE_TIMEOUT_S, device_of, failed, load, warn_of};
use super::error::DaqError;
use super::ffi::{Lib, Task};
use crate::error::{DeviceError, ErrorKind, ErrorType};
use crate::laser_guard::{EmergencyOff, GuardedLaser, LaserGuard, LaserLine, Progress};
use crate::traits::{Laser, LaserState};

/// The laser's lines and watchdog, as the instrument config describes them.
#[derive(Clone, Debug, PartialEq)]
pub struct DaqLaserSettings {
    /// NI-DAQmx's library.
    pub library: PathBuf,
    /// The gate input's digital output line (`Dev1/port0/line0`).
    pub laser_line: String,
    /// The interlock loop's digital input line; `None`: treated as closed.
    pub interlock_line: Option<String>,
    /// The LOS diffuser's digital output line; `None`: no diffuser to move.
    pub diffuser_line: Option<String>,
    /// A line toggled on every keepalive, for an external watchdog relay.
    pub heartbeat_line: Option<String>,
    /// Whether to use the device's hardware watchdog timer.
    pub hardware_watchdog: bool,
    /// The config accepts emission with neither a hardware watchdog nor a heartbeat.
    pub accept_no_watchdog: bool,
    /// The watchdog's timeout.
    pub watchdog: Duration,
}

/// What ends emission when the host goes quiet.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WatchdogMode {
    /// The DAQ device's watchdog timer drives the gate line low.
    Hardware,
    /// An external watchdog relay, fed by toggling the heartbeat line.
    Heartbeat,
    /// Nothing (the config accepted the risk).
    Unguarded,
}

/// What the driver and the guard's line share: the tasks, cleared when the last of
/// them (the driver, the guard, an e-stop's handle) lets go, so no call ever reaches a
/// cleared task.
struct LineState {
    lib: Arc<Lib>,
    who: String,
    device: String,
    laser_line: String,
    gate: Task,
    /// Whether the gate was last written high.
    high: AtomicBool,
    /// The armed watchdog timer task.
    watchdog: Mutex<Option<Task>>,
    /// The heartbeat line's task and its level.
    heartbeat: Option<(Task, AtomicBool)>,
    /// The interlock loop's input task, when its line is configured: read by the
    /// keepalive too, which latches the gate low when it finds the loop open.
    interlock: OnceLock<Task>,
    /// Held across the keepalive's latch (the gate's level read, the loop read, the
    /// gate written low) and a switch-on's write high, so neither lands between the
    /// other's read and write. Never by an off, which waits for nothing.
    switching: Mutex<()>,
}

impl LineState {
    fn watchdog(&self) -> MutexGuard<'_, Option<Task>> {
        self.watchdog.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Writes the gate low. A line whose watchdog has expired already holds its
    /// expiration state, low, and refuses writes until the expiration is cleared: that
    /// is off too.
    /// A write that failed leaves the line as it was, so it still reads high.
    fn gate_low(&self) -> Result<(), DaqError> {
        match self.lib.write_digital_lines(self.gate, &[0], WRITE_TIMEOUT_S) {
            Ok(_) | Err(code::WRITE_FAILED_BECAUSE_WATCHDOG_EXPIRED) => {
                self.high.store(false, Ordering::SeqCst);
                Ok(())
            }
            Err(c) => Err(failed(&self.lib, &self.who, "DAQmxWriteDigitalLines", c)),
        }
    }

    /// Toggles the heartbeat line, if there is one.
    fn beat(&self) -> Result<(), DaqError> {
        if let Some((task, level)) = &self.heartbeat {
            let next = !level.load(Ordering::SeqCst);
            self.lib
                .write_digital_lines(*task, &[u8::from(next)], WRITE_TIMEOUT_S)
                .map_err(|c| failed(&self.lib, &self.who, "DAQmxWriteDigitalLines (heartbeat)", c))?;
            level.store(next, Ordering::SeqCst);
        }
        Ok(())
    }

    /// Whether the interlock loop reads closed (no line configured: closed).
    fn interlock_closed(&self) -> Result<bool, DaqError> {
        let Some(&task) = self.interlock.get() else {
            return Ok(true);
        };
        let mut level = [0u8; 1];
        self.lib
            .read_digital_lines(task, &mut level, WRITE_TIMEOUT_S)
            .map_err(|c| failed(&self.lib, &self.who, "DAQmxReadDigitalLines (interlock)", c))?;
        Ok(level[0] != 0)
    }

    /// Writes the gate low when it is high and the interlock loop reads open, as the
    /// serial controller latches emission off when its loop opens: the loop (wired to
    /// cut the laser itself) gives emission back when it closes, with the gate still
    /// high, and a pair measured across the opening would read as whole. Latched, the
    /// laser reads off ([`Laser::laser_state`]) and emits again only when switched on,
    /// which the open loop refuses. Returns whether it latched.
    fn latch_if_interlock_open(&self) -> Result<bool, DaqError> {
        let _switching = self.switching.lock().unwrap_or_else(|p| p.into_inner());
        if !self.high.load(Ordering::SeqCst) || self.interlock_closed()? {
            return Ok(false);
        }
        self.gate_low()?;
        warn!(laser = %self.who, "the interlock loop opened with the laser gated on: the gate is latched low until the laser is switched on again");
        Ok(true)
    }

    /// Stops and clears the watchdog task, if one is armed.
    fn disarm(&self) {
        if let Some(task) = self.watchdog().take() {
            let _ = self.lib.stop_task(task);
            let _ = self.lib.clear_task(task);
        }
    }
}

impl Drop for LineState {
    fn drop(&mut self) {
        // A gate that would not go low keeps its watchdog armed and unfed: it expires
        // and drives the line low (its expiration state) without us.
        if self.gate_low().is_ok() {
            self.disarm();
        }
        let tasks = std::iter::once(self.gate)
            .chain(self.heartbeat.as_ref().map(|(t, _)| *t))
            .chain(self.interlock.get().copied());
        for task in tasks {
            let _ = self.lib.stop_task(task);
            let _ = self.lib.clear_task(task);
        }
    }
}

/// The guard's path to the laser: the watchdog's reset (and the heartbeat) as the
/// feed, the gate written low as the off. It holds the line weakly, as the serial
/// laser's off switch holds its port: an `EmergencyOff` kept after the driver closed
/// (the panic hook's list keeps them until the next run registers) must not keep the
/// line's tasks, which NI-DAQmx reserves, from being cleared, or the next open of the
/// same line (a run, a status reading, the idle e-stop) would be refused.
#[derive(Clone)]
struct DaqLine(Weak<LineState>);

impl DaqLine {
    fn state(&self) -> Option<Arc<LineState>> {
        self.0.upgrade()
    }
}

impl LaserLine for DaqLine {
    fn feed(&self) -> std::io::Result<()> {
        let s = self
            .state()
            .ok_or_else(|| std::io::Error::new(std::io::ErrorKind::NotConnected, "the driver is closed"))?;
        if let Some(task) = *s.watchdog() {
            s.lib
                .control_watchdog_task(task, VAL_RESET_TIMER)
                .map_err(|c| std::io::Error::other(failed(&s.lib, &s.who, "DAQmxControlWatchdogTask", c)))?;
        }
        s.beat().map_err(std::io::Error::other)?;
        // Read at every feed (a quarter of the watchdog's timeout): an opening
        // shorter than that can go unseen (docs/configuration.md). A loop that cannot
        // be read is not known closed: the gate goes low, as the watchdog would take
        // it low if the feeds failed.
        if let Err(e) = s.latch_if_interlock_open() {
            warn!(error = %e, "the interlock loop could not be read with the laser gated on: the gate is written low");
            s.gate_low().map_err(std::io::Error::other)?;
            return Err(std::io::Error::other(e));
        }
        Ok(())
    }

    /// A closed driver's line cannot be written: as the serial laser's off switch, this
    /// says so (kind `disconnected`) rather than report an off it did not make, and the
    /// e-stop opens the laser on its own.
    fn off(&self) -> Result<(), DeviceError> {
        let s = self.state().ok_or_else(|| {
            DaqError::new(
                "laser gate",
                ErrorKind::Disconnected,
                "the driver is closed (it wrote the gate low as it closed); open the laser again to switch it off",
            )
        })?;
        s.gate_low().map_err(DeviceError::from)
    }

    /// The library call does not wait for anything of ours.
    fn try_off(&self) -> bool {
        self.state().is_some_and(|s| s.gate_low().is_ok())
    }

    fn describe(&self) -> String {
        self.state()
            .map_or_else(|| "laser gate (driver closed)".to_owned(), |s| s.who.clone())
    }
}

/// The laser gated by a DAQ device's digital line.
pub struct DaqLaser {
    /// The line's tasks: this is their one strong holder, so they are cleared when the
    /// driver closes.
    line: Arc<LineState>,
    guard: LaserGuard,
    settings: DaqLaserSettings,
    diffuser: Option<Task>,
    diffuser_in: bool,
    mode: WatchdogMode,
}

impl ErrorType for DaqLaser {
    type Error = DaqError;
}

impl DaqLaser {
    /// Loads the library, creates a task per line, and writes the gate low (and the
    /// diffuser out): opening leaves the laser off, whatever a process before left.
    /// Refused when neither a watchdog nor a heartbeat is configured and the config
    /// does not accept that.
    pub fn open(settings: DaqLaserSettings) -> Result<DaqLaser, DaqError> {
        let who = format!("laser gate on {}", settings.laser_line);
        let mode = if settings.hardware_watchdog {
            WatchdogMode::Hardware
        } else if settings.heartbeat_line.is_some() {
            WatchdogMode::Heartbeat
        } else if settings.accept_no_watchdog {
            WatchdogMode::Unguarded
        } else {
            return Err(no_watchdog(&who, "daq-watchdog = false"));
        };
        let lib = load(&settings.library)?;
        let fail = |call: &str, c: i32| failed(&lib, &who, call, c);
        let output = |name: &str, line: &str| -> Result<Task, DaqError> {
            let task = lib
                .create_task(&format!("periscope-{name}"))
                .map_err(|c| fail("DAQmxCreateTask", c))?;
            lib.create_do_chan(task, line)
                .map_err(|c| ("DAQmxCreateDOChan", c))
                .and_then(|()| lib.start_task(task).map_err(|c| ("DAQmxStartTask", c)))
                .map_err(|(call, c)| {
                    let e = fail(call, c);
                    let _ = lib.clear_task(task);
                    e
                })?;
            Ok(task)
        };
        let gate = output("laser-gate", &settings.laser_line)?;
        let heartbeat = match &settings.heartbeat_line {
            Some(line) => match output("laser-heartbeat", line) {
                Ok(task) => Some((task, AtomicBool::new(false))),
                Err(e) => {
                    // The gate's task is started: cleared, or the line stays reserved.
                    let _ = lib.stop_task(gate);
                    let _ = lib.clear_task(gate);
                    return Err(e);
                }
            },
            None => None,
        };
        let state = Arc::new(LineState {
            lib: lib.clone(),
            who: who.clone(),
            device: device_of(&settings.laser_line).to_owned(),
            laser_line: settings.laser_line.clone(),
            gate,
            high: AtomicBool::new(false),
            watchdog: Mutex::new(None),
            heartbeat,
            interlock: OnceLock::new(),
            switching: Mutex::new(()),
        });
        state.gate_low()?;
        let guard = LaserGuard::new(
            "laser",
            Some(settings.watchdog),
            settings.watchdog,
            DaqLine(Arc::downgrade(&state)),
        );
        let mut laser = DaqLaser {
            line: state,
            guard,
            diffuser: None,
            diffuser_in: false,
            mode,
            settings,
        };
        if let Some(l) = laser.settings.interlock_line.clone() {
            let task = lib
                .create_task("periscope-interlock")
                .map_err(|c| fail("DAQmxCreateTask", c))?;
            // Cleared with the line's other tasks, which the keepalive may be reading.
            let _ = laser.line.interlock.set(task);
            lib.create_di_chan(task, &l)
                .map_err(|c| fail("DAQmxCreateDIChan", c))?;
            lib.start_task(task).map_err(|c| fail("DAQmxStartTask", c))?;
        } else {
            warn!("laser.interlock-line is not set: the interlock is not read and counts as closed");
        }
        if let Some(l) = laser.settings.diffuser_line.clone() {
            laser.diffuser = Some(output("diffuser", &l)?);
            laser.set_diffuser(false)?;
        }
        Ok(laser)
    }

    fn lib(&self) -> &Lib {
        &self.line.lib
    }

    fn who(&self) -> &str {
        &self.line.who
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> DaqError {
        DaqError::new(self.who(), kind, message)
    }

    /// What ends emission when the host goes quiet, as far as the driver knows (a
    /// device's missing hardware watchdog shows at the first switch-on).
    pub fn watchdog_mode(&self) -> WatchdogMode {
        self.mode
    }

    /// The configured lines.
    pub fn settings(&self) -> &DaqLaserSettings {
        &self.settings
    }
}

/// The refusal to emit without a watchdog.
fn no_watchdog(who: &str, why: &str) -> DaqError {
    DaqError::new(
        who,
        ErrorKind::Device,
        format!(
            "{why}, and no laser.heartbeat-line feeds an external watchdog relay: the laser is not switched on. \
             Wire a watchdog relay in series with the gate and set heartbeat-line, or set \
             laser.accept-no-watchdog = true to accept emission that outlives a crashed host (docs/safety.md)"
        ),
    )
}

impl Drop for DaqLaser {
    fn drop(&mut self) {
        if self.guard.release()
            && let Err(e) = self.line.gate_low()
        {
            warn!(error = %e, "switching the laser off on closing failed");
        }
        if let Some(task) = self.diffuser {
            let _ = self.lib().stop_task(task);
            let _ = self.lib().clear_task(task);
        }
    }
}

impl Laser for DaqLaser {
    /// On: refused while the interlock is open; then the guard arms the watchdog and
    /// the gate goes high. Off: the keepalive stops, the gate goes low, and the
    /// watchdog task is stopped and cleared.
    fn set_emission(&mut self, on: bool) -> Result<(), DaqError> {
        if on {
            if !self.interlock_closed()? {
                return Err(self.err(
                    ErrorKind::Interlock,
                    "the interlock loop is open: close it (door, key switch) before the laser can emit",
                ));
            }
            return self.switch_on();
        }
        // The keepalive stops first; a gate that would not go low keeps its watchdog
        // armed and unfed, so the watchdog drives the line low within its timeout
        // (until 2026-12-06 it was cleared whatever the write did, and a gate stuck
        // high had nothing left to end its emission).
        self.guard.switching_off();
        let off = self.line.gate_low();
        if off.is_ok() {
            self.line.disarm();
        }
        off
    }

    fn laser_state(&mut self) -> Result<LaserState, DaqError> {
        self.line.latch_if_interlock_open()?;
        let expired = match *self.line.watchdog() {
            Some(task) => self
                .lib()
                .watchdog_has_expired(task)
                .map_err(|c| failed(self.lib(), self.who(), "DAQmxGetWatchdogHasExpired", c))?,
            None => false,
        };
        Ok(LaserState {
            emission: self.line.high.load(Ordering::SeqCst) && !expired,
            interlock_closed: self.interlock_closed()?,
            diffuser_in: self.diffuser_in,
        })
    }

    fn interlock_closed(&mut self) -> Result<bool, DaqError> {
        self.line.interlock_closed()
    }

    fn set_diffuser(&mut self, inserted: bool) -> Result<(), DaqError> {
        let Some(task) = self.diffuser else {
            return Err(self.err(
                ErrorKind::OutOfRange,
                "no laser.diffuser-line is configured, so the LOS diffuser cannot be moved: wire it to a digital output and name the line",
            ));
        };
        self.lib()
            .write_digital_lines(task, &[u8::from(inserted)], WRITE_TIMEOUT_S)
            .map_err(|c| failed(self.lib(), self.who(), "DAQmxWriteDigitalLines (diffuser)", c))?;
        warn_of(self.lib(), self.who(), "DAQmxWriteDigitalLines");
        self.diffuser_in = inserted;
        Ok(())
    }

    fn watch_progress(&mut self, progress: Progress) {
        self.guard.watch_progress(progress);
    }

    /// The gate written low from any thread.
    fn emergency_off(&self) -> EmergencyOff {
        self.guard.emergency_off()
    }
}

impl GuardedLaser for DaqLaser {
    type Error = DaqError;

    fn guard(&mut self) -> &mut LaserGuard {
        &mut self.guard
    }

    /// A fresh watchdog timer task on the gate's device, its expiration state low on
    /// the gate line, started (with a heartbeat: one beat, so an external relay has
    /// closed before the gate goes high).
    fn arm_watchdog(&mut self, timeout: Duration) -> Result<(), DaqError> {
        let s = self.line.clone();
        if self.mode == WatchdogMode::Hardware {
            s.disarm();
            let lib = &s.lib;
            match lib.create_watchdog_timer_task_ex(&s.device, "", timeout.as_secs_f64()) {
                Ok(task) => {
                    let armed = lib
                        .cfg_watchdog_do_expir_states(task, &s.laser_line, &[VAL_LOW])
                        .map_err(|c| ("DAQmxCfgWatchdogDOExpirStates", c))
                        .and_then(|()| lib.start_task(task).map_err(|c| ("DAQmxStartTask (watchdog)", c)));
                    if let Err((call, c)) = armed {
                        let e = failed(lib, &s.who, call, c);
                        let _ = lib.clear_task(task);
                        return Err(e);
                    }
                    *s.watchdog() = Some(task);
                }
                Err(code::WATCHDOG_TIMER_NOT_SUPPORTED) => {
                    let device = s.device.clone();
                    if self.settings.heartbeat_line.is_some() {
                        warn!(
                            device,
                            "the DAQ device has no hardware watchdog: the heartbeat line's external relay is the only watchdog"
                        );
                        self.mode = WatchdogMode::Heartbeat;
                    } else if self.settings.accept_no_watchdog {
                        warn!(
                            device,
                            "the DAQ device has no hardware watchdog; emission is unguarded, as the config accepts"
                        );
                        self.mode = WatchdogMode::Unguarded;
                    } else {
                        return Err(no_watchdog(
                            &s.who,
                            &format!(
                                "{device} has no hardware watchdog timer (DAQmxErrorWatchdogTimerNotSupported)"
                            ),
                        ));
                    }
                }
                Err(c) => return Err(failed(lib, &s.who, "DAQmxCreateWatchdogTimerTaskEx", c)),
            }
        }
        if self.mode == WatchdogMode::Unguarded {
            warn!("switching the laser on with no watchdog (laser.accept-no-watchdog = true)");
        }
        s.beat()
    }

    /// The gate written high.
    fn send_on(&mut self) -> Result<(), DaqError> {
        let s = &self.line;
        let _switching = s.switching.lock().unwrap_or_else(|p| p.into_inner());
        s.lib
            .write_digital_lines(s.gate, &[1], WRITE_TIMEOUT_S)
            .map_err(|c| failed(&s.lib, &s.who, "DAQmxWriteDigitalLines", c))?;
        s.high.store(true, Ordering::SeqCst);
        Ok(())
    }

    fn latched_error(&self) -> DaqError {
        self.err(
            ErrorKind::Interrupted,
            "emission was switched off by an emergency stop and stays off with this driver",
        )
    }
}

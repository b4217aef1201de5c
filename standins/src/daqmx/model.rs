//! The simulated DAQ device and its tasks, as NI-DAQmx keeps them per process.
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use periscope_daemon::config::{GalvoLink, InstrumentConfig};
use periscope_drivers::OpticalAngles;
use periscope_drivers::daqmx::defin::{MAX_AO_VOLTS, VAL_HIGH, VAL_LOW, VAL_VOLTS, error};
use periscope_drivers::daqmx::device_of;
use periscope_sim::devices::{Arm, EmissionCause, Rig};

/// A return code: 0 or a negative `DAQmxError…`.
pub(crate) type Code = i32;

/// The environment variable naming the hardware instrument config whose DAQmx wiring
/// the stand-in takes on its first DAQmx call (with [`crate::CONFIG_ENV`] for the rig),
/// for a process that cannot call `PERISCOPE_STANDIN_DaqSetup`.
pub const DAQ_CONFIG_ENV: &str = "PERISCOPE_STANDIN_DAQ_CONFIG";

/// The next task handle: process-wide, so a handle is never given out twice, even
/// across a reset (a driver of an earlier test may still clear its old tasks while
/// its keepalive thread lets go of them). Starts high, so null is never a task.
static NEXT_HANDLE: AtomicUsize = AtomicUsize::new(0x1000);

/// An arm on two analog outputs.
struct AoArm {
    arm: Arm,
    channels: [String; 2],
    volts_per_deg: [f64; 2],
    offsets_v: [f64; 2],
}

/// A watchdog timer task's clock, shared with the thread that counts it down.
pub(crate) struct WatchdogClock {
    pub timeout: Duration,
    pub deadline: Instant,
    pub expired: bool,
}

enum Kind {
    /// Analog output channels with the range each was created with.
    Ao(Vec<(String, f64, f64)>),
    Do(Vec<String>),
    Di(Vec<String>),
    Watchdog {
        device: String,
        /// Lines and their expiration states.
        lines: Vec<(String, i32)>,
        clock: Arc<Mutex<WatchdogClock>>,
        stop: Arc<AtomicBool>,
        thread: Option<JoinHandle<()>>,
    },
}

struct Task {
    name: String,
    kind: Kind,
    started: bool,
}

impl Task {
    /// The physical channels the task reserves once started (a watchdog task's lines
    /// are the expiration states of lines other tasks drive).
    fn channels(&self) -> Vec<String> {
        match &self.kind {
            Kind::Ao(v) => v.iter().map(|(c, _, _)| c.clone()).collect(),
            Kind::Do(v) | Kind::Di(v) => v.clone(),
            Kind::Watchdog { .. } => Vec::new(),
        }
    }
}

/// Whether two physical channels overlap: the same, or a port and one of its lines.
fn same_channel(a: &str, b: &str) -> bool {
    let within = |inner: &str, outer: &str| inner.strip_prefix(outer).is_some_and(|r| r.starts_with('/'));
    a.eq_ignore_ascii_case(b) || within(a, b) || within(b, a)
}

/// The simulated DAQ device and what it is wired to.
pub(crate) struct Daq {
    rig: Rig,
    /// The device's name (`Dev1`), model and serial number.
    pub device: String,
    pub model: String,
    pub serial: u32,
    /// Whether it has a hardware watchdog timer.
    pub watchdog: bool,
    /// Gone from the bus: every call touching it fails with `DAQmxErrorDeviceRemoved`.
    pub vanished: bool,
    arms: Vec<AoArm>,
    laser_line: Option<String>,
    interlock_line: Option<String>,
    diffuser_line: Option<String>,
    heartbeat_line: Option<String>,
    tasks: BTreeMap<usize, Task>,
    /// Lines an expired watchdog task left in their expiration states when it was
    /// cleared: NI-DAQmx keeps a device's expiration past the task until a watchdog
    /// task starts on the device or the device is reset ("WriteDigChan-WatchdogTimer.c":
    /// "If the watchdog timer expires it will stay in the expired state after
    /// execution stops … Starting a watchdog task on the device also clears
    /// expiration."). Writes to them fail as to a live expired task's.
    expired_lines: Vec<String>,
    /// The voltage last written to each analog output.
    volts: BTreeMap<String, f64>,
    /// Writes that sent an arm outside the rig's hard limits (a driver bug: the
    /// driver must refuse such targets).
    pub overdriven: u32,
    /// Times the heartbeat line changed level.
    pub heartbeats: u32,
}

impl Daq {
    /// The DAQmx wiring of the hardware config at `path`, on `rig`. Every DAQmx
    /// channel and line must be on one device (the stand-in has one).
    pub(crate) fn wire(rig: Rig, path: &Path) -> Result<Daq, String> {
        let config = InstrumentConfig::load(path).map_err(|e| e.to_string())?;
        let mut arms = Vec::new();
        let mut names = Vec::new();
        for (arm, a) in [(Arm::Laser, &config.laser_arm), (Arm::Spad, &config.spad_arm)] {
            if let Some(GalvoLink::Daqmx(s)) = &a.link {
                names.extend(s.channels.iter().cloned());
                arms.push(AoArm {
                    arm,
                    channels: s.channels.clone(),
                    volts_per_deg: s.volts_per_deg,
                    offsets_v: s.offsets_v,
                });
            }
        }
        let lines = config.laser.daqmx.clone();
        if let Some(l) = &lines {
            names.push(l.laser_line.clone());
            names.extend(
                l.interlock_line
                    .iter()
                    .chain(&l.diffuser_line)
                    .chain(&l.heartbeat_line)
                    .cloned(),
            );
            rig.gate_externally();
        }
        let device = names
            .first()
            .map(|n| device_of(n).to_owned())
            .ok_or_else(|| format!("{}: no DAQmx galvo or laser line", path.display()))?;
        if let Some(n) = names.iter().find(|n| device_of(n) != device) {
            return Err(format!("{n}: the stand-in has one DAQ device, {device}"));
        }
        Ok(Daq {
            rig,
            device,
            model: "PCIe-6363".into(),
            serial: 0x01A2_B3C4,
            watchdog: true,
            vanished: false,
            arms,
            laser_line: lines.as_ref().map(|l| l.laser_line.clone()),
            interlock_line: lines.as_ref().and_then(|l| l.interlock_line.clone()),
            diffuser_line: lines.as_ref().and_then(|l| l.diffuser_line.clone()),
            heartbeat_line: lines.and_then(|l| l.heartbeat_line),
            tasks: BTreeMap::new(),
            expired_lines: Vec::new(),
            volts: BTreeMap::new(),
            overdriven: 0,
            heartbeats: 0,
        })
    }

    /// The device vanishes: its outputs lose power (the laser's gate drops).
    pub(crate) fn vanish(&mut self) {
        self.vanished = true;
        if self.laser_line.is_some() {
            self.rig.gate_laser(false, EmissionCause::PowerLoss);
        }
    }

    /// Stops every watchdog thread (the stand-in is being reset).
    pub(crate) fn shut_down(&mut self) {
        for (_, t) in std::mem::take(&mut self.tasks) {
            if let Kind::Watchdog { stop, thread, .. } = t.kind {
                stop.store(true, Ordering::SeqCst);
                if let Some(t) = thread {
                    let _ = t.join();
                }
            }
        }
    }

    fn present(&self, device: &str) -> Result<(), Code> {
        if device != self.device {
            Err(error::INVALID_DEVICE_ID)
        } else if self.vanished {
            Err(error::DEVICE_REMOVED)
        } else {
            Ok(())
        }
    }

    /// A physical channel's name checked: on this device, of the right kind.
    fn physical(&self, name: &str, prefix: &str) -> Result<String, Code> {
        let name = name.trim();
        self.present(device_of(name))?;
        let rest = &name[name.find('/').map_or(name.len(), |i| i + 1)..];
        let ok = if prefix == "ao" {
            rest.strip_prefix("ao")
                .is_some_and(|n| n.parse::<u8>().is_ok_and(|n| n < 4))
        } else {
            let mut p = rest.split('/');
            p.next()
                .and_then(|s| s.strip_prefix("port"))
                .is_some_and(|n| n == "0")
                && p.next()
                    .and_then(|s| s.strip_prefix("line"))
                    .is_some_and(|n| n.parse::<u8>().is_ok_and(|n| n < 32))
                && p.next().is_none()
        };
        if ok {
            Ok(name.to_owned())
        } else {
            Err(error::PHYSICAL_CHAN_DOES_NOT_EXIST)
        }
    }

    fn task(&mut self, handle: usize) -> Result<&mut Task, Code> {
        let vanished = self.vanished;
        let t = self.tasks.get_mut(&handle).ok_or(error::INVALID_TASK)?;
        if vanished {
            Err(error::DEVICE_REMOVED)
        } else {
            Ok(t)
        }
    }

    /// A task's name, for the record of calls.
    pub(crate) fn name(&self, handle: usize) -> String {
        self.tasks
            .get(&handle)
            .map_or_else(|| format!("{handle:#x}"), |t| t.name.clone())
    }

    pub(crate) fn create_task(&mut self, name: &str) -> Result<usize, Code> {
        // Task names are unique among the tasks that exist (NI-DAQmx answers
        // `DAQmxErrorDuplicateTask`); an empty name gets a unique one.
        if !name.is_empty() && self.tasks.values().any(|t| t.name.eq_ignore_ascii_case(name)) {
            return Err(error::DUPLICATE_TASK);
        }
        let handle = NEXT_HANDLE.fetch_add(1, Ordering::Relaxed);
        let name = if name.is_empty() {
            format!("task{handle:#x}")
        } else {
            name.to_owned()
        };
        self.tasks.insert(
            handle,
            Task {
                name,
                kind: Kind::Do(Vec::new()),
                started: false,
            },
        );
        Ok(handle)
    }

    pub(crate) fn create_ao(
        &mut self,
        handle: usize,
        channels: &str,
        min: f64,
        max: f64,
        units: i32,
    ) -> Result<(), Code> {
        if units != VAL_VOLTS {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        if !(min < max) {
            return Err(error::MIN_NOT_LESS_THAN_MAX);
        }
        if min < -MAX_AO_VOLTS || max > MAX_AO_VOLTS {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        let list = channels
            .split(',')
            .map(|c| self.physical(c, "ao").map(|c| (c, min, max)))
            .collect::<Result<Vec<_>, _>>()?;
        let t = self.task(handle)?;
        match &mut t.kind {
            Kind::Ao(v) => v.extend(list),
            Kind::Do(v) if v.is_empty() => t.kind = Kind::Ao(list),
            _ => return Err(error::INVALID_ATTRIBUTE_VALUE),
        }
        Ok(())
    }

    pub(crate) fn create_digital(&mut self, handle: usize, lines: &str, output: bool) -> Result<(), Code> {
        let list = lines
            .split(',')
            .map(|c| self.physical(c, "port"))
            .collect::<Result<Vec<_>, _>>()?;
        let t = self.task(handle)?;
        match &mut t.kind {
            Kind::Do(v) if output => v.extend(list),
            Kind::Do(v) if v.is_empty() => t.kind = Kind::Di(list),
            Kind::Di(v) if !output => v.extend(list),
            _ => return Err(error::INVALID_ATTRIBUTE_VALUE),
        }
        Ok(())
    }

    pub(crate) fn start(&mut self, handle: usize) -> Result<(), Code> {
        // A started task reserves its physical channels until it is cleared (NI-DAQmx's
        // "resource is reserved"): another task started on one of them is refused.
        let mine = self.tasks.get(&handle).map(Task::channels).unwrap_or_default();
        let taken = self.tasks.iter().any(|(&h, t)| {
            h != handle
                && t.started
                && t.channels()
                    .iter()
                    .any(|a| mine.iter().any(|b| same_channel(a, b)))
        });
        if taken {
            return Err(error::RESOURCE_ALREADY_RESERVED);
        }
        let rig = self.rig.clone();
        let laser = self.laser_line.clone();
        if matches!(
            self.tasks.get(&handle).map(|t| &t.kind),
            Some(Kind::Watchdog { .. })
        ) {
            // A watchdog task starting clears the device's expiration.
            self.expired_lines.clear();
        }
        let t = self.task(handle)?;
        t.started = true;
        if let Kind::Watchdog {
            clock,
            stop,
            thread,
            lines,
            ..
        } = &mut t.kind
        {
            if thread.is_some() {
                return Ok(());
            }
            {
                let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
                c.deadline = Instant::now() + c.timeout;
                c.expired = false;
            }
            let gates_laser = lines
                .iter()
                .any(|(l, s)| Some(l) == laser.as_ref() && *s == VAL_LOW);
            let (clock, stop) = (clock.clone(), stop.clone());
            *thread = Some(std::thread::spawn(move || {
                count_down(&clock, &stop, gates_laser, &rig)
            }));
        }
        Ok(())
    }

    pub(crate) fn stop(&mut self, handle: usize) -> Result<(), Code> {
        let t = self.tasks.get_mut(&handle).ok_or(error::INVALID_TASK)?;
        t.started = false;
        if let Kind::Watchdog { stop, thread, .. } = &mut t.kind {
            stop.store(true, Ordering::SeqCst);
            if let Some(th) = thread.take() {
                let _ = th.join();
            }
            stop.store(false, Ordering::SeqCst);
        }
        Ok(())
    }

    pub(crate) fn clear(&mut self, handle: usize) -> Result<(), Code> {
        self.stop(handle)?;
        if let Some(Task {
            kind: Kind::Watchdog { lines, clock, .. },
            ..
        }) = self.tasks.remove(&handle)
            && clock.lock().unwrap_or_else(|p| p.into_inner()).expired
        {
            self.expired_lines.extend(lines.into_iter().map(|(l, _)| l));
        }
        Ok(())
    }

    /// An expired watchdog task holding `line`, or one cleared since it expired
    /// (writes to it are refused).
    fn held_by_watchdog(&self, line: &str) -> bool {
        self.expired_lines.iter().any(|l| l == line)
            || self.tasks.values().any(|t| match &t.kind {
                Kind::Watchdog { lines, clock, .. } => {
                    lines.iter().any(|(l, _)| l == line)
                        && clock.lock().unwrap_or_else(|p| p.into_inner()).expired
                }
                _ => false,
            })
    }

    pub(crate) fn write_ao(
        &mut self,
        handle: usize,
        n: i32,
        auto_start: bool,
        volts: &[f64],
    ) -> Result<(), Code> {
        let t = self.task(handle)?;
        let Kind::Ao(channels) = &t.kind else {
            return Err(error::INVALID_TASK);
        };
        if n != 1 || volts.len() != channels.len() {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        if !t.started && !auto_start {
            return Err(error::INVALID_TASK);
        }
        for ((_, lo, hi), v) in channels.iter().zip(volts) {
            if !(*lo..=*hi).contains(v) {
                // What `DAQmxWriteAnalogF64` answers for a value outside the range the
                // channel was created with (NI's AO.Max property page).
                return Err(error::INVALID_AO_DATA_WRITE);
            }
        }
        let names: Vec<String> = channels.iter().map(|(c, _, _)| c.clone()).collect();
        for (c, v) in names.iter().zip(volts) {
            self.volts.insert(c.clone(), *v);
        }
        for a in &self.arms {
            if !a.channels.iter().any(|c| names.contains(c)) {
                continue;
            }
            let v = |i: usize| self.volts.get(&a.channels[i]).copied().unwrap_or(0.0);
            let angles = OpticalAngles {
                x: ((v(0) - a.offsets_v[0]) / a.volts_per_deg[0]).to_radians(),
                y: ((v(1) - a.offsets_v[1]) / a.volts_per_deg[1]).to_radians(),
            };
            let park = angles.x.abs() < 1e-9 && angles.y.abs() < 1e-9;
            if !self.rig.drive_galvo(a.arm, angles, park) {
                self.overdriven += 1;
            }
        }
        Ok(())
    }

    pub(crate) fn write_do(&mut self, handle: usize, n: i32, levels: &[u8]) -> Result<(), Code> {
        let t = self.task(handle)?;
        let Kind::Do(lines) = &t.kind else {
            return Err(error::INVALID_TASK);
        };
        if n != 1 || levels.len() != lines.len() {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        let lines = lines.clone();
        if lines.iter().any(|l| self.held_by_watchdog(l)) {
            return Err(error::WRITE_FAILED_BECAUSE_WATCHDOG_EXPIRED);
        }
        for (line, level) in lines.iter().zip(levels) {
            let high = *level != 0;
            if Some(line) == self.laser_line.as_ref() {
                self.rig.gate_laser(high, EmissionCause::Host);
            } else if Some(line) == self.diffuser_line.as_ref() {
                self.rig.drive_diffuser(high);
            } else if Some(line) == self.heartbeat_line.as_ref() {
                self.heartbeats += 1;
            }
        }
        Ok(())
    }

    pub(crate) fn read_di(&mut self, handle: usize, out: &mut [u8]) -> Result<i32, Code> {
        let interlock = self.interlock_line.clone();
        let closed = self.rig.interlock_closed();
        let t = self.task(handle)?;
        let Kind::Di(lines) = &t.kind else {
            return Err(error::INVALID_TASK);
        };
        if out.len() < lines.len() {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        for (o, l) in out.iter_mut().zip(lines) {
            *o = u8::from(Some(l) == interlock.as_ref() && closed);
        }
        Ok(1)
    }

    pub(crate) fn create_watchdog(&mut self, device: &str, name: &str, timeout: f64) -> Result<usize, Code> {
        self.present(device)?;
        if !self.watchdog {
            return Err(error::WATCHDOG_TIMER_NOT_SUPPORTED);
        }
        if !(timeout > 0.0 && timeout < 1e6) {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        let handle = self.create_task(name)?;
        let timeout = Duration::from_secs_f64(timeout);
        self.task(handle)?.kind = Kind::Watchdog {
            device: device.to_owned(),
            lines: Vec::new(),
            clock: Arc::new(Mutex::new(WatchdogClock {
                timeout,
                deadline: Instant::now() + timeout,
                expired: false,
            })),
            stop: Arc::new(AtomicBool::new(false)),
            thread: None,
        };
        Ok(handle)
    }

    pub(crate) fn cfg_watchdog_do(&mut self, handle: usize, lines: &str, states: &[i32]) -> Result<(), Code> {
        let list = lines
            .split(',')
            .map(|c| self.physical(c, "port"))
            .collect::<Result<Vec<_>, _>>()?;
        if list.len() != states.len() || states.iter().any(|s| *s != VAL_LOW && *s != VAL_HIGH) {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        let t = self.task(handle)?;
        match &mut t.kind {
            Kind::Watchdog { lines, device, .. } if list.iter().all(|l| device_of(l) == device) => {
                lines.extend(list.into_iter().zip(states.iter().copied()));
                Ok(())
            }
            _ => Err(error::INVALID_TASK),
        }
    }

    pub(crate) fn watchdog_clock(&mut self, handle: usize) -> Result<Arc<Mutex<WatchdogClock>>, Code> {
        match &self.task(handle)?.kind {
            Kind::Watchdog { clock, .. } => Ok(clock.clone()),
            _ => Err(error::INVALID_TASK),
        }
    }
}

/// The watchdog timer counting down: when its deadline passes unreset, its lines go
/// to their expiration states (the laser's gate low: the rig's laser off, recorded as
/// the watchdog's doing).
fn count_down(clock: &Mutex<WatchdogClock>, stop: &AtomicBool, gates_laser: bool, rig: &Rig) {
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_micros(500));
        let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
        if !c.expired && Instant::now() >= c.deadline {
            c.expired = true;
            if gates_laser {
                rig.gate_laser(false, EmissionCause::Watchdog);
            }
        }
    }
}

/// `DAQmxGetErrorString`'s words for the codes the stand-in gives.
pub(crate) fn error_name(code: Code) -> Option<&'static str> {
    Some(match code {
        0 => "no error",
        error::DEVICE_REMOVED => "DAQmxErrorDeviceRemoved: the device has been removed from the system",
        error::INVALID_DEVICE_ID => "DAQmxErrorInvalidDeviceID: device identifier is invalid",
        error::INVALID_TASK => "DAQmxErrorInvalidTask: task specified is invalid or does not exist",
        error::INVALID_ATTRIBUTE_VALUE => {
            "DAQmxErrorInvalidAttributeValue: requested value is not a supported value"
        }
        error::MIN_NOT_LESS_THAN_MAX => "DAQmxErrorMinNotLessThanMax: minimum is not less than maximum",
        error::PHYSICAL_CHAN_DOES_NOT_EXIST => {
            "DAQmxErrorPhysicalChanDoesNotExist: physical channel does not exist"
        }
        error::SAMPLE_VALUE_OUT_OF_RANGE => {
            "DAQmxErrorSampleValueOutOfRange: sample value is outside the channel's range"
        }
        error::INVALID_AO_DATA_WRITE => {
            "DAQmxErrorInvalidAODataWrite: attempted writing analog data that is too large or too small"
        }
        error::DUPLICATE_TASK => "DAQmxErrorDuplicateTask: a task with this name already exists",
        error::RESOURCE_ALREADY_RESERVED => {
            "DAQmxErrorResourceAlreadyReserved: the resource is reserved by another task"
        }
        error::OPERATION_TIMED_OUT => "DAQmxErrorOperationTimedOut: the operation timed out",
        error::WATCHDOG_TIMER_NOT_SUPPORTED => {
            "DAQmxErrorWatchdogTimerNotSupported: the device does not support a watchdog timer"
        }
        error::WRITE_FAILED_BECAUSE_WATCHDOG_EXPIRED => {
            "DAQmxErrorWriteFailedBecauseWatchdogExpired: the watchdog timer expired; clear the expiration first"
        }
        -200644 => "DAQmxErrorCantResetExpiredWatchdog: cannot reset an expired watchdog timer",
        _ => return None,
    })
}

impl Daq {
    /// The number of analog output channels of a task.
    pub(crate) fn ao_width(&mut self, handle: usize) -> Result<usize, Code> {
        match &self.task(handle)?.kind {
            Kind::Ao(c) => Ok(c.len()),
            _ => Err(error::INVALID_TASK),
        }
    }

    /// The number of lines of a digital task.
    pub(crate) fn digital_width(&mut self, handle: usize) -> Result<usize, Code> {
        match &self.task(handle)?.kind {
            Kind::Do(l) | Kind::Di(l) => Ok(l.len()),
            _ => Err(error::INVALID_TASK),
        }
    }

    /// `device` is this one, present.
    pub(crate) fn check_device(&self, device: &str) -> Result<(), Code> {
        self.present(device)
    }
}

//! NI-DAQmx's C functions, exported under their documented names with the prototypes
//! `NIDAQmx.h` declares (`int32` a C `int`, `uInt32`/`bool32` unsigned, `float64` a
//! double, `TaskHandle` a `void*`): each records the call, answers a failure a test
//! queued for it, and otherwise asks the device model. A failure's words are kept for
//! `DAQmxGetExtendedErrorInfo` on the calling thread, as the library keeps them.
//!
//! Then the DAQmx test controls, named `PERISCOPE_STANDIN_Daq*`.
use std::cell::RefCell;
use std::ffi::{CStr, c_char, c_double, c_int, c_uint, c_void};
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::time::Instant;

use periscope_drivers::daqmx::defin::{VAL_CLEAR_EXPIRATION, VAL_RESET_TIMER, error};

use super::model::{Code, error_name};
use crate::state::{State, lock};

thread_local! {
    /// The last failure's description on this thread.
    static LAST_ERROR: RefCell<String> = const { RefCell::new(String::new()) };
}

type TaskHandle = *mut c_void;

/// Runs one library call on the state: records it, answers a queued failure, or runs
/// `f`; a failure's words are kept for `DAQmxGetExtendedErrorInfo`. A panic becomes an
/// error code instead of unwinding into C.
fn call(function: &str, args: String, f: impl FnOnce(&mut State) -> Result<(), Code>) -> c_int {
    let r = std::panic::catch_unwind(AssertUnwindSafe(|| {
        let mut guard = lock();
        let state = guard.as_mut().expect("created by lock");
        state.enter_daq(function, args)?;
        f(state)
    }));
    let code = match r {
        Ok(Ok(())) => return 0,
        Ok(Err(code)) => code,
        Err(_) => error::INVALID_TASK,
    };
    let words = error_name(code).unwrap_or("an error the test queued");
    LAST_ERROR
        .with(|e| *e.borrow_mut() = format!("{words}.\nTask or function: {function}\nStatus Code: {code}"));
    code
}

/// Reads a C string argument (`INVALID_ATTRIBUTE_VALUE` for null).
///
/// # Safety
/// `s` is null or a NUL-terminated string.
unsafe fn text(s: *const c_char) -> Result<String, Code> {
    if s.is_null() {
        return Err(error::INVALID_ATTRIBUTE_VALUE);
    }
    // SAFETY: NUL-terminated per the caller.
    Ok(unsafe { CStr::from_ptr(s) }.to_string_lossy().into_owned())
}

/// A string argument for the record of calls.
///
/// # Safety
/// `s` is null or a NUL-terminated string.
unsafe fn shown(s: *const c_char) -> String {
    // SAFETY: per the caller.
    unsafe { text(s) }.unwrap_or_else(|_| "NULL".into())
}

/// Writes `s` NUL-terminated into `dst` of `cap` bytes; a string that does not fit is
/// refused as NI-DAQmx refuses it (`DAQmxErrorBufferTooSmallForString`).
///
/// # Safety
/// `dst` is null or valid for writes of `cap` bytes.
unsafe fn put_text(dst: *mut c_char, cap: c_uint, s: &str) -> Result<(), Code> {
    if dst.is_null() {
        return Err(error::INVALID_ATTRIBUTE_VALUE);
    }
    if s.len() + 1 > cap as usize {
        return Err(error::BUFFER_TOO_SMALL_FOR_STRING);
    }
    // SAFETY: `s.len() + 1 <= cap` bytes, writable per the caller.
    unsafe {
        std::ptr::copy_nonoverlapping(s.as_ptr(), dst.cast::<u8>(), s.len());
        *dst.add(s.len()) = 0;
    }
    Ok(())
}

/// Writes one value through `dst`, if it is not null.
///
/// # Safety
/// `dst` is null or valid for one write of `T`.
unsafe fn put<T>(dst: *mut T, v: T) {
    if !dst.is_null() {
        // SAFETY: non-null, and valid per the caller.
        unsafe { dst.write(v) };
    }
}

/// Rewrites the record of the call in progress (with the task's name and the values
/// written, which only the call's body knows).
fn shown_as(s: &mut State, text: String) {
    if let Some(c) = s.calls.last_mut() {
        *c = text;
    }
}

fn handle(t: TaskHandle) -> usize {
    t as usize
}

/// `DAQmxCreateTask`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `name` is NUL-terminated; `task` is valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCreateTask(name: *const c_char, task: *mut TaskHandle) -> c_int {
    // SAFETY: per the contract.
    let name = unsafe { text(name) };
    call(
        "DAQmxCreateTask",
        format!("{:?}", name.as_deref().unwrap_or("NULL")),
        |s| {
            if task.is_null() {
                return Err(error::INVALID_ATTRIBUTE_VALUE);
            }
            let h = s.daq()?.create_task(&name?)?;
            // SAFETY: non-null, valid per the contract.
            unsafe { put(task, h as TaskHandle) };
            Ok(())
        },
    )
}

macro_rules! task_fn {
    ($name:ident, $method:ident) => {
        #[doc = concat!("`", stringify!($name), "`, as `NIDAQmx.h` declares it.")]
        #[unsafe(no_mangle)]
        pub extern "C" fn $name(task: TaskHandle) -> c_int {
            call(stringify!($name), String::new(), |s| {
                let d = s.daq()?;
                let n = d.name(handle(task));
                shown_as(s, format!("{}({n})", stringify!($name)));
                s.daq()?.$method(handle(task))
            })
        }
    };
}
task_fn!(DAQmxStartTask, start);
task_fn!(DAQmxStopTask, stop);
task_fn!(DAQmxClearTask, clear);

/// `DAQmxCreateAOVoltageChan`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// String arguments are null or NUL-terminated.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCreateAOVoltageChan(
    task: TaskHandle,
    physical: *const c_char,
    _name: *const c_char,
    min: c_double,
    max: c_double,
    units: c_int,
    _scale: *const c_char,
) -> c_int {
    // SAFETY: per the contract.
    let physical = unsafe { text(physical) };
    let shown = physical.clone().unwrap_or_default();
    call(
        "DAQmxCreateAOVoltageChan",
        format!("{shown}, {min}, {max}, {units}"),
        |s| s.daq()?.create_ao(handle(task), &physical?, min, max, units),
    )
}

/// `DAQmxCreateDOChan`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// String arguments are null or NUL-terminated.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCreateDOChan(
    task: TaskHandle,
    lines: *const c_char,
    _name: *const c_char,
    grouping: c_int,
) -> c_int {
    // SAFETY: per the contract.
    let lines = unsafe { text(lines) };
    let shown = lines.clone().unwrap_or_default();
    call("DAQmxCreateDOChan", format!("{shown}, {grouping}"), |s| {
        s.daq()?.create_digital(handle(task), &lines?, true)
    })
}

/// `DAQmxCreateDIChan`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// String arguments are null or NUL-terminated.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCreateDIChan(
    task: TaskHandle,
    lines: *const c_char,
    _name: *const c_char,
    grouping: c_int,
) -> c_int {
    // SAFETY: per the contract.
    let lines = unsafe { text(lines) };
    let shown = lines.clone().unwrap_or_default();
    call("DAQmxCreateDIChan", format!("{shown}, {grouping}"), |s| {
        s.daq()?.create_digital(handle(task), &lines?, false)
    })
}

/// How many channels a task has, for reading the right number of samples.
fn width(s: &mut State, task: TaskHandle, ao: bool) -> Result<usize, Code> {
    let d = s.daq()?;
    Ok(if ao {
        d.ao_width(handle(task))?
    } else {
        d.digital_width(handle(task))?
    })
}

/// `DAQmxWriteAnalogF64`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `data` holds `samples` values per channel of the task; `written` is null or valid
/// for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxWriteAnalogF64(
    task: TaskHandle,
    samples: c_int,
    auto_start: c_uint,
    _timeout: c_double,
    _layout: c_uint,
    data: *const c_double,
    written: *mut c_int,
    _reserved: *mut c_uint,
) -> c_int {
    call("DAQmxWriteAnalogF64", String::new(), |s| {
        let n = width(s, task, true)?;
        if data.is_null() || samples != 1 {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        // SAFETY: one sample per channel of the task, per the contract.
        let volts = unsafe { std::slice::from_raw_parts(data, n) }.to_vec();
        let name = s.daq()?.name(handle(task));
        let shown: Vec<String> = volts.iter().map(|v| format!("{v:.6}")).collect();
        shown_as(s, format!("DAQmxWriteAnalogF64({name}, [{}])", shown.join(", ")));
        s.daq()?
            .write_ao(handle(task), samples, auto_start != 0, &volts)?;
        // SAFETY: null or valid per the contract.
        unsafe { put(written, samples) };
        Ok(())
    })
}

/// `DAQmxWriteDigitalLines`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `data` holds one byte per line of the task; `written` is null or valid for one
/// write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxWriteDigitalLines(
    task: TaskHandle,
    samples: c_int,
    _auto_start: c_uint,
    _timeout: c_double,
    _layout: c_uint,
    data: *const u8,
    written: *mut c_int,
    _reserved: *mut c_uint,
) -> c_int {
    call("DAQmxWriteDigitalLines", String::new(), |s| {
        let n = width(s, task, false)?;
        if data.is_null() || samples != 1 {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        // SAFETY: one byte per line of the task, per the contract.
        let levels = unsafe { std::slice::from_raw_parts(data, n) }.to_vec();
        let name = s.daq()?.name(handle(task));
        shown_as(s, format!("DAQmxWriteDigitalLines({name}, {levels:?})"));
        s.daq()?.write_do(handle(task), samples, &levels)?;
        // SAFETY: null or valid per the contract.
        unsafe { put(written, samples) };
        Ok(())
    })
}

/// `DAQmxReadDigitalLines`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `data` is valid for writes of `size` bytes; the out-pointers are null or valid for
/// one write each.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxReadDigitalLines(
    task: TaskHandle,
    samples: c_int,
    _timeout: c_double,
    _fill: c_uint,
    data: *mut u8,
    size: c_uint,
    read: *mut c_int,
    bytes_per_sample: *mut c_int,
    _reserved: *mut c_uint,
) -> c_int {
    call("DAQmxReadDigitalLines", String::new(), |s| {
        let name = s.daq()?.name(handle(task));
        shown_as(s, format!("DAQmxReadDigitalLines({name})"));
        if data.is_null() || samples != 1 {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        // SAFETY: `size` writable bytes, per the contract.
        let out = unsafe { std::slice::from_raw_parts_mut(data, size as usize) };
        let n = s.daq()?.read_di(handle(task), out)?;
        // SAFETY: null or valid per the contract.
        unsafe {
            put(read, n);
            put(bytes_per_sample, 1);
        }
        Ok(())
    })
}

/// `DAQmxCreateWatchdogTimerTaskEx`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// String arguments are null or NUL-terminated; `task` is valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCreateWatchdogTimerTaskEx(
    device: *const c_char,
    name: *const c_char,
    task: *mut TaskHandle,
    timeout: c_double,
) -> c_int {
    // SAFETY: per the contract.
    let (device, name) = unsafe { (text(device), shown(name)) };
    let dev = device.clone().unwrap_or_default();
    call(
        "DAQmxCreateWatchdogTimerTaskEx",
        format!("{dev}, {timeout}"),
        |s| {
            if task.is_null() {
                return Err(error::INVALID_ATTRIBUTE_VALUE);
            }
            let name = if name.is_empty() {
                "watchdog".to_owned()
            } else {
                name
            };
            let h = s.daq()?.create_watchdog(&device?, &name, timeout)?;
            // SAFETY: non-null, valid per the contract.
            unsafe { put(task, h as TaskHandle) };
            Ok(())
        },
    )
}

/// `DAQmxCfgWatchdogDOExpirStates`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `lines` is NUL-terminated; `states` holds `n` values.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxCfgWatchdogDOExpirStates(
    task: TaskHandle,
    lines: *const c_char,
    states: *const c_int,
    n: c_uint,
) -> c_int {
    // SAFETY: per the contract.
    let lines = unsafe { text(lines) };
    let states: Vec<i32> = if states.is_null() {
        Vec::new()
    } else {
        // SAFETY: `n` values, per the contract.
        unsafe { std::slice::from_raw_parts(states, n as usize) }.to_vec()
    };
    let shown = lines.clone().unwrap_or_default();
    call(
        "DAQmxCfgWatchdogDOExpirStates",
        format!("{shown}, {states:?}"),
        |s| s.daq()?.cfg_watchdog_do(handle(task), &lines?, &states),
    )
}

/// `DAQmxControlWatchdogTask`, as `NIDAQmx.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn DAQmxControlWatchdogTask(task: TaskHandle, action: c_int) -> c_int {
    call("DAQmxControlWatchdogTask", format!("{action}"), |s| {
        let clock = s.daq()?.watchdog_clock(handle(task))?;
        let mut c = clock.lock().unwrap_or_else(|p| p.into_inner());
        match action {
            VAL_RESET_TIMER if c.expired => Err(-200644),
            VAL_RESET_TIMER => {
                c.deadline = Instant::now() + c.timeout;
                Ok(())
            }
            VAL_CLEAR_EXPIRATION => {
                c.expired = false;
                c.deadline = Instant::now() + c.timeout;
                Ok(())
            }
            _ => Err(error::INVALID_ATTRIBUTE_VALUE),
        }
    })
}

/// `DAQmxGetWatchdogHasExpired`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `expired` is valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetWatchdogHasExpired(task: TaskHandle, expired: *mut c_uint) -> c_int {
    call("DAQmxGetWatchdogHasExpired", String::new(), |s| {
        let clock = s.daq()?.watchdog_clock(handle(task))?;
        let e = clock.lock().unwrap_or_else(|p| p.into_inner()).expired;
        if expired.is_null() {
            return Err(error::INVALID_ATTRIBUTE_VALUE);
        }
        // SAFETY: non-null, valid per the contract.
        unsafe { put(expired, c_uint::from(e)) };
        Ok(())
    })
}

/// A task's width for the two getters below, asked of the model without recording a
/// call (the driver asks before each write; the record is of what it does).
///
/// # Safety
/// `data` is null or valid for one write.
unsafe fn task_width(
    task: TaskHandle,
    data: *mut c_uint,
    f: impl FnOnce(&mut super::Daq, usize) -> Result<usize, Code>,
) -> c_int {
    let r = std::panic::catch_unwind(AssertUnwindSafe(|| {
        let mut guard = lock();
        let state = guard.as_mut().expect("created by lock");
        f(state.daq()?, handle(task))
    }));
    match r {
        Ok(Ok(n)) if !data.is_null() => {
            // SAFETY: non-null, valid per the contract.
            unsafe { put(data, c_uint::try_from(n).unwrap_or(c_uint::MAX)) };
            0
        }
        Ok(Ok(_)) => error::INVALID_ATTRIBUTE_VALUE,
        Ok(Err(code)) => code,
        Err(_) => error::INVALID_TASK,
    }
}

/// `DAQmxGetTaskNumChans`, as `NIDAQmx.h` declares it: an analog output task's
/// channels; a digital task is one channel of all its lines (`DAQmx_Val_ChanForAllLines`,
/// as the driver creates them). Not recorded as a call.
///
/// # Safety
/// `data` is null or valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetTaskNumChans(task: TaskHandle, data: *mut c_uint) -> c_int {
    // SAFETY: per the contract.
    unsafe {
        task_width(task, data, |d, h| match d.ao_width(h) {
            Ok(n) => Ok(n),
            Err(_) => d.digital_width(h).map(|_| 1),
        })
    }
}

/// `DAQmxGetWriteDigitalLinesBytesPerChan`, as `NIDAQmx.h` declares it: the lines of
/// the task's one channel. Not recorded as a call.
///
/// # Safety
/// `data` is null or valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetWriteDigitalLinesBytesPerChan(task: TaskHandle, data: *mut c_uint) -> c_int {
    // SAFETY: per the contract.
    unsafe { task_width(task, data, |d, h| d.digital_width(h)) }
}

/// `DAQmxGetExtendedErrorInfo`, as `NIDAQmx.h` declares it: the last failure on this
/// thread. Not recorded as a call (it is how a caller reads a failure, not an action).
///
/// # Safety
/// `buf` is null or valid for writes of `size` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetExtendedErrorInfo(buf: *mut c_char, size: c_uint) -> c_int {
    let text = LAST_ERROR.with(|e| e.borrow().clone());
    if buf.is_null() || size == 0 {
        return c_int::try_from(text.len() + 1).unwrap_or(c_int::MAX);
    }
    let cut = &text[..text.len().min(size as usize - 1)];
    // SAFETY: `cut` fits, per the contract.
    match unsafe { put_text(buf, size, cut) } {
        Ok(()) => 0,
        Err(c) => c,
    }
}

/// `DAQmxGetErrorString`, as `NIDAQmx.h` declares it. Not recorded as a call.
///
/// # Safety
/// `buf` is null or valid for writes of `size` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetErrorString(code: c_int, buf: *mut c_char, size: c_uint) -> c_int {
    let text = error_name(code).map_or_else(|| format!("error {code}"), str::to_owned);
    if buf.is_null() || size == 0 {
        return c_int::try_from(text.len() + 1).unwrap_or(c_int::MAX);
    }
    let cut = &text[..text.len().min(size as usize - 1)];
    // SAFETY: `cut` fits, per the contract.
    match unsafe { put_text(buf, size, cut) } {
        Ok(()) => 0,
        Err(c) => c,
    }
}

/// `DAQmxGetSysDevNames`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `buf` is valid for writes of `size` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetSysDevNames(buf: *mut c_char, size: c_uint) -> c_int {
    call("DAQmxGetSysDevNames", String::new(), |s| {
        let names = match s.daq() {
            Ok(d) if !d.vanished => d.device.clone(),
            _ => String::new(),
        };
        // SAFETY: per the contract.
        unsafe { put_text(buf, size, &names) }
    })
}

/// `DAQmxGetDevProductType`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `device` is NUL-terminated; `buf` is valid for writes of `size` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetDevProductType(
    device: *const c_char,
    buf: *mut c_char,
    size: c_uint,
) -> c_int {
    // SAFETY: per the contract.
    let device = unsafe { text(device) };
    call(
        "DAQmxGetDevProductType",
        device.clone().unwrap_or_default(),
        |s| {
            let d = s.daq()?;
            d.check_device(&device?)?;
            // SAFETY: per the contract.
            unsafe { put_text(buf, size, &d.model) }
        },
    )
}

/// `DAQmxGetDevSerialNum`, as `NIDAQmx.h` declares it.
///
/// # Safety
/// `device` is NUL-terminated; `serial` is valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn DAQmxGetDevSerialNum(device: *const c_char, serial: *mut c_uint) -> c_int {
    // SAFETY: per the contract.
    let device = unsafe { text(device) };
    call("DAQmxGetDevSerialNum", device.clone().unwrap_or_default(), |s| {
        let d = s.daq()?;
        d.check_device(&device?)?;
        // SAFETY: per the contract.
        unsafe { put(serial, d.serial) };
        Ok(())
    })
}

/// Runs a control on the state; a failure or a panic is printed and becomes -1.
fn control(what: &str, f: impl FnOnce(&mut State) -> Result<c_int, String>) -> c_int {
    crate::control::control(what, f)
}

/// Wires the simulated DAQ device as the hardware instrument config at `path` says
/// (its DAQmx galvo tables and `[laser]` lines), on the rig set up before; the rig's
/// laser is then gated by the laser line.
///
/// # Safety
/// `path` is NUL-terminated.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_DaqSetup(path: *const c_char) -> c_int {
    // SAFETY: per the contract.
    let path = unsafe { text(path) };
    control("DaqSetup", |s| {
        let path = path.map_err(|_| "null path".to_owned())?;
        s.wire_daq(Path::new(&path))?;
        Ok(0)
    })
}

/// The next call of the DAQmx function `function` (its full name) returns `code`.
///
/// # Safety
/// `function` is NUL-terminated.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_DaqFailNext(function: *const c_char, code: c_int) -> c_int {
    // SAFETY: per the contract.
    let function = unsafe { text(function) };
    control("DaqFailNext", |s| {
        s.daq_fail_next
            .push((function.map_err(|_| "null name".to_owned())?, code));
        Ok(0)
    })
}

/// The DAQ device vanishes now: its outputs lose power (the laser's gate drops, the
/// rig's log says power loss) and every call touching it fails with
/// `DAQmxErrorDeviceRemoved`.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_DaqVanish() -> c_int {
    control("DaqVanish", |s| {
        s.daq().map_err(|c| format!("no DAQ wired ({c})"))?.vanish();
        Ok(0)
    })
}

/// Whether the DAQ device has a hardware watchdog timer (1, the default) or not (0).
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_DaqWatchdogSupported(supported: c_int) -> c_int {
    control("DaqWatchdogSupported", |s| {
        s.daq().map_err(|c| format!("no DAQ wired ({c})"))?.watchdog = supported != 0;
        Ok(0)
    })
}

/// Counters of the DAQ device: writes that drove an arm outside the rig's hard limits
/// (written through `overdriven`) and heartbeat line changes (returned).
///
/// # Safety
/// `overdriven` is null or valid for one write.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_DaqCounters(overdriven: *mut c_uint) -> c_int {
    control("DaqCounters", |s| {
        let d = s.daq().map_err(|c| format!("no DAQ wired ({c})"))?;
        // SAFETY: null or valid per the contract.
        unsafe { put(overdriven, d.overdriven) };
        Ok(c_int::try_from(d.heartbeats).unwrap_or(c_int::MAX))
    })
}

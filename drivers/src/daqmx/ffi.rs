//! NI-DAQmx's C library, loaded at run time: the one module of the DAQmx driver with
//! `unsafe` code (as `picoquant/ffi.rs` is for PicoQuant's). It looks up each function
//! the driver calls by its documented name with the prototype `NIDAQmx.h` declares
//! (`int32` is a C `int` on Linux, `uInt32` and `bool32` unsigned ints, `float64` a
//! double, `TaskHandle` a `void*`), and wraps each call in a safe method that owns the
//! strings and buffers the library reads or writes. Return codes come back unchanged:
//! `Err(code)` for a negative one (an error), `Ok` otherwise, with a positive code (a
//! warning) reported through [`Lib::take_warning`].
//!
//! A task handle is kept as the address it holds ([`Task`]) so the safe types that own
//! one can cross threads; it becomes a pointer again only here, at the call. NI-DAQmx
//! is documented as thread-safe, so the laser's off switch may call into a task from
//! another thread while the driver's thread waits.
#![allow(unsafe_code)]

use std::ffi::{CString, c_char, c_double, c_int, c_uint, c_void};
use std::path::Path;
use std::sync::atomic::{AtomicI32, Ordering};

use libloading::Library;

use super::defin::{VAL_CHAN_FOR_ALL_LINES, VAL_GROUP_BY_CHANNEL, VAL_VOLTS, error};

/// A `TaskHandle`, as the address it holds.
pub(crate) type Task = usize;

type TaskHandle = *mut c_void;
type FnCreateTask = unsafe extern "C" fn(*const c_char, *mut TaskHandle) -> c_int;
type FnTask = unsafe extern "C" fn(TaskHandle) -> c_int;
type FnCreateAoVoltageChan = unsafe extern "C" fn(
    TaskHandle,
    *const c_char,
    *const c_char,
    c_double,
    c_double,
    c_int,
    *const c_char,
) -> c_int;
type FnCreateDigitalChan = unsafe extern "C" fn(TaskHandle, *const c_char, *const c_char, c_int) -> c_int;
type FnWriteAnalogF64 = unsafe extern "C" fn(
    TaskHandle,
    c_int,
    c_uint,
    c_double,
    c_uint,
    *const c_double,
    *mut c_int,
    *mut c_uint,
) -> c_int;
type FnWriteDigitalLines = unsafe extern "C" fn(
    TaskHandle,
    c_int,
    c_uint,
    c_double,
    c_uint,
    *const u8,
    *mut c_int,
    *mut c_uint,
) -> c_int;
type FnReadDigitalLines = unsafe extern "C" fn(
    TaskHandle,
    c_int,
    c_double,
    c_uint,
    *mut u8,
    c_uint,
    *mut c_int,
    *mut c_int,
    *mut c_uint,
) -> c_int;
type FnCreateWatchdog =
    unsafe extern "C" fn(*const c_char, *const c_char, *mut TaskHandle, c_double) -> c_int;
type FnCfgWatchdogDo = unsafe extern "C" fn(TaskHandle, *const c_char, *const c_int, c_uint) -> c_int;
type FnControlWatchdog = unsafe extern "C" fn(TaskHandle, c_int) -> c_int;
type FnTaskOutBool = unsafe extern "C" fn(TaskHandle, *mut c_uint) -> c_int;
type FnTaskOutU32 = unsafe extern "C" fn(TaskHandle, *mut c_uint) -> c_int;
type FnExtendedErrorInfo = unsafe extern "C" fn(*mut c_char, c_uint) -> c_int;
type FnErrorString = unsafe extern "C" fn(c_int, *mut c_char, c_uint) -> c_int;
type FnText = unsafe extern "C" fn(*mut c_char, c_uint) -> c_int;
type FnDevText = unsafe extern "C" fn(*const c_char, *mut c_char, c_uint) -> c_int;
type FnDevU32 = unsafe extern "C" fn(*const c_char, *mut c_uint) -> c_int;

/// Text buffers for error strings and names: NI's examples use 2,048 bytes for the
/// extended error information; a longer text is cut, never overrun.
const TEXT: usize = 2048;
/// The device list may be long on a PXI chassis.
const DEVICE_LIST: usize = 16_384;

/// The library's functions: plain function pointers copied out of the library, valid
/// for the process's life, which the library stays loaded for (`crate::resident`).
struct Api {
    create_task: FnCreateTask,
    start_task: FnTask,
    stop_task: FnTask,
    clear_task: FnTask,
    create_ao_voltage_chan: FnCreateAoVoltageChan,
    create_do_chan: FnCreateDigitalChan,
    create_di_chan: FnCreateDigitalChan,
    write_analog_f64: FnWriteAnalogF64,
    write_digital_lines: FnWriteDigitalLines,
    read_digital_lines: FnReadDigitalLines,
    create_watchdog_timer_task_ex: FnCreateWatchdog,
    cfg_watchdog_do_expir_states: FnCfgWatchdogDo,
    control_watchdog_task: FnControlWatchdog,
    get_watchdog_has_expired: FnTaskOutBool,
    get_task_num_chans: FnTaskOutU32,
    get_write_digital_lines_bytes_per_chan: FnTaskOutU32,
    get_extended_error_info: FnExtendedErrorInfo,
    get_error_string: FnErrorString,
    get_sys_dev_names: FnText,
    get_dev_product_type: FnDevText,
    get_dev_serial_num: FnDevU32,
}

/// NI-DAQmx's library, loaded.
pub(crate) struct Lib {
    api: Api,
    /// The last warning (positive code) a call returned, 0 if none since it was taken.
    warning: AtomicI32,
}

/// Why the library could not be used.
#[derive(Debug)]
pub(crate) enum LoadError {
    /// `dlopen` failed (no such file, wrong architecture, missing dependency).
    Open(String),
    /// A function the driver calls is missing (another library, or too old a version).
    Missing(String, String),
}

/// Reads a NUL-terminated string the library wrote into `buf`.
fn text(buf: &[u8]) -> String {
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..end]).trim().to_owned()
}

/// A C string of `s`; a name with a NUL inside cannot name a channel, so it becomes
/// the empty string (which the library refuses as a channel name).
fn c(s: &str) -> CString {
    CString::new(s).unwrap_or_default()
}

/// Buffer sizes as the `uInt32` the prototypes take (every buffer here is small).
fn len32(n: usize) -> c_uint {
    c_uint::try_from(n).unwrap_or(c_uint::MAX)
}

fn ptr(task: Task) -> TaskHandle {
    task as TaskHandle
}

impl Lib {
    /// Loads the library at `path` and looks up every function the driver calls.
    pub(crate) fn load(path: &Path) -> Result<Lib, LoadError> {
        // Kept loaded for the process's life (`crate::resident`): never unloaded
        // under a task or thread of the library's own.
        let library = crate::resident::resident(path, || {
            // SAFETY: loading runs the library's initialisers. The path is NI-DAQmx's
            // library as the operator configured it (or the test stand-in exporting the
            // same API); nothing else is loaded here.
            unsafe { Library::new(path) }.map_err(|e| e.to_string())
        })
        .map_err(LoadError::Open)?;
        macro_rules! get {
            ($name:literal) => {{
                // SAFETY: the symbol's type is the prototype NIDAQmx.h declares for
                // this name (the type aliases above); `library` stays loaded for the
                // process's life (`crate::resident`).
                let symbol = unsafe { library.get($name.as_bytes()) }
                    .map_err(|e| LoadError::Missing($name.to_owned(), e.to_string()))?;
                *symbol
            }};
        }
        let api = Api {
            create_task: get!("DAQmxCreateTask"),
            start_task: get!("DAQmxStartTask"),
            stop_task: get!("DAQmxStopTask"),
            clear_task: get!("DAQmxClearTask"),
            create_ao_voltage_chan: get!("DAQmxCreateAOVoltageChan"),
            create_do_chan: get!("DAQmxCreateDOChan"),
            create_di_chan: get!("DAQmxCreateDIChan"),
            write_analog_f64: get!("DAQmxWriteAnalogF64"),
            write_digital_lines: get!("DAQmxWriteDigitalLines"),
            read_digital_lines: get!("DAQmxReadDigitalLines"),
            create_watchdog_timer_task_ex: get!("DAQmxCreateWatchdogTimerTaskEx"),
            cfg_watchdog_do_expir_states: get!("DAQmxCfgWatchdogDOExpirStates"),
            control_watchdog_task: get!("DAQmxControlWatchdogTask"),
            get_watchdog_has_expired: get!("DAQmxGetWatchdogHasExpired"),
            get_task_num_chans: get!("DAQmxGetTaskNumChans"),
            get_write_digital_lines_bytes_per_chan: get!("DAQmxGetWriteDigitalLinesBytesPerChan"),
            get_extended_error_info: get!("DAQmxGetExtendedErrorInfo"),
            get_error_string: get!("DAQmxGetErrorString"),
            get_sys_dev_names: get!("DAQmxGetSysDevNames"),
            get_dev_product_type: get!("DAQmxGetDevProductType"),
            get_dev_serial_num: get!("DAQmxGetDevSerialNum"),
        };
        Ok(Lib {
            api,
            warning: AtomicI32::new(0),
        })
    }

    /// `Err(code)` for an error; a warning is remembered for [`Lib::take_warning`].
    fn check(&self, code: c_int) -> Result<(), i32> {
        if code < 0 {
            Err(code)
        } else {
            if code > 0 {
                self.warning.store(code, Ordering::Relaxed);
            }
            Ok(())
        }
    }

    /// The last warning code since the last call of this, if any.
    pub(crate) fn take_warning(&self) -> Option<i32> {
        Some(self.warning.swap(0, Ordering::Relaxed)).filter(|&w| w != 0)
    }

    fn task_call(&self, f: FnTask, task: Task) -> Result<(), i32> {
        // SAFETY: `f` takes a task handle the library gave us and touches no memory
        // of ours.
        self.check(unsafe { f(ptr(task)) })
    }

    /// `DAQmxCreateTask(name, &handle)`.
    pub(crate) fn create_task(&self, name: &str) -> Result<Task, i32> {
        let name = c(name);
        let mut handle: TaskHandle = std::ptr::null_mut();
        // SAFETY: a NUL-terminated name; the library writes one handle through a
        // pointer to a live local.
        self.check(unsafe { (self.api.create_task)(name.as_ptr(), &mut handle) })?;
        Ok(handle as Task)
    }

    /// `DAQmxStartTask`.
    pub(crate) fn start_task(&self, task: Task) -> Result<(), i32> {
        self.task_call(self.api.start_task, task)
    }

    /// `DAQmxStopTask`.
    pub(crate) fn stop_task(&self, task: Task) -> Result<(), i32> {
        self.task_call(self.api.stop_task, task)
    }

    /// `DAQmxClearTask`: the handle is invalid afterwards.
    pub(crate) fn clear_task(&self, task: Task) -> Result<(), i32> {
        self.task_call(self.api.clear_task, task)
    }

    /// `DAQmxCreateAOVoltageChan(task, channels, "", min, max, DAQmx_Val_Volts, NULL)`.
    pub(crate) fn create_ao_voltage_chan(
        &self,
        task: Task,
        channels: &str,
        min: f64,
        max: f64,
    ) -> Result<(), i32> {
        let (channels, name) = (c(channels), c(""));
        // SAFETY: NUL-terminated strings the library only reads; a null custom scale
        // (none), as NI's examples pass.
        self.check(unsafe {
            (self.api.create_ao_voltage_chan)(
                ptr(task),
                channels.as_ptr(),
                name.as_ptr(),
                min,
                max,
                VAL_VOLTS,
                std::ptr::null(),
            )
        })
    }

    /// `DAQmxCreateDOChan(task, lines, "", DAQmx_Val_ChanForAllLines)`.
    pub(crate) fn create_do_chan(&self, task: Task, lines: &str) -> Result<(), i32> {
        let (lines, name) = (c(lines), c(""));
        // SAFETY: NUL-terminated strings the library only reads.
        self.check(unsafe {
            (self.api.create_do_chan)(ptr(task), lines.as_ptr(), name.as_ptr(), VAL_CHAN_FOR_ALL_LINES)
        })
    }

    /// `DAQmxCreateDIChan(task, lines, "", DAQmx_Val_ChanForAllLines)`.
    pub(crate) fn create_di_chan(&self, task: Task, lines: &str) -> Result<(), i32> {
        let (lines, name) = (c(lines), c(""));
        // SAFETY: NUL-terminated strings the library only reads.
        self.check(unsafe {
            (self.api.create_di_chan)(ptr(task), lines.as_ptr(), name.as_ptr(), VAL_CHAN_FOR_ALL_LINES)
        })
    }

    /// A `uInt32` task property (`DAQmxGetTaskNumChans`, ...).
    fn task_u32(&self, f: FnTaskOutU32, task: Task) -> Result<u32, i32> {
        let mut value: c_uint = 0;
        // SAFETY: a task handle the library gave us; one uInt32 is written through a
        // pointer to a live local.
        self.check(unsafe { f(ptr(task), &mut value) })?;
        Ok(value)
    }

    /// How many values one sample of the task's channels is, as the write functions
    /// read it: `DAQmxGetTaskNumChans`, times `DAQmxGetWriteDigitalLinesBytesPerChan`
    /// for a digital task written by lines. The writes take no array size, so each
    /// asks this first and refuses a slice of another length
    /// ([`error::WRITE_NUM_CHANS_MISMATCH`]) instead of letting the library read past
    /// it: a channel list such as `Dev1/ao0,Dev1/ao2` or a whole port `Dev1/port0` makes
    /// a task wider than the caller's slice.
    fn sample_width(&self, task: Task, digital: bool) -> Result<usize, i32> {
        let chans = self.task_u32(self.api.get_task_num_chans, task)?;
        let per = if digital {
            self.task_u32(self.api.get_write_digital_lines_bytes_per_chan, task)?
        } else {
            1
        };
        Ok(usize::try_from(u64::from(chans) * u64::from(per)).unwrap_or(usize::MAX))
    }

    /// `DAQmxWriteAnalogF64`: one sample per channel (`volts`, one per channel of the
    /// task, grouped by channel), started automatically, on-demand timing.
    /// [`error::WRITE_NUM_CHANS_MISMATCH`] where the task has another number of
    /// channels: nothing is written.
    pub(crate) fn write_analog_f64(&self, task: Task, volts: &[f64], timeout_s: f64) -> Result<i32, i32> {
        if self.sample_width(task, false)? != volts.len() {
            return Err(error::WRITE_NUM_CHANS_MISMATCH);
        }
        let mut written: c_int = 0;
        // SAFETY: with one sample per channel the library reads one double per channel
        // of the task, and the task has `volts.len()` channels (asked just above). It
        // writes one int through a pointer to a live local; `reserved` is null as the
        // header asks.
        self.check(unsafe {
            (self.api.write_analog_f64)(
                ptr(task),
                1,
                1,
                timeout_s,
                VAL_GROUP_BY_CHANNEL,
                volts.as_ptr(),
                &mut written,
                std::ptr::null_mut(),
            )
        })?;
        Ok(written)
    }

    /// `DAQmxWriteDigitalLines`: one sample of `lines` (one byte per line, 0 or 1).
    /// [`error::WRITE_NUM_CHANS_MISMATCH`] where the task's sample is another number
    /// of bytes: nothing is written.
    pub(crate) fn write_digital_lines(&self, task: Task, lines: &[u8], timeout_s: f64) -> Result<i32, i32> {
        if self.sample_width(task, true)? != lines.len() {
            return Err(error::WRITE_NUM_CHANS_MISMATCH);
        }
        let mut written: c_int = 0;
        // SAFETY: one sample: the library reads the task's channels times its bytes
        // per channel, which is `lines.len()` (asked just above); one int is written
        // through a pointer to a live local; `reserved` is null.
        self.check(unsafe {
            (self.api.write_digital_lines)(
                ptr(task),
                1,
                1,
                timeout_s,
                VAL_GROUP_BY_CHANNEL,
                lines.as_ptr(),
                &mut written,
                std::ptr::null_mut(),
            )
        })?;
        Ok(written)
    }

    /// `DAQmxReadDigitalLines`: one sample into `lines` (one byte per line).
    pub(crate) fn read_digital_lines(
        &self,
        task: Task,
        lines: &mut [u8],
        timeout_s: f64,
    ) -> Result<i32, i32> {
        let (mut read, mut bytes_per_sample): (c_int, c_int) = (0, 0);
        // SAFETY: the library writes at most `arraySizeInBytes` (the buffer's length)
        // bytes into `lines`, and one int through each of two pointers to live locals;
        // `reserved` is null.
        self.check(unsafe {
            (self.api.read_digital_lines)(
                ptr(task),
                1,
                timeout_s,
                VAL_GROUP_BY_CHANNEL,
                lines.as_mut_ptr(),
                len32(lines.len()),
                &mut read,
                &mut bytes_per_sample,
                std::ptr::null_mut(),
            )
        })?;
        Ok(read)
    }

    /// `DAQmxCreateWatchdogTimerTaskEx(device, name, &handle, timeout)`.
    pub(crate) fn create_watchdog_timer_task_ex(
        &self,
        device: &str,
        name: &str,
        timeout_s: f64,
    ) -> Result<Task, i32> {
        let (device, name) = (c(device), c(name));
        let mut handle: TaskHandle = std::ptr::null_mut();
        // SAFETY: NUL-terminated strings the library only reads; one handle written
        // through a pointer to a live local.
        self.check(unsafe {
            (self.api.create_watchdog_timer_task_ex)(device.as_ptr(), name.as_ptr(), &mut handle, timeout_s)
        })?;
        Ok(handle as Task)
    }

    /// `DAQmxCfgWatchdogDOExpirStates(task, lines, states, n)`.
    pub(crate) fn cfg_watchdog_do_expir_states(
        &self,
        task: Task,
        lines: &str,
        states: &[i32],
    ) -> Result<(), i32> {
        let lines = c(lines);
        // SAFETY: the library reads `arraySize` (the slice's length) int32s and a
        // NUL-terminated string.
        self.check(unsafe {
            (self.api.cfg_watchdog_do_expir_states)(
                ptr(task),
                lines.as_ptr(),
                states.as_ptr(),
                len32(states.len()),
            )
        })
    }

    /// `DAQmxControlWatchdogTask(task, action)`.
    pub(crate) fn control_watchdog_task(&self, task: Task, action: i32) -> Result<(), i32> {
        // SAFETY: a task handle and an int; no memory of ours.
        self.check(unsafe { (self.api.control_watchdog_task)(ptr(task), action) })
    }

    /// `DAQmxGetWatchdogHasExpired`.
    pub(crate) fn watchdog_has_expired(&self, task: Task) -> Result<bool, i32> {
        let mut expired: c_uint = 0;
        // SAFETY: one bool32 written through a pointer to a live local.
        self.check(unsafe { (self.api.get_watchdog_has_expired)(ptr(task), &mut expired) })?;
        Ok(expired != 0)
    }

    /// `DAQmxGetExtendedErrorInfo`: the library's full description of the last error
    /// of this thread (empty if it has none).
    pub(crate) fn extended_error_info(&self) -> String {
        let mut buf = vec![0u8; TEXT];
        // SAFETY: the library writes at most `bufferSize` bytes, NUL included.
        let r = unsafe { (self.api.get_extended_error_info)(buf.as_mut_ptr().cast(), len32(buf.len())) };
        if r < 0 { String::new() } else { text(&buf) }
    }

    /// `DAQmxGetErrorString`: the library's short words for `code`.
    pub(crate) fn error_string(&self, code: i32) -> String {
        let mut buf = vec![0u8; TEXT];
        // SAFETY: the library writes at most `bufferSize` bytes, NUL included.
        let r = unsafe { (self.api.get_error_string)(code, buf.as_mut_ptr().cast(), len32(buf.len())) };
        if r < 0 {
            format!("unknown error {code}")
        } else {
            text(&buf)
        }
    }

    /// `DAQmxGetSysDevNames`: the devices NI-DAQmx knows, comma-separated.
    pub(crate) fn sys_dev_names(&self) -> Result<Vec<String>, i32> {
        let mut buf = vec![0u8; DEVICE_LIST];
        // SAFETY: the library writes at most `bufferSize` bytes, NUL included.
        self.check(unsafe { (self.api.get_sys_dev_names)(buf.as_mut_ptr().cast(), len32(buf.len())) })?;
        Ok(text(&buf)
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .map(str::to_owned)
            .collect())
    }

    /// `DAQmxGetDevProductType`: the model, e.g. `PCIe-6363`.
    pub(crate) fn dev_product_type(&self, device: &str) -> Result<String, i32> {
        let device = c(device);
        let mut buf = vec![0u8; TEXT];
        // SAFETY: a NUL-terminated name; at most `bufferSize` bytes written.
        self.check(unsafe {
            (self.api.get_dev_product_type)(device.as_ptr(), buf.as_mut_ptr().cast(), len32(buf.len()))
        })?;
        Ok(text(&buf))
    }

    /// `DAQmxGetDevSerialNum`.
    pub(crate) fn dev_serial_num(&self, device: &str) -> Result<u32, i32> {
        let device = c(device);
        let mut serial: c_uint = 0;
        // SAFETY: a NUL-terminated name; one uInt32 written through a pointer to a
        // live local.
        self.check(unsafe { (self.api.get_dev_serial_num)(device.as_ptr(), &mut serial) })?;
        Ok(serial)
    }
}

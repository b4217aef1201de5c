//! The vendor's C functions, exported under their documented names and prototypes
//! (`mhlib.h` 3.1 for `MH_…`, `hhlib.h` 3.0 for `HH_…`): each records the call, answers
//! a failure a test queued for it, and otherwise asks the counter model.
//!
//! Pointer arguments are checked for null (`ERROR_INVALID_ARGUMENT`) and written only
//! within the sizes the headers document: 8 bytes for versions and serial numbers, 24
//! for the model, 8 for part number and version, 40 for an error string, 16,384 for the
//! warnings text, and the histogram length in force for `GetHistogram`.
use std::ffi::{c_char, c_double, c_int, c_uint};
use std::panic::AssertUnwindSafe;

use periscope_drivers::picoquant::Family;
use periscope_drivers::picoquant::defin::error;

use crate::device::{Code, error_name};
use crate::state::{State, lock};

/// Runs one library call on the state: records it, answers a queued failure, or runs
/// `f`. A panic becomes an error code instead of unwinding into C.
fn call(
    family: Family,
    function: &str,
    args: String,
    f: impl FnOnce(&mut State) -> Result<(), Code>,
) -> c_int {
    let r = std::panic::catch_unwind(AssertUnwindSafe(|| {
        let mut guard = lock();
        let state = guard.as_mut().expect("created by lock");
        state.enter(family, function, args)?;
        f(state)
    }));
    match r {
        Ok(Ok(())) => 0,
        Ok(Err(code)) => code,
        Err(_) => error::INVALID_MEMORY,
    }
}

/// Writes `s` as a NUL-terminated string of at most `cap` bytes.
///
/// # Safety
/// `dst` is null or valid for writes of `cap` bytes.
unsafe fn put_text(dst: *mut c_char, cap: usize, s: &str) -> Result<(), Code> {
    if dst.is_null() {
        return Err(error::INVALID_ARGUMENT);
    }
    let n = s.len().min(cap - 1);
    // SAFETY: `n + 1 <= cap` bytes, which the caller guarantees are writable.
    unsafe {
        std::ptr::copy_nonoverlapping(s.as_ptr(), dst.cast::<u8>(), n);
        *dst.add(n) = 0;
    }
    Ok(())
}

/// Writes one value through `dst`.
///
/// # Safety
/// `dst` is null or valid for one write of `T`.
unsafe fn put<T>(dst: *mut T, v: T) -> Result<(), Code> {
    if dst.is_null() {
        return Err(error::INVALID_ARGUMENT);
    }
    // SAFETY: non-null, and valid per the caller.
    unsafe { dst.write(v) };
    Ok(())
}

/// Exports `$imp` for both families under `$mh` and `$hh`.
macro_rules! both {
    ($mh:ident, $hh:ident, $imp:ident($($a:ident: $t:ty),*)) => {
        #[doc = concat!("`", stringify!($mh), "`, as `mhlib.h` declares it.")]
        ///
        /// # Safety
        /// Pointer arguments are null or point at buffers of the sizes the vendor's header
        /// documents.
        #[unsafe(no_mangle)]
        pub unsafe extern "C" fn $mh($($a: $t),*) -> c_int {
            // SAFETY: the caller keeps the header's contract, which `$imp` relies on.
            unsafe { $imp(Family::MultiHarp, $($a),*) }
        }
        #[doc = concat!("`", stringify!($hh), "`, as `hhlib.h` declares it.")]
        ///
        /// # Safety
        /// Pointer arguments are null or point at buffers of the sizes the vendor's header
        /// documents.
        #[unsafe(no_mangle)]
        pub unsafe extern "C" fn $hh($($a: $t),*) -> c_int {
            // SAFETY: as above.
            unsafe { $imp(Family::HydraHarp, $($a),*) }
        }
    };
}

unsafe fn library_version(f: Family, vers: *mut c_char) -> c_int {
    call(f, "GetLibraryVersion", "*".into(), |_| {
        let v = match f {
            Family::MultiHarp => "3.1",
            Family::HydraHarp => "3.0",
        };
        // SAFETY: the header's 8-byte buffer.
        unsafe { put_text(vers, 8, v) }
    })
}
both!(MH_GetLibraryVersion, HH_GetLibraryVersion, library_version(vers: *mut c_char));

unsafe fn error_string(f: Family, buf: *mut c_char, code: c_int) -> c_int {
    call(f, "GetErrorString", format!("*, {code}"), |_| {
        let text = match error_name(code) {
            Some(name) => format!("{}{name}", f.prefix()),
            None => format!("unknown error code {code}"),
        };
        // SAFETY: the header's 40-byte buffer.
        unsafe { put_text(buf, 40, &text) }
    })
}
both!(MH_GetErrorString, HH_GetErrorString, error_string(buf: *mut c_char, code: c_int));

unsafe fn open_device(f: Family, dev: c_int, serial: *mut c_char) -> c_int {
    call(f, "OpenDevice", format!("{dev}, *"), |s| {
        let r = s.device(f, dev).and_then(|d| d.open().map(|()| d.serial.clone()));
        // SAFETY: the header's 8-byte serial buffer (empty when nothing was opened).
        unsafe { put_text(serial, 8, r.as_deref().unwrap_or(""))? };
        r.map(drop)
    })
}
both!(MH_OpenDevice, HH_OpenDevice, open_device(dev: c_int, serial: *mut c_char));

unsafe fn close_device(f: Family, dev: c_int) -> c_int {
    call(f, "CloseDevice", format!("{dev}"), |s| {
        if let Ok(d) = s.device(f, dev) {
            d.close();
        }
        Ok(())
    })
}
both!(MH_CloseDevice, HH_CloseDevice, close_device(dev: c_int));

unsafe fn initialize(f: Family, dev: c_int, mode: c_int, refsource: c_int) -> c_int {
    call(f, "Initialize", format!("{dev}, {mode}, {refsource}"), |s| {
        s.device(f, dev)?.initialise(mode, refsource)
    })
}
both!(MH_Initialize, HH_Initialize, initialize(dev: c_int, mode: c_int, refsource: c_int));

unsafe fn hardware_info(
    f: Family,
    dev: c_int,
    model: *mut c_char,
    part: *mut c_char,
    version: *mut c_char,
) -> c_int {
    call(f, "GetHardwareInfo", format!("{dev}, *, *, *"), |s| {
        let d = s.device(f, dev)?;
        d.ready(false)?;
        // SAFETY: the header's 24-, 8- and 8-byte buffers.
        unsafe {
            put_text(model, 24, &d.model)?;
            put_text(part, 8, "930001")?;
            put_text(version, 8, "2.0")
        }
    })
}
both!(MH_GetHardwareInfo, HH_GetHardwareInfo, hardware_info(dev: c_int, model: *mut c_char, part: *mut c_char, version: *mut c_char));

unsafe fn serial_number(f: Family, dev: c_int, serial: *mut c_char) -> c_int {
    call(f, "GetSerialNumber", format!("{dev}, *"), |s| {
        let d = s.device(f, dev)?;
        d.ready(false)?;
        // SAFETY: the header's 8-byte buffer.
        unsafe { put_text(serial, 8, &d.serial) }
    })
}
both!(MH_GetSerialNumber, HH_GetSerialNumber, serial_number(dev: c_int, serial: *mut c_char));

unsafe fn input_channels(f: Family, dev: c_int, n: *mut c_int) -> c_int {
    call(f, "GetNumOfInputChannels", format!("{dev}, *"), |s| {
        let d = s.device(f, dev)?;
        d.ready(false)?;
        // SAFETY: one int.
        unsafe { put(n, d.channels) }
    })
}
both!(MH_GetNumOfInputChannels, HH_GetNumOfInputChannels, input_channels(dev: c_int, n: *mut c_int));

/// `HH_Calibrate`, as `hhlib.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn HH_Calibrate(dev: c_int) -> c_int {
    call(Family::HydraHarp, "Calibrate", format!("{dev}"), |s| {
        s.device(Family::HydraHarp, dev)?.calibrate()
    })
}

unsafe fn set_sync_div(f: Family, dev: c_int, div: c_int) -> c_int {
    call(f, "SetSyncDiv", format!("{dev}, {div}"), |s| {
        s.device(f, dev)?.set_sync_div(div)
    })
}
both!(MH_SetSyncDiv, HH_SetSyncDiv, set_sync_div(dev: c_int, div: c_int));

/// Checks an edge trigger (MultiHarp) or CFD (HydraHarp) setting.
fn trigger_ok(f: Family, level: c_int, edge_or_zc: c_int) -> Result<(), Code> {
    let ok = match f {
        Family::MultiHarp => (-1200..=1200).contains(&level) && (0..=1).contains(&edge_or_zc),
        Family::HydraHarp => (0..=1000).contains(&level) && (0..=40).contains(&edge_or_zc),
    };
    if ok { Ok(()) } else { Err(error::INVALID_ARGUMENT) }
}

fn sync_trigger(f: Family, name: &str, dev: c_int, level: c_int, edge_or_zc: c_int) -> c_int {
    call(f, name, format!("{dev}, {level}, {edge_or_zc}"), |s| {
        s.device(f, dev)?.ready(false)?;
        trigger_ok(f, level, edge_or_zc)
    })
}

/// `MH_SetSyncEdgeTrg(devidx, level, edge)`, as `mhlib.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn MH_SetSyncEdgeTrg(dev: c_int, level: c_int, edge: c_int) -> c_int {
    sync_trigger(Family::MultiHarp, "SetSyncEdgeTrg", dev, level, edge)
}

/// `HH_SetSyncCFD(devidx, level, zc)`, as `hhlib.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn HH_SetSyncCFD(dev: c_int, level: c_int, zc: c_int) -> c_int {
    sync_trigger(Family::HydraHarp, "SetSyncCFD", dev, level, zc)
}

fn input_trigger(f: Family, name: &str, dev: c_int, ch: c_int, level: c_int, edge_or_zc: c_int) -> c_int {
    call(f, name, format!("{dev}, {ch}, {level}, {edge_or_zc}"), |s| {
        let d = s.device(f, dev)?;
        d.ready(false)?;
        d.channel(ch)?;
        trigger_ok(f, level, edge_or_zc)
    })
}

/// `MH_SetInputEdgeTrg(devidx, channel, level, edge)`, as `mhlib.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn MH_SetInputEdgeTrg(dev: c_int, ch: c_int, level: c_int, edge: c_int) -> c_int {
    input_trigger(Family::MultiHarp, "SetInputEdgeTrg", dev, ch, level, edge)
}

/// `HH_SetInputCFD(devidx, channel, level, zc)`, as `hhlib.h` declares it.
#[unsafe(no_mangle)]
pub extern "C" fn HH_SetInputCFD(dev: c_int, ch: c_int, level: c_int, zc: c_int) -> c_int {
    input_trigger(Family::HydraHarp, "SetInputCFD", dev, ch, level, zc)
}

unsafe fn sync_channel_offset(f: Family, dev: c_int, ps: c_int) -> c_int {
    call(f, "SetSyncChannelOffset", format!("{dev}, {ps}"), |s| {
        s.device(f, dev)?.ready(false)?;
        if (-99_999..=99_999).contains(&ps) {
            Ok(())
        } else {
            Err(error::INVALID_ARGUMENT)
        }
    })
}
both!(MH_SetSyncChannelOffset, HH_SetSyncChannelOffset, sync_channel_offset(dev: c_int, ps: c_int));

unsafe fn input_channel_offset(f: Family, dev: c_int, ch: c_int, ps: c_int) -> c_int {
    call(f, "SetInputChannelOffset", format!("{dev}, {ch}, {ps}"), |s| {
        let d = s.device(f, dev)?;
        d.ready(false)?;
        d.channel(ch)?;
        if (-99_999..=99_999).contains(&ps) {
            Ok(())
        } else {
            Err(error::INVALID_ARGUMENT)
        }
    })
}
both!(MH_SetInputChannelOffset, HH_SetInputChannelOffset, input_channel_offset(dev: c_int, ch: c_int, ps: c_int));

unsafe fn input_channel_enable(f: Family, dev: c_int, ch: c_int, on: c_int) -> c_int {
    call(f, "SetInputChannelEnable", format!("{dev}, {ch}, {on}"), |s| {
        s.device(f, dev)?.set_enable(ch, on)
    })
}
both!(MH_SetInputChannelEnable, HH_SetInputChannelEnable, input_channel_enable(dev: c_int, ch: c_int, on: c_int));

unsafe fn set_histo_len(f: Family, dev: c_int, code: c_int, actual: *mut c_int) -> c_int {
    call(f, "SetHistoLen", format!("{dev}, {code}, *"), |s| {
        let len = s.device(f, dev)?.set_histo_len(code)?;
        // SAFETY: one int.
        unsafe { put(actual, len) }
    })
}
both!(MH_SetHistoLen, HH_SetHistoLen, set_histo_len(dev: c_int, code: c_int, actual: *mut c_int));

unsafe fn set_binning(f: Family, dev: c_int, binning: c_int) -> c_int {
    call(f, "SetBinning", format!("{dev}, {binning}"), |s| {
        s.device(f, dev)?.set_binning(binning)
    })
}
both!(MH_SetBinning, HH_SetBinning, set_binning(dev: c_int, binning: c_int));

unsafe fn set_offset(f: Family, dev: c_int, ns: c_int) -> c_int {
    call(f, "SetOffset", format!("{dev}, {ns}"), |s| {
        s.device(f, dev)?.set_offset(ns)
    })
}
both!(MH_SetOffset, HH_SetOffset, set_offset(dev: c_int, ns: c_int));

unsafe fn resolution(f: Family, dev: c_int, ps: *mut c_double) -> c_int {
    call(f, "GetResolution", format!("{dev}, *"), |s| {
        let r = s.device(f, dev)?.resolution()?;
        // SAFETY: one double.
        unsafe { put(ps, r) }
    })
}
both!(MH_GetResolution, HH_GetResolution, resolution(dev: c_int, ps: *mut c_double));

unsafe fn sync_rate(f: Family, dev: c_int, rate: *mut c_int) -> c_int {
    call(f, "GetSyncRate", format!("{dev}, *"), |s| {
        let r = s.device(f, dev)?.sync_rate()?;
        // SAFETY: one int.
        unsafe { put(rate, r) }
    })
}
both!(MH_GetSyncRate, HH_GetSyncRate, sync_rate(dev: c_int, rate: *mut c_int));

unsafe fn count_rate(f: Family, dev: c_int, ch: c_int, rate: *mut c_int) -> c_int {
    call(f, "GetCountRate", format!("{dev}, {ch}, *"), |s| {
        let r = s.device(f, dev)?.count_rate(ch)?;
        // SAFETY: one int.
        unsafe { put(rate, r) }
    })
}
both!(MH_GetCountRate, HH_GetCountRate, count_rate(dev: c_int, ch: c_int, rate: *mut c_int));

unsafe fn clear_hist_mem(f: Family, dev: c_int) -> c_int {
    call(f, "ClearHistMem", format!("{dev}"), |s| s.device(f, dev)?.clear())
}
both!(MH_ClearHistMem, HH_ClearHistMem, clear_hist_mem(dev: c_int));

unsafe fn start_meas(f: Family, dev: c_int, ms: c_int) -> c_int {
    call(f, "StartMeas", format!("{dev}, {ms}"), |s| {
        s.device(f, dev)?.start(ms)
    })
}
both!(MH_StartMeas, HH_StartMeas, start_meas(dev: c_int, ms: c_int));

unsafe fn stop_meas(f: Family, dev: c_int) -> c_int {
    call(f, "StopMeas", format!("{dev}"), |s| s.device(f, dev)?.stop())
}
both!(MH_StopMeas, HH_StopMeas, stop_meas(dev: c_int));

unsafe fn ctc_status(f: Family, dev: c_int, status: *mut c_int) -> c_int {
    call(f, "CTCStatus", format!("{dev}, *"), |s| {
        let v = s.device(f, dev)?.ctc_status()?;
        // SAFETY: one int.
        unsafe { put(status, v) }
    })
}
both!(MH_CTCStatus, HH_CTCStatus, ctc_status(dev: c_int, status: *mut c_int));

fn histogram(f: Family, args: String, dev: c_int, counts: *mut c_uint, ch: c_int) -> c_int {
    call(f, "GetHistogram", args, |s| {
        if counts.is_null() {
            return Err(error::INVALID_ARGUMENT);
        }
        let h = s.device(f, dev)?.histogram(ch)?;
        // SAFETY: the manual asks for a buffer of the histogram length in force,
        // which is `h.len()`.
        unsafe { std::ptr::copy_nonoverlapping(h.as_ptr(), counts, h.len()) };
        Ok(())
    })
}

/// `MH_GetHistogram(devidx, chcount, channel)`, as `mhlib.h` declares it.
///
/// # Safety
/// `counts` is null or has room for the histogram length in force.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn MH_GetHistogram(dev: c_int, counts: *mut c_uint, ch: c_int) -> c_int {
    histogram(Family::MultiHarp, format!("{dev}, *, {ch}"), dev, counts, ch)
}

/// `HH_GetHistogram(devidx, chcount, channel, clear)`, as `hhlib.h` declares it.
///
/// # Safety
/// `counts` is null or has room for the histogram length in force.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn HH_GetHistogram(dev: c_int, counts: *mut c_uint, ch: c_int, clear: c_int) -> c_int {
    let r = histogram(
        Family::HydraHarp,
        format!("{dev}, *, {ch}, {clear}"),
        dev,
        counts,
        ch,
    );
    if r == 0 && clear != 0 {
        let mut g = lock();
        if let Some(d) = g.as_mut().and_then(|s| s.device(Family::HydraHarp, dev).ok()) {
            let _ = d.clear();
        }
    }
    r
}

unsafe fn flags(f: Family, dev: c_int, out: *mut c_int) -> c_int {
    call(f, "GetFlags", format!("{dev}, *"), |s| {
        let v = s.device(f, dev)?.flags()?;
        // SAFETY: one int.
        unsafe { put(out, v) }
    })
}
both!(MH_GetFlags, HH_GetFlags, flags(dev: c_int, out: *mut c_int));

unsafe fn warnings(f: Family, dev: c_int, out: *mut c_int) -> c_int {
    call(f, "GetWarnings", format!("{dev}, *"), |s| {
        let v = s.device(f, dev)?.warnings()?;
        // SAFETY: one int.
        unsafe { put(out, v) }
    })
}
both!(MH_GetWarnings, HH_GetWarnings, warnings(dev: c_int, out: *mut c_int));

unsafe fn warnings_text(f: Family, dev: c_int, text: *mut c_char, warnings: c_int) -> c_int {
    use periscope_drivers::picoquant::defin::warning as w;
    call(f, "GetWarningsText", format!("{dev}, *, {warnings}"), |s| {
        s.device(f, dev)?.ready(false)?;
        let mut lines = Vec::new();
        for (bit, line) in [
            (
                w::SYNC_RATE_ZERO,
                "Sync rate is zero: no signal on the sync input.",
            ),
            (w::DIVIDER_GREATER_ONE, "The sync divider is above 1."),
            (
                w::INPT_RATE_RATIO,
                "An input's rate is above 5% of the sync rate: pile-up.",
            ),
            (w::INPT_RATE_TOO_HIGH, "An input's rate is too high."),
        ] {
            if warnings & bit != 0 {
                lines.push(line);
            }
        }
        // SAFETY: the header's 16,384-byte buffer.
        unsafe { put_text(text, 16_384, &lines.join("\n")) }
    })
}
both!(MH_GetWarningsText, HH_GetWarningsText, warnings_text(dev: c_int, text: *mut c_char, warnings: c_int));

unsafe fn elapsed(f: Family, dev: c_int, ms: *mut c_double) -> c_int {
    call(f, "GetElapsedMeasTime", format!("{dev}, *"), |s| {
        let v = s.device(f, dev)?.elapsed()?;
        // SAFETY: one double.
        unsafe { put(ms, v) }
    })
}
both!(MH_GetElapsedMeasTime, HH_GetElapsedMeasTime, elapsed(dev: c_int, ms: *mut c_double));

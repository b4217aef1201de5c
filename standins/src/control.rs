//! The stand-in's test controls: extra C functions, all named `PERISCOPE_STANDIN_*`,
//! that no vendor library has. Tests call them through the same loaded library the
//! driver uses (see [`crate::client`]), so they steer the very state the driver's calls
//! reach. Each returns 0 on success and a negative number otherwise (after printing
//! why on stderr).
use std::ffi::{CStr, c_char, c_int, c_uint};
use std::path::Path;
use std::time::Instant;

use periscope_drivers::picoquant::Family;
use periscope_sim::devices::{Arm, EmissionCause};

use crate::state::{State, lock};

/// One change of the simulated laser's emission, for [`PERISCOPE_STANDIN_EmissionLog`].
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StandinEmission {
    /// How long before the call the change happened, ns.
    pub ago_ns: u64,
    /// Emission after the change: 1 on, 0 off.
    pub on: c_int,
    /// Why: 0 the host, 1 the watchdog, 2 the interlock, 3 a power loss.
    pub cause: c_int,
}

/// Runs `f` on the state; a failure or a panic is printed and becomes -1.
pub(crate) fn control(what: &str, f: impl FnOnce(&mut State) -> Result<c_int, String>) -> c_int {
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let mut guard = lock();
        f(guard.as_mut().expect("created by lock"))
    }));
    match r {
        Ok(Ok(v)) => v,
        Ok(Err(e)) => {
            eprintln!("periscope stand-in: {what}: {e}");
            -1
        }
        Err(_) => {
            eprintln!("periscope stand-in: {what} panicked");
            -1
        }
    }
}

fn family(f: c_int) -> Result<Family, String> {
    match f {
        0 => Ok(Family::MultiHarp),
        1 => Ok(Family::HydraHarp),
        _ => Err(format!("family {f}: 0 is MultiHarp, 1 HydraHarp")),
    }
}

/// Reads a C string argument.
///
/// # Safety
/// `s` is null or a NUL-terminated string.
unsafe fn text(s: *const c_char) -> Result<String, String> {
    if s.is_null() {
        return Err("null string".into());
    }
    // SAFETY: NUL-terminated per the caller.
    Ok(unsafe { CStr::from_ptr(s) }.to_string_lossy().into_owned())
}

/// Builds the simulated instrument from the config at `path` (a `backend = "sim"`
/// instrument config, whose `[sim]` table sets the scene and the time scale), drops
/// whatever was there, and plugs in one counter per family at index 0 (MultiHarp
/// serial 1045678, HydraHarp 1012345, 4 inputs each, the SPAD on the first).
///
/// # Safety
/// `path` is a NUL-terminated string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_Setup(path: *const c_char) -> c_int {
    // SAFETY: per this function's contract.
    let path = unsafe { text(path) };
    control("Setup", |s| {
        s.setup(Path::new(&path?))?;
        Ok(0)
    })
}

/// Drops the instrument, its served ports and every counter.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_Reset() -> c_int {
    control("Reset", |s| {
        s.reset();
        Ok(0)
    })
}

/// Plugs a counter of `family` (0 MultiHarp, 1 HydraHarp) with `serial` into
/// `index`, with `channels` inputs and the SPAD on input `spad_channel` (0-based).
///
/// # Safety
/// `serial` is a NUL-terminated string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_Plug(
    family_id: c_int,
    index: c_int,
    serial: *const c_char,
    channels: c_int,
    spad_channel: c_int,
) -> c_int {
    // SAFETY: per this function's contract.
    let serial = unsafe { text(serial) };
    control("Plug", |s| {
        s.plug(family(family_id)?, index, &serial?, channels, spad_channel)?;
        Ok(0)
    })
}

/// The next call of `function` (its name without the `MH_`/`HH_` prefix, e.g.
/// `StartMeas`) in `family` returns `code`.
///
/// # Safety
/// `function` is a NUL-terminated string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_FailNext(
    family_id: c_int,
    function: *const c_char,
    code: c_int,
) -> c_int {
    // SAFETY: per this function's contract.
    let function = unsafe { text(function) };
    control("FailNext", |s| {
        s.fail_next.push((family(family_id)?, function?, code));
        Ok(0)
    })
}

/// The next measurement of the counter at `index` ends with `flags` set (the
/// library's `FLAG_*` bits).
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_FlagNext(family_id: c_int, index: c_int, flags: c_int) -> c_int {
    control("FlagNext", |s| {
        let d = s
            .device(family(family_id)?, index)
            .map_err(|c| format!("no counter at {index} ({c})"))?;
        d.next_flags |= flags;
        Ok(0)
    })
}

/// The laser's sync into the counter at `index` stops once its next measurement has
/// ended: that histogram and its flags are whole, the rate meter then reads 0, and
/// every later measurement ends with `FLAG_SYNC_LOST` and no counts.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_SyncStops(family_id: c_int, index: c_int) -> c_int {
    control("SyncStops", |s| {
        let d = s
            .device(family(family_id)?, index)
            .map_err(|c| format!("no counter at {index} ({c})"))?;
        d.sync_stops_after_next = true;
        Ok(0)
    })
}

/// The counter at `index` vanishes from the bus now (mid-acquisition if one runs):
/// every call on it fails with `ERROR_USB_VCMD_FAIL`, and `refused_reopens` opens of
/// its index fail before it is back (`u32::MAX`: gone for good).
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_Vanish(family_id: c_int, index: c_int, refused_reopens: c_uint) -> c_int {
    control("Vanish", |s| {
        let d = s
            .device(family(family_id)?, index)
            .map_err(|c| format!("no counter at {index} ({c})"))?;
        d.vanished = true;
        d.refused_reopens = refused_reopens;
        Ok(0)
    })
}

/// Serves the rig's two galvo controllers on pseudo-terminals (laser arm, SPAD arm)
/// and writes their paths (`/dev/pts/N`) into `laser` and `spad`, `cap` bytes each.
///
/// # Safety
/// `laser` and `spad` are valid for writes of `cap` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_ServeGalvos(
    laser: *mut c_char,
    spad: *mut c_char,
    cap: c_int,
) -> c_int {
    control("ServeGalvos", |s| {
        let bench = s.bench.as_mut().ok_or("set the stand-in up first")?;
        let rig = bench.backend.rig().clone();
        let ports = [Arm::Laser, Arm::Spad].map(|arm| rig.serve_galvo_port(arm));
        let [l, p] = ports;
        let (l, p) = (l.map_err(|e| e.to_string())?, p.map_err(|e| e.to_string())?);
        for (dst, port) in [(laser, &l), (spad, &p)] {
            let path = port.path().as_bytes();
            if dst.is_null() || cap <= 0 || path.len() >= cap as usize {
                return Err("buffer too small for a port path".into());
            }
            // SAFETY: `path.len() + 1 <= cap` bytes, writable per the contract.
            unsafe {
                std::ptr::copy_nonoverlapping(path.as_ptr(), dst.cast::<u8>(), path.len());
                *dst.add(path.len()) = 0;
            }
        }
        bench.ports.extend([l, p]);
        Ok(0)
    })
}

/// The record of library calls since the last clear, one per line
/// (`MH_StartMeas(0, 30)`), written into `buf` (`cap` bytes, NUL-terminated,
/// truncated if it does not fit); returns the bytes the whole record needs.
///
/// # Safety
/// `buf` is null or valid for writes of `cap` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_Calls(buf: *mut c_char, cap: c_int) -> c_int {
    control("Calls", |s| {
        let all = s.calls.join("\n");
        if !buf.is_null() && cap > 0 {
            let n = all.len().min(cap as usize - 1);
            // SAFETY: `n + 1 <= cap` bytes, writable per the contract.
            unsafe {
                std::ptr::copy_nonoverlapping(all.as_ptr(), buf.cast::<u8>(), n);
                *buf.add(n) = 0;
            }
        }
        Ok(all.len() as c_int + 1)
    })
}

/// Forgets the record of calls.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_ClearCalls() -> c_int {
    control("ClearCalls", |s| {
        s.calls.clear();
        Ok(0)
    })
}

/// The simulated laser's emission changes (the rig's own log), oldest first, into
/// `out` (at most `cap`); returns how many were written.
///
/// # Safety
/// `out` is valid for writes of `cap` records.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_EmissionLog(out: *mut StandinEmission, cap: c_int) -> c_int {
    control("EmissionLog", |s| {
        let bench = s.bench.as_ref().ok_or("set the stand-in up first")?;
        let now = Instant::now();
        let log = bench.backend.rig().emission_changes();
        let n = log.len().min(cap.max(0) as usize);
        for (i, c) in log[log.len() - n..].iter().enumerate() {
            let record = StandinEmission {
                ago_ns: now.saturating_duration_since(c.at).as_nanos() as u64,
                on: c_int::from(c.on),
                cause: match c.cause {
                    EmissionCause::Host => 0,
                    EmissionCause::Watchdog => 1,
                    EmissionCause::Interlock => 2,
                    EmissionCause::PowerLoss => 3,
                },
            };
            // SAFETY: `i < n <= cap`, writable per the contract.
            unsafe { out.add(i).write(record) };
        }
        Ok(n as c_int)
    })
}

/// Whether the simulated laser emits now (1) or not (0).
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_Emission() -> c_int {
    control("Emission", |s| {
        let bench = s.bench.as_ref().ok_or("set the stand-in up first")?;
        Ok(c_int::from(bench.backend.rig().emission()))
    })
}

/// Whether each arm is parked: bit 0 the laser arm, bit 1 the SPAD arm.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_Parked() -> c_int {
    control("Parked", |s| {
        let bench = s.bench.as_ref().ok_or("set the stand-in up first")?;
        let (l, p) = bench.backend.rig().parked();
        Ok(c_int::from(l) | (c_int::from(p) << 1))
    })
}

/// Opens (0) or closes (1) the rig's interlock loop; opening it stops emission.
#[unsafe(no_mangle)]
pub extern "C" fn PERISCOPE_STANDIN_SetInterlock(closed: c_int) -> c_int {
    control("SetInterlock", |s| {
        let bench = s.bench.as_ref().ok_or("set the stand-in up first")?;
        bench.backend.rig().set_interlock(closed != 0);
        Ok(0)
    })
}

/// Where the rig's arms point, optical degrees: laser x, y, SPAD x, y into `out`.
///
/// # Safety
/// `out` is valid for writes of 4 doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn PERISCOPE_STANDIN_Pointing(out: *mut std::ffi::c_double) -> c_int {
    control("Pointing", |s| {
        let bench = s.bench.as_ref().ok_or("set the stand-in up first")?;
        let (l, p) = bench.backend.rig().pointing();
        if out.is_null() {
            return Err("null buffer".into());
        }
        for (i, v) in [l.x, l.y, p.x, p.y].into_iter().enumerate() {
            // SAFETY: `i < 4`, writable per the contract.
            unsafe { out.add(i).write(v.to_degrees()) };
        }
        Ok(0)
    })
}

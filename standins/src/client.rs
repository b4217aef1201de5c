//! The tests' side: find the built stand-in library, load it (once per process, for
//! the process's life: its measurement and firmware threads run its code, which must
//! never be unmapped), and call its `PERISCOPE_STANDIN_*` controls through it.
//!
//! The driver under test loads the same file by path, which the dynamic loader
//! answers with the library already loaded: the controls and the driver's calls reach
//! one state, as a vendor library keeps one per process. Tests in one executable share
//! it, so each holds [`exclusive`] while it uses the stand-in.
use std::ffi::{CString, c_char, c_int, c_uint};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, MutexGuard, OnceLock};
use std::time::{Duration, Instant};

use libloading::Library;
use periscope_drivers::picoquant::Family;

use crate::control::StandinEmission;

/// The library's file name.
pub const FILE: &str = "libperiscope_standins.so";

/// Where the stand-in was built: beside the test executable's folder
/// (`target/<profile>/deps/`, where Cargo puts a dependency's shared library) or one
/// folder up; `PERISCOPE_STANDIN_LIB` names another file.
pub fn library_path() -> PathBuf {
    if let Some(p) = std::env::var_os("PERISCOPE_STANDIN_LIB") {
        return PathBuf::from(p);
    }
    let exe = std::env::current_exe().expect("the test knows its path");
    let deps = exe.parent().expect("an executable has a folder");
    let candidates = [deps.join(FILE), deps.parent().unwrap_or(deps).join(FILE)];
    candidates
        .iter()
        .find(|p| p.is_file())
        .cloned()
        .unwrap_or_else(|| {
            panic!(
                "{FILE} not found in {} or its parent: list periscope-standins under the test \
                 crate's [dev-dependencies] so Cargo builds it, or set PERISCOPE_STANDIN_LIB",
                deps.display()
            )
        })
}

static LIBRARY: OnceLock<Library> = OnceLock::new();
static EXCLUSIVE: Mutex<()> = Mutex::new(());

/// Holds the stand-in for one test at a time (a failed test's panic does not block the
/// next).
pub fn exclusive() -> MutexGuard<'static, ()> {
    EXCLUSIVE.lock().unwrap_or_else(|p| p.into_inner())
}

/// The stand-in library, loaded.
#[derive(Clone, Copy)]
pub struct Standin {
    lib: &'static Library,
}

fn family_id(f: Family) -> c_int {
    match f {
        Family::MultiHarp => 0,
        Family::HydraHarp => 1,
    }
}

fn cstr(s: &str) -> CString {
    CString::new(s).expect("no NUL inside")
}

impl Standin {
    /// Loads the library (once per process).
    pub fn load() -> Standin {
        let lib = LIBRARY.get_or_init(|| {
            let path = library_path();
            // SAFETY: the stand-in's initialisers are Rust's own; it is the library this
            // crate builds.
            unsafe { Library::new(&path) }.unwrap_or_else(|e| panic!("loading {}: {e}", path.display()))
        });
        Standin { lib }
    }

    /// The path the library was loaded from (what `tdc.library` names).
    pub fn path(&self) -> PathBuf {
        library_path()
    }

    fn get<T: Copy>(&self, name: &str) -> T {
        // SAFETY: each caller names the type `control.rs` exports under `name`.
        let symbol = unsafe { self.lib.get::<T>(name.as_bytes()) }.unwrap_or_else(|e| panic!("{name}: {e}"));
        *symbol
    }

    fn ok(name: &str, r: c_int) {
        assert!(r >= 0, "{name} failed ({r}); the stand-in printed why on stderr");
    }

    /// `PERISCOPE_STANDIN_Setup`: a fresh simulated instrument from `config`.
    pub fn setup(&self, config: &Path) {
        let f: unsafe extern "C" fn(*const c_char) -> c_int = self.get("PERISCOPE_STANDIN_Setup");
        let c = cstr(&config.to_string_lossy());
        // SAFETY: a NUL-terminated string.
        Self::ok("Setup", unsafe { f(c.as_ptr()) });
    }

    /// `PERISCOPE_STANDIN_Reset`.
    pub fn reset(&self) {
        let f: extern "C" fn() -> c_int = self.get("PERISCOPE_STANDIN_Reset");
        Self::ok("Reset", f());
    }

    /// `PERISCOPE_STANDIN_Plug`.
    pub fn plug(&self, family: Family, index: i32, serial: &str, channels: i32, spad_channel: i32) {
        let f: unsafe extern "C" fn(c_int, c_int, *const c_char, c_int, c_int) -> c_int =
            self.get("PERISCOPE_STANDIN_Plug");
        let s = cstr(serial);
        // SAFETY: a NUL-terminated string.
        Self::ok("Plug", unsafe {
            f(family_id(family), index, s.as_ptr(), channels, spad_channel)
        });
    }

    /// `PERISCOPE_STANDIN_FailNext`: the next call of `function` fails with `code`.
    pub fn fail_next(&self, family: Family, function: &str, code: i32) {
        let f: unsafe extern "C" fn(c_int, *const c_char, c_int) -> c_int =
            self.get("PERISCOPE_STANDIN_FailNext");
        let s = cstr(function);
        // SAFETY: a NUL-terminated string.
        Self::ok("FailNext", unsafe { f(family_id(family), s.as_ptr(), code) });
    }

    /// `PERISCOPE_STANDIN_FlagNext`.
    pub fn flag_next(&self, family: Family, index: i32, flags: i32) {
        let f: extern "C" fn(c_int, c_int, c_int) -> c_int = self.get("PERISCOPE_STANDIN_FlagNext");
        Self::ok("FlagNext", f(family_id(family), index, flags));
    }

    /// `PERISCOPE_STANDIN_SyncStops`.
    pub fn sync_stops(&self, family: Family, index: i32) {
        let f: extern "C" fn(c_int, c_int) -> c_int = self.get("PERISCOPE_STANDIN_SyncStops");
        Self::ok("SyncStops", f(family_id(family), index));
    }

    /// `PERISCOPE_STANDIN_Vanish`.
    pub fn vanish(&self, family: Family, index: i32, refused_reopens: u32) {
        let f: extern "C" fn(c_int, c_int, c_uint) -> c_int = self.get("PERISCOPE_STANDIN_Vanish");
        Self::ok("Vanish", f(family_id(family), index, refused_reopens));
    }

    /// `PERISCOPE_STANDIN_ServeGalvos`: the laser arm's and the SPAD arm's port paths.
    pub fn serve_galvos(&self) -> (String, String) {
        let f: unsafe extern "C" fn(*mut c_char, *mut c_char, c_int) -> c_int =
            self.get("PERISCOPE_STANDIN_ServeGalvos");
        let (mut l, mut s) = ([0u8; 256], [0u8; 256]);
        // SAFETY: two 256-byte buffers.
        Self::ok("ServeGalvos", unsafe {
            f(l.as_mut_ptr().cast(), s.as_mut_ptr().cast(), 256)
        });
        let text = |b: &[u8]| {
            String::from_utf8_lossy(&b[..b.iter().position(|&c| c == 0).unwrap_or(b.len())]).into_owned()
        };
        (text(&l), text(&s))
    }

    /// `PERISCOPE_STANDIN_Calls`: the library calls since the last clear.
    pub fn calls(&self) -> Vec<String> {
        let f: unsafe extern "C" fn(*mut c_char, c_int) -> c_int = self.get("PERISCOPE_STANDIN_Calls");
        // SAFETY: a null buffer asks only for the size.
        let need = unsafe { f(std::ptr::null_mut(), 0) };
        Self::ok("Calls", need);
        let mut buf = vec![0u8; need as usize + 64];
        // SAFETY: a buffer of the length given.
        Self::ok("Calls", unsafe { f(buf.as_mut_ptr().cast(), buf.len() as c_int) });
        let end = buf.iter().position(|&c| c == 0).unwrap_or(buf.len());
        String::from_utf8_lossy(&buf[..end])
            .lines()
            .map(str::to_owned)
            .collect()
    }

    /// `PERISCOPE_STANDIN_ClearCalls`.
    pub fn clear_calls(&self) {
        let f: extern "C" fn() -> c_int = self.get("PERISCOPE_STANDIN_ClearCalls");
        Self::ok("ClearCalls", f());
    }

    /// The simulated laser's emission log: when (on this process's clock), on or off,
    /// and why (0 the host, 1 the watchdog, 2 the interlock, 3 a power loss).
    pub fn emission_log(&self) -> Vec<(Instant, bool, i32)> {
        let f: unsafe extern "C" fn(*mut StandinEmission, c_int) -> c_int =
            self.get("PERISCOPE_STANDIN_EmissionLog");
        let mut out = vec![StandinEmission::default(); 4096];
        // SAFETY: a buffer of 4,096 records.
        let n = unsafe { f(out.as_mut_ptr(), out.len() as c_int) };
        Self::ok("EmissionLog", n);
        let now = Instant::now();
        out[..n as usize]
            .iter()
            .map(|r| (now - Duration::from_nanos(r.ago_ns), r.on != 0, r.cause))
            .collect()
    }

    /// Whether the simulated laser emits now.
    pub fn emission(&self) -> bool {
        let f: extern "C" fn() -> c_int = self.get("PERISCOPE_STANDIN_Emission");
        let r = f();
        Self::ok("Emission", r);
        r == 1
    }

    /// Whether each arm is parked (laser, SPAD).
    pub fn parked(&self) -> (bool, bool) {
        let f: extern "C" fn() -> c_int = self.get("PERISCOPE_STANDIN_Parked");
        let r = f();
        Self::ok("Parked", r);
        (r & 1 != 0, r & 2 != 0)
    }

    /// `PERISCOPE_STANDIN_SetInterlock`.
    pub fn set_interlock(&self, closed: bool) {
        let f: extern "C" fn(c_int) -> c_int = self.get("PERISCOPE_STANDIN_SetInterlock");
        Self::ok("SetInterlock", f(c_int::from(closed)));
    }

    /// `PERISCOPE_STANDIN_DaqSetup`: the simulated DAQ device wired as the hardware
    /// config at `config` says.
    pub fn daq_setup(&self, config: &Path) {
        let f: unsafe extern "C" fn(*const c_char) -> c_int = self.get("PERISCOPE_STANDIN_DaqSetup");
        let c = cstr(&config.to_string_lossy());
        // SAFETY: a NUL-terminated string.
        Self::ok("DaqSetup", unsafe { f(c.as_ptr()) });
    }

    /// `PERISCOPE_STANDIN_DaqFailNext`: the next call of the DAQmx function `function`
    /// returns `code`.
    pub fn daq_fail_next(&self, function: &str, code: i32) {
        let f: unsafe extern "C" fn(*const c_char, c_int) -> c_int =
            self.get("PERISCOPE_STANDIN_DaqFailNext");
        let s = cstr(function);
        // SAFETY: a NUL-terminated string.
        Self::ok("DaqFailNext", unsafe { f(s.as_ptr(), code) });
    }

    /// `PERISCOPE_STANDIN_DaqVanish`.
    pub fn daq_vanish(&self) {
        let f: extern "C" fn() -> c_int = self.get("PERISCOPE_STANDIN_DaqVanish");
        Self::ok("DaqVanish", f());
    }

    /// `PERISCOPE_STANDIN_DaqWatchdogSupported`.
    pub fn daq_watchdog_supported(&self, supported: bool) {
        let f: extern "C" fn(c_int) -> c_int = self.get("PERISCOPE_STANDIN_DaqWatchdogSupported");
        Self::ok("DaqWatchdogSupported", f(c_int::from(supported)));
    }

    /// `PERISCOPE_STANDIN_DaqCounters`: (writes that overdrove an arm, heartbeat
    /// line changes).
    pub fn daq_counters(&self) -> (u32, u32) {
        let f: unsafe extern "C" fn(*mut c_uint) -> c_int = self.get("PERISCOPE_STANDIN_DaqCounters");
        let mut over: c_uint = 0;
        // SAFETY: a pointer to a live local.
        let beats = unsafe { f(&mut over) };
        Self::ok("DaqCounters", beats);
        (over, beats as u32)
    }

    /// `PERISCOPE_STANDIN_Pointing`: where the rig's arms point, optical degrees
    /// ((laser x, y), (SPAD x, y)).
    pub fn pointing(&self) -> ((f64, f64), (f64, f64)) {
        let f: unsafe extern "C" fn(*mut f64) -> c_int = self.get("PERISCOPE_STANDIN_Pointing");
        let mut out = [0.0f64; 4];
        // SAFETY: four doubles.
        Self::ok("Pointing", unsafe { f(out.as_mut_ptr()) });
        ((out[0], out[1]), (out[2], out[3]))
    }
}

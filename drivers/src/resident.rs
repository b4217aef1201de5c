//! Vendor libraries kept loaded for the process's life, one load per path.
//!
//! A driver is opened and dropped many times (the daemon reopens the devices for each
//! status reading while idle, and for each run), and dropping a `libloading::Library`
//! unloads it (`dlclose`). Neither NI nor PicoQuant documents unloading as supported:
//! their libraries start threads of their own, and a task the driver leaves to the
//! library on purpose (the laser's watchdog, armed when the gate's last write failed)
//! would outlive the code behind it. So each path is loaded once, the first time a
//! driver asks, and never unloaded; later opens reuse it. The loading itself, which
//! runs the library's initialisers, is the caller's (`unsafe`, in its FFI module).
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use libloading::Library;

/// The library at `path`, loaded by `open` the first time it is asked for and kept.
/// A failed load is not kept: the next call tries again (a library installed since).
pub(crate) fn resident(
    path: &Path,
    open: impl FnOnce() -> Result<Library, String>,
) -> Result<&'static Library, String> {
    static LOADED: OnceLock<Mutex<HashMap<PathBuf, &'static Library>>> = OnceLock::new();
    let mut loaded = LOADED
        .get_or_init(Mutex::default)
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    if let Some(lib) = loaded.get(path) {
        return Ok(lib);
    }
    let lib: &'static Library = Box::leak(Box::new(open()?));
    loaded.insert(path.to_owned(), lib);
    Ok(lib)
}

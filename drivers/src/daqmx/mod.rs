//! Galvo pairs driven by analog voltages and the laser gated by a digital line, through
//! National Instruments' NI-DAQmx C library (`libnidaqmx.so`), loaded at run time: the
//! daemon builds and runs without it, and finds it at the path the instrument config
//! gives.
//!
//! Split by concern: `ffi` is the one module with `unsafe` code (the symbol lookups
//! and calls); `defin` holds the header's numbers; `error` the error codes sorted into
//! kinds; `driver` the library as the drivers share it and the galvo pair (two analog
//! outputs, slew-limited, open loop); `laser` the laser's gate, interlock and diffuser
//! lines, with the laser guard's watchdog on the device's hardware watchdog timer.
//!
//! Verified against the published API only, through the workspace's stand-in library
//! (`standins`), which exports the same C functions; not yet on a DAQ device.
pub mod defin;
mod driver;
mod error;
mod ffi;
mod laser;

pub use driver::{AoGalvoSettings, DEFAULT_LIBRARY, DaqGalvo, DaqSurvey, STEP_PERIOD, device_of, survey};
pub use error::{DaqError, kind_of};
pub use laser::{DaqLaser, DaqLaserSettings, WatchdogMode};

//! Stand-ins for the vendor C libraries Periscope loads, for tests: one shared library
//! (`libperiscope_standins.so`) that exports PicoQuant's MHLib (MultiHarp 150/160) and
//! HHLib (HydraHarp 400) histogram-mode functions (`MH_OpenDevice`, `HH_GetHistogram`,
//! …) and NI-DAQmx's functions for analog outputs, digital lines and the watchdog timer
//! ([`daqmx`]: `DAQmxWriteAnalogF64`, `DAQmxCreateWatchdogTimerTaskEx`, …) by their
//! documented names and prototypes, and answers them from one simulated instrument, so
//! a bench whose galvos and laser are on a DAQ card and whose counter is a MultiHarp is
//! one rig, as in the lab. Periscope's driver loads it exactly as it loads the vendor's library, from
//! the path in the instrument config (`tdc.library`), so the tests run the real FFI path:
//! symbol lookup, calling convention, buffers, return codes.
//!
//! One process, one instrument: the library holds one [`Rig`](periscope_sim::devices::Rig)
//! (built from a simulated instrument config, as the daemon builds its own), whose TDC
//! model produces the histograms for wherever the rig's galvos point, and whose galvo
//! controllers it serves on pseudo-terminals, so a whole run drives the serial galvo
//! driver on those ports and this counter: one rig, as on a real bench.
//!
//! Tests steer it through a few extra C functions, all named `PERISCOPE_STANDIN_*`
//! (see [`control`]): set it up from a config, plug counters in, make the next call of
//! a function fail with a code, set flags on the next measurement, make a counter
//! vanish, serve the galvo ports, read the simulated laser's emission log and the
//! record of library calls. [`client`] is the Rust side of those controls, for tests.
//!
//! What it models of the vendor's library is what the published headers and demos say
//! (prototypes, error codes, flag and warning bits, ranges, length codes, binning); the
//! error strings are its own (the symbolic names), and timing follows the simulator's
//! time scale. It is not the vendor's library: a driver that passes here is verified
//! against the published API, not against a counter.
//!
//! This crate needs `unsafe`: its exported functions take the raw pointers the C API
//! passes. Each pointer is checked for null and written only within the size the
//! vendor's header documents for it.
#![allow(unsafe_code)]
#![warn(missing_docs)]

pub mod client;
pub mod control;
pub mod daqmx;
mod device;
mod exports;
mod state;

pub use daqmx::DAQ_CONFIG_ENV;
pub use exports::*;
pub use state::CONFIG_ENV;

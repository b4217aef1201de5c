//! PicoQuant's time-correlated counters (MultiHarp 150/160, HydraHarp 400) as a
//! histogrammer, through the vendor's own C library (MHLib, HHLib) loaded at run time:
//! the daemon builds and runs without it, and the library is found at the path the
//! instrument config gives.
//!
//! Split by concern: `ffi` is the one module with `unsafe` code (the symbol
//! lookups and calls); `defin` holds the headers' numbers; `family` what differs
//! between the two libraries; `error` the error codes sorted into kinds; `driver` the
//! [`Histogrammer`](crate::Histogrammer) over all of it.
//!
//! Verified against the published API only, through the workspace's stand-in library
//! (`standins`), which exports the same C functions; not yet on a counter.
pub mod defin;
mod driver;
mod error;
mod family;
mod ffi;

pub use driver::{FoundCounter, POLL, PicoQuantSettings, PicoQuantTdc, list_counters};
pub use error::{PicoQuantError, kind_of};
pub use family::{Family, Settings, Trigger};

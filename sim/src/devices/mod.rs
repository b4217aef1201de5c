//! The simulated instrument's devices: galvo controller firmware on pseudo-terminals
//! and a histogrammer behind the USB transport trait, both driven by one shared
//! [`Rig`] that knows where the mirrors point and computes what the SPAD would see.
//!
//! They speak the drivers' wire protocols byte for byte, so the daemon runs the real
//! drivers against them; only the transport's far end differs from the lab. Faults
//! (a dropped reply, a corrupted checksum, a stall, an unplug, an overflow, a short
//! read) are injected one at a time through [`Rig::inject`].
//!
//! [`InProcessGalvo`] and [`InProcessTdc`] implement the device traits straight over
//! the same controller model, without the wire or the drivers, for tests about
//! everything above the drivers.
mod firmware;
mod in_process;
mod rig;
mod tdc;

pub use firmware::PtyConnector;
pub use firmware::ServedPort;
pub use in_process::{InProcessGalvo, InProcessTdc};
pub use rig::{Arm, EmissionCause, EmissionChange, Fault, GalvoFault, Rig, RigSettings, TdcFault};
pub use tdc::SimTdcTransport;

//! The NI-DAQmx side of the stand-in: one simulated DAQ device wired to the rig as a
//! lab would wire it, from the very instrument config the daemon opens (its DAQmx
//! galvo tables and `[laser]` lines): an analog output pair's voltages become the
//! arm's optical angles through the config's volts per degree and offsets, the laser
//! line drives the rig laser's gate, the interlock line reads the rig's loop, the
//! diffuser line moves its diffuser. A watchdog timer task counts down on a thread of
//! its own and, when nobody resets it within its timeout, drives its lines to their
//! expiration states (the laser's gate low, recorded in the rig's emission log as a
//! watchdog cause) and refuses writes to them until it is cleared, as NI documents.
//!
//! What it models of NI-DAQmx is what `NIDAQmx.h` and NI's C reference say (the
//! prototypes, the codes of the errors it can give, tasks, on-demand writes, the
//! watchdog's expiration); its error texts are its own (the error's symbolic name and
//! what was wrong). It is not NI-DAQmx: timing, the kernel driver and a real card's
//! quirks are outside it.
mod exports;
mod model;

pub use exports::*;
pub use model::DAQ_CONFIG_ENV;
pub(crate) use model::Daq;

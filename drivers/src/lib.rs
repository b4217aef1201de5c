//! Hardware side of Periscope: the traits the daemon drives ([`traits`]), the real
//! drivers behind them (a serial galvo controller in [`galvo`], a USB histogrammer in
//! [`tdc`], galvo pairs and the laser on an NI DAQ device through NI-DAQmx in [`daqmx`], PicoQuant's counters through their vendor library in [`picoquant`]), their wire protocols (shared with the simulated devices), and the pieces of the instrument model that the driver side and the simulated
//! devices must share exactly (the galvo calibration model, device selectors).
//!
//! The calibration model lives here rather than in `sim` because both directions of it
//! are needed: the driver computes the optical angles that aim a galvo pair at a relay
//! point, and the simulator computes the ray that a pair at given angles emits. Using
//! one piece of code for both means a simulated capture exercises the same geometry a
//! real one does.
#![warn(missing_docs)]

pub mod daqmx;
pub mod error;
pub mod exact;
pub mod galvo;
pub mod geometry;
pub mod laser_guard;
pub mod park;
pub mod picoquant;
pub mod ports;
mod resident;
pub mod selector;
pub mod tdc;
pub mod traits;

pub use error::{DeviceError, Error, ErrorKind, ErrorType};
pub use geometry::{AngleLimits, GalvoPose, OpticalAngles, Scanner};
pub use laser_guard::{EmergencyOff, LaserGuard, LaserLine, Progress};
pub use park::{EmergencyPark, ParkLine, Parked};
pub use selector::{SelectorError, UsbSelector};
pub use traits::{
    CountRates, DeviceInfo, Erased, GalvoBox, GalvoPair, GalvoStatus, Histogram, HistogramFlags,
    Histogrammer, HistogrammerBox, Laser, LaserBox, LaserState, MotionState, Shared, TdcConfig, TdcState,
    TdcStatus,
};

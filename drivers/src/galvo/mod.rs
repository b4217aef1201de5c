//! The serial galvo controller: its line protocol (shared with the simulated
//! firmware), the byte links it runs over, and the driver.
pub mod error;
pub mod link;
pub mod protocol;
pub mod serial;

pub use crate::laser_guard::EmergencyOff;
pub use error::GalvoError;
pub use link::{Connector, Link, PortConnector};
pub use serial::{SerialGalvo, SerialGalvoSettings};

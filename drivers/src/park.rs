//! Parking a galvo pair from any thread, whatever its driver is doing.
//!
//! The e-stop switches the laser off through a handle the laser's driver hands out
//! ([`crate::EmergencyOff`]), because the thread that owns the driver may be stuck.
//! The arms need the same: a run stuck in a call that does not return (a counter that
//! never answers, a disk that blocks) still owns its galvo drivers, and the hardware
//! will not let anyone else at them (a serial port is opened exclusively, a started
//! NI-DAQmx task reserves its channels). So each [`GalvoPair`](crate::GalvoPair) hands
//! out an [`EmergencyPark`]: its driver's own way to the controller, used from the
//! e-stop's thread.
//!
//! Parking this way latches, as the laser's off does: once the handle has parked the
//! pair, its driver refuses every move (kind `Interrupted`) for the rest of its life,
//! so a move the stuck run sends when it comes back cannot point the arm anywhere but
//! the park position. Its own [`park`](crate::GalvoPair::park) still works.
use std::sync::Arc;

use crate::error::DeviceError;

/// What an emergency park could tell of its outcome.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Parked {
    /// The pair was sent to the park position, and the device said it took the
    /// command (a DAQ's write returned; an open-loop pair has nothing more to say).
    Done,
    /// The command went out, but its answer cannot be read without the driver (a
    /// serial controller answers on the link the stuck thread reads): unconfirmed.
    Sent,
}

/// A driver's way to send its pair to the park position from another thread, without
/// waiting for the thread that owns the driver.
pub trait ParkLine: Send + Sync {
    /// Latches the driver (no more moves), then sends the pair to its park position.
    /// Waits for nothing the owning thread holds for longer than one of its writes.
    fn park(&self) -> Result<Parked, DeviceError>;
    /// The arm and its device, for messages.
    fn describe(&self) -> String;
}

/// Parks a galvo pair from any thread ([`crate::GalvoPair::emergency_park`]). Cheap
/// to clone. Using it latches the driver: it refuses every move from then on.
#[derive(Clone)]
pub struct EmergencyPark(Arc<dyn ParkLine>);

impl EmergencyPark {
    /// A handle around a driver's park line.
    pub fn new(line: impl ParkLine + 'static) -> EmergencyPark {
        EmergencyPark(Arc::new(line))
    }

    /// Latches the driver and parks the pair now.
    pub fn park(&self) -> Result<Parked, DeviceError> {
        self.0.park()
    }

    /// The arm and its device.
    pub fn describe(&self) -> String {
        self.0.describe()
    }
}

impl std::fmt::Debug for EmergencyPark {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_tuple("EmergencyPark").field(&self.0.describe()).finish()
    }
}

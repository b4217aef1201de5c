//! Error kinds shared by every device driver.
//!
//! Each driver has its own error type, carrying the device's name, what went wrong and
//! what to do about it; what the daemon needs to decide (retry, reconnect, stop the
//! run, tell the operator about the interlock) is the error's [`ErrorKind`]. This is
//! embedded-hal's shape: a small trait on the error type with a `kind()` method.

/// What kind of failure a device error is, independent of the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum ErrorKind {
    /// The device did not answer in time (after the driver's one retry).
    Timeout,
    /// The device is gone: unplugged, powered off, or the port could not be opened.
    Disconnected,
    /// A requested value lies outside what the device accepts (angle limits, bin
    /// counts); nothing was sent or the device refused it.
    OutOfRange,
    /// The device answered something that does not follow the protocol (bad checksum
    /// after the retry, wrong frame, malformed reply).
    Protocol,
    /// The device is busy with an earlier request.
    Busy,
    /// The laser interlock is open, so the laser cannot emit.
    Interlock,
    /// The device reported an internal fault or refused a command for another reason.
    Device,
    /// The caller stopped the operation (pause, abort, e-stop) before it finished.
    Interrupted,
}

impl ErrorKind {
    /// A short lower-case name, as used in logs and the HTTP API.
    pub fn as_str(self) -> &'static str {
        match self {
            ErrorKind::Timeout => "timeout",
            ErrorKind::Disconnected => "disconnected",
            ErrorKind::OutOfRange => "out-of-range",
            ErrorKind::Protocol => "protocol",
            ErrorKind::Busy => "busy",
            ErrorKind::Interlock => "interlock",
            ErrorKind::Device => "device",
            ErrorKind::Interrupted => "interrupted",
        }
    }
}

impl std::fmt::Display for ErrorKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A device error that knows its [`ErrorKind`].
pub trait Error: std::error::Error + Send + Sync + 'static {
    /// The kind of failure.
    fn kind(&self) -> ErrorKind;
}

/// Names the error type of a device trait (embedded-hal's `ErrorType`).
pub trait ErrorType {
    /// The driver's error type.
    type Error: Error;
}

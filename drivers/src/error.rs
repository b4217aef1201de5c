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

/// The one error type behind every device trait object: what the daemon holds when it
/// drives a device without knowing its driver (probe-rs's boxed probe error). It keeps
/// the [`ErrorKind`] the daemon decides on, which device failed, and the driver's own
/// error as its source, whose message it shows unchanged (a driver's message already
/// names the device and says what to do).
pub struct DeviceError {
    kind: ErrorKind,
    device: String,
    source: Box<dyn Error>,
}

impl DeviceError {
    /// Wraps a driver's error; `device` names the device for callers that group
    /// failures by device (logs, the API's status).
    pub fn new(device: impl Into<String>, source: impl Error) -> DeviceError {
        DeviceError {
            kind: source.kind(),
            device: device.into(),
            source: Box::new(source),
        }
    }

    /// The device that failed, e.g. ``galvo pair `laser` `` or `histogrammer`.
    pub fn device(&self) -> &str {
        &self.device
    }

    /// The driver's own error.
    pub fn driver_error(&self) -> &(dyn Error + 'static) {
        self.source.as_ref()
    }
}

impl std::fmt::Debug for DeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DeviceError")
            .field("kind", &self.kind)
            .field("device", &self.device)
            .field("source", &self.source)
            .finish()
    }
}

/// Shows the driver's message as it is: the wrapper adds no words of its own, so a
/// message reads the same whichever layer prints it.
impl std::fmt::Display for DeviceError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Display::fmt(&self.source, f)
    }
}

impl std::error::Error for DeviceError {
    /// The driver error's own cause (its I/O error, say): the driver error itself is
    /// what [`Display`](std::fmt::Display) shows, as `#[error(transparent)]` would.
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.source.source()
    }
}

impl Error for DeviceError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

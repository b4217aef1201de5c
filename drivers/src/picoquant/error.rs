//! Errors of the PicoQuant driver: the library's error codes sorted into our
//! [`ErrorKind`]s, with the library's own words for them kept in the message.
use super::defin::error as code;
use crate::error::{DeviceError, Error, ErrorKind};

/// A PicoQuant counter's error: which device, what happened (the library's own error
/// string and code, where it gave one), what to do.
#[derive(Debug, thiserror::Error)]
#[error("{device}: {message}")]
pub struct PicoQuantError {
    /// The device (`MultiHarp 1045678`) or library (`MultiHarp library`).
    pub device: String,
    kind: ErrorKind,
    message: String,
    code: Option<i32>,
}

impl PicoQuantError {
    /// An error of `device` that no library code stands behind.
    pub fn new(device: &str, kind: ErrorKind, message: impl Into<String>) -> PicoQuantError {
        PicoQuantError {
            device: device.to_owned(),
            kind,
            message: message.into(),
            code: None,
        }
    }

    /// The library's answer `code` to `call`, in its own words `text`.
    pub(crate) fn library(device: &str, call: &str, code: i32, text: &str) -> PicoQuantError {
        let kind = kind_of(code);
        let advice = match kind {
            ErrorKind::Disconnected => {
                "the counter is gone or cannot be opened: check its USB cable and power, then `periscope devices`"
            }
            ErrorKind::Busy => {
                "another program holds the counter: close it (PicoQuant's own software, another daemon)"
            }
            ErrorKind::OutOfRange => "the instrument config or plan asks for a setting the counter refuses",
            ErrorKind::Timeout => "the counter's hardware did not answer in time: power-cycle it",
            ErrorKind::Protocol => {
                "library, kernel driver and firmware versions do not match: install the library that goes with this counter's firmware"
            }
            _ => "see the library's manual for this error",
        };
        PicoQuantError {
            device: device.to_owned(),
            kind,
            message: format!("{call} failed: {text} (error {code}); {advice}"),
            code: Some(code),
        }
    }

    /// The library's error code behind this error, if any.
    pub fn code(&self) -> Option<i32> {
        self.code
    }

    /// What the driver said, without the device prefix.
    pub fn message(&self) -> &str {
        &self.message
    }
}

/// The kind of a library error code.
pub fn kind_of(c: i32) -> ErrorKind {
    match c {
        code::DEVICE_OPEN_FAIL | code::DEVICE_NOT_OPEN => ErrorKind::Disconnected,
        code::DEVICE_BUSY | code::DEVICE_LOCKED | code::INSTANCE_RUNNING => ErrorKind::Busy,
        code::INVALID_ARGUMENT | code::INVALID_MODE | code::INVALID_OPTION => ErrorKind::OutOfRange,
        code::DEVICE_VERSION_MISMATCH | code::DEVICE_DRIVERVER_MISMATCH | code::USB_DRIVERVER_MISMATCH => {
            ErrorKind::Protocol
        }
        c if (code::MODULE_MISMATCH_LAST..=code::MODULE_MISMATCH_FIRST).contains(&c) => ErrorKind::Protocol,
        code::MODFWVER_TOO_LOW | code::MODFWVER_TOO_HIGH => ErrorKind::Protocol,
        c if (code::USB_LAST..=code::USB_FIRST).contains(&c) => ErrorKind::Disconnected,
        c if (code::TIMEOUT_LAST..=code::TIMEOUT_FIRST).contains(&c) => ErrorKind::Timeout,
        _ => ErrorKind::Device,
    }
}

impl Error for PicoQuantError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

impl From<PicoQuantError> for DeviceError {
    fn from(e: PicoQuantError) -> DeviceError {
        DeviceError::new(format!("histogrammer {}", e.device), e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_sort_into_kinds() {
        assert_eq!(kind_of(-1), ErrorKind::Disconnected);
        assert_eq!(kind_of(-2), ErrorKind::Busy);
        assert_eq!(kind_of(-17), ErrorKind::OutOfRange);
        assert_eq!(kind_of(-33), ErrorKind::Protocol);
        assert_eq!(kind_of(-37), ErrorKind::Disconnected);
        assert_eq!(kind_of(-41), ErrorKind::Timeout);
        assert_eq!(kind_of(-53), ErrorKind::Protocol);
        assert_eq!(kind_of(-22), ErrorKind::Device);
        assert_eq!(kind_of(-64), ErrorKind::Device);
    }
}

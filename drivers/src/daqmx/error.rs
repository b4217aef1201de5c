//! Errors of the DAQmx driver: NI-DAQmx's error codes sorted into our [`ErrorKind`]s,
//! with the library's own extended error information kept in the message (it names
//! the device, the channel and the property, which no code alone says).
use super::defin::error as code;
use crate::error::{DeviceError, Error, ErrorKind};

/// A DAQmx device's error: which part of the instrument on which lines, what happened
/// (the library's words and code, where it gave them), what to do.
#[derive(Debug, thiserror::Error)]
#[error("{device}: {message}")]
pub struct DaqError {
    /// The part and its lines: ``galvo pair `laser` on Dev1/ao0,Dev1/ao1``,
    /// `laser gate on Dev1/port0/line0`, or `NI-DAQmx library`.
    pub device: String,
    kind: ErrorKind,
    message: String,
    code: Option<i32>,
}

impl DaqError {
    /// An error of `device` that no library code stands behind.
    pub fn new(device: &str, kind: ErrorKind, message: impl Into<String>) -> DaqError {
        DaqError {
            device: device.to_owned(),
            kind,
            message: message.into(),
            code: None,
        }
    }

    /// The library's answer `code` to `call`, in its own words `text` (the extended
    /// error information, or the error string when that is empty).
    pub(crate) fn library(device: &str, call: &str, code: i32, text: &str) -> DaqError {
        let kind = kind_of(code);
        let advice = match (code, kind) {
            (code::WRITE_FAILED_BECAUSE_WATCHDOG_EXPIRED, _) => {
                "a hardware watchdog on this device expired (this program's, or an earlier one's) and holds the line at its \
                 expiration state: starting a watchdog task clears it, so set `laser.daq-watchdog = true`, or reset the \
                 device (NI MAX, Reset Device) and try again"
            }
            (code::DUPLICATE_TASK, _) => {
                "a task of that name exists already: another Periscope daemon (or a test panel) has this device open; \
                 close it"
            }
            (_, kind) => match kind {
                ErrorKind::Disconnected => {
                    "the DAQ device is gone or cannot be reached: check its cable and power, then `periscope devices`"
                }
                ErrorKind::Busy => {
                    "another task or program holds these lines: close it (NI MAX test panels, another daemon)"
                }
                ErrorKind::OutOfRange => {
                    "the instrument config names a channel or a value the device refuses: check the channel names against `periscope devices`"
                }
                ErrorKind::Timeout => "the device did not complete the operation in time",
                _ => "see NI-DAQmx's error reference for this code",
            },
        };
        let text = if text.is_empty() { "(no description)" } else { text };
        DaqError {
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

/// The kind of an NI-DAQmx error code.
pub fn kind_of(c: i32) -> ErrorKind {
    match c {
        code::DEVICE_REMOVED
        | code::DEV_ABSENT_OR_UNAVAILABLE
        | code::DEV_CANNOT_BE_ACCESSED
        | code::INVALID_DEVICE_ID
        | code::PAL_USB_TRANSACTION_ERROR => ErrorKind::Disconnected,
        code::RESOURCE_ALREADY_RESERVED | code::PAL_RESOURCE_RESERVED | code::DUPLICATE_TASK => {
            ErrorKind::Busy
        }
        code::INVALID_ATTRIBUTE_VALUE
        | code::MIN_NOT_LESS_THAN_MAX
        | code::PHYSICAL_CHAN_DOES_NOT_EXIST
        | code::INVALID_PHYS_CHAN_NAME
        | code::SAMPLE_VALUE_OUT_OF_RANGE
        | code::INVALID_AO_DATA_WRITE
        | code::WRITE_NUM_CHANS_MISMATCH => ErrorKind::OutOfRange,
        code::TIMEOUT_EXCEEDED | code::OPERATION_TIMED_OUT => ErrorKind::Timeout,
        _ => ErrorKind::Device,
    }
}

impl Error for DaqError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

impl From<DaqError> for DeviceError {
    fn from(e: DaqError) -> DeviceError {
        DeviceError::new(e.device.clone(), e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_sort_into_kinds() {
        assert_eq!(kind_of(-200045), ErrorKind::Disconnected);
        assert_eq!(kind_of(-50808), ErrorKind::Disconnected);
        assert_eq!(kind_of(-200022), ErrorKind::Busy);
        assert_eq!(kind_of(-200170), ErrorKind::OutOfRange);
        assert_eq!(kind_of(-200474), ErrorKind::Timeout);
        assert_eq!(kind_of(-200662), ErrorKind::Device);
        assert_eq!(kind_of(-1), ErrorKind::Device);
    }
}

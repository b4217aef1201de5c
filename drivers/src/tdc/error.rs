//! Errors of the USB histogrammer driver.
use crate::error::{Error, ErrorKind};

/// A histogrammer error: which device, what happened, what to do.
#[derive(Debug, thiserror::Error)]
#[error("histogrammer on {device}: {message}")]
pub struct TdcError {
    /// The device, as the transport describes it.
    pub device: String,
    kind: ErrorKind,
    message: String,
}

impl TdcError {
    /// An error of the histogrammer `device` (any histogrammer driver reports its
    /// failures as these).
    pub fn new(device: &str, kind: ErrorKind, message: impl Into<String>) -> Self {
        TdcError {
            device: device.to_owned(),
            kind,
            message: message.into(),
        }
    }

    /// What the driver said, without the device prefix.
    pub fn message(&self) -> &str {
        &self.message
    }
}

impl Error for TdcError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

impl From<TdcError> for crate::error::DeviceError {
    fn from(e: TdcError) -> crate::error::DeviceError {
        crate::error::DeviceError::new(format!("histogrammer on {}", e.device), e)
    }
}

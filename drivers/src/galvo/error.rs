//! Errors of the serial galvo driver.
use crate::error::{Error, ErrorKind};

/// A galvo controller error: which controller, what happened, what to do.
#[derive(Debug, thiserror::Error)]
#[error("galvo pair `{name}` on {port}: {message}")]
pub struct GalvoError {
    /// The arm's name from the instrument config (`laser`, `spad`).
    pub name: String,
    /// The port, as the connector describes it.
    pub port: String,
    kind: ErrorKind,
    message: String,
    #[source]
    source: Option<std::io::Error>,
}

impl GalvoError {
    /// An error of the controller `name` on `port` (any driver of a galvo pair or a
    /// laser reports its failures as these).
    pub fn new(name: &str, port: &str, kind: ErrorKind, message: impl Into<String>) -> Self {
        GalvoError {
            name: name.to_owned(),
            port: port.to_owned(),
            kind,
            message: message.into(),
            source: None,
        }
    }

    /// The I/O error behind it.
    pub fn with_source(mut self, source: std::io::Error) -> Self {
        self.source = Some(source);
        self
    }

    /// What the driver said, without the device prefix.
    pub fn message(&self) -> &str {
        &self.message
    }
}

impl Error for GalvoError {
    fn kind(&self) -> ErrorKind {
        self.kind
    }
}

impl From<GalvoError> for crate::error::DeviceError {
    fn from(e: GalvoError) -> crate::error::DeviceError {
        crate::error::DeviceError::new(format!("galvo pair `{}`", e.name), e)
    }
}

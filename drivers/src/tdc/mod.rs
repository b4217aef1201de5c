//! The USB TDC/SPAD histogrammer: its protocol (shared with the simulated device), the
//! transport trait with its libusb implementation, and the driver.
pub mod driver;
pub mod error;
pub mod protocol;
pub mod transport;

pub use driver::{POLL, UsbTdc};
pub use error::TdcError;
pub use transport::{RusbTransport, TransportError, UsbDeviceInfo, UsbTransport, list_usb_devices};

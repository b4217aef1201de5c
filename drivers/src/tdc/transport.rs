//! The USB transport under the histogrammer driver: three transfer types and a reopen.
//! The real one is libusb through `rusb`; the simulator implements the same trait with
//! a device model behind it, so the driver code above is the same in the lab and in CI.
use std::time::Duration;

use rusb::UsbContext;

use super::protocol::{INTERFACE, REQUEST_TYPE_IN, REQUEST_TYPE_OUT};
use crate::selector::UsbSelector;

/// How a transfer failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum TransportError {
    /// Nothing within the timeout.
    #[error("transfer timed out")]
    Timeout,
    /// The device is gone (unplugged, reset) or not found.
    #[error("device not present: {0}")]
    Disconnected(String),
    /// The endpoint stalled (the device refused the request).
    #[error("endpoint stalled")]
    Stall,
    /// Anything else libusb reports.
    #[error("{0}")]
    Other(String),
}

/// Transfers to and from one USB device.
pub trait UsbTransport: Send {
    /// Vendor control request, device → host; returns the bytes read.
    fn control_in(
        &mut self,
        request: u8,
        value: u16,
        index: u16,
        buf: &mut [u8],
        timeout: Duration,
    ) -> Result<usize, TransportError>;
    /// Vendor control request, host → device.
    fn control_out(
        &mut self,
        request: u8,
        value: u16,
        index: u16,
        data: &[u8],
        timeout: Duration,
    ) -> Result<(), TransportError>;
    /// One bulk-in transfer from `endpoint`; returns the bytes read (possibly fewer
    /// than a whole frame).
    fn bulk_in(&mut self, endpoint: u8, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError>;
    /// Drops the connection and opens the device again (after a disconnect).
    fn reopen(&mut self) -> Result<(), TransportError>;
    /// What it is connected to, for messages.
    fn describe(&self) -> String;
}

impl<T: UsbTransport + ?Sized> UsbTransport for Box<T> {
    fn control_in(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        buf: &mut [u8],
        t: Duration,
    ) -> Result<usize, TransportError> {
        (**self).control_in(r, v, i, buf, t)
    }
    fn control_out(&mut self, r: u8, v: u16, i: u16, data: &[u8], t: Duration) -> Result<(), TransportError> {
        (**self).control_out(r, v, i, data, t)
    }
    fn bulk_in(&mut self, ep: u8, buf: &mut [u8], t: Duration) -> Result<usize, TransportError> {
        (**self).bulk_in(ep, buf, t)
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        (**self).reopen()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
}

/// libusb, through `rusb`: the device chosen by a `VID:PID[:SERIAL]` selector.
pub struct RusbTransport {
    selector: UsbSelector,
    handle: Option<rusb::DeviceHandle<rusb::Context>>,
}

/// A libusb context; fails (rather than panicking, as rusb's global context does) on
/// hosts without USB support, such as containers without `/dev/bus/usb`.
fn context() -> Result<rusb::Context, TransportError> {
    rusb::Context::new().map_err(|e| {
        TransportError::Other(format!(
            "libusb cannot start ({e}): this host has no usable USB support"
        ))
    })
}

fn map(e: rusb::Error) -> TransportError {
    match e {
        rusb::Error::Timeout => TransportError::Timeout,
        rusb::Error::NoDevice | rusb::Error::NotFound | rusb::Error::Io => {
            TransportError::Disconnected(e.to_string())
        }
        rusb::Error::Pipe => TransportError::Stall,
        other => TransportError::Other(other.to_string()),
    }
}

impl RusbTransport {
    /// Opens the first device the selector matches and claims its interface.
    pub fn open(selector: UsbSelector) -> Result<RusbTransport, TransportError> {
        let mut t = RusbTransport {
            selector,
            handle: None,
        };
        t.reopen()?;
        Ok(t)
    }

    fn handle(&mut self) -> Result<&mut rusb::DeviceHandle<rusb::Context>, TransportError> {
        if self.handle.is_none() {
            self.reopen()?;
        }
        self.handle
            .as_mut()
            .ok_or_else(|| TransportError::Disconnected("not open".into()))
    }
}

/// A USB device as `periscope devices` lists it.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct UsbDeviceInfo {
    /// Vendor id.
    pub vendor_id: u16,
    /// Product id.
    pub product_id: u16,
    /// Bus number.
    pub bus: u8,
    /// Address on the bus.
    pub address: u8,
    /// Serial number, if the device has one and it could be read.
    pub serial: Option<String>,
    /// Product string, if readable.
    pub product: Option<String>,
}

/// Lists the USB devices libusb can see (descriptors only; strings where readable).
pub fn list_usb_devices() -> Result<Vec<UsbDeviceInfo>, TransportError> {
    let devices = context()?.devices().map_err(map)?;
    let mut out = Vec::new();
    for dev in devices.iter() {
        let Ok(desc) = dev.device_descriptor() else {
            continue;
        };
        let (serial, product) = match dev.open() {
            Ok(h) => (
                h.read_serial_number_string_ascii(&desc).ok(),
                h.read_product_string_ascii(&desc).ok(),
            ),
            Err(_) => (None, None),
        };
        out.push(UsbDeviceInfo {
            vendor_id: desc.vendor_id(),
            product_id: desc.product_id(),
            bus: dev.bus_number(),
            address: dev.address(),
            serial,
            product,
        });
    }
    Ok(out)
}

/// `t` as libusb must be given it: whole milliseconds, rounded up, and at least one.
/// rusb passes `t.as_millis()`, and libusb takes 0 as "no timeout": a read of the
/// last 0.7 ms before a deadline waited for ever on a device that sent nothing, and no
/// stop was seen (the driver asks between reads).
fn libusb_timeout(t: Duration) -> Duration {
    let ms = t.as_nanos().div_ceil(1_000_000).clamp(1, u128::from(u32::MAX));
    Duration::from_millis(ms as u64)
}

impl UsbTransport for RusbTransport {
    fn control_in(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        buf: &mut [u8],
        t: Duration,
    ) -> Result<usize, TransportError> {
        self.handle()?
            .read_control(REQUEST_TYPE_IN, r, v, i, buf, libusb_timeout(t))
            .map_err(map)
    }

    fn control_out(&mut self, r: u8, v: u16, i: u16, data: &[u8], t: Duration) -> Result<(), TransportError> {
        self.handle()?
            .write_control(REQUEST_TYPE_OUT, r, v, i, data, libusb_timeout(t))
            .map(drop)
            .map_err(map)
    }

    fn bulk_in(&mut self, ep: u8, buf: &mut [u8], t: Duration) -> Result<usize, TransportError> {
        let handle = self.handle()?;
        match handle.read_bulk(ep, buf, libusb_timeout(t)) {
            Err(rusb::Error::Pipe) => {
                // A halted endpoint: clear it so the next transfer can go through.
                let _ = handle.clear_halt(ep);
                Err(TransportError::Stall)
            }
            other => other.map_err(map),
        }
    }

    fn reopen(&mut self) -> Result<(), TransportError> {
        self.handle = None;
        let devices = context()?.devices().map_err(map)?;
        // A device of the model that cannot be opened or claimed (another user's, one
        // without permissions) does not end the search: the selected unit may be the
        // next one. Its error is the answer only if none is taken.
        let mut refused = None;
        for dev in devices.iter() {
            let Ok(desc) = dev.device_descriptor() else {
                continue;
            };
            if desc.vendor_id() != self.selector.vendor_id || desc.product_id() != self.selector.product_id {
                continue;
            }
            let handle = match dev.open() {
                Ok(h) => h,
                Err(e) => {
                    refused.get_or_insert(map(e));
                    continue;
                }
            };
            let serial = handle.read_serial_number_string_ascii(&desc).ok();
            if !self
                .selector
                .matches(desc.vendor_id(), desc.product_id(), serial.as_deref())
            {
                continue;
            }
            let _ = handle.set_auto_detach_kernel_driver(true);
            if let Err(e) = handle.claim_interface(INTERFACE) {
                refused.get_or_insert(map(e));
                continue;
            }
            self.handle = Some(handle);
            return Ok(());
        }
        Err(refused.unwrap_or_else(|| {
            TransportError::Disconnected(format!("no USB device matches {}", self.selector))
        }))
    }

    fn describe(&self) -> String {
        format!("USB {}", self.selector)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What libusb is given is never 0 (its "no timeout"), and never shorter than
    /// asked.
    #[test]
    fn a_timeout_under_a_millisecond_is_not_libusbs_forever() {
        for (asked, given) in [
            (Duration::ZERO, 1),
            (Duration::from_micros(700), 1),
            (Duration::from_micros(1_000), 1),
            (Duration::from_micros(1_001), 2),
            (Duration::from_millis(5), 5),
            (Duration::from_secs(u64::MAX), u64::from(u32::MAX)),
        ] {
            assert_eq!(libusb_timeout(asked), Duration::from_millis(given), "{asked:?}");
        }
    }
}

//! Serial ports on this host, for `periscope devices`.
use serde::Serialize;

/// A serial port as `periscope devices` lists it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct SerialPortInfo {
    /// Path to open (`/dev/ttyUSB0`).
    pub path: String,
    /// USB-serial adapters: `VID:PID`, and the serial number if known.
    pub usb: Option<String>,
    /// Product string of a USB-serial adapter, if known.
    pub product: Option<String>,
}

/// Lists serial ports (sysfs on Linux, so no udev is needed).
pub fn list_serial_ports() -> Result<Vec<SerialPortInfo>, String> {
    let ports = serialport::available_ports().map_err(|e| e.to_string())?;
    Ok(ports
        .into_iter()
        .map(|p| {
            let (usb, product) = match p.port_type {
                serialport::SerialPortType::UsbPort(u) => {
                    let mut id = format!("{:04x}:{:04x}", u.vid, u.pid);
                    if let Some(s) = &u.serial_number {
                        id.push(':');
                        id.push_str(s);
                    }
                    (Some(id), u.product)
                }
                _ => (None, None),
            };
            SerialPortInfo {
                path: p.port_name,
                usb,
                product,
            }
        })
        .collect())
}

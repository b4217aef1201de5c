//! Device selectors as written in instrument configs.
//!
//! A USB device is chosen by `VID:PID` or `VID:PID:SERIAL` (hexadecimal ids, the form
//! `lsusb` prints), so two identical histogrammers on one host can be told apart.
use std::fmt;
use std::str::FromStr;

/// Why a selector string could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "`{text}` is not a USB selector: {reason}; write VID:PID or VID:PID:SERIAL with hexadecimal ids, e.g. `1d50:6189` or `1d50:6189:TDC0042`"
)]
pub struct SelectorError {
    text: String,
    reason: &'static str,
}

/// Selects one USB device by vendor id, product id and optionally serial number.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UsbSelector {
    /// USB vendor id.
    pub vendor_id: u16,
    /// USB product id.
    pub product_id: u16,
    /// Serial number string; `None` matches any.
    pub serial: Option<String>,
}

impl UsbSelector {
    /// Whether a device with these descriptors is selected.
    pub fn matches(&self, vendor_id: u16, product_id: u16, serial: Option<&str>) -> bool {
        self.vendor_id == vendor_id
            && self.product_id == product_id
            && self.serial.as_deref().is_none_or(|want| serial == Some(want))
    }
}

impl FromStr for UsbSelector {
    type Err = SelectorError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let err = |reason| SelectorError {
            text: text.to_owned(),
            reason,
        };
        let mut parts = text.splitn(3, ':');
        let hex = |part: Option<&str>, what| {
            let part = part.filter(|p| !p.is_empty()).ok_or_else(|| err(what))?;
            u16::from_str_radix(part, 16).map_err(|_| err(what))
        };
        let vendor_id = hex(parts.next(), "the vendor id is not a 16-bit hexadecimal number")?;
        let product_id = hex(parts.next(), "the product id is not a 16-bit hexadecimal number")?;
        let serial = match parts.next() {
            None => None,
            Some("") => return Err(err("the serial number after the second `:` is empty")),
            Some(s) => Some(s.to_owned()),
        };
        Ok(Self {
            vendor_id,
            product_id,
            serial,
        })
    }
}

impl fmt::Display for UsbSelector {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:04x}:{:04x}", self.vendor_id, self.product_id)?;
        if let Some(serial) = &self.serial {
            write!(f, ":{serial}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_prints_round_trip() {
        for text in ["1d50:6189", "1d50:6189:TDC0042"] {
            let sel: UsbSelector = text.parse().unwrap();
            assert_eq!(sel.to_string(), text);
        }
        let sel: UsbSelector = "1D50:6189".parse().unwrap();
        assert_eq!((sel.vendor_id, sel.product_id), (0x1d50, 0x6189));
    }

    #[test]
    fn rejects_malformed_selectors_with_a_hint() {
        for text in ["", "1d50", "1d50:", "xyz:6189", "1d50:6189:", "12345:1"] {
            let err = text.parse::<UsbSelector>().unwrap_err().to_string();
            assert!(err.contains("VID:PID"), "{text}: {err}");
        }
    }

    #[test]
    fn serial_filters_only_when_given() {
        let any: UsbSelector = "1d50:6189".parse().unwrap();
        let one: UsbSelector = "1d50:6189:A".parse().unwrap();
        assert!(any.matches(0x1d50, 0x6189, None));
        assert!(one.matches(0x1d50, 0x6189, Some("A")));
        assert!(!one.matches(0x1d50, 0x6189, Some("B")));
        assert!(!one.matches(0x1d50, 0x6189, None));
    }
}

//! The histogrammer's USB protocol (see `docs/protocols/tdc-usb.md`): vendor control
//! requests for configuration and status, and bulk-in histogram frames. Encoding and
//! decoding live here and are used by both the driver and the simulated device.
//!
//! All integers are little-endian. A frame is a 32-byte header, `bins` u32 counts and
//! a CRC-32 (IEEE) of header and counts.
use crate::traits::HistogramFlags;

/// `bmRequestType` for vendor requests to the device, host → device.
pub const REQUEST_TYPE_OUT: u8 = 0x40;
/// `bmRequestType` for vendor requests to the device, device → host.
pub const REQUEST_TYPE_IN: u8 = 0xC0;
/// Bulk-in endpoint carrying histogram frames.
pub const BULK_IN_ENDPOINT: u8 = 0x81;
/// Interface the driver claims.
pub const INTERFACE: u8 = 0;
/// Protocol revision.
pub const PROTOCOL_VERSION: u16 = 1;
/// Frame magic, `PTDC` in ASCII.
pub const MAGIC: [u8; 4] = *b"PTDC";
/// Header length, bytes.
pub const HEADER_LEN: usize = 32;
/// Most bins a frame may declare (the decoder refuses larger frames as corrupt).
pub const MAX_BINS: u32 = 1 << 16;

/// Vendor control requests (`bRequest`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ControlRequest {
    /// IN, 64 bytes: [`WireInfo`].
    GetInfo = 0x01,
    /// OUT, 20 bytes: [`WireConfig`].
    SetConfig = 0x02,
    /// IN, 20 bytes: [`WireConfig`].
    GetConfig = 0x03,
    /// OUT, no data: start one acquisition; `wValue` and `wIndex` carry the low and
    /// high halves of the sequence number the frame will carry.
    Start = 0x04,
    /// IN, 16 bytes: [`WireStatus`].
    GetStatus = 0x05,
    /// OUT, no data: abort the acquisition in progress (no frame is sent).
    Abort = 0x06,
}

impl ControlRequest {
    /// The request for a `bRequest` value.
    pub fn from_u8(v: u8) -> Option<ControlRequest> {
        use ControlRequest::*;
        [GetInfo, SetConfig, GetConfig, Start, GetStatus, Abort]
            .into_iter()
            .find(|r| *r as u8 == v)
    }
}

fn u16_at(b: &[u8], i: usize) -> u16 {
    u16::from_le_bytes([b[i], b[i + 1]])
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes([b[i], b[i + 1], b[i + 2], b[i + 3]])
}

/// Configuration as it travels: integer picoseconds and microseconds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WireConfig {
    /// Bin width, ps.
    pub bin_width_ps: u32,
    /// Bin count.
    pub bins: u32,
    /// Offset of bin 0 after the sync, ps.
    pub offset_ps: u32,
    /// Sync divider.
    pub sync_divider: u32,
    /// Acquisition time, µs.
    pub acquisition_us: u32,
}

impl WireConfig {
    /// Encoded length.
    pub const LEN: usize = 20;

    /// Settings as the device takes them: whole picoseconds and microseconds, `None`
    /// when they cannot be expressed so (a zero bin width or acquisition time, or out
    /// of range).
    pub fn from_config(c: &crate::traits::TdcConfig) -> Option<WireConfig> {
        // Whole within a thousandth of a picosecond (what an f64 of seconds carries of
        // a whole number), and whole microseconds: anything else is refused, not
        // rounded behind the caller's back (the histogram reports the config asked for).
        let ps = |s: f64| {
            let v = s * 1e12;
            let r = v.round();
            (r.is_finite() && (v - r).abs() <= 1e-3 && (0.0..=u32::MAX as f64).contains(&r))
                .then_some(r as u32)
        };
        if !c.acquisition.subsec_nanos().is_multiple_of(1_000) {
            return None;
        }
        let us = c.acquisition.as_micros();
        Some(WireConfig {
            bin_width_ps: ps(c.bin_width).filter(|&p| p > 0)?,
            bins: c.bins,
            offset_ps: ps(c.offset)?,
            sync_divider: c.sync_divider,
            acquisition_us: u32::try_from(us).ok().filter(|&u| u > 0)?,
        })
    }

    /// Encodes.
    pub fn encode(&self) -> [u8; Self::LEN] {
        let mut b = [0u8; Self::LEN];
        for (i, v) in [
            self.bin_width_ps,
            self.bins,
            self.offset_ps,
            self.sync_divider,
            self.acquisition_us,
        ]
        .into_iter()
        .enumerate()
        {
            b[4 * i..4 * i + 4].copy_from_slice(&v.to_le_bytes());
        }
        b
    }

    /// Decodes; `None` if too short.
    pub fn decode(b: &[u8]) -> Option<WireConfig> {
        (b.len() >= Self::LEN).then(|| WireConfig {
            bin_width_ps: u32_at(b, 0),
            bins: u32_at(b, 4),
            offset_ps: u32_at(b, 8),
            sync_divider: u32_at(b, 12),
            acquisition_us: u32_at(b, 16),
        })
    }
}

/// Device description returned by `GET_INFO`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WireInfo {
    /// Protocol revision.
    pub protocol: u16,
    /// Firmware major, minor.
    pub firmware: (u16, u16),
    /// Most bins per histogram.
    pub max_bins: u32,
    /// Smallest bin width, ps.
    pub min_bin_width_ps: u32,
    /// Model name (up to 24 bytes, NUL-padded).
    pub model: String,
    /// Serial number (up to 24 bytes, NUL-padded).
    pub serial: String,
}

impl WireInfo {
    /// Encoded length.
    pub const LEN: usize = 64;

    fn text(b: &[u8]) -> String {
        let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
        String::from_utf8_lossy(&b[..end]).into_owned()
    }

    /// Encodes (model and serial truncated to 24 bytes).
    pub fn encode(&self) -> [u8; Self::LEN] {
        let mut b = [0u8; Self::LEN];
        b[0..2].copy_from_slice(&self.protocol.to_le_bytes());
        b[2..4].copy_from_slice(&self.firmware.0.to_le_bytes());
        b[4..6].copy_from_slice(&self.firmware.1.to_le_bytes());
        b[8..12].copy_from_slice(&self.max_bins.to_le_bytes());
        b[12..16].copy_from_slice(&self.min_bin_width_ps.to_le_bytes());
        for (dst, src) in [(16, &self.model), (40, &self.serial)] {
            let s = src.as_bytes();
            let n = s.len().min(24);
            b[dst..dst + n].copy_from_slice(&s[..n]);
        }
        b
    }

    /// Decodes; `None` if too short.
    pub fn decode(b: &[u8]) -> Option<WireInfo> {
        (b.len() >= Self::LEN).then(|| WireInfo {
            protocol: u16_at(b, 0),
            firmware: (u16_at(b, 2), u16_at(b, 4)),
            max_bins: u32_at(b, 8),
            min_bin_width_ps: u32_at(b, 12),
            model: Self::text(&b[16..40]),
            serial: Self::text(&b[40..64]),
        })
    }
}

/// Device state byte in [`WireStatus`].
pub mod state {
    /// Ready.
    pub const IDLE: u8 = 0;
    /// Acquiring.
    pub const ACQUIRING: u8 = 1;
    /// Internal error; see the error byte.
    pub const ERROR: u8 = 2;
}

/// The gate of the device's sync rate meter: `GET_STATUS` reports the sync (after
/// the divider) counted over the last whole gate.
pub const RATE_GATE: std::time::Duration = std::time::Duration::from_millis(100);

/// Status returned by `GET_STATUS`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WireStatus {
    /// One of [`state`].
    pub state: u8,
    /// Device error code, 0 = none.
    pub error: u8,
    /// Sync rate after the divider, Hz, over the last whole [`RATE_GATE`].
    pub sync_rate_hz: u32,
    /// Detector input rate, Hz.
    pub input_rate_hz: u32,
    /// Histograms sent since power-up.
    pub frames: u32,
}

impl WireStatus {
    /// Encoded length.
    pub const LEN: usize = 16;

    /// Encodes.
    pub fn encode(&self) -> [u8; Self::LEN] {
        let mut b = [0u8; Self::LEN];
        b[0] = self.state;
        b[1] = self.error;
        b[4..8].copy_from_slice(&self.sync_rate_hz.to_le_bytes());
        b[8..12].copy_from_slice(&self.input_rate_hz.to_le_bytes());
        b[12..16].copy_from_slice(&self.frames.to_le_bytes());
        b
    }

    /// Decodes; `None` if too short.
    pub fn decode(b: &[u8]) -> Option<WireStatus> {
        (b.len() >= Self::LEN).then(|| WireStatus {
            state: b[0],
            error: b[1],
            sync_rate_hz: u32_at(b, 4),
            input_rate_hz: u32_at(b, 8),
            frames: u32_at(b, 12),
        })
    }
}

/// Frame flag bits.
pub mod flag {
    /// A counter or the FIFO overflowed.
    pub const OVERFLOW: u32 = 1 << 0;
    /// Input rate above the pile-up threshold.
    pub const SATURATED: u32 = 1 << 1;
}

/// A histogram frame's header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameHeader {
    /// Sequence number from the `START` request.
    pub sequence: u32,
    /// [`flag`] bits.
    pub flags: u32,
    /// The configuration the histogram was acquired with.
    pub config: WireConfig,
}

impl FrameHeader {
    /// Flags as a struct.
    pub fn histogram_flags(&self) -> HistogramFlags {
        HistogramFlags {
            overflow: self.flags & flag::OVERFLOW != 0,
            saturated: self.flags & flag::SATURATED != 0,
        }
    }

    /// Total frame length for this header.
    pub fn frame_len(&self) -> usize {
        HEADER_LEN + 4 * self.config.bins as usize + 4
    }
}

/// Encodes a frame: header, counts, CRC-32.
pub fn encode_frame(header: &FrameHeader, counts: &[u32]) -> Vec<u8> {
    assert_eq!(
        counts.len(),
        header.config.bins as usize,
        "frame header and counts disagree"
    );
    let mut b = Vec::with_capacity(header.frame_len());
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    b.extend_from_slice(&(HEADER_LEN as u16).to_le_bytes());
    b.extend_from_slice(&header.sequence.to_le_bytes());
    b.extend_from_slice(&header.flags.to_le_bytes());
    let c = header.config;
    for v in [c.bins, c.bin_width_ps, c.offset_ps, c.acquisition_us] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    for &v in counts {
        b.extend_from_slice(&v.to_le_bytes());
    }
    let crc = crc32fast::hash(&b);
    b.extend_from_slice(&crc.to_le_bytes());
    b
}

/// Why bytes are not a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameError {
    /// Fewer bytes than the header says (need more).
    Incomplete {
        /// Total bytes the frame needs.
        needed: usize,
    },
    /// Not a frame start (magic, version or header length wrong, absurd bin count).
    BadHeader,
    /// The CRC does not match.
    BadCrc,
}

/// Parses the header at the start of `b`.
pub fn decode_header(b: &[u8]) -> Result<FrameHeader, FrameError> {
    if b.len() < HEADER_LEN {
        if !MAGIC.starts_with(&b[..b.len().min(4)]) {
            return Err(FrameError::BadHeader);
        }
        return Err(FrameError::Incomplete { needed: HEADER_LEN });
    }
    if b[0..4] != MAGIC || u16_at(b, 4) != PROTOCOL_VERSION || u16_at(b, 6) as usize != HEADER_LEN {
        return Err(FrameError::BadHeader);
    }
    let bins = u32_at(b, 16);
    if bins == 0 || bins > MAX_BINS {
        return Err(FrameError::BadHeader);
    }
    Ok(FrameHeader {
        sequence: u32_at(b, 8),
        flags: u32_at(b, 12),
        config: WireConfig {
            bins,
            bin_width_ps: u32_at(b, 20),
            offset_ps: u32_at(b, 24),
            acquisition_us: u32_at(b, 28),
            sync_divider: 0,
        },
    })
}

/// Decodes one whole frame at the start of `b`; returns it and its length.
pub fn decode_frame(b: &[u8]) -> Result<(FrameHeader, Vec<u32>, usize), FrameError> {
    let header = decode_header(b)?;
    let len = header.frame_len();
    if b.len() < len {
        return Err(FrameError::Incomplete { needed: len });
    }
    let body = &b[..len - 4];
    if crc32fast::hash(body) != u32_at(b, len - 4) {
        return Err(FrameError::BadCrc);
    }
    let counts = body[HEADER_LEN..]
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Ok((header, counts, len))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Settings are taken in whole picoseconds and microseconds, within what an f64
    /// of seconds carries of them, and refused otherwise (they were rounded and
    /// truncated, while the histogram reported the settings asked for).
    #[test]
    fn settings_finer_than_the_counter_are_refused_not_rounded() {
        let config = |offset: f64, acquisition: std::time::Duration| crate::traits::TdcConfig {
            bin_width: 16e-12,
            bins: 1024,
            offset,
            sync_divider: 1,
            acquisition,
        };
        let ms = std::time::Duration::from_millis;
        let wire = WireConfig::from_config(&config(12.345e-9, ms(20))).unwrap();
        assert_eq!((wire.offset_ps, wire.acquisition_us), (12_345, 20_000));
        assert_eq!(WireConfig::from_config(&config(12.3456e-9, ms(20))), None);
        let us = std::time::Duration::from_nanos(1_500);
        assert_eq!(WireConfig::from_config(&config(12e-9, us)), None);
        assert!(WireConfig::from_config(&config(12e-9, std::time::Duration::from_micros(1))).is_some());
    }

    fn header() -> FrameHeader {
        FrameHeader {
            sequence: 9,
            flags: flag::OVERFLOW,
            config: WireConfig {
                bin_width_ps: 16,
                bins: 4,
                offset_ps: 12_000,
                sync_divider: 0,
                acquisition_us: 1000,
            },
        }
    }

    #[test]
    fn frames_round_trip() {
        let bytes = encode_frame(&header(), &[1, 2, 3, u32::MAX]);
        assert_eq!(bytes.len(), HEADER_LEN + 16 + 4);
        let (h, counts, len) = decode_frame(&bytes).unwrap();
        assert_eq!((h, counts, len), (header(), vec![1, 2, 3, u32::MAX], bytes.len()));
        assert!(h.histogram_flags().overflow);
    }

    #[test]
    fn corrupted_and_short_frames_are_refused() {
        let bytes = encode_frame(&header(), &[1, 2, 3, 4]);
        let mut bad = bytes.clone();
        bad[HEADER_LEN + 1] ^= 0x10;
        assert_eq!(decode_frame(&bad).unwrap_err(), FrameError::BadCrc);
        assert_eq!(
            decode_frame(&bytes[..40]).unwrap_err(),
            FrameError::Incomplete { needed: bytes.len() }
        );
        assert_eq!(
            decode_frame(&bytes[..2]).unwrap_err(),
            FrameError::Incomplete { needed: HEADER_LEN }
        );
        assert_eq!(decode_frame(b"XXXX").unwrap_err(), FrameError::BadHeader);
    }

    #[test]
    fn control_payloads_round_trip() {
        let c = header().config;
        assert_eq!(WireConfig::decode(&c.encode()), Some(c));
        let info = WireInfo {
            protocol: 1,
            firmware: (2, 3),
            max_bins: 65536,
            min_bin_width_ps: 4,
            model: "PTDC-1".into(),
            serial: "SIM0001".into(),
        };
        assert_eq!(WireInfo::decode(&info.encode()), Some(info));
        let s = WireStatus {
            state: state::ACQUIRING,
            error: 0,
            sync_rate_hz: 10_000_000,
            input_rate_hz: 12345,
            frames: 7,
        };
        assert_eq!(WireStatus::decode(&s.encode()), Some(s));
    }
}

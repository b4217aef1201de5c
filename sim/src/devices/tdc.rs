//! The simulated histogrammer, behind the same USB transport trait libusb implements:
//! control requests are answered by a device model and histogram frames are queued
//! for bulk-in reads, encoded by the protocol code the driver decodes them with.
use std::collections::VecDeque;
use std::time::{Duration, Instant};

use periscope_drivers::tdc::protocol::{
    self, ControlRequest, FrameHeader, WireConfig, WireInfo, WireStatus, flag, state,
};
use periscope_drivers::tdc::{TransportError, UsbTransport};

use super::rig::{Rig, Shared, TdcFault};
use crate::detector::sample_counts;

/// Pile-up rule of thumb: above 5 % detections per sync, histograms are distorted.
const PILE_UP_FRACTION: f64 = 0.05;

/// The simulated histogrammer as a USB transport.
pub struct SimTdcTransport {
    rig: Rig,
    config: Option<WireConfig>,
    /// Bytes queued on the bulk-in endpoint, one transfer per entry, each with the
    /// moment it becomes available (the end of its acquisition).
    out: VecDeque<(Instant, Vec<u8>)>,
    frames: u32,
    acquisitions: u64,
    last_rate: f64,
    last_sequence: u32,
    disconnected: bool,
    /// The counts of the last frames produced, by sequence number, as generated
    /// (before any injected corruption): what a correct driver must return.
    sent: VecDeque<(u32, Vec<u32>)>,
}

/// Frames remembered for [`SimTdcTransport::sent_counts`].
const SENT_LOG: usize = 16;

impl SimTdcTransport {
    pub(crate) fn new(rig: Rig) -> SimTdcTransport {
        // With the cable still out the device is not on the bus: the first transfer
        // fails and only a reopen the rig allows brings it up (as a handle opened on
        // a real bus while the device is absent).
        let absent = {
            let s = rig.shared.lock();
            s.tdc_unplugged || s.tdc_refused_reopens > 0
        };
        SimTdcTransport {
            rig,
            config: None,
            out: VecDeque::new(),
            frames: 0,
            acquisitions: 0,
            last_rate: 0.0,
            last_sequence: 0,
            disconnected: absent,
            sent: VecDeque::new(),
        }
    }

    /// The counts the device generated for acquisition `sequence` (one of the last 16),
    /// before any injected fault touched the frame.
    pub fn sent_counts(&self, sequence: u32) -> Option<&[u32]> {
        self.sent
            .iter()
            .find(|(s, _)| *s == sequence)
            .map(|(_, c)| c.as_slice())
    }

    /// Whether a `START`'s dwell is still running: its frame is queued and not ready
    /// yet (`GET_STATUS` state 1, docs/protocols/tdc-usb.md). An `ABORT`, an unplug or
    /// a reopen drops the frame and with it the acquisition; a frame whose dwell has
    /// ended waits to be read with the device idle.
    fn acquiring(&self) -> bool {
        let now = Instant::now();
        self.out.iter().any(|(ready, _)| *ready > now)
    }

    fn check_present(&mut self) -> Result<(), TransportError> {
        if std::mem::take(&mut self.rig.shared.lock().tdc_unplugged) {
            self.disconnected = true;
            self.config = None;
            self.out.clear();
        }
        if self.disconnected {
            return Err(TransportError::Disconnected(
                "simulated histogrammer unplugged".into(),
            ));
        }
        Ok(())
    }

    fn next_fault(&mut self) -> Option<TdcFault> {
        let fault = self.rig.shared.lock().tdc_faults.pop_front();
        if let Some(TdcFault::Disconnect { refused_reopens }) = fault {
            self.disconnected = true;
            self.config = None;
            self.out.clear();
            self.rig.shared.lock().tdc_refused_reopens = refused_reopens;
        }
        fault
    }

    fn start(&mut self, sequence: u32) -> Result<(), TransportError> {
        let Some(cfg) = self.config else {
            // Not configured: the firmware stalls the request.
            return Err(TransportError::Stall);
        };
        let fault = self.next_fault();
        self.check_present()?;
        // The frame is ready when the dwell ends; until then bulk reads time out, and an
        // `ABORT` drops it.
        let ready = Instant::now()
            + self
                .rig
                .shared
                .scaled(Duration::from_micros(u64::from(cfg.acquisition_us)));
        self.acquisitions += 1;
        let Measurement {
            counts,
            mut flags,
            rate,
        } = measure(&self.rig.shared, cfg, self.acquisitions);
        self.last_rate = rate;
        if fault == Some(TdcFault::Overflow) {
            flags |= flag::OVERFLOW;
        }
        let header = FrameHeader {
            sequence,
            flags,
            config: WireConfig {
                sync_divider: 0,
                ..cfg
            },
        };
        let mut frame = protocol::encode_frame(&header, &counts);
        self.frames += 1;
        if self.sent.len() == SENT_LOG {
            self.sent.pop_front();
        }
        self.sent.push_back((sequence, counts));
        if fault == Some(TdcFault::StaleFrame) {
            let stale = FrameHeader {
                sequence: self.last_sequence,
                ..header
            };
            self.out
                .push_back((ready, protocol::encode_frame(&stale, &vec![1; cfg.bins as usize])));
        }
        self.last_sequence = sequence;
        match fault {
            Some(TdcFault::Stall) => {}
            Some(TdcFault::CorruptCrc) => {
                let i = (protocol::HEADER_LEN + frame.len() / 3).min(frame.len() - 5);
                frame[i] ^= 0x04;
                self.out.push_back((ready, frame));
            }
            Some(TdcFault::ShortRead) => {
                for piece in frame.chunks(61) {
                    self.out.push_back((ready, piece.to_vec()));
                }
            }
            Some(TdcFault::Truncated) => {
                frame.truncate(frame.len() / 2);
                self.out.push_back((ready, frame));
            }
            _ => self.out.push_back((ready, frame)),
        }
        Ok(())
    }
}

/// Expected counts for the current pointing and laser state.
fn expected(shared: &Shared, cfg: WireConfig) -> Vec<f64> {
    let mut det = shared.settings.detector;
    det.bins = cfg.bins as usize;
    det.bin_width = f64::from(cfg.bin_width_ps) * 1e-12;
    det.offset = f64::from(cfg.offset_ps) * 1e-12;
    let dwell = f64::from(cfg.acquisition_us) * 1e-6;
    let (laser, spad, emission, diffuser_in) = {
        let s = shared.lock();
        det.repetition_rate = s.repetition_rate;
        (s.arms[0].target, s.arms[1].target, s.emission(), s.diffuser_in)
    };
    // The laser pulses at its own rate whatever the divider; the counter's cycle
    // spans `sync_divider` pulses (until 2026-12-07 the rate was divided, which
    // multiplied each pulse's photons by the divider).
    det.sync_divider = cfg.sync_divider.max(1);
    let background = det;
    let dark = || background.expected_counts(&vec![0.0; background.bins], None, dwell);
    let Some(world) = shared.world.as_ref().filter(|_| emission) else {
        return dark();
    };
    let inst = shared.instrument();
    let laser_dir = shared.settings.laser_pose.direction(laser);
    let spad_dir = shared.settings.spad_pose.direction(spad);
    if diffuser_in {
        // The LOS scan: no gating, the direct return is the signal.
        det.gate_margin = None;
        return world
            .first_bounce(&inst, spad_dir, &det, dwell)
            .map_or_else(dark, |(_, c)| c);
    }
    match world.spots(&inst, laser_dir, spad_dir) {
        Some(pair) => world
            .third_bounce(&inst, &[pair], &det, dwell)
            .pop()
            .unwrap_or_else(dark),
        None => dark(),
    }
}

/// One acquisition's outcome, as the device produces it before any fault touches it.
pub(crate) struct Measurement {
    /// Counts per bin (Poisson draws, the `n`-th of the rig's seed).
    pub counts: Vec<u32>,
    /// Frame flags (`flag::OVERFLOW`, `flag::SATURATED`).
    pub flags: u32,
    /// Detector count rate over the dwell, Hz.
    pub rate: f64,
}

/// Acquisition number `n` with settings `cfg`, for the current pointing and laser
/// state: what the wire device frames and the in-process device returns.
pub(crate) fn measure(shared: &Shared, cfg: WireConfig, n: u64) -> Measurement {
    let expected = expected(shared, cfg);
    let counts = if shared.settings.noise {
        sample_counts(&expected, shared.settings.seed, n)
    } else {
        expected
            .iter()
            .map(|&l| {
                // A mean beyond a 32-bit counter (infinite included) fills it, as a
                // Poisson draw of it does (`sample_counts`), and is flagged below.
                if l.is_nan() {
                    0
                } else {
                    l.round().clamp(0.0, f64::from(u32::MAX)) as u32
                }
            })
            .collect()
    };
    let dwell = f64::from(cfg.acquisition_us) * 1e-6;
    let total: f64 = counts.iter().map(|&c| f64::from(c)).sum();
    let rate = total / dwell;
    let mut flags = 0;
    if counts.contains(&u32::MAX) {
        flags |= flag::OVERFLOW;
    }
    if rate > PILE_UP_FRACTION * sync_rate(shared, cfg) {
        flags |= flag::SATURATED;
    }
    Measurement { counts, flags, rate }
}

/// The sync rate after the divider, Hz.
pub(crate) fn sync_rate(shared: &Shared, cfg: WireConfig) -> f64 {
    shared.lock().repetition_rate / f64::from(cfg.sync_divider.max(1))
}

impl UsbTransport for SimTdcTransport {
    fn control_in(
        &mut self,
        request: u8,
        _value: u16,
        _index: u16,
        buf: &mut [u8],
        _t: Duration,
    ) -> Result<usize, TransportError> {
        self.check_present()?;
        let bytes: Vec<u8> = match ControlRequest::from_u8(request) {
            Some(ControlRequest::GetInfo) => WireInfo {
                protocol: protocol::PROTOCOL_VERSION,
                firmware: (1, 0),
                max_bins: protocol::MAX_BINS,
                min_bin_width_ps: 1,
                model: "PTDC-SIM".into(),
                serial: format!("SIM{:04}", self.rig.shared.settings.seed % 10_000),
            }
            .encode()
            .to_vec(),
            Some(ControlRequest::GetConfig) => self.config.ok_or(TransportError::Stall)?.encode().to_vec(),
            Some(ControlRequest::GetStatus) => {
                let sync = self.config.map_or(0.0, |c| sync_rate(&self.rig.shared, c));
                WireStatus {
                    state: if self.acquiring() {
                        state::ACQUIRING
                    } else {
                        state::IDLE
                    },
                    error: 0,
                    sync_rate_hz: sync as u32,
                    input_rate_hz: self.last_rate.min(f64::from(u32::MAX)) as u32,
                    frames: self.frames,
                }
                .encode()
                .to_vec()
            }
            _ => return Err(TransportError::Stall),
        };
        let n = bytes.len().min(buf.len());
        buf[..n].copy_from_slice(&bytes[..n]);
        Ok(n)
    }

    fn control_out(
        &mut self,
        request: u8,
        value: u16,
        index: u16,
        data: &[u8],
        _t: Duration,
    ) -> Result<(), TransportError> {
        self.check_present()?;
        match ControlRequest::from_u8(request) {
            Some(ControlRequest::SetConfig) => {
                let cfg = WireConfig::decode(data).ok_or(TransportError::Stall)?;
                let valid = (1..=protocol::MAX_BINS).contains(&cfg.bins)
                    && cfg.bin_width_ps >= 1
                    && cfg.acquisition_us >= 1
                    && cfg.sync_divider >= 1;
                if !valid {
                    return Err(TransportError::Stall);
                }
                self.config = Some(cfg);
                Ok(())
            }
            Some(ControlRequest::Start) => self.start(u32::from(value) | (u32::from(index) << 16)),
            Some(ControlRequest::Abort) => {
                self.out.clear();
                Ok(())
            }
            _ => Err(TransportError::Stall),
        }
    }

    fn bulk_in(&mut self, endpoint: u8, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError> {
        self.check_present()?;
        if endpoint != protocol::BULK_IN_ENDPOINT {
            return Err(TransportError::Stall);
        }
        if let Some((ready, _)) = self.out.front() {
            // Acquiring: the frame comes when the dwell ends, or the read times out.
            let wait = ready.saturating_duration_since(Instant::now());
            if wait > timeout {
                std::thread::sleep(timeout);
                return Err(TransportError::Timeout);
            }
            std::thread::sleep(wait);
            // Unplugged while the frame was being acquired?
            self.check_present()?;
        }
        match self.out.front_mut().map(|(_, bytes)| bytes) {
            None => {
                // Nothing will come: the host would wait out its timeout. Wait a
                // little of it (so timeouts stay real) without burning the test's time.
                std::thread::sleep(timeout.min(Duration::from_millis(5)));
                Err(TransportError::Timeout)
            }
            Some(front) => {
                let n = front.len().min(buf.len());
                buf[..n].copy_from_slice(&front[..n]);
                if n == front.len() {
                    self.out.pop_front();
                } else {
                    front.drain(..n);
                }
                Ok(n)
            }
        }
    }

    fn reopen(&mut self) -> Result<(), TransportError> {
        let mut s = self.rig.shared.lock();
        if s.tdc_refused_reopens > 0 {
            s.tdc_refused_reopens -= 1;
            return Err(TransportError::Disconnected(
                "simulated histogrammer unplugged".into(),
            ));
        }
        self.disconnected = false;
        self.config = None;
        self.out.clear();
        Ok(())
    }

    fn describe(&self) -> String {
        "simulated histogrammer (USB transport)".into()
    }
}

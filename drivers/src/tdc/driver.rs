//! The USB histogrammer driver.
//!
//! An acquisition is a `START` control request carrying a fresh sequence number and a
//! bulk-in frame carrying it back. The driver accepts a frame only when its CRC holds,
//! its sequence number is the one just requested (older frames are drained and
//! dropped) and its settings are the ones in force; anything else is never returned as
//! a histogram. A timed-out, short or corrupted acquisition is repeated once (an
//! acquisition has no side effect but its dwell). A disconnect is met by reopening the
//! device, restoring the settings, and repeating the acquisition once.
use std::time::{Duration, Instant};

use tracing::{debug, instrument, warn};

use super::error::TdcError;
use super::protocol::{self, ControlRequest, FrameError, WireConfig, WireInfo, WireStatus};
use super::transport::{TransportError, UsbTransport};
use crate::error::{Error, ErrorKind, ErrorType};
use crate::traits::{CountRates, DeviceInfo, Histogram, Histogrammer, TdcConfig, TdcState, TdcStatus};

/// The histogrammer behind a [`UsbTransport`].
pub struct UsbTdc<T: UsbTransport> {
    transport: T,
    device: String,
    /// Timeout for control transfers, and slack added to the acquisition time for the
    /// frame to arrive.
    timeout: Duration,
    config: Option<TdcConfig>,
    sequence: u32,
    rx: Vec<u8>,
    chunk: Vec<u8>,
}

impl<T: UsbTransport> ErrorType for UsbTdc<T> {
    type Error = TdcError;
}

/// How long a drain waits for more data before it counts the endpoint as empty.
const DRAIN_WAIT: Duration = Duration::from_millis(10);

/// Longest a drain on open may take (a device streaming without end is an error the
/// first acquisition reports).
pub const DRAIN_LIMIT: Duration = Duration::from_millis(500);

/// A sequence number no earlier connection is likely to have used: from the
/// process's random hash keys and the clock.
fn random_sequence() -> u32 {
    use std::hash::{BuildHasher, Hasher};
    let mut h = std::collections::hash_map::RandomState::new().build_hasher();
    h.write_u128(
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos()),
    );
    h.finish() as u32
}

/// How often an acquisition in progress asks whether to stop: the bound on how long
/// a stop waits for a dwell, whatever its length.
pub const POLL: Duration = Duration::from_millis(5);

impl<T: UsbTransport> UsbTdc<T> {
    /// Sends `ABORT` and drops whatever was received: the device discards the
    /// acquisition in progress and any frame not yet read.
    fn abort_acquisition(&mut self) -> Result<(), TdcError> {
        self.rx.clear();
        self.transport
            .control_out(ControlRequest::Abort as u8, 0, 0, &[], self.timeout)
            .map_err(|e| self.transport_err("Abort", e))
    }

    /// A driver over an open transport, starting its sequence numbers at a random
    /// value. It talks to the device only when asked; [`UsbTdc::open`] also clears
    /// what an earlier connection left behind, and is what the daemon uses.
    pub fn new(transport: T, timeout: Duration) -> UsbTdc<T> {
        UsbTdc::with_sequence(transport, timeout, random_sequence())
    }

    /// A driver whose first acquisition carries sequence number `last + 1` (scripted
    /// tests, which need to know it).
    pub fn with_sequence(transport: T, timeout: Duration, last: u32) -> UsbTdc<T> {
        let device = transport.describe();
        UsbTdc {
            transport,
            device,
            timeout,
            config: None,
            sequence: last,
            rx: Vec::new(),
            chunk: vec![0; 1 << 16],
        }
    }

    /// Opens the device for this connection: a random starting sequence number, then
    /// `ABORT` (the device drops the acquisition in progress) and a drain of the
    /// bulk-in endpoint, so a frame an earlier connection (a crashed daemon, a failed
    /// open) left behind can never be taken for a fresh one.
    pub fn open(transport: T, timeout: Duration) -> Result<UsbTdc<T>, TdcError> {
        let mut tdc = UsbTdc::new(transport, timeout);
        tdc.clear_device()?;
        Ok(tdc)
    }

    /// `ABORT`, then reads and drops whatever the bulk-in endpoint still holds, until
    /// it stays empty for a short wait (at most [`DRAIN_LIMIT`] in all).
    fn clear_device(&mut self) -> Result<(), TdcError> {
        self.abort_acquisition()?;
        let t = Instant::now();
        let mut dropped = 0usize;
        while t.elapsed() < DRAIN_LIMIT {
            match self
                .transport
                .bulk_in(protocol::BULK_IN_ENDPOINT, &mut self.chunk, DRAIN_WAIT)
            {
                Ok(0) | Err(TransportError::Timeout) => break,
                Ok(n) => dropped += n.min(self.chunk.len()),
                Err(e) => return Err(self.transport_err("draining", e)),
            }
        }
        if dropped > 0 {
            debug!(device = %self.device, bytes = dropped, "dropped data an earlier connection left on the device");
        }
        self.rx.clear();
        Ok(())
    }

    /// The transport (for tests and the simulator's fault injection).
    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    fn err(&self, kind: ErrorKind, message: impl Into<String>) -> TdcError {
        TdcError::new(&self.device, kind, message)
    }

    fn transport_err(&self, what: &str, e: TransportError) -> TdcError {
        match e {
            TransportError::Timeout => self.err(
                ErrorKind::Timeout,
                format!("{what} timed out: check the USB cable and that the device is powered"),
            ),
            TransportError::Disconnected(why) => self.err(
                ErrorKind::Disconnected,
                format!("{what}: the device is gone ({why}); plug it in, check `periscope devices` and the `usb` selector in the instrument config"),
            ),
            TransportError::Stall => self.err(ErrorKind::Busy, format!("{what}: the device stalled the request")),
            TransportError::Other(why) => self.err(ErrorKind::Device, format!("{what}: {why}")),
        }
    }

    /// Runs `f`; on a disconnect, reopens the device, restores the settings and runs
    /// it once more. Also retries once on the kinds listed in `retry_on`.
    fn with_recovery<R>(
        &mut self,
        retry_on: &[ErrorKind],
        mut f: impl FnMut(&mut Self) -> Result<R, TdcError>,
    ) -> Result<R, TdcError> {
        match f(self) {
            Ok(r) => Ok(r),
            Err(e) if e.kind() == ErrorKind::Disconnected => {
                warn!(device = %self.device, error = %e, "reconnecting to the histogrammer");
                self.transport
                    .reopen()
                    .map_err(|e| self.transport_err("reconnecting", e))?;
                // A new connection: new sequence numbers, and nothing from before.
                self.sequence = random_sequence();
                self.clear_device()?;
                if let Some(config) = self.config {
                    self.send_config(&config)?;
                }
                f(self)
            }
            Err(e) if retry_on.contains(&e.kind()) => {
                warn!(device = %self.device, error = %e, "repeating the request once");
                f(self)
            }
            Err(e) => Err(e),
        }
    }

    fn control_in(&mut self, req: ControlRequest, len: usize) -> Result<Vec<u8>, TdcError> {
        let mut buf = vec![0u8; len];
        let n = self
            .transport
            .control_in(req as u8, 0, 0, &mut buf, self.timeout)
            .map_err(|e| self.transport_err(&format!("{req:?}"), e))?;
        if n < len {
            return Err(self.err(
                ErrorKind::Protocol,
                format!(
                    "{req:?} returned {n} of {len} bytes: the firmware does not speak this protocol version"
                ),
            ));
        }
        Ok(buf)
    }

    fn send_config(&mut self, config: &TdcConfig) -> Result<(), TdcError> {
        let wire = WireConfig::from_config(config).ok_or_else(|| {
            self.err(
                ErrorKind::OutOfRange,
                format!("settings {config:?} cannot be expressed in whole picoseconds and microseconds (1 µs to 71 min)"),
            )
        })?;
        self.transport
            .control_out(ControlRequest::SetConfig as u8, 0, 0, &wire.encode(), self.timeout)
            .map_err(|e| match e {
                TransportError::Stall => self.err(
                    ErrorKind::OutOfRange,
                    format!("the device refused the settings {wire:?} (bins, bin width or acquisition time outside its range)"),
                ),
                e => self.transport_err("SetConfig", e),
            })?;
        let back = self.control_in(ControlRequest::GetConfig, WireConfig::LEN)?;
        if WireConfig::decode(&back) != Some(wire) {
            return Err(self.err(
                ErrorKind::Protocol,
                format!(
                    "the device reports settings {:?} after being sent {wire:?}",
                    WireConfig::decode(&back)
                ),
            ));
        }
        Ok(())
    }

    /// One attempt at an acquisition: start, then read until our frame arrives, asking
    /// `stop` every [`POLL`]; when it says stop, the acquisition is aborted on the
    /// device and the error's kind is `Interrupted`.
    #[instrument(level = "trace", skip(self, stop))]
    fn acquire_once(&mut self, config: TdcConfig, stop: &dyn Fn() -> bool) -> Result<Histogram, TdcError> {
        if stop() {
            // A repeat after a failed attempt (`with_recovery`) that a stop overtook:
            // nothing is started.
            return Err(self.err(
                ErrorKind::Interrupted,
                "the acquisition was stopped before it started",
            ));
        }
        self.sequence = self.sequence.wrapping_add(1);
        let seq = self.sequence;
        self.rx.clear();
        self.transport
            .control_out(
                ControlRequest::Start as u8,
                seq as u16,
                (seq >> 16) as u16,
                &[],
                self.timeout,
            )
            .map_err(|e| self.transport_err("Start", e))?;
        let deadline = Instant::now() + config.acquisition + self.timeout;
        let expected = WireConfig::from_config(&config).expect("validated when configured");
        loop {
            if stop() {
                // Stopped either way: an abort the device does not take is reported,
                // not turned into an error `with_recovery` would answer with a fresh
                // acquisition (the dwell ends by itself, and the next `Start` or
                // `open` clears what it leaves).
                if let Err(e) = self.abort_acquisition() {
                    warn!(device = %self.device, error = %e, "the stopped acquisition could not be aborted on the device");
                }
                return Err(self.err(
                    ErrorKind::Interrupted,
                    format!("acquisition {seq} was stopped and aborted on the device"),
                ));
            }
            // Parse what we have.
            loop {
                match protocol::decode_frame(&self.rx) {
                    Ok((header, counts, len)) => {
                        self.rx.drain(..len);
                        if header.sequence != seq {
                            debug!(got = header.sequence, want = seq, "dropping a stale frame");
                            continue;
                        }
                        let got = WireConfig {
                            sync_divider: expected.sync_divider,
                            ..header.config
                        };
                        if got != expected {
                            return Err(self.err(
                                ErrorKind::Protocol,
                                format!("frame {seq} was acquired with {got:?}, not the settings in force {expected:?}"),
                            ));
                        }
                        return Ok(Histogram {
                            sequence: seq,
                            counts,
                            flags: header.histogram_flags(),
                            config,
                        });
                    }
                    Err(FrameError::Incomplete { .. }) => break,
                    Err(FrameError::BadHeader) => {
                        // Re-synchronise: skip to the next possible frame start.
                        let skip = self.rx[1..]
                            .windows(4)
                            .position(|w| w == protocol::MAGIC)
                            .map_or(self.rx.len(), |p| p + 1);
                        self.rx.drain(..skip);
                    }
                    Err(FrameError::BadCrc) => {
                        return Err(self.err(
                            ErrorKind::Protocol,
                            format!(
                                "frame {seq} failed its CRC: check the USB cable; the histogram was discarded"
                            ),
                        ));
                    }
                }
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(if self.rx.is_empty() {
                    self.err(
                        ErrorKind::Timeout,
                        format!(
                            "no histogram frame {} ms after the acquisition should have ended",
                            self.timeout.as_millis()
                        ),
                    )
                } else {
                    self.err(
                        ErrorKind::Protocol,
                        format!(
                            "frame {seq} arrived incomplete ({} bytes); the histogram was discarded",
                            self.rx.len()
                        ),
                    )
                });
            }
            match self.transport.bulk_in(
                protocol::BULK_IN_ENDPOINT,
                &mut self.chunk,
                (deadline - now).min(POLL),
            ) {
                Ok(n) => {
                    let (rx, chunk) = (&mut self.rx, &self.chunk);
                    rx.extend_from_slice(&chunk[..n]);
                }
                Err(TransportError::Timeout) => {}
                Err(e) => return Err(self.transport_err("reading a histogram frame", e)),
            }
        }
    }
}

impl<T: UsbTransport> Histogrammer for UsbTdc<T> {
    fn identify(&mut self) -> Result<DeviceInfo, TdcError> {
        self.with_recovery(&[ErrorKind::Timeout], |d| {
            let b = d.control_in(ControlRequest::GetInfo, WireInfo::LEN)?;
            let info = WireInfo::decode(&b).expect("length checked");
            if info.protocol != protocol::PROTOCOL_VERSION {
                return Err(d.err(
                    ErrorKind::Protocol,
                    format!(
                        "device speaks protocol {}, this driver {}: update the firmware or Periscope",
                        info.protocol,
                        protocol::PROTOCOL_VERSION
                    ),
                ));
            }
            Ok(DeviceInfo {
                model: info.model,
                firmware: format!("{}.{}", info.firmware.0, info.firmware.1),
                serial: info.serial,
                protocol: u32::from(info.protocol),
            })
        })
    }

    fn configure(&mut self, config: &TdcConfig) -> Result<(), TdcError> {
        let c = *config;
        self.with_recovery(&[ErrorKind::Timeout, ErrorKind::Protocol], |d| d.send_config(&c))?;
        self.config = Some(c);
        Ok(())
    }

    fn config(&self) -> Option<TdcConfig> {
        self.config
    }

    fn acquire(&mut self) -> Result<Histogram, TdcError> {
        self.acquire_until(&|| false)
    }

    fn acquire_until(&mut self, stop: &dyn Fn() -> bool) -> Result<Histogram, TdcError> {
        let config = self.config.ok_or_else(|| {
            self.err(
                ErrorKind::Device,
                "acquire called before configure: the driver has no settings to acquire with",
            )
        })?;
        self.with_recovery(&[ErrorKind::Timeout, ErrorKind::Protocol], |d| {
            d.acquire_once(config, stop)
        })
    }

    fn abort(&mut self) -> Result<(), TdcError> {
        self.abort_acquisition()
    }

    fn status(&mut self) -> Result<TdcStatus, TdcError> {
        self.with_recovery(&[ErrorKind::Timeout], |d| {
            let b = d.control_in(ControlRequest::GetStatus, WireStatus::LEN)?;
            let s = WireStatus::decode(&b).expect("length checked");
            let state = match s.state {
                protocol::state::IDLE => TdcState::Idle,
                protocol::state::ACQUIRING => TdcState::Acquiring,
                _ => TdcState::Error,
            };
            Ok(TdcStatus {
                state,
                rates: CountRates {
                    sync: f64::from(s.sync_rate_hz),
                    detector: f64::from(s.input_rate_hz),
                },
                acquisitions: s.frames,
            })
        })
    }

    /// The protocol's rate meter counts the sync over gates of
    /// [`protocol::RATE_GATE`]: a change shows in full once a whole gate has passed
    /// after it, so within two.
    fn rate_latency(&self) -> Duration {
        2 * protocol::RATE_GATE
    }
}

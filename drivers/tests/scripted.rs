//! Byte-exact exchanges for every galvo command and every histogrammer request,
//! against scripted fakes (PyMeasure's `expected_protocol`, probe-rs's `FakeProbe`):
//! the driver must send exactly these bytes and read exactly these replies. The lines
//! are the examples of `docs/protocols/galvo-serial.md`, CRCs computed independently.
use std::collections::VecDeque;
use std::io;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use periscope_drivers::galvo::protocol::MotionState;
use periscope_drivers::galvo::{Connector, Link, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::protocol::{self, FrameHeader, WireConfig, WireInfo, WireStatus};
use periscope_drivers::tdc::{TransportError, UsbTdc, UsbTransport};
use periscope_drivers::{
    AngleLimits, Error, ErrorKind, GalvoPair, Histogrammer, Laser, OpticalAngles, TdcConfig,
};

type Script = Arc<Mutex<VecDeque<(&'static str, &'static str)>>>;

/// A link that expects exactly the scripted requests and answers each with its reply.
struct ScriptedLink {
    script: Script,
    rx: VecDeque<u8>,
}

impl Link for ScriptedLink {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        let (want, reply) = self
            .script
            .lock()
            .unwrap()
            .pop_front()
            .expect("an unexpected request was sent");
        assert_eq!(String::from_utf8_lossy(bytes), want, "request bytes");
        self.rx.extend(reply.as_bytes());
        Ok(())
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if self.rx.is_empty() {
            std::thread::sleep(timeout.min(Duration::from_millis(1)));
            return Ok(0);
        }
        let n = buf.len().min(self.rx.len());
        for (dst, src) in buf.iter_mut().zip(self.rx.drain(..n)) {
            *dst = src;
        }
        Ok(n)
    }

    fn discard_input(&mut self) -> io::Result<()> {
        self.rx.clear();
        Ok(())
    }
}

struct ScriptedConnector(Script);

impl Connector for ScriptedConnector {
    fn connect(&mut self) -> io::Result<Box<dyn Link>> {
        Ok(Box::new(ScriptedLink {
            script: self.0.clone(),
            rx: VecDeque::new(),
        }))
    }

    fn describe(&self) -> String {
        "scripted".into()
    }
}

fn galvo_with(limit: f64, script: &[(&'static str, &'static str)]) -> (SerialGalvo, Script) {
    galvo_settings(limit, None, script)
}

fn galvo_watchdog(watchdog: Duration, script: &[(&'static str, &'static str)]) -> (SerialGalvo, Script) {
    galvo_settings(0.3, Some(watchdog), script)
}

fn galvo_settings(
    limit: f64,
    watchdog: Option<Duration>,
    script: &[(&'static str, &'static str)],
) -> (SerialGalvo, Script) {
    let script: Script = Arc::new(Mutex::new(script.iter().copied().collect()));
    let settings = SerialGalvoSettings {
        name: "laser".into(),
        limits: AngleLimits {
            x: [-limit, limit],
            y: [-limit, limit],
        },
        timeout: Duration::from_millis(20),
        settle: Duration::from_micros(100),
        watchdog,
    };
    (
        SerialGalvo::new(settings, Box::new(ScriptedConnector(script.clone()))),
        script,
    )
}

fn galvo(script: &[(&'static str, &'static str)]) -> (SerialGalvo, Script) {
    galvo_with(0.3, script)
}

fn done(script: &Script) {
    let left = script.lock().unwrap();
    assert!(left.is_empty(), "scripted requests never sent: {left:?}");
}

#[test]
fn identify() {
    let (mut g, s) = galvo(&[("01 IDN*01\n", "01 OK PGC-2 1.0.0 2 SN123 LASER*20\n")]);
    let info = g.identify().unwrap();
    assert_eq!(
        (info.model.as_str(), info.firmware.as_str(), info.serial.as_str()),
        ("PGC-2", "1.0.0", "SN123")
    );
    done(&s);
}

#[test]
fn identify_refuses_another_protocol_version() {
    let (mut g, s) = galvo(&[("01 IDN*01\n", "01 OK PGC-2 1.0.0 3 SN123 LASER*B4\n")]);
    let err = g.identify().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Protocol);
    assert!(err.to_string().contains("protocol 3"), "{err}");
    done(&s);
}

#[test]
fn move_then_settle() {
    // The controller answers a move once the pair has settled.
    let (mut g, s) = galvo(&[(
        "01 MOVE 0.1000000 -0.0500000*15\n",
        "01 OK SETTLED 0.1000000 -0.0500000*06\n",
    )]);
    let pos = g
        .move_settled(OpticalAngles { x: 0.1, y: -0.05 }, Duration::from_secs(1))
        .unwrap();
    assert_eq!(pos, OpticalAngles { x: 0.1, y: -0.05 });
    done(&s);
}

#[test]
fn a_command_after_an_unawaited_move_collects_its_reply_first() {
    let (mut g, s) = galvo(&[
        (
            "01 MOVE 0.1000000 -0.0500000*15\n",
            "01 OK SETTLED 0.1000000 -0.0500000*06\n",
        ),
        ("02 STAT*4D\n", "02 OK SETTLED 0.1000000 -0.0500000*22\n"),
    ]);
    g.move_to(OpticalAngles { x: 0.1, y: -0.05 }).unwrap();
    assert_eq!(g.status().unwrap().state, MotionState::Settled);
    done(&s);
}

#[test]
fn settling_after_a_park_polls_while_moving() {
    let (mut g, s) = galvo(&[
        ("01 PARK*5B\n", "01 OK*C4\n"),
        ("02 STAT*4D\n", "02 OK MOVING 0.0000000 0.0000000*A3\n"),
        ("03 STAT*64\n", "03 OK PARKED 0.0000000 0.0000000*8F\n"),
    ]);
    g.park().unwrap();
    g.wait_settled(Duration::from_secs(1)).unwrap();
    done(&s);
}

#[test]
fn a_settled_position_off_target_is_refused() {
    let (mut g, s) = galvo(&[(
        "01 MOVE 0.1000000 -0.0500000*15\n",
        "01 OK SETTLED 0.1000000 -0.0400000*2F\n",
    )]);
    let err = g
        .move_settled(OpticalAngles { x: 0.1, y: -0.05 }, Duration::from_secs(1))
        .unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Device);
    assert!(err.to_string().contains("instead of the target"), "{err}");
    done(&s);
}

#[test]
fn position_status_park_limits() {
    let (mut g, s) = galvo(&[
        ("01 POS*5D\n", "01 OK 0.0100000 0.0200000*25\n"),
        ("02 STAT*4D\n", "02 OK SETTLED 0.1000000 -0.0500000*22\n"),
    ]);
    assert_eq!(g.position().unwrap(), OpticalAngles { x: 0.01, y: 0.02 });
    assert_eq!(g.status().unwrap().state, MotionState::Settled);
    done(&s);
    let (mut g, s) = galvo(&[
        ("01 PARK*5B\n", "01 OK*C4\n"),
        ("02 IDN*A7\n", "02 OK PGC-2 1.0.0 2 SN123 LASER*70\n"),
    ]);
    g.park().unwrap();
    g.identify().unwrap();
    done(&s);
    let (mut g, s) = galvo(&[(
        "01 LIM*21\n",
        "01 OK -0.3490659 0.3490659 -0.2617994 0.2617994*C1\n",
    )]);
    let l = g.hard_limits().unwrap();
    assert_eq!((l.x, l.y), ([-0.3490659, 0.3490659], [-0.2617994, 0.2617994]));
    done(&s);
}

#[test]
fn laser_commands() {
    let (mut g, s) = galvo(&[("01 LASER ON*08\n", "01 ERR 6 interlock open*87\n")]);
    let err = g.set_emission(true).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Interlock);
    assert!(err.to_string().contains("interlock is open"), "{err}");
    done(&s);
    let (mut g, s) = galvo(&[
        ("01 LSTAT*3D\n", "01 OK ON CLOSED OUT*40\n"),
        ("02 IDN*A7\n", "02 OK PGC-2 1.0.0 2 SN123 LASER*70\n"),
    ]);
    let st = g.laser_state().unwrap();
    assert!(st.emission && st.interlock_closed && !st.diffuser_in);
    g.identify().unwrap();
    done(&s);
    let (mut g, s) = galvo(&[("01 ILK*B2\n", "01 OK CLOSED*59\n")]);
    assert!(g.interlock_closed().unwrap());
    done(&s);
    let (mut g, s) = galvo(&[("01 DIFF IN*2A\n", "01 OK*C4\n")]);
    g.set_diffuser(true).unwrap();
    done(&s);
    let (mut g, s) = galvo(&[("01 LASER OFF*45\n", "01 OK*C4\n")]);
    g.set_emission(false).unwrap();
    done(&s);
}

/// Switching the laser off while a move waits for its reply neither waits for that
/// reply nor fails with it (a servo fault here): the confirmed `LASER OFF` goes at
/// once, and settling then polls the status against the move's own target (until
/// 2026-12-06 the move was finished first, and a fault returned before the laser
/// went off; and a poll was checked against the last park's target, or nothing).
#[test]
fn switching_off_does_not_wait_on_an_outstanding_move() {
    let target = OpticalAngles { x: 0.1, y: -0.05 };
    let (mut g, s) = galvo(&[
        (
            "01 MOVE 0.1000000 -0.0500000*15\n",
            "01 OK FAULT 0.0900000 -0.0500000*31\n",
        ),
        ("02 LASER OFF*64\n", "02 OK*FE\n"),
        ("03 STAT*64\n", "03 OK SETTLED 0.1000000 -0.0500000*3E\n"),
    ]);
    g.move_to(target).unwrap();
    g.set_emission(false).unwrap();
    assert_eq!(g.wait_settled(Duration::from_secs(1)).unwrap(), target);
    done(&s);
    // Settled somewhere else: refused, against the move's target.
    let (mut g, s) = galvo(&[
        (
            "01 MOVE 0.1000000 -0.0500000*15\n",
            "01 OK SETTLED 0.1000000 -0.0500000*06\n",
        ),
        ("02 LASER OFF*64\n", "02 OK*FE\n"),
        ("03 STAT*64\n", "03 OK SETTLED 0.0900000 -0.0500000*6A\n"),
    ]);
    g.move_to(target).unwrap();
    g.set_emission(false).unwrap();
    let err = g.wait_settled(Duration::from_secs(1)).unwrap_err();
    assert!(err.to_string().contains("instead of the target"), "{err}");
    done(&s);
}

/// Parking while a move waits for its reply does the same: the `PARK` goes at once,
/// neither held up by the move's reply nor kept from the wire by its failure (a servo
/// fault here), and the stale reply is dropped when it comes. Until 2026-12-07 `park`
/// finished the move first, and a failed move (or its repeat) returned before `PARK`
/// was sent, leaving the arm at the move's target as the instrument was made safe.
#[test]
fn parking_does_not_wait_on_an_outstanding_move() {
    let (mut g, s) = galvo(&[
        (
            "01 MOVE 0.1000000 -0.0500000*15\n",
            "01 OK FAULT 0.0900000 -0.0500000*31\n",
        ),
        ("02 PARK*20\n", "02 OK*FE\n"),
        ("03 STAT*64\n", "03 OK PARKED 0.0000000 0.0000000*8F\n"),
    ]);
    g.move_to(OpticalAngles { x: 0.1, y: -0.05 }).unwrap();
    g.park().unwrap();
    g.wait_settled(Duration::from_secs(1)).unwrap();
    done(&s);
}

#[test]
fn switching_on_sets_the_watchdog_first() {
    // With a watchdog configured, `LASER ON` follows a `WDOG` that the controller
    // must confirm with the same timeout (and its trip count).
    let (mut g, s) = galvo_watchdog(
        Duration::from_millis(250),
        &[
            ("01 WDOG 250*BE\n", "01 OK 250 0*AF\n"),
            ("02 LASER ON*B0\n", "02 OK*FE\n"),
            // Dropped with the laser on: LASER OFF out of band, answered before closing.
            ("00 LASER OFF*5A\n", "00 OK*D2\n"),
        ],
    );
    g.set_emission(true).unwrap();
    drop(g);
    done(&s);
    // A controller that keeps another timeout is refused, and the laser stays off.
    let (mut g, s) = galvo_watchdog(
        Duration::from_millis(250),
        &[("01 WDOG 250*BE\n", "01 OK 500 0*C8\n")],
    );
    let err = g.set_emission(true).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Device);
    assert!(err.to_string().contains("not switched on"), "{err}");
    done(&s);
    // Reading it back: timeout and trips since power-up.
    let (mut g, s) = galvo(&[("01 WDOG*63\n", "01 OK 500 1*CF\n")]);
    assert_eq!(g.watchdog().unwrap(), (Duration::from_millis(500), 1));
    done(&s);
}

#[test]
fn a_stale_reply_is_skipped_for_the_right_one() {
    // The reply to an earlier request (tag 01) arrives first and must be dropped.
    let (mut g, s) = galvo(&[(
        "01 IDN*01\n",
        "02 OK PGC-2 1.0.0 2 SN123 LASER*70\n01 OK PGC-2 1.0.0 2 SN123 LASER*20\n",
    )]);
    g.identify().unwrap();
    done(&s);
}

#[test]
fn the_controllers_out_of_range_reply_maps_to_its_kind() {
    // Inside the driver's limits (1 rad), outside the controller's.
    let (mut g, s) = galvo_with(
        1.0,
        &[("01 MOVE 0.5000000 0.0000000*0C\n", "01 ERR 4 out of range*B8\n")],
    );
    g.move_to(OpticalAngles { x: 0.5, y: 0.0 }).unwrap();
    let err = g.wait_settled(Duration::from_millis(10)).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange);
    done(&s);
}

// ---- USB ------------------------------------------------------------------------

#[derive(Debug, PartialEq)]
enum Xfer {
    In(u8, u16, u16),
    Out(u8, u16, u16, Vec<u8>),
    Bulk(u8),
}

struct ScriptedUsb {
    script: VecDeque<(Xfer, Vec<u8>)>,
}

impl ScriptedUsb {
    fn next(&mut self, got: Xfer) -> Vec<u8> {
        let (want, reply) = self
            .script
            .pop_front()
            .unwrap_or_else(|| panic!("unexpected transfer {got:?}"));
        assert_eq!(got, want, "transfer");
        reply
    }
}

impl UsbTransport for ScriptedUsb {
    fn control_in(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        buf: &mut [u8],
        _t: Duration,
    ) -> Result<usize, TransportError> {
        let reply = self.next(Xfer::In(r, v, i));
        buf[..reply.len()].copy_from_slice(&reply);
        Ok(reply.len())
    }
    fn control_out(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        data: &[u8],
        _t: Duration,
    ) -> Result<(), TransportError> {
        self.next(Xfer::Out(r, v, i, data.to_vec()));
        Ok(())
    }
    fn bulk_in(&mut self, ep: u8, buf: &mut [u8], _t: Duration) -> Result<usize, TransportError> {
        let reply = self.next(Xfer::Bulk(ep));
        buf[..reply.len()].copy_from_slice(&reply);
        Ok(reply.len())
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        Ok(())
    }
    fn describe(&self) -> String {
        "scripted USB".into()
    }
}

/// The documented SET_CONFIG payload for 16 ps × 4 bins, offset 12 ns, divider 1,
/// 1 ms: five little-endian u32.
const CONFIG_BYTES: [u8; 20] = [
    16, 0, 0, 0, 4, 0, 0, 0, 0xE0, 0x2E, 0, 0, 1, 0, 0, 0, 0xE8, 0x03, 0, 0,
];

fn config() -> TdcConfig {
    TdcConfig {
        bin_width: 16e-12,
        bins: 4,
        offset: 12e-9,
        sync_divider: 1,
        acquisition: Duration::from_millis(1),
    }
}

fn frame(bin_width_ps: u32) -> Vec<u8> {
    let wire = WireConfig::decode(&CONFIG_BYTES).unwrap();
    protocol::encode_frame(
        &FrameHeader {
            sequence: 1,
            flags: 0,
            config: WireConfig {
                sync_divider: 0,
                bin_width_ps,
                ..wire
            },
        },
        &[5, 6, 7, 8],
    )
}

/// The documented frame (`docs/protocols/tdc-usb.md`, Examples): sequence 1 under
/// [`CONFIG_BYTES`], counts 5, 6, 7, 8, CRC from zlib's `crc32`. Written by hand.
#[rustfmt::skip]
const DOC_FRAME: [u8; 52] = [
    0x50, 0x54, 0x44, 0x43, 0x01, 0x00, 0x20, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x04, 0x00, 0x00, 0x00, 0x10, 0x00, 0x00, 0x00, 0xe0, 0x2e, 0x00, 0x00, 0xe8, 0x03, 0x00, 0x00,
    0x05, 0x00, 0x00, 0x00, 0x06, 0x00, 0x00, 0x00, 0x07, 0x00, 0x00, 0x00, 0x08, 0x00, 0x00, 0x00,
    0xf1, 0x80, 0x06, 0x6f,
];

/// The documented info block: `PTDC-1`, firmware 2.1, serial `A1`.
#[rustfmt::skip]
const DOC_INFO: [u8; 64] = [
    0x01, 0x00, 0x02, 0x00, 0x01, 0x00, 0x00, 0x00, 0x00, 0x00, 0x01, 0x00, 0x01, 0x00, 0x00, 0x00,
    0x50, 0x54, 0x44, 0x43, 0x2d, 0x31, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x41, 0x31, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
    0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00,
];

/// The documented status block: idle, 10 MHz sync, 2,500 counts/s, one frame.
const DOC_STATUS: [u8; 16] = [0, 0, 0, 0, 0x80, 0x96, 0x98, 0, 0xc4, 0x09, 0, 0, 1, 0, 0, 0];

#[test]
fn the_documented_usb_bytes_are_what_our_encoder_writes() {
    let wire = WireConfig {
        bin_width_ps: 16,
        bins: 4,
        offset_ps: 12_000,
        sync_divider: 1,
        acquisition_us: 1000,
    };
    assert_eq!(WireConfig::decode(&CONFIG_BYTES), Some(wire));
    assert_eq!(wire.encode(), CONFIG_BYTES);
    assert_eq!(frame(16), DOC_FRAME);
    let (header, counts, used) = protocol::decode_frame(&DOC_FRAME).unwrap();
    assert_eq!((header.sequence, header.flags, used), (1, 0, 52));
    assert_eq!(counts, [5, 6, 7, 8]);
    let info = WireInfo {
        protocol: 1,
        firmware: (2, 1),
        max_bins: 65536,
        min_bin_width_ps: 1,
        model: "PTDC-1".into(),
        serial: "A1".into(),
    };
    assert_eq!(WireInfo::decode(&DOC_INFO), Some(info.clone()));
    assert_eq!(info.encode(), DOC_INFO);
    let status = WireStatus {
        state: 0,
        error: 0,
        sync_rate_hz: 10_000_000,
        input_rate_hz: 2500,
        frames: 1,
    };
    assert_eq!(WireStatus::decode(&DOC_STATUS), Some(status));
    assert_eq!(status.encode(), DOC_STATUS);
    // One flipped bit anywhere fails the CRC.
    for i in 0..DOC_FRAME.len() {
        let mut bad = DOC_FRAME;
        bad[i] ^= 0x40;
        assert!(
            protocol::decode_frame(&bad).is_err(),
            "byte {i} flipped was accepted"
        );
    }
}

#[test]
fn usb_configure_acquire_status_identify() {
    let frame = DOC_FRAME.to_vec();
    let mut tdc = UsbTdc::with_sequence(
        ScriptedUsb {
            script: [
                (Xfer::Out(0x02, 0, 0, CONFIG_BYTES.to_vec()), vec![]),
                (Xfer::In(0x03, 0, 0), CONFIG_BYTES.to_vec()),
                (Xfer::Out(0x04, 1, 0, vec![]), vec![]),
                (Xfer::Bulk(0x81), frame[..10].to_vec()),
                (Xfer::Bulk(0x81), frame[10..].to_vec()),
                (Xfer::In(0x05, 0, 0), DOC_STATUS.to_vec()),
                (Xfer::In(0x01, 0, 0), DOC_INFO.to_vec()),
            ]
            .into_iter()
            .collect(),
        },
        Duration::from_millis(20),
        0,
    );
    tdc.configure(&config()).unwrap();
    let h = tdc.acquire().unwrap();
    assert_eq!((h.sequence, h.counts.as_slice()), (1, &[5, 6, 7, 8][..]));
    let st = tdc.status().unwrap();
    assert_eq!((st.rates.sync, st.rates.detector), (10e6, 2500.0));
    let id = tdc.identify().unwrap();
    assert_eq!(
        (id.model.as_str(), id.firmware.as_str(), id.serial.as_str()),
        ("PTDC-1", "2.1", "A1")
    );
    assert!(tdc.transport_mut().script.is_empty());
}

#[test]
fn usb_frame_with_other_settings_is_refused() {
    let wrong = frame(32);
    let mut second = wrong.clone();
    second[8] = 2; // sequence 2 for the retry (the CRC no longer holds: refused too)
    let mut tdc = UsbTdc::with_sequence(
        ScriptedUsb {
            script: [
                (Xfer::Out(0x02, 0, 0, CONFIG_BYTES.to_vec()), vec![]),
                (Xfer::In(0x03, 0, 0), CONFIG_BYTES.to_vec()),
                (Xfer::Out(0x04, 1, 0, vec![]), vec![]),
                (Xfer::Bulk(0x81), wrong),
                (Xfer::Out(0x04, 2, 0, vec![]), vec![]),
                (Xfer::Bulk(0x81), second),
            ]
            .into_iter()
            .collect(),
        },
        Duration::from_millis(20),
        0,
    );
    tdc.configure(&config()).unwrap();
    let err = tdc.acquire().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Protocol);
    assert!(tdc.transport_mut().script.is_empty());
}

/// A histogrammer that keeps what it has not delivered on its bulk-in endpoint across
/// connections (as a real device's FIFO does when the host goes away mid-read): it
/// echoes its config, answers `START(seq)` with a frame of that sequence number and
/// counts [1, 2, 3, 4], and `ABORT` stops acquiring but does not empty the FIFO.
struct FifoDevice {
    fifo: Arc<Mutex<VecDeque<Vec<u8>>>>,
    config: Vec<u8>,
}

impl UsbTransport for FifoDevice {
    fn control_in(
        &mut self,
        r: u8,
        _v: u16,
        _i: u16,
        buf: &mut [u8],
        _t: Duration,
    ) -> Result<usize, TransportError> {
        match r {
            0x03 => {
                buf[..self.config.len()].copy_from_slice(&self.config);
                Ok(self.config.len())
            }
            _ => Err(TransportError::Stall),
        }
    }
    fn control_out(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        data: &[u8],
        _t: Duration,
    ) -> Result<(), TransportError> {
        match r {
            0x02 => self.config = data.to_vec(),
            0x04 => {
                let seq = u32::from(v) | (u32::from(i) << 16);
                let wire = WireConfig::decode(&self.config).unwrap();
                let f = protocol::encode_frame(
                    &FrameHeader {
                        sequence: seq,
                        flags: 0,
                        config: WireConfig {
                            sync_divider: 0,
                            ..wire
                        },
                    },
                    &[1, 2, 3, 4],
                );
                self.fifo.lock().unwrap().push_back(f);
            }
            _ => {}
        }
        Ok(())
    }
    fn bulk_in(&mut self, _ep: u8, buf: &mut [u8], _t: Duration) -> Result<usize, TransportError> {
        match self.fifo.lock().unwrap().pop_front() {
            Some(f) => {
                buf[..f.len()].copy_from_slice(&f);
                Ok(f.len())
            }
            None => Err(TransportError::Timeout),
        }
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        Ok(())
    }
    fn describe(&self) -> String {
        "FIFO device".into()
    }
}

#[test]
fn a_frame_left_by_an_earlier_connection_is_never_taken_for_a_fresh_one() {
    // An earlier daemon started acquisition 1 and died before reading its frame, whose
    // counts are [9, 9, 9, 9]: it still sits in the device's FIFO.
    let stale = {
        let wire = WireConfig::decode(&CONFIG_BYTES).unwrap();
        protocol::encode_frame(
            &FrameHeader {
                sequence: 1,
                flags: 0,
                config: WireConfig {
                    sync_divider: 0,
                    ..wire
                },
            },
            &[9, 9, 9, 9],
        )
    };
    let fifo = Arc::new(Mutex::new(VecDeque::from([stale.clone()])));
    let device = || FifoDevice {
        fifo: Arc::clone(&fifo),
        config: Vec::new(),
    };
    // What the driver did before: sequence numbers from 1 and no drain on open. The
    // stale frame matches sequence 1 and is returned as this acquisition's histogram.
    let mut naive = UsbTdc::with_sequence(device(), Duration::from_millis(20), 0);
    naive.configure(&config()).unwrap();
    assert_eq!(naive.acquire().unwrap().counts, vec![9, 9, 9, 9]);

    // Opened properly, with the same stale frame waiting: it is drained, and the
    // histogram is the one this connection asked for.
    fifo.lock().unwrap().clear();
    fifo.lock().unwrap().push_back(stale);
    let mut tdc = UsbTdc::open(device(), Duration::from_millis(20)).unwrap();
    tdc.configure(&config()).unwrap();
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts, vec![1, 2, 3, 4]);
    assert!(fifo.lock().unwrap().is_empty());
    // Each connection starts at its own random sequence number.
    let firsts: std::collections::HashSet<u32> = (0..8)
        .map(|_| {
            let mut t = UsbTdc::open(device(), Duration::from_millis(20)).unwrap();
            t.configure(&config()).unwrap();
            t.acquire().unwrap().sequence
        })
        .collect();
    assert!(firsts.len() >= 7, "{firsts:?}");
}

/// A transport for the stop path: `START` is taken, `ABORT` times out, and a dwell's
/// bulk reads find nothing; every control transfer is recorded.
struct AbortTimesOut {
    sent: Vec<u8>,
}

impl UsbTransport for AbortTimesOut {
    fn control_in(
        &mut self,
        _r: u8,
        _v: u16,
        _i: u16,
        buf: &mut [u8],
        _t: Duration,
    ) -> Result<usize, TransportError> {
        buf[..CONFIG_BYTES.len()].copy_from_slice(&CONFIG_BYTES);
        Ok(CONFIG_BYTES.len())
    }
    fn control_out(
        &mut self,
        r: u8,
        _v: u16,
        _i: u16,
        _data: &[u8],
        _t: Duration,
    ) -> Result<(), TransportError> {
        self.sent.push(r);
        if r == protocol::ControlRequest::Abort as u8 {
            return Err(TransportError::Timeout);
        }
        Ok(())
    }
    fn bulk_in(&mut self, _ep: u8, _buf: &mut [u8], _t: Duration) -> Result<usize, TransportError> {
        Err(TransportError::Timeout)
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        Ok(())
    }
    fn describe(&self) -> String {
        "USB whose ABORT times out".into()
    }
}

/// A stop whose `ABORT` the device does not take is still a stop: kind `interrupted`
/// (which the pipeline answers with the pause or abort asked for), not a timeout that
/// the driver's retry answered with a second `START` while the laser stayed on.
#[test]
fn a_stop_whose_abort_times_out_is_interrupted_and_starts_nothing_more() {
    let mut tdc = UsbTdc::with_sequence(AbortTimesOut { sent: vec![] }, Duration::from_millis(20), 0);
    tdc.configure(&config()).unwrap();
    let polls = std::cell::Cell::new(0);
    // Stop at the first poll after `START`.
    let err = tdc
        .acquire_until(&|| {
            polls.set(polls.get() + 1);
            polls.get() > 1
        })
        .unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Interrupted, "{err}");
    let start = protocol::ControlRequest::Start as u8;
    let abort = protocol::ControlRequest::Abort as u8;
    let sent = &tdc.transport_mut().sent;
    assert_eq!(sent.iter().filter(|&&r| r == start).count(), 1, "{sent:?}");
    assert_eq!(sent.last(), Some(&abort), "{sent:?}");
}

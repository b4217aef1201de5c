//! The galvo controller's line protocol (see `docs/protocols/galvo-serial.md`), shared
//! by the driver and the simulated firmware so both sides encode and parse the same
//! bytes.
//!
//! Every line is `TT BODY*CC\n`: a two-digit hexadecimal tag that the reply echoes, the
//! command or reply text, and a CRC-8 of everything before the `*`. The tag lets the
//! driver tell its reply from a late reply to an earlier request; the checksum lets
//! either side reject a corrupted line instead of acting on it.
use crate::error::ErrorKind;
use crate::geometry::{AngleLimits, OpticalAngles};

/// Protocol revision this code speaks; the controller reports its own in `IDN`.
/// Revision 2 added the laser watchdog (`WDOG`, `KEEP`) and out-of-band requests.
pub const PROTOCOL_VERSION: u32 = 2;

/// The tag reserved for out-of-band requests (`KEEP`, and `LASER OFF` from an
/// emergency stop): the host may send them at any time, even while another request
/// is outstanding, and does not wait for their replies. Ordinary requests never use
/// it (their tags wrap from `FF` to `01`).
pub const OUT_OF_BAND_TAG: u8 = 0x00;

/// The laser watchdog's timeout at power-up, milliseconds.
pub const WATCHDOG_DEFAULT_MS: u32 = 500;

/// The range of watchdog timeouts a controller accepts, milliseconds. The watchdog
/// cannot be switched off.
pub const WATCHDOG_RANGE_MS: std::ops::RangeInclusive<u32> = 20..=60_000;

/// Longest line either side accepts, bytes (a longer one is garbage).
pub const MAX_LINE: usize = 256;

/// CRC-8 with polynomial 0x07, initial value 0, no reflection (CRC-8/SMBUS).
pub fn crc8(bytes: &[u8]) -> u8 {
    let mut crc = 0u8;
    for &b in bytes {
        crc ^= b;
        for _ in 0..8 {
            crc = if crc & 0x80 != 0 {
                (crc << 1) ^ 0x07
            } else {
                crc << 1
            };
        }
    }
    crc
}

/// Encodes one line: `TT BODY*CC\n`.
pub fn encode_line(tag: u8, body: &str) -> String {
    let head = format!("{tag:02X} {body}");
    let crc = crc8(head.as_bytes());
    format!("{head}*{crc:02X}\n")
}

/// Why a received line was rejected.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum LineError {
    /// No `*CC` trailer, or a tag that is not two hexadecimal digits.
    Malformed,
    /// The checksum does not match; carries the tag if it could be read.
    Checksum(Option<u8>),
}

/// Exactly two upper-case hex digits, as the protocol writes tags and CRCs (not `+1`,
/// `a`, or `000A`, which a lenient parser would take).
fn hex_byte(s: &str) -> Option<u8> {
    let b = s.as_bytes();
    let digit = |c: u8| match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    };
    match b {
        [h, l] => Some(digit(*h)? << 4 | digit(*l)?),
        _ => None,
    }
}

/// Decodes one line (without its `\n`; a trailing `\r` is ignored) into its tag and
/// body.
pub fn decode_line(line: &[u8]) -> Result<(u8, &str), LineError> {
    let line = line.strip_suffix(b"\r").unwrap_or(line);
    let text = std::str::from_utf8(line).map_err(|_| LineError::Malformed)?;
    let (head, crc) = text.rsplit_once('*').ok_or(LineError::Malformed)?;
    let tag = head
        .get(..2)
        .filter(|_| head.as_bytes().get(2) == Some(&b' '))
        .and_then(hex_byte);
    let crc = hex_byte(crc).ok_or(LineError::Malformed)?;
    if crc != crc8(head.as_bytes()) {
        return Err(LineError::Checksum(tag));
    }
    let tag = tag.ok_or(LineError::Malformed)?;
    Ok((tag, &head[3..]))
}

/// A command to the controller.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Request {
    /// `IDN`: model, firmware version, protocol version, serial number, capabilities.
    Identify,
    /// `LIM`: the controller's hard angle limits.
    Limits,
    /// `MOVE x y`: start a move to optical angles (radians).
    Move(OpticalAngles),
    /// `POS`: the measured position.
    Position,
    /// `STAT`: motion state and measured position.
    Status,
    /// `PARK`: move to the park position (0, 0) and hold there.
    Park,
    /// `LASER ON|OFF`: laser emission (controllers with a laser only).
    Laser(bool),
    /// `LSTAT`: emission, interlock and diffuser state.
    LaserStatus,
    /// `ILK`: the interlock loop state.
    Interlock,
    /// `DIFF IN|OUT`: the LOS diffuser in or out of the laser path.
    Diffuser(bool),
    /// `WDOG [ms]`: read the laser watchdog (timeout and trips since power-up), or set
    /// its timeout (laser controller only).
    Watchdog(Option<u32>),
    /// `KEEP`: a keepalive; like every valid line, it feeds the laser watchdog.
    KeepAlive,
}

fn on_off(on: bool) -> &'static str {
    if on { "ON" } else { "OFF" }
}

impl Request {
    /// The command text.
    pub fn body(&self) -> String {
        match self {
            Request::Identify => "IDN".into(),
            Request::Limits => "LIM".into(),
            Request::Move(a) => format!("MOVE {} {}", fmt_angle(a.x), fmt_angle(a.y)),
            Request::Position => "POS".into(),
            Request::Status => "STAT".into(),
            Request::Park => "PARK".into(),
            Request::Laser(on) => format!("LASER {}", on_off(*on)),
            Request::LaserStatus => "LSTAT".into(),
            Request::Interlock => "ILK".into(),
            Request::Diffuser(inserted) => format!("DIFF {}", if *inserted { "IN" } else { "OUT" }),
            Request::Watchdog(None) => "WDOG".into(),
            Request::Watchdog(Some(ms)) => format!("WDOG {ms}"),
            Request::KeepAlive => "KEEP".into(),
        }
    }

    /// Parses a command text (the firmware side).
    pub fn parse(body: &str) -> Result<Request, ErrorCode> {
        let mut words = body.split_ascii_whitespace();
        let cmd = words.next().ok_or(ErrorCode::UnknownCommand)?;
        let args: Vec<&str> = words.collect();
        let no_args = |r: Request| {
            if args.is_empty() {
                Ok(r)
            } else {
                Err(ErrorCode::BadArgument)
            }
        };
        let one = |yes: &str, no: &str| match args.as_slice() {
            [a] if *a == yes => Ok(true),
            [a] if *a == no => Ok(false),
            _ => Err(ErrorCode::BadArgument),
        };
        match cmd {
            "IDN" => no_args(Request::Identify),
            "LIM" => no_args(Request::Limits),
            "POS" => no_args(Request::Position),
            "STAT" => no_args(Request::Status),
            "PARK" => no_args(Request::Park),
            "LSTAT" => no_args(Request::LaserStatus),
            "ILK" => no_args(Request::Interlock),
            "LASER" => one("ON", "OFF").map(Request::Laser),
            "DIFF" => one("IN", "OUT").map(Request::Diffuser),
            "KEEP" => no_args(Request::KeepAlive),
            "WDOG" => match args.as_slice() {
                [] => Ok(Request::Watchdog(None)),
                [ms] => ms
                    .parse::<u32>()
                    .ok()
                    .filter(|ms| WATCHDOG_RANGE_MS.contains(ms))
                    .map(|ms| Request::Watchdog(Some(ms)))
                    .ok_or(ErrorCode::BadArgument),
                _ => Err(ErrorCode::BadArgument),
            },
            "MOVE" => match args.as_slice() {
                [x, y] => Ok(Request::Move(OpticalAngles {
                    x: parse_angle(x).ok_or(ErrorCode::BadArgument)?,
                    y: parse_angle(y).ok_or(ErrorCode::BadArgument)?,
                })),
                _ => Err(ErrorCode::BadArgument),
            },
            _ => Err(ErrorCode::UnknownCommand),
        }
    }
}

/// Angles travel as radians with seven decimals (0.1 µrad).
pub fn fmt_angle(a: f64) -> String {
    format!("{a:.7}")
}

/// Parses an angle field; rejects non-finite values.
pub fn parse_angle(s: &str) -> Option<f64> {
    s.parse::<f64>().ok().filter(|a| a.is_finite())
}

/// Error codes in `ERR code text` replies.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ErrorCode {
    /// The request's checksum did not match (the line was corrupted on the way).
    BadChecksum = 1,
    /// Unknown command.
    UnknownCommand = 2,
    /// Wrong number or form of arguments.
    BadArgument = 3,
    /// Target outside the controller's hard limits.
    OutOfRange = 4,
    /// The controller is busy (e.g. parking).
    Busy = 5,
    /// Laser emission refused: the interlock loop is open.
    InterlockOpen = 6,
    /// This controller has no laser (the SPAD arm).
    NoLaser = 7,
    /// Internal fault (servo error, over-temperature).
    Fault = 8,
    /// A `MOVE` an out-of-band `PARK` overrode before it settled: the pair is parked,
    /// not at the move's target.
    Interrupted = 9,
}

impl ErrorCode {
    /// The code for a number, if known.
    pub fn from_number(n: u8) -> Option<ErrorCode> {
        use ErrorCode::*;
        [
            BadChecksum,
            UnknownCommand,
            BadArgument,
            OutOfRange,
            Busy,
            InterlockOpen,
            NoLaser,
            Fault,
            Interrupted,
        ]
        .into_iter()
        .find(|c| *c as u8 == n)
    }

    /// The text the firmware sends after the code.
    pub fn text(self) -> &'static str {
        match self {
            ErrorCode::BadChecksum => "bad checksum",
            ErrorCode::UnknownCommand => "unknown command",
            ErrorCode::BadArgument => "bad argument",
            ErrorCode::OutOfRange => "out of range",
            ErrorCode::Busy => "busy",
            ErrorCode::InterlockOpen => "interlock open",
            ErrorCode::NoLaser => "no laser on this controller",
            ErrorCode::Fault => "fault",
            ErrorCode::Interrupted => "interrupted by park",
        }
    }

    /// The reply body `ERR n text`.
    pub fn reply(self) -> String {
        format!("ERR {} {}", self as u8, self.text())
    }
}

/// What a controller's refusal means for the host: the error kind and what to do,
/// for a reply `ERR <code>` (`None`: a code this driver does not know).
pub fn refusal(code: Option<ErrorCode>) -> (ErrorKind, &'static str) {
    match code {
        Some(ErrorCode::BadChecksum) => (ErrorKind::Protocol, "the controller received a corrupted line"),
        Some(ErrorCode::OutOfRange) => (
            ErrorKind::OutOfRange,
            "the target is outside the controller's hard limits",
        ),
        Some(ErrorCode::Busy) => (
            ErrorKind::Busy,
            "the controller is busy; try again when it has settled",
        ),
        Some(ErrorCode::InterlockOpen) => (
            ErrorKind::Interlock,
            "the laser interlock is open: close the enclosure door or key switch",
        ),
        Some(ErrorCode::NoLaser) => (
            ErrorKind::Device,
            "this controller has no laser: check which arm the config calls `laser`",
        ),
        Some(ErrorCode::Fault) => (
            ErrorKind::Device,
            "the controller reports a fault: power-cycle it",
        ),
        Some(ErrorCode::Interrupted) => (
            ErrorKind::Interrupted,
            "an emergency park overrode the move: the pair is parked at (0, 0)",
        ),
        Some(ErrorCode::UnknownCommand | ErrorCode::BadArgument) | None => (
            ErrorKind::Protocol,
            "the controller's firmware does not understand this protocol version",
        ),
    }
}

/// A parsed reply body: `OK fields…` or `ERR code text`.
#[derive(Clone, Debug, PartialEq)]
pub enum Reply<'a> {
    /// Success, with the reply's fields.
    Ok(Vec<&'a str>),
    /// Refusal; the code is `None` when the number is unknown to this side.
    Err(Option<ErrorCode>, &'a str),
}

impl<'a> Reply<'a> {
    /// Parses a reply body; `None` if it is neither `OK…` nor `ERR n…`.
    pub fn parse(body: &'a str) -> Option<Reply<'a>> {
        if let Some(rest) = body.strip_prefix("OK") {
            if !rest.is_empty() && !rest.starts_with(' ') {
                return None;
            }
            return Some(Reply::Ok(rest.split_ascii_whitespace().collect()));
        }
        let rest = body.strip_prefix("ERR ")?;
        let (num, text) = rest.split_once(' ').unwrap_or((rest, ""));
        let code = num.parse::<u8>().ok()?;
        Some(Reply::Err(ErrorCode::from_number(code), text))
    }
}

pub use crate::traits::MotionState;

/// The words `STAT` reports a [`MotionState`] by.
impl MotionState {
    /// The word on the wire.
    pub fn word(self) -> &'static str {
        match self {
            MotionState::Settled => "SETTLED",
            MotionState::Moving => "MOVING",
            MotionState::Parked => "PARKED",
            MotionState::Fault => "FAULT",
        }
    }

    /// Parses the word on the wire.
    pub fn from_word(w: &str) -> Option<MotionState> {
        [
            MotionState::Settled,
            MotionState::Moving,
            MotionState::Parked,
            MotionState::Fault,
        ]
        .into_iter()
        .find(|s| s.word() == w)
    }
}

/// Formats `x y` fields.
pub fn fmt_angles(a: OpticalAngles) -> String {
    format!("{} {}", fmt_angle(a.x), fmt_angle(a.y))
}

/// Parses two angle fields.
pub fn parse_angles(fields: &[&str]) -> Option<OpticalAngles> {
    match fields {
        [x, y] => Some(OpticalAngles {
            x: parse_angle(x)?,
            y: parse_angle(y)?,
        }),
        _ => None,
    }
}

/// Formats `xmin xmax ymin ymax`.
pub fn fmt_limits(l: AngleLimits) -> String {
    format!(
        "{} {} {} {}",
        fmt_angle(l.x[0]),
        fmt_angle(l.x[1]),
        fmt_angle(l.y[0]),
        fmt_angle(l.y[1])
    )
}

/// Parses `xmin xmax ymin ymax`.
pub fn parse_limits(fields: &[&str]) -> Option<AngleLimits> {
    match fields {
        [a, b, c, d] => Some(AngleLimits {
            x: [parse_angle(a)?, parse_angle(b)?],
            y: [parse_angle(c)?, parse_angle(d)?],
        }),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tags_and_crcs_are_exactly_two_upper_case_hex_digits() {
        let good = encode_line(0x1A, "POS?");
        assert_eq!(decode_line(good.trim_end().as_bytes()).unwrap(), (0x1A, "POS?"));
        // Each would pass a lenient parser: the CRC holds over what is written.
        for bad in [
            format!("1a POS?*{:02X}", crc8(b"1a POS?")),
            format!("+1 POS?*{:02X}", crc8(b"+1 POS?")),
            format!("1A POS?*0{:02X}", crc8(b"1A POS?")),
        ] {
            assert!(decode_line(bad.as_bytes()).is_err(), "{bad} was accepted");
        }
    }

    #[test]
    fn crc8_matches_the_published_check_value() {
        // CRC-8/SMBUS check value for "123456789".
        assert_eq!(crc8(b"123456789"), 0xF4);
    }

    #[test]
    fn lines_round_trip_and_reject_corruption() {
        let line = encode_line(0x2A, "MOVE 0.1000000 -0.0500000");
        let (tag, body) = decode_line(line.trim_end().as_bytes()).unwrap();
        assert_eq!((tag, body), (0x2A, "MOVE 0.1000000 -0.0500000"));
        let mut bad = line.trim_end().as_bytes().to_vec();
        bad[5] ^= 0x01;
        assert_eq!(decode_line(&bad), Err(LineError::Checksum(Some(0x2A))));
        assert_eq!(decode_line(b"garbage"), Err(LineError::Malformed));
    }

    #[test]
    fn requests_round_trip_through_text() {
        let all = [
            Request::Identify,
            Request::Limits,
            Request::Move(OpticalAngles { x: 0.25, y: -0.125 }),
            Request::Position,
            Request::Status,
            Request::Park,
            Request::Laser(true),
            Request::Laser(false),
            Request::LaserStatus,
            Request::Interlock,
            Request::Diffuser(true),
            Request::Diffuser(false),
            Request::Watchdog(None),
            Request::Watchdog(Some(500)),
            Request::KeepAlive,
        ];
        for r in all {
            assert_eq!(Request::parse(&r.body()), Ok(r), "{}", r.body());
        }
        assert_eq!(Request::parse("MOVE 1"), Err(ErrorCode::BadArgument));
        assert_eq!(Request::parse("MOVE nan 0"), Err(ErrorCode::BadArgument));
        assert_eq!(Request::parse("JUMP"), Err(ErrorCode::UnknownCommand));
        // The watchdog cannot be switched off or set out of its range.
        assert_eq!(Request::parse("WDOG 0"), Err(ErrorCode::BadArgument));
        assert_eq!(Request::parse("WDOG 60001"), Err(ErrorCode::BadArgument));
        assert_eq!(Request::parse("WDOG -5"), Err(ErrorCode::BadArgument));
    }

    #[test]
    fn replies_parse() {
        assert_eq!(Reply::parse("OK"), Some(Reply::Ok(vec![])));
        assert_eq!(Reply::parse("OK 1 2"), Some(Reply::Ok(vec!["1", "2"])));
        assert_eq!(
            Reply::parse("ERR 4 out of range"),
            Some(Reply::Err(Some(ErrorCode::OutOfRange), "out of range"))
        );
        assert_eq!(Reply::parse("OKAY"), None);
        assert_eq!(Reply::parse("ERR x"), None);
    }
}

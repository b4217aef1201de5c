//! The instrument config: which back-end runs the instrument, the poses and limits of
//! the two galvo pairs, the laser, the SPAD and the TDC.
//!
//! Units in the file carry their unit in the key (`bin-width-ps`, `power-mw`) so a lab
//! user never has to guess; the validated types hold SI units (metres, seconds, watts,
//! radians), as the rest of the code base does.
use std::path::{Path, PathBuf};
use std::time::Duration;

use glam::DVec3;
use periscope_drivers::daqmx::{AoGalvoSettings, DaqLaserSettings};
use periscope_drivers::picoquant::{Family, Trigger};
use periscope_drivers::{AngleLimits, GalvoPose, UsbSelector};
use serde::Deserialize;

use super::daqmx::{self, RawDaqGalvo, RawDaqLaser, RawGalvoDriver};
use super::{ConfigError, TomlSource};

/// Which implementation drives the instrument.
#[derive(Clone, Debug, PartialEq)]
pub enum Backend {
    /// The simulated galvos and TDC from `periscope-sim`.
    Sim(SimSettings),
    /// Real galvos on serial ports and a real TDC on USB.
    Hardware,
}

/// Settings only the simulated instrument uses: the scene it images and the optics a
/// real instrument has physically (aperture, spot size, losses, ambient light).
#[derive(Clone, Debug, PartialEq)]
pub struct SimSettings {
    /// Seed for every random draw of the simulation (noise, sampling).
    pub seed: u64,
    /// The scene file, resolved against the instrument config's folder; `None` uses
    /// the built-in planar wall + letter scene.
    pub scene: Option<std::path::PathBuf>,
    /// Collection aperture diameter, metres.
    pub aperture: f64,
    /// Diameter of the laser and SPAD spots on the relay, metres.
    pub spot: f64,
    /// Optical transmission, 0..1.
    pub transmission: f64,
    /// Detected ambient background rate, Hz.
    pub ambient_rate: f64,
    /// Half angle of the LOS diffuser's cone, radians.
    pub diffuser_half_angle: f64,
    /// Gate opening after the direct path, path length in metres; `None` = ungated.
    pub gate_margin: Option<f64>,
    /// Model pile-up and dead time.
    pub pile_up: bool,
    /// Spacing of the hidden-surface samples, metres.
    pub sample_spacing: f64,
    /// Real seconds per simulated second of galvo settling and TDC dwell: 0 runs as
    /// fast as the physics computes, 1 in real time.
    pub time_scale: f64,
    /// Whether the simulated interlock loop starts closed.
    pub interlock_closed: bool,
    /// How the daemon reaches the simulated devices.
    pub devices: SimDevices,
    /// Poisson noise on the simulated counts (`sim.noise`, default on).
    pub noise: bool,
    /// Where the simulated arms really are (`[sim.true-pose.laser]`,
    /// `[sim.true-pose.spad]`), laser then SPAD: the configured poses unless the table
    /// says otherwise. A simulated instrument whose arms differ from its config is one
    /// to practise and test `periscope calibrate` on. Boxed: [`Backend`] stays small.
    pub true_poses: Box<[GalvoPose; 2]>,
    /// How fast the simulated laser really pulses, hertz (`sim.true-rep-rate-mhz`):
    /// `laser.rep-rate-mhz` unless the key says otherwise. The photons and the
    /// counter's sync rate follow it; a run checks that rate against the config when
    /// the laser goes on.
    pub true_repetition_rate: f64,
}

/// How the daemon reaches the simulated devices (`sim.devices`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum SimDevices {
    /// Through the real drivers, over pseudo-terminals and the USB transport trait,
    /// speaking the wire protocols byte for byte (the default: CI runs the code the lab
    /// runs).
    #[default]
    Wire,
    /// Straight over the simulator's controller model, without wire or drivers (for
    /// tests of what lies above the drivers; faster, and wire faults do not apply).
    InProcess,
}

/// A validated instrument config.
#[derive(Clone, Debug, PartialEq)]
pub struct InstrumentConfig {
    /// Human-readable instrument name.
    pub name: String,
    /// The back-end that drives it.
    pub backend: Backend,
    /// The galvo pair that steers the laser.
    pub laser_arm: GalvoArm,
    /// The galvo pair that steers the SPAD's field of view.
    pub spad_arm: GalvoArm,
    /// The pulsed laser.
    pub laser: LaserSettings,
    /// The single-photon detector.
    pub spad: SpadSettings,
    /// The time-to-digital converter / histogrammer.
    pub tdc: TdcSettings,
    /// The HTTP API (`periscope serve`).
    pub api: ApiSettings,
    /// Memory and disk one run may need (`[budget]`).
    pub budget: BudgetLimits,
}

/// Settings of the HTTP API, from the optional `[api]` table. Its `Debug` output
/// never shows the token.
#[derive(Clone, PartialEq)]
pub struct ApiSettings {
    /// Bearer token for mutating endpoints (`PERISCOPE_TOKEN` overrides it).
    pub token: Option<String>,
    /// Host names (besides IP literals and `localhost`) that requests may name in
    /// their `Host` header: the names operators reach this machine by. Anything else
    /// is refused, which stops DNS-rebinding pages from reaching the API.
    pub hosts: Vec<String>,
    /// How often the idle worker reads the devices for `GET /instrument`.
    pub status_interval: Duration,
    /// Most runs waiting (queued or paused) at once; more submissions get 429.
    pub max_queue: usize,
    /// Most event-stream clients at once; more get 503.
    pub max_streams: usize,
    /// Most file downloads in flight at once; more get 503.
    pub max_downloads: usize,
    /// Where runs are stored and the queue is kept.
    pub runs_dir: PathBuf,
    /// Whether read-only endpoints answer clients that are not on loopback without a
    /// token.
    pub open_reads: bool,
    /// Largest request body accepted, bytes.
    pub body_limit: usize,
    /// Longest time a request may take to answer (event streams excepted once open).
    pub request_timeout: Duration,
    /// Longest wait for a request's headers, and for the next request on an idle
    /// keep-alive connection; then the connection is closed.
    pub header_timeout: Duration,
    /// Most connections at once (lowered to the descriptor limit less a reserve).
    pub max_connections: usize,
    /// Most connections one remote address may hold at once (loopback's are not
    /// counted against it: the instrument's own computer has a reserve of its own).
    pub max_connections_per_peer: usize,
    /// Most requests answered at once; more wait their turn (the e-stop and the health
    /// check never wait).
    pub max_concurrent: usize,
    /// Most plan checks (`POST /check`, submissions' parsing) at once.
    pub max_checks: usize,
    /// Largest capture file (all its files together) `POST /imports` accepts, bytes.
    pub import_limit: u64,
    /// Longest an import's upload may go without a byte arriving; then it is dropped
    /// and nothing of it is kept.
    pub import_stall: Duration,
}

impl std::fmt::Debug for ApiSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ApiSettings")
            .field("token", &self.token.as_ref().map(|_| "<redacted>"))
            .field("hosts", &self.hosts)
            .field("runs_dir", &self.runs_dir)
            .field("open_reads", &self.open_reads)
            .field("body_limit", &self.body_limit)
            .field("request_timeout", &self.request_timeout)
            .field("header_timeout", &self.header_timeout)
            .field("max_connections", &self.max_connections)
            .field("max_connections_per_peer", &self.max_connections_per_peer)
            .field("max_concurrent", &self.max_concurrent)
            .field("max_checks", &self.max_checks)
            .field("import_limit", &self.import_limit)
            .field("import_stall", &self.import_stall)
            .field("status_interval", &self.status_interval)
            .field("max_queue", &self.max_queue)
            .field("max_streams", &self.max_streams)
            .field("max_downloads", &self.max_downloads)
            .finish()
    }
}

/// One galvo pair.
#[derive(Clone, Debug, PartialEq)]
pub struct GalvoArm {
    /// Pose of the pair (pivot and frame), world frame.
    pub pose: GalvoPose,
    /// Optical angle limits, radians.
    pub limits: AngleLimits,
    /// Time to wait after a move before the position counts as settled.
    pub settle: Duration,
    /// What drives it (required for the hardware back-end; a simulated instrument
    /// without one uses the simulator's pseudo-terminal or in-process devices).
    pub link: Option<GalvoLink>,
}

/// What drives a galvo pair (`galvo.<arm>.driver`).
#[derive(Clone, Debug, PartialEq)]
pub enum GalvoLink {
    /// A galvo controller on a serial port (`"serial"`, the default).
    Serial(SerialLink),
    /// Two analog outputs of an NI DAQ device through NI-DAQmx (`"daqmx"`).
    Daqmx(AoGalvoSettings),
}

impl GalvoArm {
    /// The serial link, if the pair is on one.
    pub fn serial(&self) -> Option<&SerialLink> {
        match &self.link {
            Some(GalvoLink::Serial(s)) => Some(s),
            _ => None,
        }
    }
}

/// A serial link to a galvo controller.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SerialLink {
    /// Device path, e.g. `/dev/ttyUSB0`.
    pub port: String,
    /// Baud rate.
    pub baud: u32,
    /// How long to wait for a reply.
    pub timeout: Duration,
}

/// The pulsed laser.
#[derive(Clone, Debug, PartialEq)]
pub struct LaserSettings {
    /// Wavelength, metres.
    pub wavelength: f64,
    /// Average power, watts.
    pub power: f64,
    /// Pulse repetition rate, hertz.
    pub repetition_rate: f64,
    /// The laser controller's watchdog: emission stops when the controller hears
    /// nothing from the host for this long.
    pub watchdog: Duration,
    /// How long a run may show no progress (no checkpoint, no stop poll) with the
    /// laser on before the keepalive stops feeding the watchdog.
    pub stall: Duration,
    /// The laser's digital lines on a DAQ device; set exactly when the laser arm is
    /// on one (`galvo.laser.driver = "daqmx"`), whose library it shares.
    pub daqmx: Option<DaqLaserSettings>,
}

/// The single-photon avalanche diode.
#[derive(Clone, Debug, PartialEq)]
pub struct SpadSettings {
    /// Photon detection efficiency, in (0, 1].
    pub efficiency: f64,
    /// Dark count rate, hertz.
    pub dark_count_rate: f64,
    /// Dead time after a detection, seconds.
    pub dead_time: f64,
    /// Full width at half maximum of the timing jitter (laser, SPAD and TDC), seconds.
    pub jitter_fwhm: f64,
}

/// The time-to-digital converter.
#[derive(Clone, Debug, PartialEq)]
pub struct TdcSettings {
    /// Histogram bin width, seconds.
    pub bin_width: f64,
    /// Number of bins per histogram.
    pub bins: u32,
    /// Time of the first bin's start after the sync pulse, seconds.
    pub offset: f64,
    /// Sync divider (1 = every laser pulse).
    pub sync_divider: u32,
    /// Fixed system delay (cables, electronics), seconds; subtracted as `c0·t_sys`.
    pub system_delay: f64,
    /// Undo pile-up (Coates) and the SPAD's dead time on every stored histogram before
    /// it is reconstructed (`tdc.pile-up-correction`, default on).
    pub pile_up_correction: bool,
    /// The USB device (required for the hardware back-end with the `usb` driver).
    pub usb: Option<UsbSelector>,
    /// Which driver reaches the histogrammer (`tdc.driver`).
    pub driver: TdcDriver,
}

/// The histogrammer's driver (`tdc.driver`).
#[derive(Clone, Debug, PartialEq)]
pub enum TdcDriver {
    /// Periscope's own USB histogrammer (`"usb"`, the default), at `tdc.usb`.
    Usb,
    /// A PicoQuant counter through the vendor's library (`"multiharp"`, `"hydraharp"`).
    PicoQuant(PicoQuantCounter),
}

/// A PicoQuant counter as the config describes it.
#[derive(Clone, Debug, PartialEq)]
pub struct PicoQuantCounter {
    /// MultiHarp (MHLib) or HydraHarp (HHLib).
    pub family: Family,
    /// The library to load (`tdc.library`; the vendor's install path by default).
    pub library: PathBuf,
    /// The counter's serial number (`tdc.serial`); `None` takes the first found.
    pub serial: Option<String>,
    /// The SPAD's input, 0-based (`tdc.channel` is 1-based, as the front panel).
    pub channel: u32,
    /// The sync input's trigger.
    pub sync_trigger: Trigger,
    /// The SPAD input's trigger.
    pub input_trigger: Trigger,
    /// The SPAD input's channel offset, ps.
    pub input_offset_ps: i32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawInstrument {
    name: String,
    backend: RawBackend,
    galvo: RawGalvos,
    laser: RawLaser,
    spad: RawSpad,
    tdc: RawTdc,
    sim: Option<RawSim>,
    api: Option<RawApi>,
    budget: Option<RawBudget>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawBudget {
    memory_gib: Option<f64>,
    disk_gib: Option<f64>,
    hours: Option<f64>,
}

/// Refuses two arms on one serial port or on one analog output (NI-DAQmx names its
/// channels without regard to case, and so does this): they load, and then fail as
/// the devices open with a vendor's resource error that names neither key. Within an
/// arm, its own two outputs are checked where they are read.
fn arms_apart(src: &TomlSource, laser: &GalvoArm, spad: &GalvoArm) -> Result<(), ConfigError> {
    match (&laser.link, &spad.link) {
        (Some(GalvoLink::Serial(a)), Some(GalvoLink::Serial(b))) if a.port == b.port => Err(src.invalid(
            "galvo.spad.serial.port",
            format!(
                "`{}` is galvo.laser.serial.port too: each pair has a controller and a port of its own",
                b.port
            ),
        )),
        (Some(GalvoLink::Daqmx(a)), Some(GalvoLink::Daqmx(b))) => {
            for (i, ch) in b.channels.iter().enumerate() {
                if let Some(j) = a.channels.iter().position(|c| c.eq_ignore_ascii_case(ch)) {
                    return Err(src.invalid(
                        &format!("galvo.spad.channels[{i}]"),
                        format!("`{ch}` is galvo.laser.channels[{j}] too: each axis needs an analog output of its own"),
                    ));
                }
            }
            Ok(())
        }
        _ => Ok(()),
    }
}

/// The smallest memory or disk budget a config may give, GiB (a MiB).
const MIN_BUDGET_GIB: f64 = 1.0 / 1024.0;

fn budget_limits(check: &Check<'_>, raw: RawBudget) -> Result<BudgetLimits, ConfigError> {
    let d = BudgetLimits::default();
    let gib = |key: &str, v: Option<f64>, default: u64, max: f64| -> Result<u64, ConfigError> {
        match v {
            None => Ok(default),
            // At least a MiB: a tiny positive value made 0 bytes, which refused every plan.
            Some(g) => Ok((check.range(key, g, MIN_BUDGET_GIB, max, "GiB")? * (1u64 << 30) as f64) as u64),
        }
    };
    Ok(BudgetLimits {
        memory: gib("budget.memory-gib", raw.memory_gib, d.memory, 65_536.0)?,
        disk: gib("budget.disk-gib", raw.disk_gib, d.disk, 1_048_576.0)?,
        hours: raw
            .hours
            .map(|h| check.positive("budget.hours", h, 8784.0, "hours (a year)"))
            .transpose()?,
    })
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawApi {
    token: Option<String>,
    #[serde(default)]
    hosts: Vec<String>,
    #[serde(default = "default_status_interval_s")]
    status_interval_s: f64,
    #[serde(default = "default_max_queue")]
    max_queue: f64,
    #[serde(default = "default_max_streams")]
    max_streams: f64,
    #[serde(default = "default_max_downloads")]
    max_downloads: f64,
    #[serde(default = "default_runs_dir")]
    runs_dir: PathBuf,
    #[serde(default)]
    open_reads: bool,
    #[serde(default = "default_body_limit_kib")]
    body_limit_kib: f64,
    #[serde(default = "default_request_timeout_s")]
    request_timeout_s: f64,
    #[serde(default = "default_header_timeout_s")]
    header_timeout_s: f64,
    #[serde(default = "default_max_connections")]
    max_connections: f64,
    #[serde(default = "default_max_connections_per_peer")]
    max_connections_per_peer: f64,
    #[serde(default = "default_max_concurrent")]
    max_concurrent: f64,
    #[serde(default = "default_max_checks")]
    max_checks: f64,
    #[serde(default = "default_import_limit_mib")]
    import_limit_mib: f64,
    #[serde(default = "default_import_stall_s")]
    import_stall_s: f64,
}

impl Default for RawApi {
    fn default() -> Self {
        RawApi {
            token: None,
            hosts: Vec::new(),
            status_interval_s: default_status_interval_s(),
            max_queue: default_max_queue(),
            max_streams: default_max_streams(),
            max_downloads: default_max_downloads(),
            runs_dir: default_runs_dir(),
            open_reads: false,
            body_limit_kib: default_body_limit_kib(),
            request_timeout_s: default_request_timeout_s(),
            header_timeout_s: default_header_timeout_s(),
            max_connections: default_max_connections(),
            max_connections_per_peer: default_max_connections_per_peer(),
            max_concurrent: default_max_concurrent(),
            max_checks: default_max_checks(),
            import_limit_mib: default_import_limit_mib(),
            import_stall_s: default_import_stall_s(),
        }
    }
}

fn default_runs_dir() -> PathBuf {
    PathBuf::from("runs")
}
fn default_body_limit_kib() -> f64 {
    1024.0
}
fn default_request_timeout_s() -> f64 {
    30.0
}
fn default_header_timeout_s() -> f64 {
    10.0
}
fn default_max_connections() -> f64 {
    512.0
}
fn default_max_connections_per_peer() -> f64 {
    32.0
}
fn default_max_concurrent() -> f64 {
    8.0
}
fn default_max_checks() -> f64 {
    2.0
}
fn default_import_limit_mib() -> f64 {
    4096.0
}
fn default_import_stall_s() -> f64 {
    30.0
}
fn default_status_interval_s() -> f64 {
    10.0
}
fn default_max_queue() -> f64 {
    100.0
}
fn default_max_streams() -> f64 {
    64.0
}
fn default_max_downloads() -> f64 {
    4.0
}

fn api_settings(check: &Check<'_>, raw: RawApi) -> Result<ApiSettings, ConfigError> {
    if let Some(t) = &raw.token
        && t.trim().len() < 16
    {
        return Err(check.src.invalid(
            "api.token",
            "is shorter than 16 characters: use a long random string (e.g. `openssl rand -hex 24`)",
        ));
    }
    for (i, h) in raw.hosts.iter().enumerate() {
        let ok = !h.is_empty()
            && h.len() <= 253
            && h.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.');
        if !ok {
            return Err(check.src.invalid(
                &format!("api.hosts[{i}]"),
                format!(
                    "`{h}` is not a host name: give names like \"lab-pc.example.org\", without port or scheme"
                ),
            ));
        }
    }
    // Counts are whole numbers: 1.5 was rounded to 2 without a word.
    let count = |key: &str, v: f64, max: f64| -> Result<usize, ConfigError> {
        let n = check.range(key, v, 1.0, max, "")?;
        if n.fract() != 0.0 {
            return Err(check
                .src
                .invalid(key, format!("{v} is not a whole number: give a count")));
        }
        Ok(n as usize)
    };
    if raw.runs_dir.as_os_str().is_empty() {
        return Err(check.src.invalid(
            "api.runs-dir",
            "is empty: give the directory runs are kept in (default \"runs\")",
        ));
    }
    Ok(ApiSettings {
        token: raw.token,
        hosts: raw.hosts.iter().map(|h| h.to_ascii_lowercase()).collect(),
        status_interval: Duration::from_secs_f64(check.range(
            "api.status-interval-s",
            raw.status_interval_s,
            0.1,
            3600.0,
            "s",
        )?),
        max_queue: count("api.max-queue", raw.max_queue, 100_000.0)?,
        max_streams: count("api.max-streams", raw.max_streams, 10_000.0)?,
        max_downloads: count("api.max-downloads", raw.max_downloads, 1_000.0)?,
        runs_dir: raw.runs_dir,
        open_reads: raw.open_reads,
        // At least a few KiB (a plan, a JSON body; 0.0001 made a 0-byte limit that
        // refused every body), and a request at least half a second.
        body_limit: (check.range(
            "api.body-limit-kib",
            raw.body_limit_kib,
            4.0,
            1024.0 * 1024.0,
            "KiB",
        )? * 1024.0) as usize,
        request_timeout: Duration::from_secs_f64(check.range(
            "api.request-timeout-s",
            raw.request_timeout_s,
            0.5,
            3600.0,
            "s",
        )?),
        header_timeout: Duration::from_secs_f64(check.range(
            "api.header-timeout-s",
            raw.header_timeout_s,
            0.1,
            3600.0,
            "s",
        )?),
        max_connections: count("api.max-connections", raw.max_connections, 1_000_000.0)?,
        max_connections_per_peer: count(
            "api.max-connections-per-peer",
            raw.max_connections_per_peer,
            1_000_000.0,
        )?,
        max_concurrent: count("api.max-concurrent", raw.max_concurrent, 10_000.0)?,
        max_checks: count("api.max-checks", raw.max_checks, 1_000.0)?,
        // The readers take files up to 16 GiB (y-tal's cap).
        // At least a KiB: a tiny positive value made 0 bytes, which refused every import.
        import_limit: (check.range(
            "api.import-limit-mib",
            raw.import_limit_mib,
            1.0 / 1024.0,
            (periscope_recon::io::formats::MAX_FILE_BYTES >> 20) as f64,
            "MiB",
        )? * 1_048_576.0) as u64,
        import_stall: Duration::from_secs_f64(check.range(
            "api.import-stall-s",
            raw.import_stall_s,
            0.1,
            3600.0,
            "s",
        )?),
    })
}

#[derive(Deserialize, Clone, Copy, PartialEq)]
#[serde(rename_all = "kebab-case")]
enum RawBackend {
    Sim,
    Hardware,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawGalvos {
    laser: RawGalvo,
    spad: RawGalvo,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawGalvo {
    #[serde(deserialize_with = "crate::config::exact::array")]
    origin: [f64; 3],
    #[serde(deserialize_with = "crate::config::exact::array")]
    boresight: [f64; 3],
    #[serde(deserialize_with = "crate::config::exact::array", default = "default_up")]
    up: [f64; 3],
    #[serde(default)]
    scanner: Option<periscope_drivers::Scanner>,
    angle_limits_deg: RawLimits,
    #[serde(default)]
    settle_us: f64,
    serial: Option<RawSerial>,
    #[serde(default)]
    driver: RawGalvoDriver,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    channels: Option<[String; 2]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    volts_per_deg: Option<[f64; 2]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    offsets_v: Option<[f64; 2]>,
    max_slew_deg_per_ms: Option<f64>,
    library: Option<PathBuf>,
}

fn default_up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawLimits {
    #[serde(deserialize_with = "crate::config::exact::array")]
    x: [f64; 2],
    #[serde(deserialize_with = "crate::config::exact::array")]
    y: [f64; 2],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawSerial {
    port: String,
    #[serde(default = "default_baud")]
    baud: u32,
    #[serde(default = "default_timeout_ms")]
    timeout_ms: u64,
}

fn default_baud() -> u32 {
    115_200
}

fn default_timeout_ms() -> u64 {
    200
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawLaser {
    wavelength_nm: f64,
    power_mw: f64,
    rep_rate_mhz: f64,
    #[serde(default = "default_watchdog_ms")]
    watchdog_ms: f64,
    #[serde(default = "default_stall_ms")]
    stall_ms: f64,
    laser_line: Option<String>,
    interlock_line: Option<String>,
    diffuser_line: Option<String>,
    heartbeat_line: Option<String>,
    daq_watchdog: Option<bool>,
    accept_no_watchdog: Option<bool>,
}

fn default_stall_ms() -> f64 {
    5000.0
}

fn default_watchdog_ms() -> f64 {
    f64::from(periscope_drivers::galvo::protocol::WATCHDOG_DEFAULT_MS)
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawSpad {
    efficiency: f64,
    #[serde(default)]
    dark_count_rate_hz: f64,
    #[serde(default)]
    dead_time_ns: f64,
    #[serde(default)]
    jitter_fwhm_ps: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawTdc {
    bin_width_ps: f64,
    bins: u32,
    #[serde(default)]
    offset_ns: f64,
    #[serde(default = "default_sync_divider")]
    sync_divider: u32,
    #[serde(default)]
    system_delay_ns: f64,
    #[serde(default = "default_true")]
    pile_up_correction: bool,
    usb: Option<String>,
    #[serde(default)]
    driver: RawTdcDriver,
    library: Option<PathBuf>,
    serial: Option<String>,
    channel: Option<u32>,
    sync_level_mv: Option<f64>,
    input_level_mv: Option<f64>,
    sync_edge: Option<RawEdge>,
    input_edge: Option<RawEdge>,
    sync_zero_cross_mv: Option<f64>,
    input_zero_cross_mv: Option<f64>,
    input_offset_ps: Option<f64>,
}

#[derive(Deserialize, Clone, Copy, Default, PartialEq)]
#[serde(rename_all = "kebab-case")]
enum RawTdcDriver {
    #[default]
    Usb,
    Multiharp,
    Hydraharp,
}

#[derive(Deserialize, Clone, Copy, PartialEq)]
#[serde(rename_all = "kebab-case")]
enum RawEdge {
    Rising,
    Falling,
}

fn default_sync_divider() -> u32 {
    1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawSim {
    #[serde(default)]
    seed: u64,
    scene: Option<std::path::PathBuf>,
    #[serde(default = "default_aperture_mm")]
    aperture_mm: f64,
    #[serde(default = "default_spot_mm")]
    spot_mm: f64,
    #[serde(default = "default_transmission")]
    transmission: f64,
    #[serde(default)]
    ambient_rate_hz: f64,
    #[serde(default = "default_diffuser_deg")]
    diffuser_half_angle_deg: f64,
    #[serde(default = "default_true")]
    gate: bool,
    #[serde(default = "default_gate_mm")]
    gate_margin_mm: f64,
    #[serde(default)]
    pile_up: bool,
    #[serde(default = "default_spacing_mm")]
    sample_spacing_mm: f64,
    #[serde(default)]
    time_scale: f64,
    #[serde(default = "default_true")]
    interlock_closed: bool,
    #[serde(default)]
    devices: SimDevices,
    #[serde(default = "default_true")]
    noise: bool,
    #[serde(default)]
    true_pose: RawTruePoses,
    #[serde(default)]
    true_rep_rate_mhz: Option<f64>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawTruePoses {
    laser: Option<RawTruePose>,
    spad: Option<RawTruePose>,
}

/// A simulated arm's true pose; a key left out keeps the configured arm's value.
#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawTruePose {
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    origin: Option<[f64; 3]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    boresight: Option<[f64; 3]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    up: Option<[f64; 3]>,
    /// The kinematics the simulated pair really has (a config's `scanner` that is
    /// not the pair's shows as calibration residuals and misplaced relay points).
    #[serde(default)]
    scanner: Option<periscope_drivers::Scanner>,
}

fn default_aperture_mm() -> f64 {
    10.0
}
fn default_spot_mm() -> f64 {
    5.0
}
fn default_transmission() -> f64 {
    0.5
}
fn default_diffuser_deg() -> f64 {
    25.0
}
fn default_gate_mm() -> f64 {
    100.0
}
fn default_true() -> bool {
    true
}
fn default_spacing_mm() -> f64 {
    5.0
}

impl Default for RawSim {
    fn default() -> Self {
        toml::from_str("").expect("every [sim] key has a default")
    }
}

/// The true pose `[sim.true-pose.<arm>]` gives, the configured `pose` where it says
/// nothing.
fn true_pose(
    check: &Check<'_>,
    arm: &str,
    raw: Option<RawTruePose>,
    configured: GalvoPose,
) -> Result<GalvoPose, ConfigError> {
    let Some(raw) = raw else {
        return Ok(configured);
    };
    let key = format!("sim.true-pose.{arm}");
    let r = configured.rotation;
    let vector = |name: &str, v: Option<[f64; 3]>, default: DVec3| match v {
        Some(v) => check.finite3(&format!("{key}.{name}"), v),
        None => Ok(default),
    };
    let origin = vector("origin", raw.origin, configured.origin)?;
    let boresight = vector("boresight", raw.boresight, r.z_axis)?;
    let up = vector("up", raw.up, r.y_axis)?;
    GalvoPose::looking(origin, boresight, up)
        .map(|pose| pose.with_scanner(raw.scanner.unwrap_or(configured.scanner)))
        .ok_or_else(|| {
            check.src.invalid(
                &format!("{key}.boresight"),
                "must be a non-zero direction that is not parallel to `up`",
            )
        })
}

fn sim_settings(
    check: &Check<'_>,
    raw: RawSim,
    arms: [GalvoPose; 2],
    repetition_rate: f64,
) -> Result<SimSettings, ConfigError> {
    let true_poses = [
        true_pose(check, "laser", raw.true_pose.laser, arms[0])?,
        true_pose(check, "spad", raw.true_pose.spad, arms[1])?,
    ];
    let base = check.src.path().parent().unwrap_or(Path::new("."));
    let mut scene = raw.scene.map(|p| base.join(p));
    // A config held in memory (the built-in default) has no folder to resolve against:
    // a scene that cannot be found there means the built-in scene.
    if !check.src.path().is_file() && scene.as_ref().is_some_and(|p| !p.is_file()) {
        scene = None;
    }
    if let Some(path) = &scene
        && path.exists()
        && !path.is_file()
    {
        return Err(check.src.invalid(
            "sim.scene",
            format!(
                "{} is not a regular file (a directory, a device or a pipe): give the scene's TOML file",
                path.display()
            ),
        ));
    }
    if let Some(path) = &scene
        && !path.is_file()
    {
        return Err(check.src.invalid(
            "sim.scene",
            format!(
                "scene file {} does not exist: give a path relative to this config",
                path.display()
            ),
        ));
    }
    Ok(SimSettings {
        seed: raw.seed,
        scene,
        aperture: check.positive("sim.aperture-mm", raw.aperture_mm, 1e3, "mm")? * 1e-3,
        spot: check.positive("sim.spot-mm", raw.spot_mm, 1e3, "mm")? * 1e-3,
        transmission: check.positive("sim.transmission", raw.transmission, 1.0, "(a fraction)")?,
        ambient_rate: check.range("sim.ambient-rate-hz", raw.ambient_rate_hz, 0.0, 1e9, "Hz")?,
        diffuser_half_angle: check
            .range(
                "sim.diffuser-half-angle-deg",
                raw.diffuser_half_angle_deg,
                0.1,
                90.0,
                "degrees",
            )?
            .to_radians(),
        gate_margin: match raw.gate {
            true => Some(check.range("sim.gate-margin-mm", raw.gate_margin_mm, 0.0, 1e5, "mm")? * 1e-3),
            false => None,
        },
        pile_up: raw.pile_up,
        sample_spacing: check.range("sim.sample-spacing-mm", raw.sample_spacing_mm, 0.5, 100.0, "mm")? * 1e-3,
        time_scale: check.range(
            "sim.time-scale",
            raw.time_scale,
            0.0,
            100.0,
            "(real seconds per simulated second)",
        )?,
        interlock_closed: raw.interlock_closed,
        devices: raw.devices,
        noise: raw.noise,
        true_poses: Box::new(true_poses),
        true_repetition_rate: match raw.true_rep_rate_mhz {
            Some(mhz) => check.positive("sim.true-rep-rate-mhz", mhz, 1e4, "MHz")? * 1e6,
            None => repetition_rate,
        },
    })
}

/// Checks one numeric field against a range and reports it against its key.
struct Check<'a> {
    src: &'a TomlSource,
}

impl Check<'_> {
    fn range(&self, key: &str, value: f64, lo: f64, hi: f64, unit: &str) -> Result<f64, ConfigError> {
        if value.is_finite() && (lo..=hi).contains(&value) {
            Ok(value)
        } else {
            Err(self.src.invalid(
                key,
                format!("{value} is out of range: it must lie between {lo} and {hi} {unit}"),
            ))
        }
    }

    fn positive(&self, key: &str, value: f64, hi: f64, unit: &str) -> Result<f64, ConfigError> {
        if value.is_finite() && value > 0.0 && value <= hi {
            Ok(value)
        } else {
            Err(self.src.invalid(
                key,
                format!("{value} is out of range: it must be above 0 and at most {hi} {unit}"),
            ))
        }
    }

    fn finite3(&self, key: &str, v: [f64; 3]) -> Result<DVec3, ConfigError> {
        match v.iter().position(|c| !c.is_finite()) {
            Some(i) => Err(self
                .src
                .invalid(&format!("{key}[{i}]"), "must be a finite number")),
            None => Ok(DVec3::from_array(v)),
        }
    }
}

/// An instrument config's text with its secret (`[api] token`) taken out, for storing
/// with a run and serving as a download: the token line becomes a comment and the rest
/// keeps its layout. Text whose token cannot be cut out line by line (a multi-line
/// string, an inline table) is written back from its parsed form without the token;
/// text that does not parse keeps no line that mentions `token`.
pub fn redact_secrets(text: &str) -> String {
    const NOTE: &str = "# token = <redacted: secrets are not stored with runs>";
    let mut table = String::new();
    let mut out = String::with_capacity(text.len());
    for line in text.split_inclusive('\n') {
        let t = line.trim_start();
        if t.starts_with('[') {
            table = t
                .trim_start_matches('[')
                .split(']')
                .next()
                .unwrap_or("")
                .trim()
                .trim_matches('"')
                .to_owned();
        }
        let key = t.split('=').next().unwrap_or("").trim();
        let key = key.replace(['"', '\'', ' ', '\t'], "");
        let secret = t.contains('=')
            && !t.starts_with('#')
            && ((table == "api" && key == "token") || (table.is_empty() && key.starts_with("api.token")));
        if secret {
            out.push_str(NOTE);
            out.push('\n');
        } else {
            out.push_str(line);
        }
    }
    // The cut text is kept only if it means exactly the config without its token: a
    // multi-line token can leave part of itself behind, parsing as some other key
    // (`token = '''` then `abcdefghijklmnop=1#'''` left `api.abcdefghijklmnop`; a
    // backslash-joined `"""` string hides its pieces from any search for its lines).
    let without_token = text.parse::<toml::Table>().map(|mut whole| {
        if let Some(api) = whole.get_mut("api").and_then(|a| a.as_table_mut()) {
            api.remove("token");
        }
        whole
    });
    match (out.parse::<toml::Table>(), without_token) {
        (Ok(cut), Ok(whole)) if cut == whole => out,
        (_, Ok(whole)) => format!("{NOTE}\n{}", toml::to_string(&whole).unwrap_or_default()),
        (_, Err(_)) => text
            .lines()
            .filter(|l| !l.contains("token"))
            .map(|l| format!("{l}\n"))
            .collect(),
    }
}

impl InstrumentConfig {
    /// Loads and validates the instrument config at `path`.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        Self::from_source(&TomlSource::load(path)?)
    }

    /// Validates an instrument config held in memory.
    pub fn from_source(src: &TomlSource) -> Result<Self, ConfigError> {
        let raw: RawInstrument = src.parse()?;
        let check = Check { src };
        if raw.name.trim().is_empty() {
            return Err(src.invalid("name", "must not be empty: give the instrument a name"));
        }
        let hardware = raw.backend == RawBackend::Hardware;
        let laser_arm = galvo_arm(&check, "galvo.laser", raw.galvo.laser, hardware)?;
        let spad_arm = galvo_arm(&check, "galvo.spad", raw.galvo.spad, hardware)?;
        arms_apart(src, &laser_arm, &spad_arm)?;
        let raw_daq_laser = RawDaqLaser {
            laser_line: raw.laser.laser_line.clone(),
            interlock_line: raw.laser.interlock_line.clone(),
            diffuser_line: raw.laser.diffuser_line.clone(),
            heartbeat_line: raw.laser.heartbeat_line.clone(),
            daq_watchdog: raw.laser.daq_watchdog,
            accept_no_watchdog: raw.laser.accept_no_watchdog,
        };
        let laser = LaserSettings {
            wavelength: check.range(
                "laser.wavelength-nm",
                raw.laser.wavelength_nm,
                200.0,
                2500.0,
                "nm",
            )? * 1e-9,
            power: check.positive("laser.power-mw", raw.laser.power_mw, 1e5, "mW")? * 1e-3,
            repetition_rate: check.positive("laser.rep-rate-mhz", raw.laser.rep_rate_mhz, 1e4, "MHz")? * 1e6,
            watchdog: {
                let range = periscope_drivers::galvo::protocol::WATCHDOG_RANGE_MS;
                let ms = check.range(
                    "laser.watchdog-ms",
                    raw.laser.watchdog_ms,
                    f64::from(*range.start()),
                    f64::from(*range.end()),
                    "ms (the controller cannot switch its watchdog off)",
                )?;
                Duration::from_millis(ms.round() as u64)
            },
            stall: {
                let ms = check.range(
                    "laser.stall-ms",
                    raw.laser.stall_ms,
                    100.0,
                    600_000.0,
                    "ms (how long a run may show no progress with the laser on)",
                )?;
                Duration::from_millis(ms.round() as u64)
            },
            daqmx: None,
        };
        let laser = LaserSettings {
            daqmx: match &laser_arm.link {
                Some(GalvoLink::Daqmx(arm)) => Some(daqmx::laser(
                    src,
                    raw_daq_laser,
                    arm.library.clone(),
                    laser.watchdog,
                )?),
                _ => {
                    daqmx::refuse_keys(
                        src,
                        "laser",
                        &raw_daq_laser.given(),
                        "is a laser line on a DAQ device, read only with galvo.laser.driver = \"daqmx\": remove it (with a serial controller the laser is on the controller)",
                    )?;
                    None
                }
            },
            ..laser
        };
        // A DAQmx pair ramps on the run's thread, a step a millisecond, and settles after
        // its last write; the two pairs move one after the other with nothing to show
        // progress. Moves that could outlast the stall rule would have the keepalive stop
        // and the watchdog end emission on every long move.
        let ramp_ms = |arm: &GalvoArm| match &arm.link {
            Some(GalvoLink::Daqmx(d)) => {
                let span = (d.limits.x[1] - d.limits.x[0])
                    .max(d.limits.y[1] - d.limits.y[0])
                    .to_degrees();
                (span / d.max_slew_deg_per_ms).ceil() + d.settle.as_secs_f64() * 1e3
            }
            _ => 0.0,
        };
        let moves_ms = ramp_ms(&laser_arm) + ramp_ms(&spad_arm);
        if moves_ms >= laser.stall.as_secs_f64() * 1e3 {
            return Err(src.invalid(
                "laser.stall-ms",
                format!(
                    "is {} ms, but a pair's moves across the DAQmx galvos' limits take up to {moves_ms:.0} ms (max-slew-deg-per-ms and settle-us), with nothing to show progress: the stall rule would stop the keepalive mid-move; raise stall-ms or the slew limit",
                    laser.stall.as_millis()
                ),
            ));
        }
        let spad = SpadSettings {
            efficiency: check.positive("spad.efficiency", raw.spad.efficiency, 1.0, "(a fraction)")?,
            dark_count_rate: check.range(
                "spad.dark-count-rate-hz",
                raw.spad.dark_count_rate_hz,
                0.0,
                1e8,
                "Hz",
            )?,
            dead_time: check.range("spad.dead-time-ns", raw.spad.dead_time_ns, 0.0, 1e6, "ns")? * 1e-9,
            jitter_fwhm: check.range("spad.jitter-fwhm-ps", raw.spad.jitter_fwhm_ps, 0.0, 1e5, "ps")? * 1e-12,
        };
        let tdc = tdc_settings(&check, raw.tdc, hardware)?;
        if let Some((end, period)) = window_past_period(
            tdc.offset,
            tdc.bins,
            tdc.bin_width,
            tdc.sync_divider,
            laser.repetition_rate,
        ) {
            return Err(src.invalid(
                "tdc.offset-ns",
                format!(
                    "with tdc.bins and tdc.bin-width-ps the window ends at {:.2} ns, past the sync period of {:.2} ns (laser.rep-rate-mhz {}, tdc.sync-divider {}): a counter times each photon from the last sync, so the window must end within it; fewer or narrower bins, an earlier offset, or a larger divider",
                    end * 1e9,
                    period * 1e9,
                    laser.repetition_rate * 1e-6,
                    tdc.sync_divider
                ),
            ));
        }
        // The sync check reads the counter's rate meter, which counts over gates of
        // 100 ms (Periscope's counter; PicoQuant's are as long): below ten syncs a gate
        // it reads nothing, and the run would fail blaming the sync cable.
        let sync_hz = laser.repetition_rate / f64::from(tdc.sync_divider);
        // A sync out of range names the divider where there is one, else the laser.
        let sync_key = if tdc.sync_divider > 1 {
            "tdc.sync-divider"
        } else {
            "laser.rep-rate-mhz"
        };
        let sync_is = format!(
            "laser.rep-rate-mhz = {} over tdc.sync-divider = {} gives {} of sync",
            laser.repetition_rate / 1e6,
            tdc.sync_divider,
            hz_text(sync_hz)
        );
        if sync_hz < MIN_SYNC_RATE_HZ {
            return Err(src.invalid(
                sync_key,
                format!(
                    "{sync_is}, under the {MIN_SYNC_RATE_HZ} Hz a counter's rate meter (100 ms gates) can read: every run would fail its sync check{}",
                    if tdc.sync_divider > 1 && matches!(tdc.driver, TdcDriver::PicoQuant(_)) {
                        " (PicoQuant counters take dividers of 1 to 16)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        // PicoQuant's inputs take the sync up to a rate after the divider (HHLib's and
        // MHLib's manuals, `SetSyncDiv`): above it the timing is not what the manual
        // specifies, whatever the check of the rate says.
        if let TdcDriver::PicoQuant(counter) = &tdc.driver {
            let most = counter.family.max_sync_rate_hz();
            if sync_hz > most {
                let least = (1..=16u32)
                    .filter(|&d| counter.family.sync_divider_ok(d))
                    .find(|&d| laser.repetition_rate / f64::from(d) <= most);
                return Err(src.invalid(
                    sync_key,
                    format!(
                        "{sync_is}, above the {} the {}'s sync input takes after its divider (its manual, SetSyncDiv): {}",
                        hz_text(most),
                        counter.family,
                        match least {
                            Some(d) => format!("set tdc.sync-divider = {d} or more"),
                            None => "no divider brings it down: use a slower laser".to_owned(),
                        }
                    ),
                ));
            }
        }
        let backend = match raw.backend {
            // A config never holds a setting nothing reads: a [sim] table left in a
            // config switched to the hardware would look as if it did something.
            RawBackend::Hardware if raw.sim.is_some() => {
                return Err(src.invalid(
                    "sim",
                    "is read only with backend = \"sim\" (the simulator's scene, true poses and optics): remove the [sim] table from a hardware config",
                ));
            }
            RawBackend::Hardware => Backend::Hardware,
            RawBackend::Sim => Backend::Sim(sim_settings(
                &check,
                raw.sim.unwrap_or_default(),
                [laser_arm.pose, spad_arm.pose],
                laser.repetition_rate,
            )?),
        };
        let api = api_settings(&check, raw.api.unwrap_or_default())?;
        let budget = budget_limits(&check, raw.budget.unwrap_or_default())?;
        Ok(Self {
            name: raw.name,
            backend,
            laser_arm,
            spad_arm,
            laser,
            spad,
            tdc,
            api,
            budget,
        })
    }

    /// The instrument as `periscope calibrate` runs it: the SPAD free-running, since
    /// the laser-spot scan needs the direct return that a gated SPAD blanks. On the
    /// simulator that is `sim.gate` off; a hardware SPAD's gate is set on its module,
    /// which the daemon does not drive (docs/calibration.md says what to set).
    pub fn with_spad_ungated(&self) -> InstrumentConfig {
        let mut config = self.clone();
        if let Backend::Sim(sim) = &mut config.backend {
            sim.gate_margin = None;
        }
        config
    }

    /// The sync rate the counter should read, hertz: the laser's pulse rate over the
    /// sync divider.
    pub fn expected_sync_rate(&self) -> f64 {
        self.laser.repetition_rate / f64::from(self.tdc.sync_divider.max(1))
    }

    /// What is wrong with a sync rate the counter read with the laser pulsing, if
    /// anything: none at all, or a rate more than [`SYNC_TOLERANCE`] from
    /// [`InstrumentConfig::expected_sync_rate`]. The pile-up correction counts laser
    /// cycles with the configured rate, and the window's check against the sync
    /// period rests on it, so a laser that pulses at another rate than its config says
    /// corrupts both silently. `after_divider` says whether the counter's meter counts
    /// after the divider ([`periscope_drivers::Histogrammer::sync_after_divider`]):
    /// before it, the laser's own rate is expected; where that is not known (`None`)
    /// and the divider is above 1, either passes.
    pub fn sync_fault(&self, measured_hz: f64, after_divider: Option<bool>) -> Option<String> {
        let (laser, divided) = (self.laser.repetition_rate, self.expected_sync_rate());
        let expected = if after_divider == Some(false) {
            laser
        } else {
            divided
        };
        let keys = format!(
            "laser.rep-rate-mhz = {} over tdc.sync-divider = {} gives {}{}",
            laser / 1e6,
            self.tdc.sync_divider,
            hz_text(divided),
            match after_divider {
                Some(false) => format!(
                    " ({} before the divider, where this counter counts)",
                    hz_text(laser)
                ),
                None if self.tdc.sync_divider > 1 => {
                    format!(" ({} if this counter counts before the divider)", hz_text(laser))
                }
                _ => String::new(),
            }
        );
        if !(measured_hz > 0.0) {
            return Some(format!(
                "the counter reads no sync pulses with the laser on, where {keys}: check the cable from the laser's sync output to the counter's sync input, and that the laser is pulsing"
            ));
        }
        let off = |rate: f64| (measured_hz / rate - 1.0).abs();
        let either = after_divider.is_none() && off(laser) <= SYNC_TOLERANCE;
        (off(expected) > SYNC_TOLERANCE && !either).then(|| {
            format!(
                "the counter reads a sync rate of {} with the laser on, {:.1} % off what {keys}: set laser.rep-rate-mhz (and tdc.sync-divider) to what the laser really does, since the pile-up correction and the window's check rest on them",
                hz_text(measured_hz),
                off(expected) * 100.0,
            )
        })
    }

    /// One line describing the instrument, for logs and `--help`-style summaries.
    pub fn summary(&self) -> String {
        let backend = match &self.backend {
            Backend::Sim(sim) => format!("simulated (seed {})", sim.seed),
            Backend::Hardware => "hardware".to_owned(),
        };
        format!(
            "instrument `{}`: {backend}, {} bins of {:.1} ps",
            self.name,
            self.tdc.bins,
            self.tdc.bin_width * 1e12
        )
    }
}

fn galvo_arm(check: &Check<'_>, key: &str, raw: RawGalvo, hardware: bool) -> Result<GalvoArm, ConfigError> {
    let src = check.src;
    let origin = check.finite3(&format!("{key}.origin"), raw.origin)?;
    let boresight = check.finite3(&format!("{key}.boresight"), raw.boresight)?;
    let up = check.finite3(&format!("{key}.up"), raw.up)?;
    let pose = GalvoPose::looking(origin, boresight, up)
        .ok_or_else(|| {
            src.invalid(
                &format!("{key}.boresight"),
                "must be a non-zero direction that is not parallel to `up`",
            )
        })?
        .with_scanner(raw.scanner.unwrap_or_default());
    let mut limits = [[0.0; 2]; 2];
    for (axis, name, range) in [(0, "x", raw.angle_limits_deg.x), (1, "y", raw.angle_limits_deg.y)] {
        let k = format!("{key}.angle-limits-deg.{name}");
        let lo = check.range(&format!("{k}[0]"), range[0], -89.0, 89.0, "degrees")?;
        let hi = check.range(&format!("{k}[1]"), range[1], -89.0, 89.0, "degrees")?;
        if lo >= hi {
            return Err(src.invalid(
                &k,
                format!("[{lo}, {hi}] is empty: write [min, max] with min < max"),
            ));
        }
        limits[axis] = [lo.to_radians(), hi.to_radians()];
    }
    let settle_us = check.range(&format!("{key}.settle-us"), raw.settle_us, 0.0, 1e6, "µs")?;
    let settle = Duration::from_secs_f64(settle_us * 1e-6);
    let limits = AngleLimits {
        x: limits[0],
        y: limits[1],
    };
    let raw_daq = RawDaqGalvo {
        channels: raw.channels,
        volts_per_deg: raw.volts_per_deg,
        offsets_v: raw.offsets_v,
        max_slew_deg_per_ms: raw.max_slew_deg_per_ms,
        library: raw.library,
    };
    let link = match raw.driver {
        RawGalvoDriver::Daqmx => {
            if raw.serial.is_some() {
                return Err(src.invalid(
                    &format!("{key}.serial"),
                    "names a serial controller, but driver = \"daqmx\" drives this pair from a DAQ's analog outputs: remove it",
                ));
            }
            if !hardware {
                return Err(src.invalid(
                    &format!("{key}.driver"),
                    "the DAQmx driver needs backend = \"hardware\": the simulated instrument has its own galvos \
                     (to run the driver against the simulator, see `standins` in docs/drivers.md)",
                ));
            }
            // Driven open loop: nothing says the mirrors have arrived but this wait
            // after the last write (a serial controller answers once settled).
            if settle_us <= 0.0 {
                return Err(src.invalid(
                    &format!("{key}.settle-us"),
                    "must be above 0 with driver = \"daqmx\": the pair is driven open loop, and the driver waits this long after the last write before it reports the mirrors settled (a data sheet's small-step settling time, typically 100-500 µs)",
                ));
            }
            let name = key.rsplit('.').next().unwrap_or(key);
            Some(GalvoLink::Daqmx(daqmx::galvo(
                src, key, name, raw_daq, limits, settle,
            )?))
        }
        RawGalvoDriver::Serial => {
            daqmx::refuse_galvo_keys(src, key, &raw_daq)?;
            raw.serial
                .map(|s| {
                    if s.port.trim().is_empty() {
                        return Err(src.invalid(
                            &format!("{key}.serial.port"),
                            "must name a serial device, e.g. /dev/ttyUSB0",
                        ));
                    }
                    if !(1..=60_000).contains(&s.timeout_ms) {
                        return Err(
                            src.invalid(&format!("{key}.serial.timeout-ms"), "must be 1 to 60,000 ms")
                        );
                    }
                    if !(300..=4_000_000).contains(&s.baud) {
                        // 0 would hang the line up on POSIX; a rate the adapter cannot
                        // make shows only as timeouts.
                        return Err(src.invalid(
                            &format!("{key}.serial.baud"),
                            "must be 300 to 4,000,000 baud: the controller's rate (docs/protocols/galvo-serial.md)",
                        ));
                    }
                    Ok(GalvoLink::Serial(SerialLink {
                        port: s.port,
                        baud: s.baud,
                        timeout: Duration::from_millis(s.timeout_ms),
                    }))
                })
                .transpose()?
        }
    };
    if hardware && link.is_none() {
        return Err(src.invalid(
            key,
            format!(
                "backend = \"hardware\" needs a [{key}.serial] table with the controller's `port`, \
                 or driver = \"daqmx\" with the pair's analog output channels"
            ),
        ));
    }
    if hardware && raw.scanner.is_none() {
        // The default (one pivot) is the simulator's: on a real galvo pair it places
        // relay points millimetres off, with nothing to say so.
        return Err(src.invalid(
            &format!("{key}.scanner"),
            "is required with backend = \"hardware\": \"two-mirror\" for a galvo pair (the x mirror first, \
             then the y mirror), or \"pivot\" for a scanner with one pivot for both angles; the two place a \
             relay point millimetres apart (docs/configuration.md)",
        ));
    }
    Ok(GalvoArm {
        pose,
        limits,
        settle,
        link,
    })
}

/// How far a sync rate the counter reads may lie from the configured one
/// ([`InstrumentConfig::sync_fault`]): 2 %. A pulsed diode's or a mode-locked laser's
/// rate holds to far better; a wrong preset, divider or laser is off by far more.
pub const SYNC_TOLERANCE: f64 = 0.02;

/// A rate in the unit that reads best: MHz, kHz or Hz.
/// `ns` (an offset) in seconds, if it is a whole number of picoseconds: counters place
/// their window in whole picoseconds.
pub fn whole_ps_offset(ns: f64) -> Option<f64> {
    let ps = (ns * 1e3).round();
    ((ns * 1e3 - ps).abs() <= 1e-6).then_some(ps * 1e-12)
}

/// The slowest sync (laser pulses over the divider) a config may give, hertz: ten in
/// each of the rate meter's 100 ms gates.
const MIN_SYNC_RATE_HZ: f64 = 100.0;

fn hz_text(hz: f64) -> String {
    if hz >= 1e6 {
        format!("{:.4} MHz", hz * 1e-6)
    } else if hz >= 1e3 {
        format!("{:.3} kHz", hz * 1e-3)
    } else if hz >= 10.0 {
        format!("{hz:.0} Hz")
    } else {
        format!("{hz:.3} Hz")
    }
}

/// Where a window of `bins` bins of `bin_width` from `offset` (seconds) ends and the
/// sync period (`sync_divider` pulses of a laser at `repetition_rate`), if it ends past
/// it: a TDC times each photon from the last sync, so such a window records nothing at
/// its end and folds longer returns into its first bins.
pub(crate) fn window_past_period(
    offset: f64,
    bins: u32,
    bin_width: f64,
    sync_divider: u32,
    repetition_rate: f64,
) -> Option<(f64, f64)> {
    let period = f64::from(sync_divider) / repetition_rate;
    let end = offset + f64::from(bins) * bin_width;
    (end > period * (1.0 + 1e-9)).then_some((end, period))
}

fn tdc_settings(check: &Check<'_>, raw: RawTdc, hardware: bool) -> Result<TdcSettings, ConfigError> {
    let src = check.src;
    // As a plan's acquisition.bins and bin-width-ps: the counter bins in whole
    // picoseconds, and a histogram holds at least 16 bins.
    if !(16..=65_536).contains(&raw.bins) {
        return Err(src.invalid(
            "tdc.bins",
            format!("{} is out of range: it must lie between 16 and 65536", raw.bins),
        ));
    }
    if !(raw.bin_width_ps >= 1.0 && raw.bin_width_ps.fract() == 0.0) {
        return Err(src.invalid(
            "tdc.bin-width-ps",
            format!(
                "{} is not a whole number of picoseconds of at least 1: the counter bins in whole picoseconds (12.5 would be binned at 13, and the time axis read at 12.5)",
                raw.bin_width_ps
            ),
        ));
    }
    if raw.sync_divider == 0 {
        return Err(src.invalid("tdc.sync-divider", "must be at least 1"));
    }
    let usb = raw
        .usb
        .as_ref()
        .map(|text| {
            text.parse::<UsbSelector>()
                .map_err(|err| src.invalid("tdc.usb", err.to_string()))
        })
        .transpose()?;
    let driver = tdc_driver(check, &raw, hardware)?;
    if !hardware && usb.is_some() {
        return Err(src.invalid(
            "tdc.usb",
            "names a USB histogrammer, but backend = \"sim\" has its own: remove it, or set backend = \"hardware\"",
        ));
    }
    if hardware && driver == TdcDriver::Usb && usb.is_none() {
        return Err(src.invalid(
            "tdc",
            "backend = \"hardware\" needs `usb = \"VID:PID\"` naming the histogrammer (or `driver = \"multiharp\"`/`\"hydraharp\"` for a PicoQuant counter); `periscope devices` lists what is plugged in",
        ));
    }
    Ok(TdcSettings {
        bin_width: check.positive("tdc.bin-width-ps", raw.bin_width_ps, 1e6, "ps")? * 1e-12,
        bins: raw.bins,
        offset: whole_ps_offset(check.range("tdc.offset-ns", raw.offset_ns, 0.0, 1e6, "ns")?)
            .ok_or_else(|| {
                src.invalid(
                    "tdc.offset-ns",
                    format!(
                        "{} ns is not a whole number of picoseconds: counters place the window in whole picoseconds",
                        raw.offset_ns
                    ),
                )
            })?,
        sync_divider: raw.sync_divider,
        system_delay: check.range("tdc.system-delay-ns", raw.system_delay_ns, -1e3, 1e3, "ns")? * 1e-9,
        pile_up_correction: raw.pile_up_correction,
        usb,
        driver,
    })
}

/// `tdc.driver` and the keys that go with it: the PicoQuant keys are refused with the
/// `usb` driver, the edge keys on a HydraHarp and the zero-cross keys on a MultiHarp,
/// so a config never holds a setting nothing reads.
fn tdc_driver(check: &Check<'_>, raw: &RawTdc, hardware: bool) -> Result<TdcDriver, ConfigError> {
    let src = check.src;
    let family = match raw.driver {
        RawTdcDriver::Usb => None,
        RawTdcDriver::Multiharp => Some(Family::MultiHarp),
        RawTdcDriver::Hydraharp => Some(Family::HydraHarp),
    };
    let picoquant_keys = [
        ("tdc.library", raw.library.is_some()),
        ("tdc.serial", raw.serial.is_some()),
        ("tdc.channel", raw.channel.is_some()),
        ("tdc.sync-level-mv", raw.sync_level_mv.is_some()),
        ("tdc.input-level-mv", raw.input_level_mv.is_some()),
        ("tdc.sync-edge", raw.sync_edge.is_some()),
        ("tdc.input-edge", raw.input_edge.is_some()),
        ("tdc.sync-zero-cross-mv", raw.sync_zero_cross_mv.is_some()),
        ("tdc.input-zero-cross-mv", raw.input_zero_cross_mv.is_some()),
        ("tdc.input-offset-ps", raw.input_offset_ps.is_some()),
    ];
    let Some(family) = family else {
        if let Some((key, _)) = picoquant_keys.iter().find(|(_, given)| *given) {
            return Err(src.invalid(
                key,
                "is a PicoQuant counter's setting: add `driver = \"multiharp\"` or `\"hydraharp\"` to [tdc], or remove it",
            ));
        }
        return Ok(TdcDriver::Usb);
    };
    if !hardware {
        return Err(src.invalid(
            "tdc.driver",
            format!(
                "the {family} driver needs backend = \"hardware\": the simulated instrument has its own histogrammer \
                 (to run the driver against the simulator, see `standins` in docs/drivers.md)"
            ),
        ));
    }
    if raw.usb.is_some() {
        return Err(src.invalid(
            "tdc.usb",
            format!("names a USB histogrammer, but tdc.driver picks a {family}: remove it"),
        ));
    }
    let (foreign, own) = if family.uses_cfd() {
        (
            [
                ("tdc.sync-edge", raw.sync_edge.is_some()),
                ("tdc.input-edge", raw.input_edge.is_some()),
            ],
            "a HydraHarp's inputs are constant-fraction discriminators: give `sync-zero-cross-mv`/`input-zero-cross-mv`",
        )
    } else {
        (
            [
                ("tdc.sync-zero-cross-mv", raw.sync_zero_cross_mv.is_some()),
                ("tdc.input-zero-cross-mv", raw.input_zero_cross_mv.is_some()),
            ],
            "a MultiHarp's inputs are edge triggers: give `sync-edge`/`input-edge` (\"rising\" or \"falling\")",
        )
    };
    if let Some((key, _)) = foreign.iter().find(|(_, given)| *given) {
        return Err(src.invalid(key, own));
    }
    let whole = |key: &str, v: f64, lo: f64, hi: f64, unit: &str| -> Result<i32, ConfigError> {
        let v = check.range(key, v, lo, hi, unit)?;
        if v.fract() != 0.0 {
            return Err(src.invalid(key, format!("{v} is not a whole number of {unit}")));
        }
        Ok(v as i32)
    };
    let trigger = |side: &str,
                   level: Option<f64>,
                   edge: Option<RawEdge>,
                   zc: Option<f64>|
     -> Result<Trigger, ConfigError> {
        Ok(match family.default_trigger() {
            Trigger::Edge { level_mv, rising } => Trigger::Edge {
                level_mv: match level {
                    Some(v) => whole(&format!("tdc.{side}-level-mv"), v, -1200.0, 1200.0, "mV")?,
                    None => level_mv,
                },
                rising: edge.map_or(rising, |e| e == RawEdge::Rising),
            },
            Trigger::Cfd {
                level_mv,
                zero_cross_mv,
            } => Trigger::Cfd {
                level_mv: match level {
                    Some(v) => whole(&format!("tdc.{side}-level-mv"), v, 0.0, 1000.0, "mV")?,
                    None => level_mv,
                },
                zero_cross_mv: match zc {
                    Some(v) => whole(&format!("tdc.{side}-zero-cross-mv"), v, 0.0, 40.0, "mV")?,
                    None => zero_cross_mv,
                },
            },
        })
    };
    if !family.sync_divider_ok(raw.sync_divider) {
        return Err(src.invalid(
            "tdc.sync-divider",
            format!(
                "the {family} does not take sync divider {}: {}",
                raw.sync_divider,
                if family.uses_cfd() {
                    "use 1, 2, 4, 8 or 16"
                } else {
                    "use 1 to 16"
                }
            ),
        ));
    }
    let channel = match raw.channel {
        None => 0,
        Some(c) if (1..=64).contains(&c) => c - 1,
        Some(c) => {
            return Err(src.invalid(
                "tdc.channel",
                format!("{c} is not an input: inputs are numbered 1 to 64, from 1 as on the front panel"),
            ));
        }
    };
    if let Some(serial) = &raw.serial
        && (serial.is_empty() || serial.len() > 8 || !serial.chars().all(|c| c.is_ascii_alphanumeric()))
    {
        return Err(src.invalid(
            "tdc.serial",
            format!("`{serial}` is not a serial number (up to 8 letters and digits; `periscope devices` lists them)"),
        ));
    }
    Ok(TdcDriver::PicoQuant(PicoQuantCounter {
        family,
        library: raw
            .library
            .clone()
            .unwrap_or_else(|| PathBuf::from(family.default_library())),
        serial: raw.serial.clone(),
        channel,
        sync_trigger: trigger("sync", raw.sync_level_mv, raw.sync_edge, raw.sync_zero_cross_mv)?,
        input_trigger: trigger(
            "input",
            raw.input_level_mv,
            raw.input_edge,
            raw.input_zero_cross_mv,
        )?,
        input_offset_ps: match raw.input_offset_ps {
            Some(v) => whole("tdc.input-offset-ps", v, -99_999.0, 99_999.0, "ps")?,
            None => 0,
        },
    }))
}

/// Memory, disk and time limits for one run, from the instrument config's `[budget]`
/// table.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BudgetLimits {
    /// Most memory one run may need, bytes.
    pub memory: u64,
    /// Most disk one run may write, bytes.
    pub disk: u64,
    /// Longest one run may keep the instrument (its LOS scan and capture, by the
    /// plan's estimate), hours; `None`: no limit.
    pub hours: Option<f64>,
}

impl Default for BudgetLimits {
    /// 16 GiB of memory (two thirds of a 24 GiB machine, leaving the daemon, the OS and
    /// the page cache room) and 64 GiB of disk per run, and no limit on time.
    fn default() -> BudgetLimits {
        BudgetLimits {
            memory: 16 << 30,
            disk: 64 << 30,
            hours: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SIM: &str = include_str!("../../../configs/instrument/sim.toml");
    const LAB: &str = include_str!("../../../configs/instrument/lab.example.toml");

    fn load(text: &str) -> Result<InstrumentConfig, ConfigError> {
        InstrumentConfig::from_source(&TomlSource::from_text("test.toml", text))
    }

    /// `[api]` values that parsed but did not work: a fractional count rounded, a body
    /// limit of no bytes, a request timeout of nothing, an empty runs directory.
    #[test]
    fn api_values_that_cannot_work_are_refused_by_key() {
        let with = |line: &str| {
            let text = if SIM.contains("\n[api]\n") {
                SIM.replacen("\n[api]\n", &format!("\n[api]\n{line}\n"), 1)
            } else {
                format!("{SIM}\n[api]\n{line}\n")
            };
            load(&text)
        };
        for (line, key) in [
            ("max-queue = 1.5", "api.max-queue"),
            ("body-limit-kib = 0.0001", "api.body-limit-kib"),
            ("request-timeout-s = 1e-300", "api.request-timeout-s"),
            ("runs-dir = \"\"", "api.runs-dir"),
            // Positive but under a KiB: 0 bytes, every import refused (until 2026-12-07).
            ("import-limit-mib = 1e-7", "api.import-limit-mib"),
        ] {
            let e = with(line).unwrap_err();
            assert_eq!(e.key(), Some(key), "{line}: {e}");
        }
        let ok = with("max-queue = 3.0\nbody-limit-kib = 64\nrequest-timeout-s = 1").unwrap();
        assert_eq!(ok.api.max_queue, 3);
    }

    #[test]
    fn shipped_configs_are_valid() {
        let sim = load(SIM).unwrap();
        assert!(matches!(sim.backend, Backend::Sim(_)));
        let lab = load(LAB).unwrap();
        assert_eq!(lab.backend, Backend::Hardware);
        assert!(lab.tdc.usb.is_some() && lab.laser_arm.serial().is_some());
        // The lab's pairs are galvo pairs; the simulator's the ideal pivot.
        use periscope_drivers::Scanner;
        assert_eq!(lab.laser_arm.pose.scanner, Scanner::TwoMirror);
        assert_eq!(lab.spad_arm.pose.scanner, Scanner::TwoMirror);
        assert_eq!(sim.laser_arm.pose.scanner, Scanner::Pivot);
        let e = load(&LAB.replacen("scanner = \"two-mirror\"", "scanner = \"three-mirror\"", 1)).unwrap_err();
        assert!(
            e.to_string().contains("scanner") && e.to_string().contains("two-mirror"),
            "{e}"
        );
    }

    #[test]
    fn units_are_converted_to_si() {
        let sim = load(SIM).unwrap();
        assert!(sim.tdc.bin_width > 1e-12 && sim.tdc.bin_width < 1e-9);
        assert!(sim.laser.wavelength > 1e-7 && sim.laser.wavelength < 3e-6);
        assert!(sim.laser_arm.limits.x[1] < 1.6);
    }

    #[test]
    fn out_of_range_values_name_their_key_and_line() {
        let text = SIM.replace("efficiency = 0.3", "efficiency = 1.5");
        let line = text.lines().position(|l| l.starts_with("efficiency")).unwrap() + 1;
        let err = load(&text).unwrap_err();
        assert_eq!(err.key(), Some("spad.efficiency"), "{err}");
        assert_eq!(err.line(), Some(line), "{err}");
    }

    /// A hardware arm must say how its mirrors turn the ray: the default pivot is
    /// the simulator's, and on a galvo pair it places relay points millimetres off
    /// (until 2026-12-07 a lab config without `scanner` took it silently). Nor is a
    /// serial rate of 0 (a hang-up on POSIX) taken.
    #[test]
    fn a_hardware_arm_names_its_scanner_and_a_real_baud_rate() {
        let e = load(&LAB.replacen("scanner = \"two-mirror\"", "", 1)).unwrap_err();
        assert_eq!(e.key(), Some("galvo.laser.scanner"), "{e}");
        assert!(
            e.to_string().contains("two-mirror") && e.to_string().contains("pivot"),
            "{e}"
        );
        assert!(load(&LAB.replacen("scanner = \"two-mirror\"", "scanner = \"pivot\"", 1)).is_ok());
        for baud in ["0", "10000000"] {
            let e = load(&LAB.replacen("baud = 115200", &format!("baud = {baud}"), 1)).unwrap_err();
            assert_eq!(e.key(), Some("galvo.laser.serial.baud"), "{baud}: {e}");
        }
        assert!(load(&LAB.replacen("baud = 115200", "baud = 921600", 1)).is_ok());
    }

    /// A budget under a MiB is refused by key (until 2026-12-07 `memory-gib = 1e-10`
    /// made a budget of 0 bytes, which refused every plan as over it).
    #[test]
    fn a_budget_under_a_mib_is_refused_by_key() {
        for key in ["memory-gib", "disk-gib"] {
            let e = load(&format!("{SIM}\n[budget]\n{key} = 1e-10\n")).unwrap_err();
            assert_eq!(e.key(), Some(format!("budget.{key}").as_str()), "{e}");
        }
        let ok = load(&format!("{SIM}\n[budget]\nmemory-gib = 0.5\n")).unwrap();
        assert_eq!(ok.budget.memory, 1 << 29);
    }

    #[test]
    fn hardware_backend_requires_links() {
        let text = SIM.replace("backend = \"sim\"", "backend = \"hardware\"");
        let err = load(&text).unwrap_err().to_string();
        assert!(err.contains("galvo.laser") && err.contains("serial"), "{err}");
    }

    /// The lab example with its USB histogrammer swapped for `tdc_lines`.
    fn lab_with(tdc_lines: &str) -> String {
        LAB.replace(
            "usb = \"1d50:6189\"           # VID:PID, or VID:PID:SERIAL to pick one of several",
            tdc_lines,
        )
    }

    #[test]
    fn a_multiharp_takes_the_vendors_defaults() {
        let lab = load(&lab_with("driver = \"multiharp\"")).unwrap();
        let TdcDriver::PicoQuant(c) = &lab.tdc.driver else {
            panic!("{:?}", lab.tdc.driver)
        };
        assert_eq!(c.family, Family::MultiHarp);
        assert_eq!(c.library, PathBuf::from("/usr/local/lib64/mh150/mhlib.so"));
        assert_eq!((c.channel, c.serial.as_deref(), c.input_offset_ps), (0, None, 0));
        assert_eq!(c.sync_trigger, Family::MultiHarp.default_trigger());
        let lab = load(&lab_with(
            "driver = \"hydraharp\"\nserial = \"1012345\"\nchannel = 3\ninput-level-mv = 120\ninput-zero-cross-mv = 8\nlibrary = \"/opt/hhlib.so\"",
        ))
        .unwrap();
        let TdcDriver::PicoQuant(c) = &lab.tdc.driver else {
            panic!()
        };
        assert_eq!(
            (c.family, c.channel, c.serial.as_deref()),
            (Family::HydraHarp, 2, Some("1012345"))
        );
        assert_eq!(
            c.input_trigger,
            Trigger::Cfd {
                level_mv: 120,
                zero_cross_mv: 8
            }
        );
        assert_eq!(c.library, PathBuf::from("/opt/hhlib.so"));
        assert_eq!(load(LAB).unwrap().tdc.driver, TdcDriver::Usb);
        // The example the lab config carries in comments, uncommented.
        let mut example = lab_with("");
        let start = example.find("# driver = \"multiharp\"").unwrap();
        let block = example.split_off(start).replace("\n# ", "\n");
        let lab = load(&format!("{example}{}", &block[2..])).unwrap();
        assert!(
            matches!(lab.tdc.driver, TdcDriver::PicoQuant(ref c) if c.serial.as_deref() == Some("1045678"))
        );
    }

    #[test]
    fn counter_keys_that_nothing_would_read_are_refused_by_key_and_line() {
        let cases = [
            (
                "driver = \"multiharp\"\nsync-zero-cross-mv = 10",
                "tdc.sync-zero-cross-mv",
            ),
            (
                "driver = \"hydraharp\"\ninput-edge = \"rising\"",
                "tdc.input-edge",
            ),
            ("usb = \"1d50:6189\"\nserial = \"1045678\"", "tdc.serial"),
            ("driver = \"multiharp\"\nusb = \"1d50:6189\"", "tdc.usb"),
            ("driver = \"multiharp\"\nchannel = 0", "tdc.channel"),
            (
                "driver = \"multiharp\"\nsync-level-mv = -1500",
                "tdc.sync-level-mv",
            ),
            (
                "driver = \"multiharp\"\ninput-offset-ps = 12.5",
                "tdc.input-offset-ps",
            ),
            ("driver = \"hydraharp\"\nserial = \"12 34\"", "tdc.serial"),
        ];
        for (lines, key) in cases {
            let text = lab_with(lines);
            let err = load(&text).unwrap_err();
            assert_eq!(err.key(), Some(key), "{lines}: {err}");
            let last = lines.lines().last().unwrap();
            let line = text.lines().position(|l| l == last).unwrap() + 1;
            assert_eq!(err.line(), Some(line), "{lines}: {err}");
        }
        let text = lab_with("driver = \"hydraharp\"").replace("sync-divider = 1", "sync-divider = 3");
        assert_eq!(load(&text).unwrap_err().key(), Some("tdc.sync-divider"));
        // A sync faster than the counter's input takes after its divider (12.5 MHz on
        // the HydraHarp, 78 MHz on the MultiHarp): the divider that brings it down.
        let fast = |driver: &str, divider: u32| {
            lab_with(&format!("driver = \"{driver}\""))
                .replace("rep-rate-mhz = 10.0", "rep-rate-mhz = 40.0")
                .replace("sync-divider = 1", &format!("sync-divider = {divider}"))
        };
        let e = load(&fast("hydraharp", 1)).unwrap_err();
        assert_eq!(e.key(), Some("laser.rep-rate-mhz"), "{e}");
        assert!(
            e.to_string()
                .contains("above the 12.5000 MHz the HydraHarp's sync input takes")
                && e.to_string().contains("set tdc.sync-divider = 4 or more"),
            "{e}"
        );
        let e = load(&fast("hydraharp", 2)).unwrap_err();
        assert_eq!(e.key(), Some("tdc.sync-divider"), "{e}");
        assert!(load(&fast("hydraharp", 4)).is_ok());
        assert!(load(&fast("multiharp", 1)).is_ok());
        // The simulated instrument has its own histogrammer.
        let text = SIM.replace("[tdc]\n", "[tdc]\ndriver = \"multiharp\"\n");
        let err = load(&text).unwrap_err();
        assert_eq!(err.key(), Some("tdc.driver"), "{err}");
    }

    #[test]
    fn a_true_pose_keeps_the_configured_values_it_does_not_name() {
        let text = format!("{SIM}\n[sim.true-pose.spad]\norigin = [0.11, 0.0, 2.0]\n");
        let c = load(&text).unwrap();
        let Backend::Sim(sim) = &c.backend else {
            panic!("sim")
        };
        assert_eq!(sim.true_poses[0], c.laser_arm.pose);
        assert_eq!(sim.true_poses[1].origin, DVec3::new(0.11, 0.0, 2.0));
        assert_eq!(sim.true_poses[1].rotation, c.spad_arm.pose.rotation);
        let text = format!("{SIM}\n[sim.true-pose.laser]\nboresight = [0.0, 1.0, 0.0]\n");
        let err = load(&text).unwrap_err();
        assert_eq!(err.key(), Some("sim.true-pose.laser.boresight"), "{err}");
    }

    #[test]
    fn empty_angle_ranges_are_rejected() {
        let text = SIM.replacen("x = [-20.0, 20.0]", "x = [20.0, -20.0]", 1);
        let err = load(&text).unwrap_err();
        assert_eq!(err.key(), Some("galvo.laser.angle-limits-deg.x"), "{err}");
    }

    /// The lab example with its laser arm (and the laser) on a DAQ: `galvo` replaces
    /// the laser arm's serial line, `laser` is added to `[laser]`.
    fn daq_lab(galvo: &str, laser: &str) -> String {
        let serial = "serial = { port = \"/dev/ttyUSB0\", baud = 115200, timeout-ms = 200 }\n";
        LAB.replacen(serial, galvo, 1).replacen(
            "rep-rate-mhz = 10.0\n",
            &format!("rep-rate-mhz = 10.0\n{laser}"),
            1,
        )
    }

    const DAQ_GALVO: &str = "driver = \"daqmx\"\nchannels = [\"Dev1/ao0\", \"Dev1/ao1\"]\n\
                             volts-per-deg = [0.4, 0.4]\nmax-slew-deg-per-ms = 2.0\n";

    /// Two arms on one serial port, or on one analog output (NI-DAQmx's names read
    /// without regard to case), are refused by key: until 2026-12-07 they loaded and
    /// failed as the devices opened, with a resource error naming neither.
    #[test]
    fn two_arms_on_one_port_or_output_are_refused_by_key() {
        let e = load(&LAB.replacen("/dev/ttyUSB1", "/dev/ttyUSB0", 1)).unwrap_err();
        assert_eq!(e.key(), Some("galvo.spad.serial.port"), "{e}");
        let line = "laser-line = \"Dev1/port0/line0\"\n";
        let spad_serial = "serial = { port = \"/dev/ttyUSB1\", baud = 115200, timeout-ms = 200 }\n";
        let both = |spad: &str| daq_lab(DAQ_GALVO, line).replacen(spad_serial, spad, 1);
        let e = load(&both(
            &DAQ_GALVO
                .replace("Dev1/ao0", "dev1/AO1")
                .replace("\"Dev1/ao1\"", "\"Dev1/ao2\""),
        ))
        .unwrap_err();
        assert_eq!(e.key(), Some("galvo.spad.channels[0]"), "{e}");
        assert!(e.to_string().contains("galvo.laser.channels[1]"), "{e}");
        assert!(load(&both(&DAQ_GALVO.replace("ao0", "ao2").replace("ao1", "ao3"))).is_ok());
        let e = load(&daq_lab(&DAQ_GALVO.replace("\"Dev1/ao1\"", "\"dev1/AO0\""), line)).unwrap_err();
        assert_eq!(e.key(), Some("galvo.laser.channels"), "{e}");
    }

    /// A setting the backend does not read is refused by key, not ignored: the
    /// simulator's table in a hardware config, a USB histogrammer in a simulated one.
    #[test]
    fn what_the_backend_does_not_read_is_refused_by_key() {
        let e = load(&format!("{LAB}\n[sim]\nseed = 3\n")).unwrap_err();
        assert_eq!(e.key(), Some("sim"), "{e}");
        let e = load(&SIM.replacen("[tdc]\n", "[tdc]\nusb = \"1d50:6189\"\n", 1)).unwrap_err();
        assert_eq!(e.key(), Some("tdc.usb"), "{e}");
    }

    #[test]
    fn daqmx_galvos_and_laser_lines_load_and_errors_name_their_key() {
        let c = load(&daq_lab(DAQ_GALVO, "laser-line = \"Dev1/port0/line0\"\n")).unwrap();
        let Some(GalvoLink::Daqmx(arm)) = &c.laser_arm.link else {
            panic!("{:?}", c.laser_arm.link)
        };
        assert_eq!(arm.channels, ["Dev1/ao0".to_owned(), "Dev1/ao1".to_owned()]);
        assert_eq!(arm.offsets_v, [0.0, 0.0]);
        assert_eq!(
            arm.library,
            PathBuf::from(periscope_drivers::daqmx::DEFAULT_LIBRARY)
        );
        let l = c.laser.daqmx.as_ref().unwrap();
        assert!(l.hardware_watchdog && l.interlock_line.is_none() && !l.accept_no_watchdog);
        assert!(c.spad_arm.serial().is_some() && c.laser_arm.serial().is_none());

        let err = |galvo: &str, laser: &str| load(&daq_lab(galvo, laser)).unwrap_err();
        let e = err(DAQ_GALVO, "");
        assert_eq!(e.key(), Some("laser"), "{e}");
        assert!(e.to_string().contains("laser-line"), "{e}");
        let e = err(
            &DAQ_GALVO.replace("0.4, 0.4", "0.6, 0.4"),
            "laser-line = \"Dev1/port0/line0\"\n",
        );
        assert_eq!(e.key(), Some("galvo.laser.volts-per-deg"), "{e}");
        assert!(e.line().is_some() && e.to_string().contains("±10 V"), "{e}");
        let e = err(
            &DAQ_GALVO.replace("\"Dev1/ao1\"", "\"Dev1/ao0\""),
            "laser-line = \"Dev1/port0/line0\"\n",
        );
        assert_eq!(e.key(), Some("galvo.laser.channels"), "{e}");
        // Three channels, volts or offsets for a pair of mirrors: refused, not cut to two.
        for (from, to, key) in [
            (
                "\"Dev1/ao1\"]",
                "\"Dev1/ao1\", \"Dev1/ao2\"]",
                "galvo.laser.channels",
            ),
            ("0.4, 0.4", "0.4, 0.4, 99.0", "galvo.laser.volts-per-deg"),
        ] {
            let e = err(
                &DAQ_GALVO.replace(from, to),
                "laser-line = \"Dev1/port0/line0\"\n",
            );
            assert!(e.to_string().contains("exactly 2"), "{key}: {e}");
            assert!(
                e.to_string().contains(key.rsplit('.').next().unwrap()),
                "{key}: {e}"
            );
        }
        let e = err(
            &DAQ_GALVO.replace("max-slew-deg-per-ms = 2.0\n", ""),
            "laser-line = \"Dev1/port0/line0\"\n",
        );
        assert!(e.to_string().contains("max-slew-deg-per-ms"), "{e}");
        let e = err(
            DAQ_GALVO,
            "laser-line = \"Dev1/port0/line0\"\ndaq-watchdog = false\n",
        );
        assert_eq!(e.key(), Some("laser.daq-watchdog"), "{e}");
        let e = err(
            DAQ_GALVO,
            "laser-line = \"Dev1/port0/line0\"\ndiffuser-line = \"Dev1/port0/line0\"\n",
        );
        assert_eq!(e.key(), Some("laser.diffuser-line"), "{e}");
        // One line, one output: a whole port (eight lines the driver's one-byte writes
        // do not fill), a range or a list is refused by name.
        for (line, key) in [
            ("laser-line = \"Dev1/port0\"\n", "laser.laser-line"),
            ("laser-line = \"Dev1/port0/line0:3\"\n", "laser.laser-line"),
            (
                "laser-line = \"Dev1/port0/line0\"\ninterlock-line = \"Dev1/port1\"\n",
                "laser.interlock-line",
            ),
            ("laser-line = \"Dev1/line0\"\n", "laser.laser-line"),
        ] {
            let e = err(DAQ_GALVO, line);
            assert_eq!(e.key(), Some(key), "{line}: {e}");
            assert!(e.to_string().contains("Dev1/port0/line0"), "{e}");
        }
        let e = err(
            &DAQ_GALVO.replace("\"Dev1/ao1\"", "\"Dev1/port0\""),
            "laser-line = \"Dev1/port0/line0\"\n",
        );
        assert_eq!(e.key(), Some("galvo.laser.channels[1]"), "{e}");
        // DAQmx keys without the DAQmx driver are refused, not ignored.
        let serial = "serial = { port = \"/dev/ttyUSB0\", baud = 115200, timeout-ms = 200 }\n";
        let e = err(serial, "laser-line = \"Dev1/port0/line0\"\n");
        assert_eq!(e.key(), Some("laser.laser-line"), "{e}");
        let e = err(&format!("{serial}channels = [\"Dev1/ao0\", \"Dev1/ao1\"]\n"), "");
        assert_eq!(e.key(), Some("galvo.laser.channels"), "{e}");
        // Moves slower than the stall rule allows are refused by the stall rule's key.
        let e = load(&daq_lab(
            &DAQ_GALVO.replace("max-slew-deg-per-ms = 2.0", "max-slew-deg-per-ms = 0.005"),
            "laser-line = \"Dev1/port0/line0\"\n",
        ))
        .unwrap_err();
        assert_eq!(e.key(), Some("laser.stall-ms"), "{e}");
        // Open loop: a settling time is required.
        let e = load(
            &daq_lab(DAQ_GALVO, "laser-line = \"Dev1/port0/line0\"\n").replacen(
                "settle-us = 400.0",
                "settle-us = 0.0",
                1,
            ),
        )
        .unwrap_err();
        assert_eq!(e.key(), Some("galvo.laser.settle-us"), "{e}");
        // And only on the hardware backend.
        let e = load(&SIM.replacen(
            "settle-us = 300.0\n",
            &format!("settle-us = 300.0\n{DAQ_GALVO}"),
            1,
        ))
        .unwrap_err();
        assert_eq!(e.key(), Some("galvo.laser.driver"), "{e}");
    }

    /// The sync a counter reads is judged against `laser.rep-rate-mhz` over
    /// `tdc.sync-divider` (or the laser's own rate, for a meter that counts before the
    /// divider): within 2 % passes, none or further off is named with both keys.
    /// A sync too slow for the counter's rate meter to read (until 2026-12-06 any
    /// divider was taken, and every run failed its sync check blaming the cable).
    #[test]
    fn a_sync_too_slow_to_read_is_refused_naming_its_key() {
        let e = load(&SIM.replace("sync-divider = 1", "sync-divider = 4294967295")).unwrap_err();
        assert_eq!(e.key(), Some("tdc.sync-divider"), "{e}");
        assert!(
            e.to_string().contains("gives 0.002 Hz of sync, under the 100 Hz"),
            "{e}"
        );
        let e = load(&SIM.replace("rep-rate-mhz = 10.0", "rep-rate-mhz = 0.00005")).unwrap_err();
        assert_eq!(e.key(), Some("laser.rep-rate-mhz"), "{e}");
        assert!(load(&SIM.replace("sync-divider = 1", "sync-divider = 100000")).is_ok());
    }

    #[test]
    fn a_sync_rate_off_the_configured_one_is_named_with_its_keys() {
        let sim = load(&SIM.replace("sync-divider = 1", "sync-divider = 4")).unwrap();
        assert_eq!(sim.expected_sync_rate(), 2.5e6);
        let after = Some(true);
        assert_eq!(sim.sync_fault(2.5e6, after), None);
        assert_eq!(sim.sync_fault(2.5e6 * 1.019, after), None);
        assert_eq!(sim.sync_fault(2.5e6 * 0.981, after), None);
        // A meter that counts after the divider reading the laser's own rate is a laser
        // at four times the configured rate.
        for wrong in [2.5e6 * 1.03, 2.5e6 * 0.97, 10e6, 5e6, 20e6] {
            let e = sim
                .sync_fault(wrong, after)
                .expect("a rate 3 % or more off passed");
            assert!(
                e.contains("laser.rep-rate-mhz = 10 over tdc.sync-divider = 4 gives 2.5000 MHz")
                    && e.contains("% off"),
                "{e}"
            );
        }
        // A meter that counts before it expects the laser's rate; one not known, either.
        assert_eq!(sim.sync_fault(10e6 * 1.01, Some(false)), None);
        assert!(sim.sync_fault(2.5e6, Some(false)).is_some());
        assert_eq!(sim.sync_fault(10e6 * 1.01, None), None);
        assert_eq!(sim.sync_fault(2.5e6, None), None);
        let e = sim.sync_fault(5e6, None).unwrap();
        assert!(
            e.contains("10.0000 MHz if this counter counts before the divider"),
            "{e}"
        );
        let odd = load(&SIM.replace("rep-rate-mhz = 10.0", "rep-rate-mhz = 2.7")).unwrap();
        let e = odd.sync_fault(1e6, after).unwrap();
        assert!(e.contains("laser.rep-rate-mhz = 2.7 over"), "{e}");
        for none in [0.0, -1.0, f64::NAN] {
            let e = sim.sync_fault(none, after).expect("no sync passed");
            assert!(e.contains("no sync pulses") && e.contains("sync input"), "{e}");
        }
    }

    /// `sim.true-rep-rate-mhz` sets how the simulated laser really pulses, and is
    /// checked as the configured rate is.
    #[test]
    fn the_simulated_lasers_true_rate_is_the_configured_one_unless_set() {
        let rate = |text: &str| match load(text).map(|c| c.backend) {
            Ok(Backend::Sim(sim)) => Ok(sim.true_repetition_rate),
            Ok(b) => panic!("{b:?}"),
            Err(e) => Err(e),
        };
        assert_eq!(rate(SIM).unwrap(), 10e6);
        let with = |v: &str| SIM.replacen("[sim]\n", &format!("[sim]\ntrue-rep-rate-mhz = {v}\n"), 1);
        assert_eq!(rate(&with("20.0")).unwrap(), 20e6);
        for bad in ["0.0", "-5.0", "nan", "1e9"] {
            let e = rate(&with(bad)).unwrap_err();
            assert_eq!(e.key(), Some("sim.true-rep-rate-mhz"), "{bad}: {e}");
        }
    }
}

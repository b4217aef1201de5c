//! Capture plans (`configs/plans/*.toml`): what to scan, which pairs to measure, how
//! long, and how to reconstruct. Two stages like every config: a raw serde mirror of
//! the file, then a validated [`Plan`] whose errors name file, line and key.
mod pairs;
mod recon;

use std::path::Path;
use std::time::Duration;

use glam::DVec3;
use periscope_recon::relay::Region;
use serde::Deserialize;

pub use pairs::{PairMode, PlannedPair, RelayView, plan_pairs};
pub use recon::{LaserFalloff, Method, ReconSettings, VirtualScan, check_recon, default_recon, load_recon};

use crate::config::{ConfigError, InstrumentConfig, TomlSource};

/// A validated capture plan.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Name, for run ids and summaries.
    pub name: String,
    /// The LOS first-bounce scan.
    pub los: LosStage,
    /// Turning LOS points into the relay.
    pub relay: RelayStage,
    /// Which pairs to measure: all of them, or (`adaptive`) the candidates the running
    /// fit chooses from.
    pub pairs: PairMode,
    /// Whether the capture is adaptive (`[pairs] mode = "adaptive"`): `pairs` lays out
    /// the candidates, and `recon.adaptive` says how many are measured and how they
    /// are chosen (docs/adaptive.md).
    pub adaptive: bool,
    /// How each pair is measured.
    pub acquisition: Acquisition,
    /// How the hidden scene is reconstructed.
    pub recon: ReconSettings,
    /// Conditions that suspend the capture with the laser off.
    pub suspend: Suspenders,
}

/// Suspenders (Bluesky's word): conditions watched during a run that switch the laser
/// off and hold the run until they clear. The interlock is always watched.
#[derive(Clone, Debug, PartialEq)]
pub struct Suspenders {
    /// Consecutive histograms flagged overflow or saturated that suspend the capture
    /// (0: never).
    pub flagged_frames: u32,
    /// Detector count rate above which the capture is suspended, hertz (pile-up, a
    /// bright object in the path).
    pub max_count_rate: f64,
    /// Who resumes a suspended run.
    pub resume: SuspendResume,
}

/// Who resumes a suspended run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SuspendResume {
    /// The run pauses (laser off, arms parked); an operator resumes it.
    Operator,
    /// The run waits with the laser off and goes on by itself once the condition has
    /// stayed clear this long (for a rate or flag suspender: once this long has passed,
    /// with the pair measured again to check).
    Auto {
        /// How long the condition must stay clear.
        clear_for: Duration,
    },
}

/// The LOS scan: the SPAD arm sweeps a grid of optical angles under the diffused laser.
#[derive(Clone, Debug, PartialEq)]
pub struct LosStage {
    /// θx range, radians.
    pub x: [f64; 2],
    /// θy range, radians.
    pub y: [f64; 2],
    /// Points along θx and θy.
    pub grid: [usize; 2],
    /// Dwell per point.
    pub dwell: Duration,
}

/// Relay extraction.
#[derive(Clone, Debug, PartialEq)]
pub struct RelayStage {
    /// Depth window along the SPAD ray, metres.
    pub depth: [f64; 2],
    /// Intensity floor as a fraction of the brightest LOS return.
    pub min_intensity: f64,
    /// Neighbours for normals.
    pub neighbours: usize,
    /// Where the laser may point.
    pub illumination: Region,
    /// Where the SPAD may look.
    pub detection: Region,
    /// Whether each transient's known gain is the relay's albedo at its two spots,
    /// read from the LOS scan's first-bounce counts ([`periscope_recon::relay::RelayAlbedo`]).
    pub albedo_from_scan: bool,
}

/// The fewest and most bins a plan's histogram may have (`acquisition.bins`).
pub(crate) const MIN_BINS: u32 = 16;
pub(crate) const MAX_BINS: u32 = 65_536;
/// The latest offset a plan may give its TDC window (`acquisition.offset-ns`), ns.
pub(crate) const MAX_OFFSET_NS: f64 = 1e6;

/// Per-pair acquisition.
#[derive(Clone, Debug, PartialEq)]
pub struct Acquisition {
    /// Dwell per histogram.
    pub dwell: Duration,
    /// Bins (default: the instrument's).
    pub bins: u32,
    /// Bin width, seconds.
    pub bin_width: f64,
    /// TDC offset, seconds.
    pub offset: f64,
    /// Histograms summed per pair.
    pub repeats: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawPlan {
    name: String,
    los: RawLos,
    #[serde(default)]
    relay: RawRelay,
    pairs: pairs::RawPairs,
    acquisition: RawAcquisition,
    recon: recon::RawRecon,
    #[serde(default)]
    suspend: RawSuspend,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawSuspend {
    flagged_frames: Option<u32>,
    max_count_rate_hz: Option<f64>,
    resume: Option<String>,
    clear_for_s: Option<f64>,
}

/// Default consecutive flagged frames that suspend a capture.
const DEFAULT_FLAGGED_FRAMES: u32 = 3;

/// Default count-rate limit, as a fraction of the laser's pulse rate: the TDC flags
/// pile-up at 5 %; twice that means something bright is in the path.
const DEFAULT_RATE_FRACTION: f64 = 0.1;

/// Default time a condition must stay clear before an automatic resume.
const DEFAULT_CLEAR_FOR_S: f64 = 5.0;

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawLos {
    angles_deg: RawAngles,
    #[serde(deserialize_with = "crate::config::exact::array")]
    grid: [usize; 2],
    dwell_ms: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawAngles {
    #[serde(deserialize_with = "crate::config::exact::array")]
    x: [f64; 2],
    #[serde(deserialize_with = "crate::config::exact::array")]
    y: [f64; 2],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawRelay {
    #[serde(deserialize_with = "crate::config::exact::array", default = "default_depth")]
    depth_m: [f64; 2],
    #[serde(default = "default_intensity")]
    min_intensity: f64,
    #[serde(default = "default_neighbours")]
    neighbours: usize,
    illumination: Option<RawRegion>,
    detection: Option<RawRegion>,
    #[serde(default = "default_albedo_from_scan")]
    albedo_from_scan: bool,
}

impl Default for RawRelay {
    fn default() -> Self {
        RawRelay {
            depth_m: default_depth(),
            min_intensity: default_intensity(),
            neighbours: default_neighbours(),
            illumination: None,
            detection: None,
            albedo_from_scan: default_albedo_from_scan(),
        }
    }
}

fn default_albedo_from_scan() -> bool {
    true
}

fn default_depth() -> [f64; 2] {
    [0.2, 10.0]
}
fn default_intensity() -> f64 {
    0.05
}
fn default_neighbours() -> usize {
    16
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawRegion {
    #[serde(deserialize_with = "crate::config::exact::array")]
    min: [f64; 3],
    #[serde(deserialize_with = "crate::config::exact::array")]
    max: [f64; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawAcquisition {
    dwell_ms: f64,
    bins: Option<u32>,
    bin_width_ps: Option<f64>,
    offset_ns: Option<f64>,
    #[serde(default = "default_repeats")]
    repeats: u32,
}

fn default_repeats() -> u32 {
    1
}

impl Plan {
    /// Whether a run of this plan has its 3D-GTR fit estimate per-transient gains
    /// (`recon.gtr.pair-gains`, resolved on a run's data by
    /// [`periscope_recon::gtr::PairGains::resolve`]): per illumination point where the
    /// laser visits more than one, where asked for or (`auto`) where the relay scan
    /// gives no gains; per detection point where asked for. Each round renders the
    /// whole capture.
    pub fn estimates_gains(&self) -> bool {
        use periscope_recon::gtr::PairGains;
        let scans = !matches!(self.pairs, PairMode::FixedLaser { .. });
        self.recon.method == Method::Gtr
            && match self.recon.train.pair_gains {
                PairGains::None => false,
                PairGains::Illumination => scans,
                PairGains::Detection => true,
                PairGains::Auto => scans && !self.relay.albedo_from_scan,
            }
    }

    /// Loads and validates a plan for an instrument.
    pub fn load(path: &Path, instrument: &InstrumentConfig) -> Result<Plan, ConfigError> {
        Self::from_source(&TomlSource::load(path)?, instrument)
    }

    /// Validates a plan held in memory, as a new run's: besides every value, that the
    /// instrument can carry it out (the LOS scan within the SPAD arm's limits and
    /// enough points for the relay, a solver the layout's pairs suit).
    pub fn from_source(src: &TomlSource, instrument: &InstrumentConfig) -> Result<Plan, ConfigError> {
        Self::read(src, instrument, true)
    }

    /// Reads the plan a run stored when it was made: every value is validated, but not
    /// what [`Plan::from_source`] asks of a new run beyond them, so a run a later
    /// version would refuse to start still opens, and its data stays readable.
    pub fn stored(src: &TomlSource, instrument: &InstrumentConfig) -> Result<Plan, ConfigError> {
        Self::read(src, instrument, false)
    }

    fn read(src: &TomlSource, instrument: &InstrumentConfig, new: bool) -> Result<Plan, ConfigError> {
        let raw: RawPlan = src.parse()?;
        if raw.name.trim().is_empty() || raw.name.len() > 64 {
            return Err(src.invalid("name", "must be 1 to 64 bytes long (64 ASCII characters)"));
        }
        // A run stored before control characters were refused still opens.
        if let Some(c) = raw.name.chars().find(|c| new && c.is_control()) {
            return Err(src.invalid(
                "name",
                format!(
                    "holds the control character {:?}: a plan's name is one line of text (it names the run and is written into every export)",
                    c
                ),
            ));
        }
        let los = {
            let l = &raw.los;
            for (k, r) in [
                ("los.angles-deg.x", l.angles_deg.x),
                ("los.angles-deg.y", l.angles_deg.y),
            ] {
                if !(r[0].is_finite() && r[1].is_finite() && r[1] > r[0]) {
                    return Err(src.invalid(
                        k,
                        format!("must be [min, max] in degrees with max > min, got {r:?}"),
                    ));
                }
            }
            if l.grid.iter().any(|&n| !(2..=1024).contains(&n)) {
                return Err(src.invalid("los.grid", "must be two counts, 2 to 1024"));
            }
            // The SPAD arm scans the LOS grid (the laser parked, its diffuser in): a
            // corner past its limits would fail the run at that point with the laser on.
            let lim = instrument.spad_arm.limits;
            let (lim, neighbours) = if new {
                (lim, raw.relay.neighbours.max(8))
            } else {
                (
                    periscope_drivers::AngleLimits {
                        x: [f64::NEG_INFINITY, f64::INFINITY],
                        y: [f64::NEG_INFINITY, f64::INFINITY],
                    },
                    0,
                )
            };
            for (k, r, allowed) in [
                ("los.angles-deg.x", l.angles_deg.x, lim.x),
                ("los.angles-deg.y", l.angles_deg.y, lim.y),
            ] {
                let within = |a: f64| (allowed[0]..=allowed[1]).contains(&a.to_radians());
                if !(within(r[0]) && within(r[1])) {
                    return Err(src.invalid(
                        k,
                        format!(
                            "is [{}, {}]°, past the SPAD arm's limits [{:.2}, {:.2}]° (the instrument's galvo.spad.angle-limits-deg): narrow the scan",
                            r[0],
                            r[1],
                            allowed[0].to_degrees(),
                            allowed[1].to_degrees()
                        ),
                    ));
                }
            }
            if l.grid[0] * l.grid[1] < neighbours {
                return Err(src.invalid(
                    "los.grid",
                    format!(
                        "gives {} LOS points, fewer than the {neighbours} the relay needs (relay.neighbours, and at least 8) before any is left out: give a finer grid",
                        l.grid[0] * l.grid[1]
                    ),
                ));
            }
            LosStage {
                x: l.angles_deg.x.map(f64::to_radians),
                y: l.angles_deg.y.map(f64::to_radians),
                grid: l.grid,
                dwell: dwell(src, "los.dwell-ms", l.dwell_ms)?,
            }
        };
        let region = |key: &str, r: &Option<RawRegion>| -> Result<Region, ConfigError> {
            match r {
                None => Ok(Region::All),
                Some(r) => {
                    let (min, max) = (DVec3::from_array(r.min), DVec3::from_array(r.max));
                    if !(min.is_finite() && max.is_finite() && min.cmplt(max).all()) {
                        return Err(src.invalid(key, "must be a box with min < max on every axis, in metres"));
                    }
                    Ok(Region::Box { min, max })
                }
            }
        };
        let relay = RelayStage {
            depth: {
                let d = raw.relay.depth_m;
                if !(d[0] >= 0.0 && d[1] > d[0] && d[1].is_finite()) {
                    return Err(src.invalid(
                        "relay.depth-m",
                        "must be [near, far] in metres with 0 ≤ near < far",
                    ));
                }
                d
            },
            min_intensity: {
                let v = raw.relay.min_intensity;
                if !(0.0..1.0).contains(&v) {
                    return Err(src.invalid(
                        "relay.min-intensity",
                        "must be a fraction in [0, 1) of the brightest return",
                    ));
                }
                v
            },
            neighbours: {
                let k = raw.relay.neighbours;
                if !(3..=256).contains(&k) {
                    return Err(src.invalid("relay.neighbours", "must be 3 to 256"));
                }
                k
            },
            illumination: region("relay.illumination", &raw.relay.illumination)?,
            detection: region("relay.detection", &raw.relay.detection)?,
            albedo_from_scan: raw.relay.albedo_from_scan,
        };
        let adaptive = raw.pairs.is_adaptive();
        let pairs = pairs::pair_mode(src, raw.pairs, new)?;
        if new {
            pairs::refuse_too_many(src, &pairs)?;
        }
        let a = raw.acquisition;
        let acquisition = Acquisition {
            dwell: dwell(src, "acquisition.dwell-ms", a.dwell_ms)?,
            bins: match a.bins {
                None => instrument.tdc.bins,
                Some(b) if (MIN_BINS..=MAX_BINS).contains(&b) => b,
                Some(_) => return Err(src.invalid("acquisition.bins", "must be 16 to 65,536")),
            },
            bin_width: match a.bin_width_ps {
                None => instrument.tdc.bin_width,
                Some(w) if (1.0..=1e6).contains(&w) && w.fract() == 0.0 => w * 1e-12,
                Some(_) => {
                    return Err(src.invalid(
                        "acquisition.bin-width-ps",
                        "must be a whole number of picoseconds, 1 to 1,000,000",
                    ));
                }
            },
            offset: match a.offset_ns {
                None => instrument.tdc.offset,
                Some(o) if (0.0..=MAX_OFFSET_NS).contains(&o) => crate::config::whole_ps_offset(o).ok_or_else(|| {
                    src.invalid(
                        "acquisition.offset-ns",
                        format!("{o} ns is not a whole number of picoseconds: counters place the window in whole picoseconds"),
                    )
                })?,
                Some(_) => return Err(src.invalid("acquisition.offset-ns", "must be 0 to 1,000,000 ns")),
            },
            repeats: match a.repeats {
                r @ 1..=1000 => r,
                _ => return Err(src.invalid("acquisition.repeats", "must be 1 to 1000")),
            },
        };
        if new {
            // As the instrument's own window: it must end within the sync period.
            if let Some((end, period)) = crate::config::window_past_period(
                acquisition.offset,
                acquisition.bins,
                acquisition.bin_width,
                instrument.tdc.sync_divider,
                instrument.laser.repetition_rate,
            ) {
                return Err(src.invalid(
                    "acquisition.bins",
                    format!(
                        "with acquisition.bin-width-ps and offset-ns the window ends at {:.2} ns, past the instrument's sync period of {:.2} ns (laser.rep-rate-mhz, tdc.sync-divider): a counter times each photon from the last sync; fewer or narrower bins, or an earlier offset",
                        end * 1e9,
                        period * 1e9
                    ),
                ));
            }
        }
        let recon = recon::recon_settings(src, "recon.", raw.recon, None)?;
        if adaptive && recon.method != Method::Gtr {
            return Err(src.invalid(
                "pairs.mode",
                "\"adaptive\" needs recon.method = \"gtr\": the running 3D-GTR fit chooses the pairs; use another mode with a solver",
            ));
        }
        if new {
            confocal_solver_fits(src, &recon, &pairs)?;
            envelope_fits(src, &recon, &acquisition)?;
            // 3D-GTR's virtual relay is a plane fitted to the detection points: fewer
            // than three never make one, which the run would learn only after its LOS
            // scan (three in a line are still refused there, once the relay is known).
            let points = pairs.max_detection_points();
            let budget = recon.adaptive.pairs;
            if adaptive && (1..3).contains(&budget) && points >= 3 {
                return Err(src.invalid(
                    "recon.adaptive.pairs",
                    format!(
                        "a budget of {budget} pair(s) measures at most {budget} detection point(s), but 3D-GTR fits a plane to them and needs at least three: give a larger budget, or 0 for half the candidates"
                    ),
                ));
            }
            if recon.method == Method::Gtr && points < 3 {
                return Err(src.invalid(
                    if adaptive { "pairs.candidates" } else { "pairs.mode" },
                    format!(
                        "gives at most {points} detection point(s), but recon.method = \"gtr\" fits a plane to them and needs at least three: give more, or reconstruct with \"fbp\""
                    ),
                ));
            }
        }
        let sus = raw.suspend;
        let suspend = Suspenders {
            flagged_frames: match sus.flagged_frames.unwrap_or(DEFAULT_FLAGGED_FRAMES) {
                n @ 0..=10_000 => n,
                _ => return Err(src.invalid("suspend.flagged-frames", "must be 0 (off) to 10,000")),
            },
            max_count_rate: match sus.max_count_rate_hz {
                None => DEFAULT_RATE_FRACTION * instrument.laser.repetition_rate,
                Some(r) if r.is_finite() && r > 0.0 => r,
                Some(_) => {
                    return Err(src.invalid("suspend.max-count-rate-hz", "must be a positive rate in hertz"));
                }
            },
            resume: match sus.resume.as_deref() {
                None | Some("operator") => {
                    if sus.clear_for_s.is_some() {
                        return Err(src.invalid("suspend.clear-for-s", "applies only with resume = \"auto\""));
                    }
                    SuspendResume::Operator
                }
                Some("auto") => SuspendResume::Auto {
                    clear_for: match sus.clear_for_s.unwrap_or(DEFAULT_CLEAR_FOR_S) {
                        s if (0.0..=3600.0).contains(&s) => Duration::from_secs_f64(s),
                        _ => return Err(src.invalid("suspend.clear-for-s", "must be 0 to 3600 seconds")),
                    },
                },
                Some(other) => {
                    return Err(
                        src.invalid("suspend.resume", format!("`{other}` is not `operator` or `auto`"))
                    );
                }
            },
        };
        Ok(Plan {
            name: raw.name,
            los,
            relay,
            pairs,
            adaptive,
            acquisition,
            recon,
            suspend,
        })
    }
}

/// A wavelength the plan sets for FBP's phasor filter or RSD, whose envelope (6 σ)
/// is longer than the solvers take against the window's length (8 times: the
/// padding would not fit in memory), is refused here, as the solver would refuse it,
/// but before the capture rather than after it (`wavelength = 10.0`, a typo for 0.10).
/// A wavelength left to its default depends on the relay's sampling, which the scan
/// finds, so it is left to the solver.
fn envelope_fits(src: &TomlSource, recon: &ReconSettings, acq: &Acquisition) -> Result<(), ConfigError> {
    use periscope_recon::solver::{MAX_ENVELOPE_SPANS, SIGMA_PER_WAVELENGTH, SolverKind};
    let span = f64::from(acq.bins) * acq.bin_width * periscope_recon::C0;
    let (key, lambda, sigma) = match recon.method {
        Method::Solver(SolverKind::Fbp)
            if recon.solvers.fbp.filter == periscope_recon::solver::FbpFilter::Phasor =>
        {
            let Some(l) = recon.solvers.fbp.wavelength else {
                return Ok(());
            };
            let per = recon
                .solvers
                .fbp
                .sigma_per_wavelength
                .unwrap_or(SIGMA_PER_WAVELENGTH);
            ("recon.fbp.wavelength", l, per * l)
        }
        Method::Solver(SolverKind::Rsd) => {
            let Some(l) = recon.solvers.rsd.wavelength else {
                return Ok(());
            };
            ("recon.rsd.wavelength", l, recon.solvers.rsd.cycles * l / 6.0)
        }
        _ => return Ok(()),
    };
    if 6.0 * sigma <= MAX_ENVELOPE_SPANS * span {
        return Ok(());
    }
    Err(src.invalid(
        key,
        format!(
            "is {lambda} m: its envelope (6 sigma) of {:.3} m is more than {MAX_ENVELOPE_SPANS} times the window's \
             {:.3} m of path (acquisition.bins × bin-width-ps), longer than the solver takes; a shorter wavelength \
             (metres: 0.1 is 10 cm), or a longer window",
            6.0 * sigma,
            span
        ),
    ))
}

/// LCT and f-k take confocal pairs only (illumination and detection within the
/// solver's `grid-tolerance`): a plan whose layout cannot give them is refused here,
/// not by the solver after the whole capture.
fn confocal_solver_fits(
    src: &TomlSource,
    recon: &ReconSettings,
    pairs: &PairMode,
) -> Result<(), ConfigError> {
    use periscope_recon::solver::SolverKind;
    let (name, tolerance) = match recon.method {
        Method::Solver(SolverKind::Lct) => ("lct", recon.solvers.lct.grid_tolerance),
        Method::Solver(SolverKind::Fk) => ("fk", recon.solvers.fk.grid_tolerance),
        _ => return Ok(()),
    };
    match pairs {
        PairMode::Confocal { offset, .. } | PairMode::Mask { offset, .. } if *offset > tolerance => Err(src.invalid(
            "pairs.offset-mm",
            format!(
                "is {:.1} mm, but recon.method = \"{name}\" takes confocal pairs, their two points at most recon.{name}.grid-tolerance ({:.1} mm) apart: lower the offset, raise the tolerance, or reconstruct with \"fbp\" or \"gtr\", which take any pairs",
                offset * 1e3,
                tolerance * 1e3
            ),
        )),
        PairMode::Confocal { .. } | PairMode::Mask { .. } => Ok(()),
        _ => Err(src.invalid(
            "recon.method",
            format!(
                "\"{name}\" takes confocal pairs (pairs.mode = \"confocal\" or \"mask\"), not this plan's {}: reconstruct it with \"fbp\" or \"gtr\", which take any pairs",
                pairs.describe()
            ),
        )),
    }
}

fn dwell(src: &TomlSource, key: &str, ms: f64) -> Result<Duration, ConfigError> {
    if !(0.001..=3_600_000.0).contains(&ms) {
        return Err(src.invalid(key, "must be 0.001 ms to 1 hour, in milliseconds"));
    }
    // Counters time an acquisition in whole microseconds: a finer dwell would be cut
    // (Periscope's USB counter refuses it, as its protocol says).
    let us = (ms * 1e3).round();
    if (ms * 1e3 - us).abs() > 1e-6 {
        return Err(src.invalid(
            key,
            format!("{ms} ms is not a whole number of microseconds: counters time an acquisition in whole microseconds"),
        ));
    }
    Ok(Duration::from_micros(us as u64))
}

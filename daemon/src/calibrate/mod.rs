//! `periscope calibrate`: each galvo arm's pose (origin, boresight, up) and the
//! laser-to-SPAD alignment, fitted to scans of a flat target.
//!
//! Two scans, through the device traits like the pipeline's (`scan.rs`):
//!
//! - **ranges** (diffuser in): at an N × N grid of SPAD angles θ the first-bounce
//!   peak gives the path ℓ(θ) = |p − L| + |p − S| for the point p where the SPAD ray
//!   meets the target;
//! - **spots** (diffuser out): for a grid of laser angles φ, the SPAD angles that see
//!   the laser's spot, found by chords through the spot at half its height.
//!
//! The model (`model.rs`) predicts both from the arms' poses and the target plane;
//! a Levenberg–Marquardt fit (`solve.rs`) moves nine parameters to match.
//!
//! **Gauge and observability.** The world frame is the configured (nominal) frame.
//! Nothing the instrument measures relative to a flat target changes when the whole
//! instrument moves along the target or turns about its normal, so those motions are
//! fixed explicitly:
//!
//! - *target known* (`--target-distance`: the target is the plane that distance from
//!   the SPAD origin along the configured SPAD boresight, facing it): the SPAD
//!   origin's position along the target and its frame's twist about the target normal
//!   stay as configured; fitted are the SPAD origin's distance from the target and
//!   its frame's tilt (ranges: the path's growth across the grid), the laser origin
//!   (ranges: the |p − L| term; spots: parallax) and the laser frame's rotation
//!   (spots only: with the diffuser in, the laser's pointing does not matter).
//! - *target fitted*: the SPAD pose stays as configured (it defines the frame);
//!   fitted are the target's distance and tilt (ranges), and the laser pose relative
//!   to the SPAD arm (ranges and spots).
//!
//! The SPAD's rotation about its boresight is seen only through the 2-D grid (a line
//! scan leaves it free), and absolute positions only through the known target or the
//! laser-to-SPAD baseline. A parameter the scans do not constrain is refused by name
//! (`CalibrateError::Unconstrained`), never returned as a guess.
mod model;
mod scan;
mod solve;
mod toml_out;

use std::time::Duration;

use glam::DVec3;
use periscope_drivers::{DeviceError, OpticalAngles};

pub use model::{Geometry, Plane, in_gauge, rotation_between};
pub use scan::Calibrator;
pub use toml_out::calibrated_toml;

use crate::config::{ConfigError, InstrumentConfig};
use crate::devices::OpenError;
use model::{PARAMETERS, Parameters};

/// Fewest range samples a fit accepts (the range-only parameters are six).
pub const MIN_RANGES: usize = 12;

/// The smallest `--grid` whose square holds [`MIN_RANGES`] angles.
pub const MIN_RANGE_GRID: usize = 4;
const _: () = assert!(MIN_RANGE_GRID * MIN_RANGE_GRID >= MIN_RANGES);
/// Fewest laser spots a fit accepts (each gives two angles; the laser's rotation and
/// the parallax of its origin need three spots off one line).
pub const MIN_SPOTS: usize = 3;

/// How the calibration scans.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    /// The SPAD range grid is `grid` × `grid` angles (at least [`MIN_RANGE_GRID`]).
    pub grid: usize,
    /// Fraction of the SPAD arm's angle limits the range grid spans (centred).
    pub span: f64,
    /// The laser spot grid is `spots` × `spots` laser angles.
    pub spots: usize,
    /// Fraction of the laser arm's angle limits the spot grid spans (centred).
    pub spot_span: f64,
    /// Distance of the flat target from the SPAD origin along the configured SPAD
    /// boresight, metres; `None`: fitted, with its tilt.
    pub target_distance: Option<f64>,
    /// Dwell of a range measurement.
    pub range_dwell: Duration,
    /// Dwell of a spot measurement.
    pub spot_dwell: Duration,
    /// Step of the spot search, radians: below the spot's angular size.
    pub spot_step: f64,
    /// How far from the configured poses' prediction a spot is searched, radians.
    pub spot_search: f64,
}

impl Default for Settings {
    /// A 9 × 9 range grid over 75 % of the SPAD limits, 3 × 3 spots over half the
    /// laser limits, 1 ms per range and 0.1 ms per spot reading, spots searched 35 mrad
    /// (2°) around their predicted angles in 1 mrad steps (a 5 mm spot at 2 m spans
    /// 2.5 mrad).
    fn default() -> Settings {
        Settings {
            grid: 9,
            span: 0.75,
            spots: 3,
            spot_span: 0.5,
            target_distance: None,
            range_dwell: Duration::from_millis(1),
            spot_dwell: Duration::from_micros(100),
            spot_step: 1e-3,
            spot_search: 35e-3,
        }
    }
}

impl Settings {
    /// Refuses settings no scan can use.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        let bad = |why: String| Err(CalibrateError::Settings(why));
        // A grid of fewer than MIN_RANGES angles cannot be fitted even if every angle
        // returns: refused before the laser is switched on, not after its scan.
        if !(MIN_RANGE_GRID..=101).contains(&self.grid) {
            return bad(format!(
                "--grid {} must lie between {MIN_RANGE_GRID} and 101 (the fit needs at least {MIN_RANGES} ranges: {MIN_RANGE_GRID} × {MIN_RANGE_GRID} angles)",
                self.grid
            ));
        }
        if !(2..=11).contains(&self.spots) {
            return bad(format!("{} spots per side must lie between 2 and 11", self.spots));
        }
        if let Some(d) = self.target_distance
            && !(d.is_finite() && d > 0.0 && d <= 100.0)
        {
            return bad(format!(
                "--target-distance {d} must be a distance in metres above 0 and at most 100"
            ));
        }
        let fraction = |f: f64| f.is_finite() && f > 0.0 && f <= 1.0;
        if !(fraction(self.span) && fraction(self.spot_span)) {
            return bad("the scanned fractions of the angle limits must lie in (0, 1]".into());
        }
        if self.range_dwell.is_zero() || self.spot_dwell.is_zero() {
            return bad("dwells must be above zero".into());
        }
        if !(self.spot_step > 0.0 && self.spot_search > self.spot_step) {
            return bad("the spot search must be wider than its step".into());
        }
        Ok(())
    }
}

/// One first-bounce range: the SPAD angles and the measured path, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeSample {
    /// SPAD angles.
    pub spad: OpticalAngles,
    /// Path laser → target → SPAD, metres.
    pub path: f64,
}

/// One laser spot: the laser angles and the SPAD angles that see the spot's centre.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpotSample {
    /// Laser angles.
    pub laser: OpticalAngles,
    /// SPAD angles.
    pub spad: OpticalAngles,
}

/// What the scans measured.
#[derive(Clone, Debug, PartialEq)]
pub struct Measurements {
    /// Ranges, one per SPAD angle that saw a return.
    pub ranges: Vec<RangeSample>,
    /// SPAD angles the range scan tried.
    pub range_angles: usize,
    /// Spots, one per laser angle.
    pub spots: Vec<SpotSample>,
}

/// Why a calibration failed.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// The settings cannot be used.
    #[error("calibration settings: {0}")]
    Settings(String),
    /// The instrument config is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The devices could not be opened.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// A device failed.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// A stop was asked for (a signal, an abort); the laser is off and the arms parked.
    #[error("the calibration was stopped; the laser is off, the arms parked and nothing was written")]
    Stopped,
    /// The counter's sync rate, read with the laser on, is none or not the one the
    /// config gives ([`InstrumentConfig::sync_fault`]).
    #[error("{0}: the laser is off, the arms parked and nothing was written")]
    Sync(String),
    /// Emission stopped while a scan measured.
    #[error("{0} during the calibration: the laser is off; close the interlock and calibrate again")]
    LaserLost(String),
    /// Too few SPAD angles saw a return.
    #[error(
        "only {got} of {tried} SPAD angles saw a first-bounce return (at least {MIN_RANGES} are needed): \
         put a flat target in front of the instrument within the histogram's range (tdc.offset-ns, tdc.bins), \
         or raise --grid"
    )]
    TooFewRanges {
        /// Returns seen.
        got: usize,
        /// Angles tried.
        tried: usize,
    },
    /// A laser spot was not found.
    #[error(
        "laser angles ({:.2}°, {:.2}°): the spot was not found: {why}",
        laser.x.to_degrees(),
        laser.y.to_degrees()
    )]
    NoSpot {
        /// The laser angles.
        laser: OpticalAngles,
        /// Why.
        why: &'static str,
    },
    /// A laser spot the configured poses place outside the SPAD arm's limits, where no
    /// angle within them saw it.
    #[error(
        "laser angles ({:.2}°, {:.2}°): the configured poses put the spot at SPAD angles ({:.2}°, {:.2}°), \
         outside the SPAD arm's limits (`galvo.spad.angle-limits-deg`: x [{:.1}, {:.1}], y [{:.1}, {:.1}]), \
         and no angle within them saw it: check both arms' `origin` and `boresight`, or widen the SPAD \
         arm's limits if it can turn that far",
        laser.x.to_degrees(),
        laser.y.to_degrees(),
        expected.x.to_degrees(),
        expected.y.to_degrees(),
        limits.x[0].to_degrees(),
        limits.x[1].to_degrees(),
        limits.y[0].to_degrees(),
        limits.y[1].to_degrees()
    )]
    SpotOutsideLimits {
        /// The laser angles.
        laser: OpticalAngles,
        /// Where the configured poses put the spot, in SPAD angles.
        expected: OpticalAngles,
        /// The SPAD arm's limits.
        limits: periscope_drivers::AngleLimits,
    },
    /// Too few spots for the fit.
    #[error("only {0} laser spots were measured; the fit needs at least {MIN_SPOTS}")]
    TooFewSpots(usize),
    /// The configured poses cannot explain the measurements at all.
    #[error(
        "the configured poses do not see the target where it was measured ({0}): check the arms' origin and boresight in the instrument config"
    )]
    Geometry(&'static str),
    /// The scans leave a parameter free.
    #[error(
        "the scans do not constrain {0}: widen the grid (--grid, the angle limits) or give --target-distance"
    )]
    Unconstrained(&'static str),
    /// The calibrated config could not be written.
    #[error("the calibrated config: {0}")]
    Output(String),
    /// A bug: code in the calibration panicked. The instrument was made safe.
    #[error(
        "internal error in the calibration: {message}; the instrument was made safe (please report this)"
    )]
    Panicked {
        /// The panic's message.
        message: String,
    },
}

impl CalibrateError {
    /// Whether the fault is in the settings or the config (exit code 2).
    pub fn is_config(&self) -> bool {
        matches!(self, CalibrateError::Settings(_) | CalibrateError::Config(_))
            || matches!(self, CalibrateError::Open(OpenError::Config(_)))
    }
}

pub(crate) fn enough_ranges(got: usize, tried: usize) -> Result<(), CalibrateError> {
    if got < MIN_RANGES {
        return Err(CalibrateError::TooFewRanges { got, tried });
    }
    Ok(())
}

/// How far `--target-distance` may be from the ranges' median depth, as a share of it
/// and at least in metres: more than the configured poses' own error moves the depth.
pub const TARGET_DISTANCE_SLACK: f64 = 0.05;
/// See [`TARGET_DISTANCE_SLACK`].
pub const TARGET_DISTANCE_SLACK_M: f64 = 0.05;

/// The configured geometry: the arms as configured, the target as given by its
/// distance (refused where the ranges' median depth contradicts it by more than
/// [`TARGET_DISTANCE_SLACK`]), or else facing the SPAD boresight at that median depth.
pub fn nominal_geometry(
    config: &InstrumentConfig,
    settings: &Settings,
    ranges: &[RangeSample],
) -> Result<Geometry, CalibrateError> {
    let (laser, spad) = (config.laser_arm.pose, config.spad_arm.pose);
    let boresight = spad.rotation.z_axis;
    let mut depths: Vec<f64> = ranges
        .iter()
        .filter_map(|r| {
            let d = spad.direction(r.spad);
            crate::pipeline::first_bounce_range(r.path, laser.origin, spad.origin, d)
                .map(|t| t * d.dot(boresight))
        })
        .filter(|t| t.is_finite() && *t > 0.0)
        .collect();
    depths.sort_by(f64::total_cmp);
    let median = (depths.len() >= MIN_RANGES).then(|| depths[depths.len() / 2]);
    let distance = match (settings.target_distance, median) {
        // A given distance the ranges contradict (a slip of the tape, the wrong unit)
        // would be fitted around, into wrong poses with small residuals.
        (Some(d), Some(m)) if (d - m).abs() > (TARGET_DISTANCE_SLACK * m).max(TARGET_DISTANCE_SLACK_M) => {
            return Err(CalibrateError::Settings(format!(
                "--target-distance {d} m is not what the ranges measure: their first-bounce returns put the \
                 target {m:.3} m along the SPAD arm's boresight (through the configured poses); measure it \
                 again in metres from the SPAD arm's origin along its boresight, or leave --target-distance \
                 out to take the ranges'"
            )));
        }
        (Some(d), _) => d,
        (None, Some(m)) => m,
        (None, None) => {
            return Err(CalibrateError::Geometry(
                "the measured paths are shorter than the laser-to-SPAD baseline",
            ));
        }
    };
    Ok(Geometry {
        laser,
        spad,
        target: Plane {
            point: spad.origin + boresight * distance,
            normal: -boresight,
        },
    })
}

/// Residual sizes for one geometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Residuals {
    /// Ranges the geometry can predict.
    pub ranges: usize,
    /// RMS of measured − predicted path, metres.
    pub range_rms: f64,
    /// Largest |measured − predicted| path, metres.
    pub range_max: f64,
    /// Spots the geometry can predict.
    pub spots: usize,
    /// RMS of the angle between measured and predicted SPAD angles, radians.
    pub angle_rms: f64,
    /// Largest such angle, radians.
    pub angle_max: f64,
}

impl Residuals {
    /// The residuals of `g` against `m`, over the samples `g` can predict.
    pub fn of(g: &Geometry, m: &Measurements) -> Residuals {
        let ranges: Vec<f64> = m
            .ranges
            .iter()
            .filter_map(|r| g.path(r.spad).map(|p| r.path - p))
            .collect();
        let angles: Vec<f64> = m
            .spots
            .iter()
            .filter_map(|s| g.spot(s.laser).map(|p| (s.spad.x - p.x).hypot(s.spad.y - p.y)))
            .collect();
        let rms = |v: &[f64]| {
            if v.is_empty() {
                f64::NAN
            } else {
                (v.iter().map(|e| e * e).sum::<f64>() / v.len() as f64).sqrt()
            }
        };
        let max = |v: &[f64]| v.iter().map(|e| e.abs()).fold(0.0, f64::max);
        Residuals {
            ranges: ranges.len(),
            range_rms: rms(&ranges),
            range_max: max(&ranges),
            spots: angles.len(),
            angle_rms: rms(&angles),
            angle_max: max(&angles),
        }
    }
}

/// A fitted calibration.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// The configured arms, with the target the fit would give them (given, or fitted
    /// to the scans with the arms held as configured).
    pub configured: Geometry,
    /// The fitted geometry.
    pub fitted: Geometry,
    /// Whether the target was given (`--target-distance`) rather than fitted.
    pub known_target: bool,
    /// Residuals of the configured geometry.
    pub before: Residuals,
    /// Residuals of the fitted geometry.
    pub after: Residuals,
    /// Ranges and spots left out of the fit as outliers (a return off something in
    /// front of the target, a spot partly hidden from the SPAD).
    pub outliers: usize,
    /// The fitted parameters' names and standard uncertainties (metres or radians).
    pub uncertainty: Vec<(&'static str, f64)>,
    /// Whether both full fits (the first, which chooses the outliers, and the final
    /// one) ended because no step lowered the residuals any further: `false` when the
    /// iterations of either ran out (`solve::MAX_ITERATIONS`) with each step still
    /// lowering them, so the poses may not be the best the scans allow; the table says
    /// so.
    pub converged: bool,
}

/// A priori measurement uncertainties that weigh the two kinds of residual in the first
/// pass: 1 mm of path, 0.05 mrad of angle. The second pass uses each kind's own RMS.
const PRIOR_PATH_SIGMA: f64 = 1e-3;
const PRIOR_ANGLE_SIGMA: f64 = 5e-5;

/// Fits the geometry to `m`: a first pass with a priori weights, range outliers
/// (a return off something in front of the target) dropped, then a second pass
/// weighted by each kind's own residual RMS.
pub fn fit(
    config: &InstrumentConfig,
    m: &Measurements,
    settings: &Settings,
) -> Result<Calibration, CalibrateError> {
    settings.validate()?;
    enough_ranges(m.ranges.len(), m.range_angles)?;
    if m.spots.len() < MIN_SPOTS {
        return Err(CalibrateError::TooFewSpots(m.spots.len()));
    }
    let nominal = nominal_geometry(config, settings, &m.ranges)?;
    let known_target = settings.target_distance.is_some();
    let params = Parameters::new(nominal, known_target);
    let names = params.names();
    let solve = |m: &Measurements, x: &[f64], sigma: (f64, f64), free: usize| {
        // The first `free` parameters move; the rest stay at `x`'s values.
        let f = |p: &[f64]| {
            let mut all = x.to_vec();
            all[..free].copy_from_slice(p);
            residuals(&params.geometry(&all), m, sigma.0, sigma.1)
        };
        solve::least_squares(&f, &x[..free]).map_err(|e| match e {
            solve::SolveError::Start => {
                CalibrateError::Geometry("a SPAD ray or the laser spot misses the target plane")
            }
            solve::SolveError::Unconstrained { index } => CalibrateError::Unconstrained(names[index]),
        })
    };
    let prior = (PRIOR_PATH_SIGMA, PRIOR_ANGLE_SIGMA);
    // The configured arms against the target that suits them best (a fitted target
    // moves only the first three parameters; a known one, none).
    let configured = if known_target {
        nominal
    } else {
        let target = solve(m, &[0.0; PARAMETERS], prior, 3)?.x;
        let mut x = [0.0; PARAMETERS];
        x[..3].copy_from_slice(&target);
        params.geometry(&x)
    };
    let first = solve(m, &[0.0; PARAMETERS], prior, PARAMETERS)?;
    let (kept, outliers) = without_outliers(&params.geometry(&first.x), m);
    enough_ranges(kept.ranges.len(), m.range_angles)?;
    if kept.spots.len() < MIN_SPOTS {
        return Err(CalibrateError::TooFewSpots(kept.spots.len()));
    }
    let r = Residuals::of(&params.geometry(&first.x), &kept);
    // Floors: a noiseless simulation must not give a weight of infinity.
    let sigma = (r.range_rms.max(1e-6), (r.angle_rms / 2f64.sqrt()).max(1e-7));
    let solution = solve(&kept, &first.x, sigma, PARAMETERS)?;
    let fitted = params.geometry(&solution.x);
    let variances = solve::inverse_diagonal(&solution.normal)
        .ok_or(CalibrateError::Unconstrained("the parameters jointly"))?;
    let dof = (solution.residuals.len().saturating_sub(PARAMETERS)).max(1) as f64;
    let scale = solution.residuals.iter().map(|r| r * r).sum::<f64>() / dof;
    let uncertainty = names
        .iter()
        .zip(variances)
        .map(|(&n, v)| (n, (v * scale).sqrt()))
        .collect();
    Ok(Calibration {
        configured,
        fitted,
        known_target,
        before: Residuals::of(&configured, &kept),
        after: Residuals::of(&fitted, &kept),
        outliers,
        uncertainty,
        // The first pass chose the outliers the final one leaves out: both must have
        // converged for the poses to be the best the scans allow.
        converged: first.converged && solution.converged,
    })
}

fn pick<T: Copy>(all: &[T], keep: Vec<bool>) -> Vec<T> {
    all.iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(x, _)| *x)
        .collect()
}

/// `m` without the ranges and spots whose residual under `g` is far outside the rest's
/// spread (6 robust standard deviations, at least 2 mm of path or 0.05 mrad of angle:
/// a return off something in front of the target, a spot whose chord an object cut),
/// and how many were dropped.
fn without_outliers(g: &Geometry, m: &Measurements) -> (Measurements, usize) {
    let ranges: Vec<f64> = m
        .ranges
        .iter()
        .map(|r| g.path(r.spad).map_or(f64::INFINITY, |p| (r.path - p).abs()))
        .collect();
    let spots: Vec<f64> = m
        .spots
        .iter()
        .map(|s| {
            g.spot(s.laser)
                .map_or(f64::INFINITY, |p| (s.spad.x - p.x).hypot(s.spad.y - p.y))
        })
        .collect();
    let keep = |errors: &[f64], floor: f64| -> Vec<bool> {
        let mut sorted: Vec<f64> = errors.iter().copied().filter(|v| v.is_finite()).collect();
        sorted.sort_by(f64::total_cmp);
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0.0);
        let limit = (6.0 * 1.4826 * median).max(floor);
        errors.iter().map(|e| *e <= limit).collect()
    };
    let kept = Measurements {
        ranges: pick(&m.ranges, keep(&ranges, 2e-3)),
        spots: pick(&m.spots, keep(&spots, 5e-5)),
        range_angles: m.range_angles,
    };
    let dropped = m.ranges.len() + m.spots.len() - kept.ranges.len() - kept.spots.len();
    (kept, dropped)
}

/// The weighted residuals of `g`: paths over `sp`, the two angles of each spot over
/// `sa`; `None` if `g` cannot predict one of them.
fn residuals(g: &Geometry, m: &Measurements, sp: f64, sa: f64) -> Option<Vec<f64>> {
    let mut out = Vec::with_capacity(m.ranges.len() + 2 * m.spots.len());
    for r in &m.ranges {
        out.push((r.path - g.path(r.spad)?) / sp);
    }
    for s in &m.spots {
        let p = g.spot(s.laser)?;
        out.push((s.spad.x - p.x) / sa);
        out.push((s.spad.y - p.y) / sa);
    }
    Some(out)
}

/// A fitted position whose 1σ uncertainty is above this, metres, is named as poorly
/// determined: a millimetre of path is 3.3 ps, and relay points are placed from it.
pub const WEAK_POSITION: f64 = 2e-3;

/// A fitted rotation or tilt whose 1σ uncertainty is above this, radians: 2 mm at 1 m.
pub const WEAK_ROTATION: f64 = 2e-3;

impl Calibration {
    /// The fitted parameters the scans determine only loosely (1σ above
    /// [`WEAK_POSITION`] or [`WEAK_ROTATION`]), with their uncertainty. Only an exactly
    /// free one is refused (`Unconstrained`); these are fitted and written, and named
    /// in the table with what to do. With bench-like noise (1 mm of path, 0.05 mrad a
    /// spot) SPAD limits of ±5° leave the laser's lateral origin at 12 mm and its
    /// rotation at 3 mrad, where ±20° gives 1 mm and 0.3 mrad.
    pub fn weakly_determined(&self) -> Vec<(&'static str, f64)> {
        self.uncertainty
            .iter()
            .filter(|(name, s)| {
                let angular = name.contains("rotation") || name.contains("tilt");
                !(*s <= if angular { WEAK_ROTATION } else { WEAK_POSITION })
            })
            .copied()
            .collect()
    }

    /// The table `periscope calibrate` prints: configured and fitted values, their
    /// change, the uncertainties and the residuals before and after.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let v = |d: DVec3| format!("[{:>9.6}, {:>9.6}, {:>9.6}]", d.x, d.y, d.z);
        let mut t = String::new();
        let _ = writeln!(t, "{:<22}{:<36}{:<36}change", "", "configured", "fitted");
        for (name, c, f) in [
            ("spad", &self.configured.spad, &self.fitted.spad),
            ("laser", &self.configured.laser, &self.fitted.laser),
        ] {
            let _ = writeln!(
                t,
                "{:<22}{:<36}{:<36}{:.3} mm",
                format!("{name} origin (m)"),
                v(c.origin),
                v(f.origin),
                c.origin.distance(f.origin) * 1e3
            );
            let bore = c.rotation.z_axis.angle_between(f.rotation.z_axis);
            let _ = writeln!(
                t,
                "{:<22}{:<36}{:<36}{:.3} mrad",
                format!("{name} boresight"),
                v(c.rotation.z_axis),
                v(f.rotation.z_axis),
                bore * 1e3
            );
            let _ = writeln!(
                t,
                "{:<22}{:<36}{:<36}{:.3} mrad (whole frame)",
                format!("{name} up"),
                v(c.rotation.y_axis),
                v(f.rotation.y_axis),
                rotation_between(c.rotation, f.rotation) * 1e3
            );
        }
        // The SPAD origin's distance from the target.
        let distance = |g: &Geometry| g.target.normal.dot(g.spad.origin - g.target.point);
        let _ = writeln!(
            t,
            "{:<22}{:<36}{:<36}{}",
            "target distance (m)",
            format!("{:.6}", distance(&self.configured)),
            format!("{:.6}", distance(&self.fitted)),
            if self.known_target { "given" } else { "fitted" }
        );
        if !self.known_target {
            let _ = writeln!(
                t,
                "{:<22}{:<36}{:<36}{:.3} mrad",
                "target normal",
                v(self.configured.target.normal),
                v(self.fitted.target.normal),
                self.configured
                    .target
                    .normal
                    .angle_between(self.fitted.target.normal)
                    * 1e3
            );
        }
        let _ = writeln!(t, "\nuncertainty (1σ) of the fitted parameters:");
        for (name, s) in &self.uncertainty {
            let (value, unit) = if name.contains("rotation") || name.contains("tilt") {
                (s * 1e3, "mrad")
            } else {
                (s * 1e3, "mm")
            };
            let _ = writeln!(t, "  {name:<46}{value:>10.4} {unit}");
        }
        let weak = self.weakly_determined();
        if !weak.is_empty() {
            let names: Vec<&str> = weak.iter().map(|(n, _)| *n).collect();
            let _ = writeln!(
                t,
                "warning: the scans determine {} only to more than {:.0} mm or {:.0} mrad (1σ): \
                 widen the range grid's angles (the SPAD arm's angle-limits-deg) or give \
                 --target-distance, and calibrate again before relying on these poses (with \
                 millimetres of range residual below, check galvo.*.scanner too: a galvo \
                 pair is \"two-mirror\")",
                names.join(", "),
                WEAK_POSITION * 1e3,
                WEAK_ROTATION * 1e3
            );
        }
        if !self.converged {
            let _ = writeln!(
                t,
                "warning: the fit had not converged after {} iterations (each still lowered the \
                 residuals), so these poses may not be the best the scans allow: check the \
                 configured poses are within a few centimetres and degrees of the arms, and \
                 calibrate again",
                solve::MAX_ITERATIONS
            );
        }
        let row = |r: &Residuals| {
            format!(
                "{:>9.3} mm RMS {:>9.3} max   {:>9.4} mrad RMS {:>9.4} max",
                r.range_rms * 1e3,
                r.range_max * 1e3,
                r.angle_rms * 1e3,
                r.angle_max * 1e3
            )
        };
        let _ = writeln!(
            t,
            "\nresiduals ({} ranges, {} spots; {} left out as outliers):",
            self.after.ranges, self.after.spots, self.outliers
        );
        let _ = writeln!(t, "  configured poses  {}", row(&self.before));
        let _ = writeln!(t, "  fitted poses      {}", row(&self.after));
        if self.before.ranges < self.after.ranges || self.before.spots < self.after.spots {
            let _ = writeln!(
                t,
                "  (the configured poses predict only {} ranges and {} spots)",
                self.before.ranges, self.before.spots
            );
        }
        t
    }
}

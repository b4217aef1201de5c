//! `periscope calibrate` on the simulator whose arms are not where the config says
//! (`[sim.true-pose.*]`): the fit must find where they are, to 1 mm and 0.5 mrad,
//! with and without photon noise; the fitted config fed back must explain the scans;
//! degenerate inputs must give errors that say what is wrong; and the laser must be
//! off, the arms parked, however the calibration ends.
use std::time::{Duration, Instant};

use glam::{DMat3, DQuat, DVec3};
use periscope_daemon::calibrate::{
    self, CalibrateError, Calibration, Calibrator, Geometry, Measurements, Plane, Settings, in_gauge,
    rotation_between,
};
use periscope_daemon::config::{InstrumentConfig, TomlSource};
use periscope_daemon::devices::sim::SimBackend;
use periscope_daemon::pipeline::Control;
use periscope_drivers::GalvoPose;

/// The bounds the calibration promises (docs/calibration.md).
const ORIGIN_TOLERANCE_MM: f64 = 1.0;
const ANGLE_TOLERANCE_MRAD: f64 = 0.5;

fn root() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn rot(w: DVec3) -> DMat3 {
    DMat3::from_quat(DQuat::from_scaled_axis(w))
}

/// Where the simulated arms really are: the configured poses moved by a few
/// millimetres and turned by a few milliradians, about every axis (the SPAD's twist
/// about its boresight and its sideways shift included: the gauge takes those out).
fn misaligned(config: &InstrumentConfig) -> (GalvoPose, GalvoPose) {
    let (l, s) = (config.laser_arm.pose, config.spad_arm.pose);
    let laser = GalvoPose {
        origin: l.origin + DVec3::new(-4.0e-3, 2.5e-3, -3.0e-3),
        rotation: rot(DVec3::new(-3.0e-3, 2.0e-3, 4.0e-3)) * l.rotation,
        ..l
    };
    let spad = GalvoPose {
        origin: s.origin + DVec3::new(3.0e-3, -2.0e-3, 4.0e-3),
        rotation: rot(DVec3::new(2.0e-3, -1.5e-3, 3.0e-3)) * s.rotation,
        ..s
    };
    (laser, spad)
}

fn toml_vec(v: DVec3) -> String {
    format!("[{:.15}, {:.15}, {:.15}]", v.x, v.y, v.z)
}

/// The default simulated instrument, in process and instant, with `noise`, and with
/// its arms truly at `truth` if given. `text` replaces the shipped config's text.
fn instrument(text: Option<&str>, noise: bool, truth: Option<(GalvoPose, GalvoPose)>) -> TomlSource {
    instrument_with(text, noise, truth, None)
}

/// [`instrument`] with both arms' `scanner` set.
fn instrument_with(
    text: Option<&str>,
    noise: bool,
    truth: Option<(GalvoPose, GalvoPose)>,
    scanner: Option<&str>,
) -> TomlSource {
    let path = root().join("configs/instrument/sim.toml");
    let mut text = match text {
        Some(t) => t.to_owned(),
        None => std::fs::read_to_string(&path).unwrap().replace(
            "[sim]\n",
            &format!("[sim]\ndevices = \"in-process\"\ntime-scale = 0.0\nnoise = {noise}\n"),
        ),
    };
    if let Some(s) = scanner {
        for arm in ["[galvo.laser]", "[galvo.spad]"] {
            let at = text.find(arm).expect("the config has both arms") + arm.len();
            let line_end = at + text[at..].find('\n').unwrap() + 1;
            text.insert_str(line_end, &format!("scanner = \"{s}\"\n"));
        }
    }
    if let Some((laser, spad)) = truth {
        for (arm, p) in [("laser", laser), ("spad", spad)] {
            text.push_str(&format!(
                "\n[sim.true-pose.{arm}]\norigin = {}\nboresight = {}\nup = {}\n",
                toml_vec(p.origin),
                toml_vec(p.rotation.z_axis),
                toml_vec(p.rotation.y_axis)
            ));
        }
    }
    TomlSource::from_text(path, text)
}

fn backend(config: &InstrumentConfig) -> SimBackend {
    SimBackend::from_config(&config.with_spad_ungated())
        .unwrap()
        .unwrap()
}

fn measure(
    config: &InstrumentConfig,
    sim: &SimBackend,
    settings: &Settings,
) -> Result<Measurements, CalibrateError> {
    Calibrator::open(config, Some(sim), Control::new())?.measure(settings)
}

/// The largest origin error (mm) and frame error (mrad) of the fit against the truth
/// moved into the fit's gauge.
fn errors(cal: &Calibration, truth: (GalvoPose, GalvoPose)) -> (f64, f64) {
    let truth = Geometry {
        laser: truth.0,
        spad: truth.1,
        // The built-in scene's relay: the plane z = 0, facing the instrument.
        target: Plane {
            point: DVec3::ZERO,
            normal: DVec3::Z,
        },
    };
    let t = in_gauge(&truth, &cal.configured, cal.known_target);
    let f = &cal.fitted;
    let mut origin = f
        .laser
        .origin
        .distance(t.laser.origin)
        .max(f.spad.origin.distance(t.spad.origin))
        * 1e3;
    let mut angle = rotation_between(f.laser.rotation, t.laser.rotation)
        .max(rotation_between(f.spad.rotation, t.spad.rotation))
        * 1e3;
    if !cal.known_target {
        // The fitted target stands in for the SPAD's own pose: its distance and tilt.
        let d = |g: &Geometry| g.target.normal.dot(g.spad.origin - g.target.point);
        origin = origin.max((d(f) - d(&t)).abs() * 1e3);
        angle = angle.max(f.target.normal.angle_between(t.target.normal) * 1e3);
    }
    (origin, angle)
}

fn run(noise: bool, target_distance: Option<f64>) -> (Calibration, (GalvoPose, GalvoPose)) {
    run_on(None, noise, target_distance)
}

/// [`run`] on arms with the `scanner` kinematics (the shipped config's where `None`).
fn run_on(
    scanner: Option<&str>,
    noise: bool,
    target_distance: Option<f64>,
) -> (Calibration, (GalvoPose, GalvoPose)) {
    let nominal = InstrumentConfig::from_source(&instrument_with(None, noise, None, scanner)).unwrap();
    let truth = misaligned(&nominal);
    let config = InstrumentConfig::from_source(&instrument_with(None, noise, Some(truth), scanner)).unwrap();
    let sim = backend(&config);
    let settings = Settings {
        target_distance,
        ..Settings::default()
    };
    let started = Instant::now();
    let m = measure(&config, &sim, &settings).unwrap();
    let cal = calibrate::fit(&config, &m, &settings).unwrap();
    let (origin, angle) = errors(&cal, truth);
    eprintln!(
        "noise {noise}, target {target_distance:?}: origin error {origin:.4} mm, angle error {angle:.4} mrad \
         ({:.1} s)\n{}",
        started.elapsed().as_secs_f64(),
        cal.table()
    );
    assert!(
        origin < ORIGIN_TOLERANCE_MM && angle < ANGLE_TOLERANCE_MRAD,
        "origin error {origin:.4} mm (tolerance {ORIGIN_TOLERANCE_MM}), angle error {angle:.4} mrad \
         (tolerance {ANGLE_TOLERANCE_MRAD})\n{}",
        cal.table()
    );
    // The misalignment is far outside the tolerance: the fit moved the poses.
    let (o0, a0) = errors(
        &Calibration {
            fitted: cal.configured,
            ..cal.clone()
        },
        truth,
    );
    assert!(
        o0 > 3.0 * ORIGIN_TOLERANCE_MM && a0 > 3.0 * ANGLE_TOLERANCE_MRAD,
        "{o0} mm, {a0} mrad"
    );
    // Every parameter is well determined here, and the table warns of none; inflated
    // to 3 mm and 5 mrad, two are named with what to do.
    assert!(cal.weakly_determined().is_empty(), "{}", cal.table());
    assert!(cal.converged, "{}", cal.table());
    assert!(!cal.table().contains("warning"), "{}", cal.table());
    let unfinished = Calibration {
        converged: false,
        ..cal.clone()
    };
    assert!(
        unfinished.table().contains("had not converged after"),
        "{}",
        unfinished.table()
    );
    let mut loose = cal.clone();
    loose.uncertainty[0].1 = 3e-3;
    let last = loose.uncertainty.len() - 1;
    loose.uncertainty[last].1 = 5e-3;
    let weak: Vec<&str> = loose.weakly_determined().iter().map(|(n, _)| *n).collect();
    assert_eq!(weak, [loose.uncertainty[0].0, loose.uncertainty[last].0]);
    let table = loose.table();
    assert!(
        table.contains("warning") && table.contains(weak[0]) && table.contains("--target-distance"),
        "{table}"
    );
    (cal, truth)
}

#[test]
fn the_poses_are_recovered_without_noise() {
    run(false, Some(2.0));
}

#[test]
fn the_poses_are_recovered_with_photon_noise() {
    run(true, Some(2.0));
}

#[test]
fn the_laser_is_recovered_against_a_fitted_target() {
    run(true, None);
}

/// Galvo pairs as they are built, two mirrors (their pincushion in the model), both
/// against a known target and a fitted one. Configured with the pivot kinematics
/// instead, the same pairs leave millimetres of range residual that no pose absorbs.
#[test]
fn two_mirror_pairs_are_recovered() {
    let (cal, _) = run_on(Some("two-mirror"), true, Some(2.0));
    assert_eq!(cal.fitted.laser.scanner, periscope_drivers::Scanner::TwoMirror);
    assert_eq!(cal.fitted.spad.scanner, periscope_drivers::Scanner::TwoMirror);
    let matched = cal.after.range_rms;
    run_on(Some("two-mirror"), true, None);

    // Pivot kinematics configured on pairs that are two mirrors.
    let nominal = InstrumentConfig::from_source(&instrument(None, true, None)).unwrap();
    let truth = misaligned(&nominal);
    let mut text = instrument(None, true, Some(truth)).text().to_owned();
    for arm in ["laser", "spad"] {
        let at = text.find(&format!("[sim.true-pose.{arm}]\n")).unwrap();
        let end = at + text[at..].find('\n').unwrap() + 1;
        text.insert_str(end, "scanner = \"two-mirror\"\n");
    }
    let config = InstrumentConfig::from_source(&instrument(Some(&text), true, None)).unwrap();
    let settings = Settings {
        target_distance: Some(2.0),
        ..Settings::default()
    };
    let sim = backend(&config);
    let m = measure(&config, &sim, &settings).unwrap();
    let mismatched = calibrate::fit(&config, &m, &settings).unwrap();
    eprintln!(
        "range residual RMS: {:.3} mm with the kinematics the pairs have, {:.3} mm with the pivot's\n{}",
        matched * 1e3,
        mismatched.after.range_rms * 1e3,
        mismatched.table()
    );
    assert!(
        mismatched.after.range_rms > 3.0 * matched,
        "{} against {}",
        mismatched.after.range_rms,
        matched
    );
}

#[test]
fn the_fitted_config_fed_back_explains_the_scans() {
    let nominal = InstrumentConfig::from_source(&instrument(None, true, None)).unwrap();
    let truth = misaligned(&nominal);
    let src = instrument(None, true, Some(truth));
    let config = InstrumentConfig::from_source(&src).unwrap();
    let settings = Settings {
        target_distance: Some(2.0),
        ..Settings::default()
    };
    let first = calibrate::fit(
        &config,
        &measure(&config, &backend(&config), &settings).unwrap(),
        &settings,
    )
    .unwrap();
    // The calibrated file keeps `[sim.true-pose.*]`: the same true instrument. A known
    // target is placed from the configured SPAD pose, which has now moved: checking a
    // calibrated instrument again fits the target (docs/calibration.md).
    let text = calibrate::calibrated_toml(src.text(), &first.fitted, src.path(), src.path()).unwrap();
    let src = instrument(Some(&text), true, None);
    let config = InstrumentConfig::from_source(&src).unwrap();
    let settings = Settings::default();
    let second = calibrate::fit(
        &config,
        &measure(&config, &backend(&config), &settings).unwrap(),
        &settings,
    )
    .unwrap();
    eprintln!("first:\n{}\nsecond:\n{}", first.table(), second.table());
    let (b1, b2) = (first.before, second.before);
    assert!(
        b2.range_rms < 0.2 * b1.range_rms && b2.angle_rms < 0.2 * b1.angle_rms,
        "configured residuals before {b1:?}, after feeding the fit back {b2:?}"
    );
    // Fed back, the configured poses explain the scans about as well as a fit does.
    let a2 = second.after;
    assert!(
        b2.range_rms < 3.0 * a2.range_rms + 1e-4 && b2.angle_rms < 3.0 * a2.angle_rms + 2e-5,
        "{b2:?} against {a2:?}"
    );
}

/// Whether the simulated laser is off and both arms parked, by the rig's own state.
fn assert_safe(sim: &SimBackend) {
    assert!(!sim.emission(), "the laser is on");
    assert_eq!(sim.parked(), (true, true), "arms not parked");
}

#[test]
fn the_laser_is_on_only_while_a_scan_measures() {
    let config = InstrumentConfig::from_source(&instrument(None, true, None)).unwrap();
    let sim = backend(&config);
    let settings = Settings {
        target_distance: Some(2.0),
        grid: 4,
        ..Settings::default()
    };
    measure(&config, &sim, &settings).unwrap();
    assert_safe(&sim);
    let on: Vec<_> = sim.emission_changes().into_iter().filter(|c| c.on).collect();
    assert_eq!(
        on.len(),
        2,
        "on for the range scan and the spot scan only: {on:?}"
    );
}

#[test]
fn an_abort_stops_the_calibration_with_the_laser_off() {
    let config = InstrumentConfig::from_source(&instrument(None, true, None)).unwrap();
    let sim = backend(&config);
    let control = Control::new();
    let watcher = {
        let (sim, control) = (sim.clone(), control.clone());
        std::thread::spawn(move || {
            let started = Instant::now();
            while !sim.emission() && started.elapsed() < Duration::from_secs(10) {
                std::thread::sleep(Duration::from_micros(200));
            }
            control.abort();
        })
    };
    let settings = Settings {
        target_distance: Some(2.0),
        grid: 31,
        ..Settings::default()
    };
    let err = Calibrator::open(&config, Some(&sim), control)
        .unwrap()
        .measure(&settings)
        .unwrap_err();
    watcher.join().unwrap();
    assert!(matches!(err, CalibrateError::Stopped), "{err}");
    assert_safe(&sim);
}

/// A laser pulsing at another rate than `laser.rep-rate-mhz` says: the calibration
/// reads the counter's sync once the laser is on and stops before it measures,
/// naming the keys, with the laser off and the arms parked.
#[test]
fn a_laser_at_another_rate_than_configured_stops_the_calibration_before_it_measures() {
    let text = std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace(
            "[sim]\n",
            "[sim]\ndevices = \"in-process\"\ntrue-rep-rate-mhz = 9.5\n",
        );
    let config = InstrumentConfig::from_source(&instrument(Some(&text), true, None)).unwrap();
    let sim = backend(&config);
    let err = measure(&config, &sim, &Settings::default()).unwrap_err();
    assert!(matches!(err, CalibrateError::Sync(_)), "{err}");
    assert!(
        err.to_string().contains("sync rate of 9.5000 MHz") && err.to_string().contains("laser.rep-rate-mhz"),
        "{err}"
    );
    assert_safe(&sim);
}

/// A `--target-distance` the ranges contradict (1.6 m, the target at 2.0 m) is
/// refused after the range scan, naming the key and the depth the ranges measure, the
/// instrument safe. Until 2026-12-06 it was fitted around, into wrong poses with small
/// residuals, or the spot search failed blaming the SPAD's gate.
#[test]
fn a_target_distance_the_ranges_contradict_is_refused() {
    let nominal = InstrumentConfig::from_source(&instrument(None, false, None)).unwrap();
    let config = InstrumentConfig::from_source(&instrument(None, false, Some(misaligned(&nominal)))).unwrap();
    let sim = backend(&config);
    let settings = Settings {
        target_distance: Some(1.6),
        ..Settings::default()
    };
    let err = measure(&config, &sim, &settings).unwrap_err();
    assert!(matches!(err, CalibrateError::Settings(_)), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("--target-distance 1.6 m") && text.contains("target 2.0"),
        "{text}"
    );
    assert_safe(&sim);
}

#[test]
fn a_target_out_of_view_is_a_clear_error() {
    // The SPAD arm looks away from the wall: no return anywhere.
    let text = std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("[sim]\n", "[sim]\ndevices = \"in-process\"\n");
    let text = text.replacen(
        "origin = [0.10, 0.0, 2.0]\nboresight = [0.0, 0.0, -1.0]",
        "origin = [0.10, 0.0, 2.0]\nboresight = [0.0, 0.0, 1.0]",
        1,
    );
    let config = InstrumentConfig::from_source(&instrument(Some(&text), true, None)).unwrap();
    let sim = backend(&config);
    let err = measure(&config, &sim, &Settings::default()).unwrap_err();
    assert!(
        matches!(err, CalibrateError::TooFewRanges { got: 0, tried: 81 }),
        "{err}"
    );
    assert!(err.to_string().contains("flat target"), "{err}");
    assert_safe(&sim);
}

#[test]
fn a_gated_spad_is_named_when_no_spot_is_seen() {
    let config = InstrumentConfig::from_source(&instrument(None, true, None)).unwrap();
    // Built without `with_spad_ungated`: the gate blanks the spot's direct return.
    let sim = SimBackend::from_config(&config).unwrap().unwrap();
    let settings = Settings {
        grid: 4,
        spot_search: 4e-3,
        ..Settings::default()
    };
    let err = measure(&config, &sim, &settings).unwrap_err();
    assert!(matches!(err, CalibrateError::NoSpot { .. }), "{err}");
    assert!(err.to_string().contains("gated"), "{err}");
    assert_safe(&sim);
}

/// A spot the configured poses place outside the SPAD arm's limits is named so, with
/// the limits' key, not blamed on a gated SPAD (a review, 2026-12-06).
#[test]
fn a_spot_outside_the_spad_arms_limits_names_them() {
    let text = std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("[sim]\n", "[sim]\ndevices = \"in-process\"\n");
    // The SPAD arm's limits narrowed to ±1° (its section is the second): the range grid
    // still sees the wall, but the spots lie a few degrees out.
    let spad = text.find("[galvo.spad]").expect("sim.toml has [galvo.spad]");
    let (head, tail) = text.split_at(spad);
    let tail = tail.replacen(
        "angle-limits-deg = { x = [-20.0, 20.0], y = [-20.0, 20.0] }",
        "angle-limits-deg = { x = [-1.0, 1.0], y = [-1.0, 1.0] }",
        1,
    );
    assert!(
        tail.contains("x = [-1.0, 1.0]"),
        "the SPAD limits were not narrowed"
    );
    let config =
        InstrumentConfig::from_source(&instrument(Some(&format!("{head}{tail}")), false, None)).unwrap();
    let sim = backend(&config);
    let settings = Settings {
        grid: 4,
        spot_search: 4e-3,
        ..Settings::default()
    };
    let err = measure(&config, &sim, &settings).unwrap_err();
    assert!(matches!(err, CalibrateError::SpotOutsideLimits { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains("galvo.spad.angle-limits-deg")
            && text.contains("x [-1.0, 1.0]")
            && !text.contains("gated"),
        "{text}"
    );
    assert_safe(&sim);
}

#[test]
fn too_few_or_degenerate_measurements_are_refused_by_name() {
    let nominal = InstrumentConfig::from_source(&instrument(None, false, None)).unwrap();
    let config = InstrumentConfig::from_source(&instrument(None, false, Some(misaligned(&nominal)))).unwrap();
    let settings = Settings {
        target_distance: Some(2.0),
        ..Settings::default()
    };
    let m = measure(&config, &backend(&config), &settings).unwrap();
    let fit = |m: &Measurements| calibrate::fit(&config, m, &settings);

    let few = Measurements {
        ranges: m.ranges[..5].to_vec(),
        ..m.clone()
    };
    let err = fit(&few).unwrap_err();
    assert!(
        matches!(err, CalibrateError::TooFewRanges { got: 5, .. }),
        "{err}"
    );

    let few = Measurements {
        spots: m.spots[..2].to_vec(),
        ..m.clone()
    };
    assert!(matches!(fit(&few).unwrap_err(), CalibrateError::TooFewSpots(2)));

    // One spot measured three times: the laser's rotation about that ray is free.
    let same = Measurements {
        spots: vec![m.spots[4]; 3],
        ..m.clone()
    };
    let err = fit(&same).unwrap_err();
    assert!(matches!(err, CalibrateError::Unconstrained(_)), "{err}");
    assert!(err.to_string().contains("laser"), "{err}");

    // A single row of ranges cannot see the SPAD's tilt across it: the fit refuses,
    // or, if the spots pin it, returns finite poses; never NaN.
    let row = Measurements {
        ranges: m
            .ranges
            .iter()
            .filter(|r| r.spad.y == m.ranges[0].spad.y)
            .copied()
            .collect(),
        ..m.clone()
    };
    match fit(&row) {
        Err(e) => assert!(
            matches!(
                e,
                CalibrateError::TooFewRanges { .. } | CalibrateError::Unconstrained(_)
            ),
            "{e}"
        ),
        Ok(c) => assert!(c.fitted.laser.origin.is_finite() && c.fitted.spad.rotation.is_finite()),
    }

    // A 3 × 3 grid holds 9 angles, fewer than the fit's 12 ranges: refused before the
    // laser scans them, not after (it was accepted, and every run of it failed).
    for grid in [2, 3] {
        let bad = Settings {
            grid,
            ..settings.clone()
        };
        let e = bad.validate().unwrap_err();
        assert!(
            matches!(e, CalibrateError::Settings(ref why) if why.contains("--grid")),
            "{e}"
        );
    }
    assert!(
        Settings {
            grid: 4,
            ..settings.clone()
        }
        .validate()
        .is_ok()
    );
    let bad = Settings {
        target_distance: Some(f64::NAN),
        ..settings
    };
    assert!(matches!(bad.validate().unwrap_err(), CalibrateError::Settings(_)));
}

//! The simulator's physics against closed-form expectations: a small patch's return
//! sits at its path length with the 1/(di² dd²) falloff and all four cosines, mirror
//! scenes give mirror transients, noise is Poisson, seeds reproduce, the LOS return
//! locates the relay, the gate removes the direct return, pile-up only removes counts.
use glam::DVec3;
use periscope_sim::detector::C0;
use periscope_sim::scene::ShapeKind;
use periscope_sim::scene::Surface;
use periscope_sim::{Detector, Instrument, Mesh, Scene, SpotPair, SurfaceHit, World, sample_counts, shapes};

fn detector() -> Detector {
    Detector {
        bin_width: 16e-12,
        bins: 1024,
        offset: 10e-9,
        system_delay: 0.0,
        jitter_fwhm: 60e-12,
        efficiency: 0.3,
        dark_count_rate: 100.0,
        ambient_rate: 0.0,
        dead_time: 50e-9,
        laser_power: 0.4,
        wavelength: 532e-9,
        repetition_rate: 10e6,
        sync_divider: 1,
        aperture_area: 2e-4,
        spot_area: 2e-5,
        diffuser_solid_angle: 0.6,
        transmission: 0.5,
        gate_margin: Some(0.1),
        pile_up: false,
    }
}

const INST: Instrument = Instrument {
    laser: DVec3::new(-0.1, 0.0, 2.0),
    spad: DVec3::new(0.1, 0.0, 2.0),
};

fn scene(hidden: Vec<Mesh>) -> Scene {
    Scene {
        name: "test".into(),
        relay: Surface {
            label: "relay".into(),
            shape: ShapeKind::Plane,
            mesh: shapes::plane([2.0, 2.0]),
            albedo: 0.8,
            variation: None,
        },
        hidden: hidden
            .into_iter()
            .enumerate()
            .map(|(i, mesh)| Surface {
                label: format!("hidden[{i}]"),
                shape: ShapeKind::Mesh,
                mesh,
                albedo: 0.9,
                variation: None,
            })
            .collect(),
    }
}

fn spot(x: f64, y: f64) -> SurfaceHit {
    SurfaceHit {
        point: DVec3::new(x, y, 0.0),
        normal: DVec3::Z,
        albedo: 0.8,
        distance: 2.0,
        on_relay: true,
    }
}

/// A 1 cm patch at `centre`, facing −z (toward the relay).
fn patch(centre: DVec3) -> Mesh {
    Mesh::rectangle([-0.005, 0.005], [-0.005, 0.005]).transformed(glam::DMat3::IDENTITY, centre)
}

fn hidden_only(det: &Detector) -> Detector {
    Detector {
        dark_count_rate: 0.0,
        ambient_rate: 0.0,
        ..*det
    }
}

#[test]
fn a_small_patch_returns_at_its_path_length_with_the_expected_falloff() {
    let centre = DVec3::new(0.1, -0.05, 0.6);
    let world = World::new(scene(vec![patch(centre)]), 0.001, 1);
    let det = hidden_only(&detector());
    let pairs = [
        SpotPair {
            illumination: spot(-0.2, 0.1),
            detection: spot(0.3, -0.2),
        },
        SpotPair {
            illumination: spot(0.5, 0.4),
            detection: spot(-0.4, 0.3),
        },
    ];
    let counts = world.third_bounce(&INST, &pairs, &det, 1.0);
    let mut totals = Vec::new();
    for (pair, h) in pairs.iter().zip(&counts) {
        let (xi, xd) = (pair.illumination.point, pair.detection.point);
        let path =
            INST.laser.distance(xi) + xi.distance(centre) + centre.distance(xd) + xd.distance(INST.spad);
        let total: f64 = h.iter().sum();
        let mean_bin = h
            .iter()
            .enumerate()
            .map(|(b, v)| (b as f64 + 0.5) * v)
            .sum::<f64>()
            / total;
        let mean_path = (mean_bin * det.bin_width + det.offset) * C0;
        assert!(total > 0.0, "no hidden return");
        // The patch is 1 cm wide, so its own spread of path lengths is < 1 mm about the
        // centre's; the detector keeps the mean arrival exactly.
        assert!((mean_path - path).abs() < 1e-3, "mean path {mean_path} vs {path}");
        let (a, b) = (centre - xi, centre - xd);
        let geometry = a.z / a.length() * b.z / b.length() * (a.z / a.length()) * (b.z / b.length())
            / (a.length_squared() * b.length_squared());
        totals.push((total, geometry, xd));
    }
    // Ratio of totals = ratio of geometry × the SPAD collection at each detection spot.
    let collect = |xd: DVec3| {
        let s = INST.spad - xd;
        s.z / s.length() / s.length_squared()
    };
    let measured = totals[0].0 / totals[1].0;
    let expected = totals[0].1 * collect(totals[0].2) / (totals[1].1 * collect(totals[1].2));
    assert!(
        (measured / expected - 1.0).abs() < 0.02,
        "falloff ratio {measured} vs {expected} (2 % tolerance)"
    );
}

#[test]
fn mirror_symmetric_scenes_give_mirror_transients() {
    let world = World::new(
        scene(vec![
            shapes::bars(3, 0.02, 0.3, 0.02).transformed(glam::DMat3::IDENTITY, DVec3::new(0.0, 0.0, 0.5)),
        ]),
        0.002,
        3,
    );
    let inst = Instrument {
        laser: DVec3::new(0.0, 0.3, 2.0),
        spad: DVec3::new(0.0, -0.3, 2.0),
    };
    let det = hidden_only(&detector());
    let pair = |s: f64| SpotPair {
        illumination: spot(0.25 * s, 0.1),
        detection: spot(-0.15 * s, -0.2),
    };
    let h = world.third_bounce(&inst, &[pair(1.0), pair(-1.0)], &det, 1.0);
    let total: f64 = h[0].iter().sum();
    let diff: f64 = h[0].iter().zip(&h[1]).map(|(a, b)| (a - b).abs()).sum();
    // Stratified jitter makes the two sample sets differ slightly; 3 % in L1.
    assert!(
        total > 0.0 && diff / total < 0.03,
        "L1 asymmetry {}",
        diff / total
    );
}

#[test]
fn noise_is_poisson_and_reproducible() {
    let lambda = vec![3.7; 20_000];
    let a = sample_counts(&lambda, 11, 5);
    assert_eq!(a, sample_counts(&lambda, 11, 5));
    assert_ne!(a, sample_counts(&lambda, 11, 6));
    assert_ne!(a, sample_counts(&lambda, 12, 5));
    let n = a.len() as f64;
    let mean = a.iter().map(|&v| v as f64).sum::<f64>() / n;
    let var = a.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / (n - 1.0);
    // Standard errors: mean √(λ/n) ≈ 0.014, variance ≈ λ√(2/n) ≈ 0.04 (plus excess
    // kurtosis); bounds at about 5 standard errors.
    assert!((mean - 3.7).abs() < 0.07, "mean {mean}");
    assert!((var - 3.7).abs() < 0.25, "variance {var}");
    // P(0) = e^{−λ}.
    let zeros = a.iter().filter(|&&v| v == 0).count() as f64 / n;
    assert!((zeros - (-3.7f64).exp()).abs() < 0.005, "zero fraction {zeros}");
    assert_eq!(sample_counts(&[0.0, f64::NAN, -1.0], 1, 1), vec![0, 0, 0]);
}

/// A mean a 32-bit bin counter cannot hold fills it: `u32::MAX`, which the devices
/// flag as overflow, however far past it the mean lies (infinite included). Until
/// 2026-12-07 a mean beyond the Poisson sampler's range (about 1.8·10¹⁹) gave 0 counts
/// and no flag.
#[test]
fn a_mean_beyond_what_a_counter_holds_fills_it() {
    let means = [f64::from(u32::MAX), 5e9, 1e20, f64::INFINITY, 1e6];
    let counts = sample_counts(&means, 2, 1);
    assert_eq!(counts[..4], [u32::MAX; 4]);
    // A large mean a counter holds is still drawn: within 5 σ of it.
    assert!((f64::from(counts[4]) - 1e6).abs() < 5e3, "{}", counts[4]);
}

#[test]
fn first_bounce_locates_the_relay() {
    let world = World::new(scene(vec![patch(DVec3::new(0.0, 0.0, 0.6))]), 0.005, 1);
    let det = hidden_only(&detector());
    let target = DVec3::new(0.3, -0.2, 0.0);
    let dir = (target - INST.spad).normalize();
    let (hit, h) = world.first_bounce(&INST, dir, &det, 1e-3).unwrap();
    assert!(hit.on_relay && hit.point.distance(target) < 1e-9, "{hit:?}");
    let path = target.distance(INST.laser) + target.distance(INST.spad);
    let peak = h.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
    let expected = det.bin_of_path(path);
    assert!(
        (peak as f64 + 0.5 - expected).abs() <= 1.0,
        "peak bin {peak}, expected {expected}"
    );
    assert!(h[peak] > 100.0, "a LOS return should be strong: {}", h[peak]);
}

#[test]
fn the_gate_removes_the_direct_return_of_a_confocal_pair() {
    let world = World::new(scene(vec![patch(DVec3::new(0.0, 0.0, 0.6))]), 0.002, 1);
    let pair = SpotPair {
        illumination: spot(0.1, 0.1),
        detection: spot(0.1, 0.1),
    };
    let det = hidden_only(&detector());
    let ungated = Detector {
        gate_margin: None,
        ..det
    };
    let gated = world.third_bounce(&INST, &[pair], &det, 1.0);
    let open = world.third_bounce(&INST, &[pair], &ungated, 1.0);
    let direct_bin = det.bin_of_path(
        INST.laser.distance(pair.illumination.point) + pair.illumination.point.distance(INST.spad),
    ) as usize;
    assert!(
        open[0][direct_bin] > 1e3 * gated[0].iter().sum::<f64>().max(1e-30),
        "direct return present without gate"
    );
    assert_eq!(gated[0][direct_bin], 0.0);
    // The hidden return (1.2 m further) survives the gate.
    assert!(gated[0].iter().sum::<f64>() > 0.0);
}

/// An ungated SPAD whose window starts after the confocal direct return is blinded by
/// it: the direct return takes each cycle's one detection before the window opens,
/// and the hidden return inside the window is all but gone, as on a real first-photon
/// counter; gated, or without pile-up, nothing before the window takes anything.
/// Until 2026-12-07 arrivals before the window were dropped, and the ungated SPAD
/// showed the hidden return as cleanly as the gated one.
#[test]
fn a_direct_return_before_the_window_blinds_an_ungated_spad() {
    let world = World::new(scene(vec![patch(DVec3::new(0.0, 0.0, 0.6))]), 0.002, 1);
    let pair = SpotPair {
        illumination: spot(0.1, 0.1),
        detection: spot(0.1, 0.1),
    };
    let det = Detector {
        offset: 15e-9,
        pile_up: true,
        ..hidden_only(&detector())
    };
    let direct = INST.laser.distance(pair.illumination.point) + pair.illumination.point.distance(INST.spad);
    assert!(
        det.bin_of_path(direct) < 0.0,
        "the direct return falls before the window"
    );
    let sum = |d: &Detector| -> f64 { world.third_bounce(&INST, &[pair], d, 1.0)[0].iter().sum() };
    let ungated = |d: &Detector| Detector {
        gate_margin: None,
        ..*d
    };
    let (gated, blinded) = (sum(&det), sum(&ungated(&det)));
    assert!(gated > 0.0, "the hidden return is in the window");
    assert!(blinded < 1e-3 * gated, "ungated {blinded} against gated {gated}");
    let no_pile_up = Detector {
        pile_up: false,
        ..det
    };
    let (a, b) = (sum(&no_pile_up), sum(&ungated(&no_pile_up)));
    assert!((a - b).abs() <= 1e-9 * a, "{a} against {b}");
}

#[test]
fn pile_up_only_removes_counts_and_weighs_on_late_bins() {
    let det = Detector {
        pile_up: true,
        ..detector()
    };
    let mut signal = vec![0.0; det.bins];
    signal[100] = 2.0;
    signal[600] = 2.0;
    let with = det.expected_counts(&signal, None, 1e-3);
    let without = Detector {
        pile_up: false,
        ..det
    }
    .expected_counts(&signal, None, 1e-3);
    assert!(with.iter().zip(&without).all(|(a, b)| *a <= *b + 1e-9));
    // The later peak is shadowed by the earlier one.
    assert!(with[600] < 0.9 * with[100], "{} vs {}", with[600], with[100]);
    assert!(with.iter().sum::<f64>() <= det.cycles(1e-3));
}

#[test]
fn a_plate_in_front_shadows_the_patch_behind_it() {
    let behind = DVec3::new(0.0, 0.0, 0.9);
    let plate = Mesh::rectangle([-0.3, 0.3], [-0.3, 0.3])
        .transformed(glam::DMat3::IDENTITY, DVec3::new(0.0, 0.0, 0.45));
    let det = hidden_only(&detector());
    let pair = SpotPair {
        illumination: spot(-0.05, 0.02),
        detection: spot(0.04, -0.03),
    };
    let (xi, xd) = (pair.illumination.point, pair.detection.point);
    let path = INST.laser.distance(xi) + xi.distance(behind) + behind.distance(xd) + xd.distance(INST.spad);
    let bin = det.bin_of_path(path) as usize;
    let window = |h: &[f64]| h[bin - 3..=bin + 3].iter().sum::<f64>();
    let open = World::new(scene(vec![patch(behind)]), 0.002, 1).third_bounce(&INST, &[pair], &det, 1.0);
    let shadowed =
        World::new(scene(vec![patch(behind), plate]), 0.002, 1).third_bounce(&INST, &[pair], &det, 1.0);
    assert!(window(&open[0]) > 0.0, "the patch alone returns light");
    assert_eq!(
        window(&shadowed[0]),
        0.0,
        "the plate must block the patch behind it"
    );
}

/// A sync divider of N leaves each pulse's photons as they are: a TDC cycle then
/// spans N pulses, so the window holds each pulse's return a pulse period apart, and
/// the dwell has N times fewer cycles. Until 2026-12-07 the divider divided the
/// repetition rate, which multiplied each pulse's photons by N: the same total, one
/// peak, the signal N times a real counter's.
#[test]
fn a_sync_divider_shows_each_pulse_of_a_cycle_and_keeps_its_photons() {
    let centre = DVec3::new(0.1, -0.05, 0.6);
    let world = World::new(scene(vec![patch(centre)]), 0.001, 1);
    // 100 MHz: a pulse every 10 ns, 625 bins of 16 ps, within a 2048-bin window.
    let det = Detector {
        repetition_rate: 100e6,
        bins: 2048,
        ..hidden_only(&detector())
    };
    let pair = [SpotPair {
        illumination: spot(-0.2, 0.1),
        detection: spot(0.3, -0.2),
    }];
    let one = world.third_bounce(&INST, &pair, &det, 1e-3).pop().unwrap();
    let two = world
        .third_bounce(
            &INST,
            &pair,
            &Detector {
                sync_divider: 2,
                ..det
            },
            1e-3,
        )
        .pop()
        .unwrap();
    let peak = one
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(b, _)| b)
        .unwrap();
    assert!(
        peak + 625 + 10 < det.bins,
        "the second pulse's return in the window"
    );
    let around = |h: &[f64], at: usize| h[at - 10..at + 10].iter().sum::<f64>();
    let (first, second, whole) = (around(&two, peak), around(&two, peak + 625), around(&one, peak));
    // Half the cycles, each holding the first pulse's photons: half the counts there.
    assert!((first / whole - 0.5).abs() < 1e-9, "{first} against {whole}");
    // The second pulse's return, a period later, as large.
    assert!((second / first - 1.0).abs() < 0.02, "{second} against {first}");
    // Without pile-up the total is the same: as many pulses over the dwell.
    let (t1, t2) = (one.iter().sum::<f64>(), two.iter().sum::<f64>());
    assert!((t2 / t1 - 1.0).abs() < 0.02, "{t2} against {t1}");
}

/// A gated SPAD is gated on every laser pulse, not once a cycle: with a sync divider
/// of 2 and a window longer than a period, a confocal pair's direct return is blocked
/// for both pulses, the second a period after the first, while each pulse's hidden
/// return passes whole. Until 2026-12-07 the gate opened once, at the first pulse's
/// direct path, and the second pulse's direct return passed ungated.
#[test]
fn the_gate_blocks_the_direct_return_of_every_pulse_of_a_cycle() {
    let centre = DVec3::new(0.0, 0.0, 0.6);
    let world = World::new(scene(vec![patch(centre)]), 0.002, 1);
    let pair = SpotPair {
        illumination: spot(0.1, 0.1),
        detection: spot(0.1, 0.1),
    };
    // 100 MHz: a pulse every 10 ns, 625 bins of 16 ps, within a 2048-bin window.
    let period = 625;
    let gated = Detector {
        repetition_rate: 100e6,
        bins: 2048,
        sync_divider: 2,
        ..hidden_only(&detector())
    };
    let ungated = Detector {
        gate_margin: None,
        ..gated
    };
    let with_gate = world.third_bounce(&INST, &[pair], &gated, 1.0).pop().unwrap();
    let without = world.third_bounce(&INST, &[pair], &ungated, 1.0).pop().unwrap();
    let xi = pair.illumination.point;
    let (first_leg, last_leg) = (INST.laser.distance(xi), xi.distance(INST.spad));
    let direct = gated.bin_of_path(first_leg + last_leg) as usize;
    let hidden = gated.bin_of_path(first_leg + 2.0 * xi.distance(centre) + last_leg) as usize;
    assert!(
        direct >= 10 && hidden + period + 10 < gated.bins,
        "both pulses' returns in the window"
    );
    let around = |h: &[f64], at: usize| h[at - 10..at + 10].iter().sum::<f64>();
    for pulse in [0, period] {
        assert!(
            around(&without, direct + pulse) > 1e3 * around(&with_gate, hidden + pulse),
            "the direct return {pulse} bins on, without the gate"
        );
        assert_eq!(
            around(&with_gate, direct + pulse),
            0.0,
            "the gate must block the direct return {pulse} bins on"
        );
        let (passed, all) = (
            around(&with_gate, hidden + pulse),
            around(&without, hidden + pulse),
        );
        assert!(
            all > 0.0 && (passed / all - 1.0).abs() < 1e-12,
            "the hidden return {pulse} bins on: {passed} of {all}"
        );
    }
}

/// The SPAD's dead time costs counts beyond Coates' first-photon model only where it
/// can reach from one cycle's window into the next: `detector()`'s 50 ns against a
/// 100 ns cycle and a 16 ns window cannot, 50 ns against a 40 ns cycle can.
#[test]
fn dead_time_costs_counts_only_where_it_reaches_the_next_window() {
    let det = Detector {
        pile_up: true,
        ..detector()
    };
    let mut signal = vec![0.0; det.bins];
    signal[100] = 0.3;
    let coates = |det: &Detector| {
        // The dark counts between the sync and the window take their share first.
        let before = (det.dark_count_rate + det.ambient_rate) * det.offset;
        let (mut survive, mut sum) = ((-before).exp(), 0.0);
        for &s in &signal {
            let r = det.efficiency * det.transmission * s + det.dark_count_rate * det.bin_width;
            sum += survive * (1.0 - (-r).exp());
            survive *= (-r).exp();
        }
        sum * det.cycles(1e-3)
    };
    assert!(!det.dead_time_reaches_next_cycle());
    let total: f64 = det.expected_counts(&signal, None, 1e-3).iter().sum();
    assert!(
        (total / coates(&det) - 1.0).abs() < 1e-9,
        "{total} against {}",
        coates(&det)
    );
    let fast = Detector {
        repetition_rate: 25e6,
        ..det
    };
    assert!(fast.dead_time_reaches_next_cycle());
    let total: f64 = fast.expected_counts(&signal, None, 1e-3).iter().sum();
    assert!(total < 0.99 * coates(&fast), "{total} against {}", coates(&fast));
}

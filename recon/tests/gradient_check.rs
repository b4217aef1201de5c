//! The analytic gradient of the 3D-GTR loss against central finite differences, in
//! f64, for every raw parameter of many random primitives seen from random pairs on a
//! curved relay with tilted and opposite-facing normals, confocal and not.
use glam::{DQuat, DVec3};
use periscope_recon::gpu::testing::gpu;
use periscope_recon::gtr::{
    GaussianCloud, Loss, Primitive, RawGrads, RenderOptions, ScaleBounds, batch_loss, batch_loss_grad,
    batch_loss_grad_gpu, render_set,
};
use periscope_recon::{Pair, RoiBox, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Step for the central differences on raw parameters (all O(1) by construction).
/// Truncation error is O(h²) ≈ 1e-10 relative, round-off ≈ ε·L/h ≈ 1e-11 relative.
const STEP: f64 = 1e-5;
/// Relative agreement required per parameter: the error budget above leaves five
/// orders of magnitude of margin, so 1e-5 still catches any wrong term.
const RTOL: f64 = 1e-5;
/// Absolute floor, relative to the largest gradient entry of the same group: entries
/// that are ~1e-8 of the group's scale are numerically zero for the optimiser.
const ATOL_OF_GROUP_MAX: f64 = 1e-7;

fn random_unit(rng: &mut ChaCha8Rng) -> DVec3 {
    loop {
        let v = DVec3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        if let Some(u) = v.try_normalize() {
            return u;
        }
    }
}

/// A curved (S-shaped in x) relay at z ≈ 0 facing +z, with tilted normals, one
/// opposite-facing normal and some confocal pairs.
fn pairs(rng: &mut ChaCha8Rng, n: usize) -> Vec<Pair> {
    (0..n)
        .map(|i| {
            let mut point = || {
                let x: f64 = rng.random_range(-0.5..0.5);
                let y: f64 = rng.random_range(-0.5..0.5);
                let z = 0.08 * (std::f64::consts::PI * x * 2.0).sin();
                let tilt = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 1.0);
                (DVec3::new(x, y, z), tilt.normalize())
            };
            let (xi, ni) = point();
            let (xd, nd) = point();
            match i % 5 {
                0 => Pair::confocal(xi, ni),
                1 => Pair { xi, ni: -ni, xd, nd }, // illumination normal facing away
                _ => Pair { xi, ni, xd, nd },
            }
        })
        .collect()
}

/// Primitives, pairs and "measurements" of the same magnitude as the rendered signal
/// (peak about 1), so the loss responds to every parameter well above round-off. Also
/// returns the gain that brings the rendering to that scale.
fn scene(seed: u64, k: usize, n_pairs: usize) -> (GaussianCloud, TransientSet, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let roi = RoiBox::from_bounds(DVec3::new(-0.4, -0.4, 0.3), DVec3::new(0.4, 0.4, 0.9)).unwrap();
    let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 2e-3, max: 0.2 }).unwrap();
    for _ in 0..k {
        let centre = DVec3::new(
            rng.random_range(-0.35..0.35),
            rng.random_range(-0.35..0.35),
            rng.random_range(0.35..0.85),
        );
        let scale = DVec3::new(
            rng.random_range(0.004..0.06),
            rng.random_range(0.004..0.06),
            rng.random_range(0.004..0.06),
        );
        let rotation = DQuat::from_axis_angle(random_unit(&mut rng), rng.random_range(0.0..3.0));
        cloud
            .push(Primitive {
                centre,
                scale,
                rotation,
                albedo: rng.random_range(0.2..2.0),
            })
            .unwrap();
    }
    let axis = TimeAxis {
        start: 0.4,
        width: 0.01,
        bins: 260,
    };
    let mut geometry = TransientSet::new(axis).unwrap();
    for pair in pairs(&mut rng, n_pairs) {
        geometry.push(pair, &vec![0.0; axis.bins]).unwrap();
    }
    let rendered = render_set(&cloud.kernels(), &geometry, &RenderOptions::default());
    let gain = 1.0 / rendered.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut set = TransientSet::new(axis).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        // Measured = a distorted copy of the rendering plus a little background.
        let hist: Vec<f32> = rendered[i * axis.bins..(i + 1) * axis.bins]
            .iter()
            .map(|&v| (gain * v * rng.random_range(0.3..1.5) + rng.random_range(0.0..0.05)) as f32)
            .collect();
        set.push(*pair, &hist).unwrap();
    }
    (cloud, set, gain)
}

fn options(gain: f64, use_ni: bool, use_nd: bool) -> RenderOptions {
    RenderOptions {
        gain,
        // Wide window: the truncation of far tails is a separate, documented
        // approximation; here we test the derivative of the smooth model.
        window_sigmas: 9.0,
        sigma_sys: 0.004,
        use_ni,
        use_nd,
        ..RenderOptions::default()
    }
}

/// Access to one raw-parameter group of a cloud.
type Field = fn(&mut GaussianCloud) -> &mut Vec<f64>;

fn check(seed: u64, use_ni: bool, use_nd: bool) {
    check_loss(seed, use_ni, use_nd, Loss::L2);
}

fn check_loss(seed: u64, use_ni: bool, use_nd: bool, loss: Loss) {
    let (mut cloud, set, gain) = scene(seed, 12, 10);
    let opt = RenderOptions {
        loss,
        ..options(gain, use_ni, use_nd)
    };
    let batch: Vec<usize> = (0..set.len()).collect();
    let mut grads = RawGrads::default();
    let loss = batch_loss_grad(&cloud, &cloud.kernels(), &set, &batch, &opt, &mut grads);
    assert!(loss.is_finite() && loss > 0.0);
    let groups: [(&str, Field, &Vec<f64>); 4] = [
        ("centres", |c| &mut c.centres, &grads.centres),
        ("scales", |c| &mut c.scales, &grads.scales),
        ("rotations", |c| &mut c.rotations, &grads.rotations),
        ("albedo", |c| &mut c.albedo, &grads.albedo),
    ];
    let mut checked = 0;
    for (name, field, analytic) in groups {
        let group_max = analytic.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(group_max > 0.0, "{name}: gradient is identically zero");
        for i in 0..analytic.len() {
            let original = field(&mut cloud)[i];
            field(&mut cloud)[i] = original + STEP;
            let plus = batch_loss(&cloud.kernels(), &set, &batch, &opt).0;
            field(&mut cloud)[i] = original - STEP;
            let minus = batch_loss(&cloud.kernels(), &set, &batch, &opt).0;
            field(&mut cloud)[i] = original;
            let numeric = (plus - minus) / (2.0 * STEP);
            let a = analytic[i];
            let tol = RTOL * a.abs().max(numeric.abs()) + ATOL_OF_GROUP_MAX * group_max;
            assert!(
                (a - numeric).abs() <= tol,
                "seed {seed}, {name}[{i}]: analytic {a:e} vs finite difference {numeric:e} (tolerance {tol:e})"
            );
            checked += 1;
        }
    }
    assert_eq!(checked, 12 * 11);
}

#[test]
fn gradient_matches_finite_differences() {
    for seed in 0..4 {
        check(seed, true, true);
    }
}

#[test]
fn gradient_matches_without_relay_normals() {
    // The paper's ablations: cosine weights switched off one at a time and together.
    check(10, false, true);
    check(11, true, false);
    check(12, false, false);
}

#[test]
fn poisson_deviance_gradient_matches_finite_differences() {
    // The photon-count loss: its per-bin weight 1/(τ̂ + β) varies with the model, so
    // this checks the chain through the rate, with a background small against the
    // signal (peak about 1) and one as large as the weakest bins.
    for (seed, background) in [(20, 1e-3), (21, 0.05), (22, 0.3)] {
        check_loss(seed, true, true, Loss::Poisson { background });
    }
    check_loss(23, false, false, Loss::Poisson { background: 0.05 });
}

#[test]
fn poisson_deviance_is_zero_for_a_perfect_fit_and_positive_otherwise() {
    let (cloud, set, gain) = scene(24, 12, 10);
    let background = 0.02;
    let opt = RenderOptions {
        loss: Loss::Poisson { background },
        ..options(gain, true, true)
    };
    let batch: Vec<usize> = (0..set.len()).collect();
    let rendered = render_set(&cloud.kernels(), &set, &opt);
    // Data equal to the rate the model predicts: the deviance vanishes.
    let mut exact = TransientSet::new(*set.axis()).unwrap();
    for (i, pair) in set.pairs().iter().enumerate() {
        let bins = set.axis().bins;
        let h: Vec<f32> = rendered[i * bins..(i + 1) * bins]
            .iter()
            .map(|&v| (v + background) as f32)
            .collect();
        exact.push(*pair, &h).unwrap();
    }
    let (at_truth, _) = batch_loss(&cloud.kernels(), &exact, &batch, &opt);
    let total: f64 = rendered.iter().sum();
    assert!(at_truth.abs() <= 1e-5 * total, "deviance {at_truth} at the truth");
    let (elsewhere, _) = batch_loss(&cloud.kernels(), &set, &batch, &opt);
    assert!(
        elsewhere > 100.0 * at_truth.abs() && elsewhere.is_finite(),
        "{elsewhere}"
    );
}

#[test]
fn back_facing_pairs_contribute_nothing() {
    let (cloud, set, gain) = scene(3, 12, 10);
    // Pair 1 (i % 5 == 1) has its illumination normal flipped away from the ROI.
    let flipped = set.pairs()[1];
    assert!(
        cloud
            .kernels()
            .iter()
            .all(|k| flipped.ni.dot(k.x - flipped.xi) < 0.0)
    );
    let mut grads = RawGrads::default();
    let opt = options(gain, true, true);
    let with = batch_loss_grad(&cloud, &cloud.kernels(), &set, &[1], &opt, &mut grads);
    let measured: f64 = set.histogram(1).iter().map(|&c| (c as f64).powi(2)).sum();
    assert!(
        (with - measured).abs() <= 1e-12 * measured,
        "{with} vs {measured}"
    );
    assert!(grads.centres.iter().chain(&grads.albedo).all(|&g| g == 0.0));
}

/// `set` with each pair's recording narrowed to a window of its own, as legs that
/// differ from pair to pair shift a TDC window on the hidden-path axis: 0.6 of the
/// axis, starting at 0, 0.1, ... 0.4 of it (so every pair misses some of it, and some
/// of the light).
fn windowed(set: &TransientSet) -> TransientSet {
    let mut out = set.clone();
    let axis = *set.axis();
    let span = axis.end() - axis.start;
    for i in 0..out.len() {
        let from = axis.start + 0.1 * (i % 5) as f64 * span;
        out.limit_recorded(i, (from, from + 0.6 * span));
    }
    out
}

/// Bins a pair's recording did not cover ([`TransientSet::limit_recorded`]) take no
/// part in the fit: whatever they hold (zeros, or counts nobody should trust), a
/// batch's loss and gradient are the same bits, on the CPU and on the GPU; while the
/// same counts in recorded bins change both.
#[test]
fn a_pairs_unrecorded_bins_change_neither_the_loss_nor_its_gradient() {
    let (cloud, set, gain) = scene(13, 40, 10);
    let opt = RenderOptions {
        loss: Loss::Poisson { background: 0.02 },
        ..options(gain, true, true)
    };
    let zeros = windowed(&set);
    // The same windows over histograms that hold 7 counts a bin outside them.
    let mut junk = TransientSet::new(*set.axis()).unwrap();
    for i in 0..set.len() {
        let kept = zeros.recorded(i);
        assert!(kept.len() < set.axis().bins && !kept.is_empty(), "{kept:?}");
        let h: Vec<f32> = (0..set.axis().bins)
            .map(|b| {
                if kept.contains(&b) {
                    zeros.histogram(i)[b]
                } else {
                    7.0
                }
            })
            .collect();
        junk.push(set.pairs()[i], &h).unwrap();
    }
    let everywhere = junk.clone();
    let junk = windowed(&junk);
    let batch: Vec<usize> = (0..set.len()).collect();
    let kernels = cloud.kernels();
    let run = |set: &TransientSet| {
        let mut grads = RawGrads::default();
        let loss = batch_loss_grad(&cloud, &kernels, set, &batch, &opt, &mut grads);
        (loss, grads)
    };
    let bits = |(loss, g): &(f64, RawGrads)| {
        std::iter::once(*loss)
            .chain(
                g.centres
                    .iter()
                    .chain(&g.scales)
                    .chain(&g.rotations)
                    .chain(&g.albedo)
                    .copied(),
            )
            .map(f64::to_bits)
            .collect::<Vec<_>>()
    };
    let (a, b, c) = (run(&zeros), run(&junk), run(&everywhere));
    assert!(a.0 > 0.0 && a.1.albedo.iter().any(|&g| g != 0.0));
    assert_eq!(
        bits(&a),
        bits(&b),
        "unrecorded bins moved the CPU's loss or gradient"
    );
    assert!(
        c.0 > 1.5 * a.0,
        "recorded, the junk counts: loss {} against {}",
        c.0,
        a.0
    );
    if let Some(gpu) = gpu("a_pairs_unrecorded_bins_change_neither_the_loss_nor_its_gradient") {
        let on_gpu = |set: &TransientSet| {
            let mut grads = RawGrads::default();
            let loss = batch_loss_grad_gpu(&gpu, &cloud, &kernels, set, &batch, &opt, &mut grads).unwrap();
            (loss, grads)
        };
        let (ga, gb) = (on_gpu(&zeros), on_gpu(&junk));
        assert_eq!(
            bits(&ga),
            bits(&gb),
            "unrecorded bins moved the GPU's loss or gradient"
        );
        assert!(
            (ga.0 - a.0).abs() <= 1e-4 * a.0,
            "GPU {} against CPU {}",
            ga.0,
            a.0
        );
    }
}

/// Relative L2 distance of `got` from `want`.
fn relative_l2(got: &[f64], want: &[f64]) -> f64 {
    let num: f64 = got.iter().zip(want).map(|(a, b)| (a - b) * (a - b)).sum();
    let den: f64 = want.iter().map(|b| b * b).sum();
    (num / den).sqrt()
}

/// A mini-batch's loss and raw gradient on the GPU (f32) agree with the CPU's (f64):
/// 300 primitives, 12 pairs (with known per-pair gains: a point-source laser's
/// falloff), the L2 loss and the Poisson deviance, with and without the cosines, and
/// each pair's recording narrowed to a window of its own. Bound: 1e-4 relative on the
/// loss and 1e-3 relative L2 on each parameter group.
#[test]
fn the_gpu_step_is_the_cpu_step() {
    let Some(gpu) = gpu("the_gpu_step_is_the_cpu_step") else {
        return;
    };
    let (cloud, set, gain) = scene(5, 300, 12);
    // Per-pair gains: a laser in front of the relay lights the pairs whose
    // illumination normal faces it (not those of pair i % 5 == 1).
    let facing: Vec<usize> = (0..set.len()).filter(|i| i % 5 != 1).collect();
    let mut lit = set.subset(&facing);
    lit.compensate_laser_falloff(DVec3::new(0.0, -0.8, 1.2)).unwrap();
    let windowed = windowed(&lit);
    let kernels = cloud.kernels();
    let batch: Vec<usize> = (0..lit.len()).rev().collect();
    for (loss, use_ni, set) in [
        (Loss::L2, true, &set),
        (Loss::Poisson { background: 0.02 }, true, &lit),
        (Loss::L2, false, &lit),
        (Loss::Poisson { background: 0.02 }, true, &windowed),
    ] {
        let opt = RenderOptions {
            loss,
            window_sigmas: 4.0,
            ..options(gain, use_ni, true)
        };
        let mut want = RawGrads::default();
        let l_cpu = batch_loss_grad(&cloud, &kernels, set, &batch, &opt, &mut want);
        let mut got = RawGrads::default();
        let l_gpu = batch_loss_grad_gpu(&gpu, &cloud, &kernels, set, &batch, &opt, &mut got).unwrap();
        eprintln!("{loss:?}: loss {l_gpu} against {l_cpu}");
        assert!(
            l_cpu > 0.0 && (l_gpu - l_cpu).abs() <= 1e-4 * l_cpu,
            "{loss:?}: {l_gpu} against {l_cpu}"
        );
        for (name, a, b) in [
            ("centres", &got.centres, &want.centres),
            ("scales", &got.scales, &want.scales),
            ("rotations", &got.rotations, &want.rotations),
            ("albedo", &got.albedo, &want.albedo),
        ] {
            let e = relative_l2(a, b);
            eprintln!("{loss:?}: {name} relative L2 {e:.2e}");
            assert!(b.iter().any(|&v| v != 0.0), "{name}: the gradient is seen");
            assert!(e <= 1e-3, "{loss:?}, {name}: relative L2 {e:e}");
        }
    }
}

/// The GPU's analytic gradient against central differences of the GPU's own (f32)
/// loss, for every raw parameter of 12 primitives seen from 10 pairs, with steps of
/// 5e-3: within 2 % plus 1e-3 of the parameter group's largest entry. The f32 loss
/// carries round-off of about 1e-7 of itself that is not smooth in the parameters
/// (each bin's mass is a difference of two tails), which steps of 1e-3 turned into
/// differences wrong by up to 0.8 of this tolerance; at 5e-3 the worst is 0.21.
#[test]
fn the_gpu_gradient_matches_finite_differences() {
    let Some(gpu) = gpu("the_gpu_gradient_matches_finite_differences") else {
        return;
    };
    const GPU_STEP: f64 = 5e-3;
    let (mut cloud, set, gain) = scene(7, 12, 10);
    let opt = options(gain, true, true);
    let batch: Vec<usize> = (0..set.len()).collect();
    let loss_of = |cloud: &GaussianCloud, grads: &mut RawGrads| {
        batch_loss_grad_gpu(&gpu, cloud, &cloud.kernels(), &set, &batch, &opt, grads).unwrap()
    };
    let mut grads = RawGrads::default();
    let loss = loss_of(&cloud, &mut grads);
    assert!(loss.is_finite() && loss > 0.0);
    let groups: [(&str, Field, Vec<f64>); 4] = [
        ("centres", |c| &mut c.centres, grads.centres.clone()),
        ("scales", |c| &mut c.scales, grads.scales.clone()),
        ("rotations", |c| &mut c.rotations, grads.rotations.clone()),
        ("albedo", |c| &mut c.albedo, grads.albedo.clone()),
    ];
    let mut scratch = RawGrads::default();
    let mut worst = 0.0f64;
    for (name, field, analytic) in groups {
        let top = analytic.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        assert!(top > 0.0, "{name}: the gradient is identically zero");
        for (i, &a) in analytic.iter().enumerate() {
            let original = field(&mut cloud)[i];
            field(&mut cloud)[i] = original + GPU_STEP;
            let plus = loss_of(&cloud, &mut scratch);
            field(&mut cloud)[i] = original - GPU_STEP;
            let minus = loss_of(&cloud, &mut scratch);
            field(&mut cloud)[i] = original;
            let numeric = (plus - minus) / (2.0 * GPU_STEP);
            let tol = 0.02 * a.abs().max(numeric.abs()) + 1e-3 * top;
            worst = worst.max((a - numeric).abs() / tol);
            assert!(
                (a - numeric).abs() <= tol,
                "{name}[{i}]: analytic {a:e} vs finite difference {numeric:e} (tolerance {tol:e})"
            );
        }
    }
    eprintln!("worst disagreement {worst:.2} of the tolerance");
}

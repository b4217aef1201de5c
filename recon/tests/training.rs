//! Behaviour of the trainer: degenerate input never produces NaN, results are
//! reproducible, transients can stream in while it runs, and cancellation is clean.
mod common;
use common::on_threads;
use std::sync::mpsc;
use std::time::Duration;

use glam::{DQuat, DVec3};
use periscope_recon::gtr::{
    AverageBatch, CancelToken, CoarseFit, Convergence, DENSIFY_ROUNDS, DensifySettings, GaussianCloud, Init,
    Loss, LossChoice, PairGains, Primitive, PruneSettings, RawGrads, RenderOptions, ScaleBounds,
    SurfacePrior, TrainConfig, TrainError, TrainEvent, TrainSummary, Trainer, batch_loss_grad,
    default_target_scale, densify, densify_after, estimate_background, estimate_pair_gains, first_negative,
    gain_groups, render_set, resolvable_separation,
};
use periscope_recon::{Pair, RoiBox, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn roi() -> RoiBox {
    RoiBox::from_bounds(DVec3::new(-0.3, -0.3, 0.4), DVec3::new(0.3, 0.3, 0.8)).unwrap()
}

fn axis() -> TimeAxis {
    TimeAxis::from_seconds(0.6, 32e-12, 240)
}

/// Planar-relay transients of one known primitive.
fn data(n: usize, seed: u64) -> TransientSet {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut truth = GaussianCloud::new(roi(), ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
    truth
        .push(Primitive {
            centre: DVec3::new(0.05, -0.04, 0.6),
            scale: DVec3::splat(0.02),
            rotation: DQuat::IDENTITY,
            albedo: 1.0,
        })
        .unwrap();
    let mut geometry = TransientSet::new(axis()).unwrap();
    for _ in 0..n {
        let xi = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
        let xd = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
        geometry
            .push(
                Pair {
                    xi,
                    ni: DVec3::Z,
                    xd,
                    nd: DVec3::Z,
                },
                &vec![0.0; axis().bins],
            )
            .unwrap();
    }
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let peak = rendered.iter().fold(0.0f64, |m, &v| m.max(v));
    let mut set = TransientSet::new(axis()).unwrap();
    for (i, pair) in geometry.pairs().iter().enumerate() {
        let h: Vec<f32> = rendered[i * axis().bins..(i + 1) * axis().bins]
            .iter()
            .map(|&v| (50.0 * v / peak) as f32)
            .collect();
        set.push(*pair, &h).unwrap();
    }
    set
}

fn config(primitives: usize, epochs: usize) -> TrainConfig {
    TrainConfig {
        primitives,
        epochs,
        initial_scale: Some(0.03),
        seed: 9,
        ..TrainConfig::default()
    }
}

fn all_finite(cloud: &GaussianCloud) -> bool {
    [&cloud.centres, &cloud.scales, &cloud.rotations, &cloud.albedo]
        .iter()
        .all(|v| v.iter().all(|x| x.is_finite()))
}

/// Runs `t` to the end: each counted or live epoch's (epoch, pairs, steps so far), and
/// the summary.
fn epochs_of(t: &mut Trainer) -> (Vec<(usize, usize, usize)>, TrainSummary) {
    let mut seen = Vec::new();
    let summary = t
        .run(None, &CancelToken::new(), &mut |e| {
            if let TrainEvent::Epoch {
                epoch, pairs, step, ..
            } = e
            {
                seen.push((*epoch, *pairs, *step));
            }
        })
        .unwrap();
    (seen, summary)
}

/// The bits of every centre of `cloud`, to compare two fits exactly.
fn centre_bits(cloud: &GaussianCloud) -> Vec<u64> {
    (0..cloud.len())
        .flat_map(|k| cloud.primitive(k).centre.to_array())
        .map(f64::to_bits)
        .collect()
}

#[test]
fn same_seed_same_result_whatever_the_thread_count() {
    let fit = |threads: usize| {
        on_threads(threads, || {
            let mut t = Trainer::new(config(300, 2), roi(), data(60, 1)).unwrap();
            t.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
            t.cloud().clone()
        })
    };
    let one = fit(1);
    assert_eq!(one, fit(2), "results differ between 1 and 2 threads");
    assert_eq!(one, fit(1), "results differ between two runs");
    let mut other = config(300, 2);
    other.seed = 10;
    let mut t = Trainer::new(other, roi(), data(60, 1)).unwrap();
    t.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
    assert_ne!(&one, t.cloud(), "the seed has no effect");
}

#[test]
fn zero_histograms_leave_parameters_finite() {
    let mut set = TransientSet::new(axis()).unwrap();
    for p in data(20, 2).pairs() {
        set.push(*p, &vec![0.0; axis().bins]).unwrap();
    }
    let mut t = Trainer::new(config(50, 3), roi(), set).unwrap();
    t.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
    assert!(all_finite(t.cloud()));
}

#[test]
fn empty_batches_and_degenerate_primitives_give_finite_gradients() {
    let set = data(10, 3);
    let bounds = ScaleBounds { min: 1e-6, max: 0.1 };
    let mut cloud = GaussianCloud::new(roi(), bounds).unwrap();
    let relay_point = set.pairs()[0].xi;
    let cases = [
        // A needle: two scales at the lower bound.
        (DVec3::new(0.0, 0.0, 0.6), DVec3::new(1.01e-6, 1.01e-6, 0.05)),
        // A flat disc seen edge-on from above.
        (DVec3::new(0.1, 0.1, 0.5), DVec3::new(0.05, 0.05, 1.01e-6)),
        // Just inside the ROI's corner.
        (roi().max() - 1e-9, DVec3::splat(0.01)),
    ];
    for (centre, scale) in cases {
        cloud
            .push(Primitive {
                centre,
                scale,
                rotation: DQuat::IDENTITY,
                albedo: 1.0,
            })
            .unwrap();
    }
    let opt = RenderOptions {
        gain: 1e6,
        ..RenderOptions::default()
    };
    let mut grads = RawGrads::default();
    let batch: Vec<usize> = (0..set.len()).collect();
    let loss = batch_loss_grad(&cloud, &cloud.kernels(), &set, &batch, &opt, &mut grads);
    assert!(loss.is_finite());
    for g in [&grads.centres, &grads.scales, &grads.rotations, &grads.albedo] {
        assert!(g.iter().all(|x| x.is_finite()), "{g:?}");
    }
    assert_eq!(
        batch_loss_grad(&cloud, &cloud.kernels(), &set, &[], &opt, &mut grads),
        0.0
    );
    assert!(grads.centres.iter().all(|&g| g == 0.0));

    // A primitive sitting on a relay point cannot be represented in a ROI in front of
    // the relay, so check the kernel directly: it must contribute nothing, not NaN.
    let on_relay =
        periscope_recon::gtr::Kernel::new(relay_point, glam::DMat3::IDENTITY, DVec3::splat(0.01), 1.0);
    let mut out = vec![0.0; axis().bins];
    periscope_recon::gtr::render_pair(&[on_relay], &set.pairs()[0], &axis(), &opt, &mut out);
    assert!(out.iter().all(|&v| v == 0.0));
}

#[test]
fn primitives_behind_the_relay_are_reported() {
    let behind = RoiBox::from_bounds(DVec3::new(-0.3, -0.3, -0.8), DVec3::new(0.3, 0.3, -0.4)).unwrap();
    let err = Trainer::new(config(50, 1), behind, data(10, 4)).err().unwrap();
    assert!(err.to_string().contains("in front of the relay"), "{err}");
}

#[test]
fn streamed_transients_are_fitted_and_counted_after_the_capture_ends() {
    let all = data(120, 5);
    let (tx, rx) = mpsc::channel();
    let empty = TransientSet::new(axis()).unwrap();
    let mut trainer = Trainer::new(config(40, 3), roi(), empty).unwrap();
    let producer = std::thread::spawn(move || {
        for start in (0..all.len()).step_by(30) {
            let mut part = TransientSet::new(*all.axis()).unwrap();
            for i in start..(start + 30).min(all.len()) {
                part.push(all.pairs()[i], all.histogram(i)).unwrap();
            }
            tx.send(part).unwrap();
            std::thread::sleep(Duration::from_millis(20));
        }
    });
    let mut events = Vec::new();
    let summary = trainer
        .run(Some(rx), &CancelToken::new(), &mut |e| events.push(e.clone()))
        .unwrap();
    producer.join().unwrap();
    assert_eq!(trainer.data().len(), 120);
    assert_eq!(summary.epochs, 3);
    let counted: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            TrainEvent::Epoch { epoch, pairs, .. } if *epoch > 0 => Some(*pairs),
            _ => None,
        })
        .collect();
    assert_eq!(
        counted,
        vec![120; 3],
        "counted epochs must see the complete data: {events:?}"
    );
    assert!(
        events
            .iter()
            .any(|e| matches!(e, TrainEvent::DataAdded { pairs: 120 }))
    );
    assert!(matches!(events.first(), Some(TrainEvent::DataAdded { .. })));
    assert!(matches!(events.last(), Some(TrainEvent::Pruned { .. })));
}

#[test]
fn a_small_capture_gets_more_epochs_to_reach_the_minimum_steps() {
    // 50 pairs in batches of 4 are 13 steps a pass: 2 epochs take 26 steps, so 60
    // steps need 5 epochs; the full 120 pairs (30 steps a pass) need only the 2.
    let mut cfg = TrainConfig {
        min_steps: 60,
        ..config(30, 2)
    };
    cfg.densify.rounds = 1;
    assert_eq!(cfg.counted_epochs(50), 5);
    assert_eq!(cfg.counted_epochs(120), 2);
    assert_eq!(
        cfg.counted_epochs(0),
        60,
        "no data: one step a pass, never a division by 0"
    );
    assert_eq!(
        config(30, 2).counted_epochs(50),
        2,
        "min_steps 0: exactly `epochs`"
    );

    let mut trainer = Trainer::new(cfg, roi(), data(50, 5)).unwrap();
    let (mut seen, mut densified) = (Vec::new(), Vec::new());
    let summary = trainer
        .run(None, &CancelToken::new(), &mut |e| match e {
            TrainEvent::Epoch { epoch, .. } => seen.push(*epoch),
            TrainEvent::Densified { epoch, .. } => densified.push(*epoch),
            _ => {}
        })
        .unwrap();
    assert_eq!(summary.epochs, 5);
    assert_eq!(trainer.steps(), 65);
    assert_eq!(seen, vec![1, 2, 3, 4, 5]);
    // One round in the first half of the 5 counted epochs (epochs 1 and 2), at its
    // end: a fit of 2 epochs spread over 5 does not densify after every one.
    assert_eq!(densified, vec![2]);
}

/// The averaged epochs take `average_batch` pairs a step and as many steps as the
/// others, so they train on fewer pairs, in turn from a shuffled pass over the capture.
/// `Same` is the fit before, step for step.
#[test]
fn averaged_epochs_take_fewer_pairs_a_step_in_as_many_steps() {
    assert_eq!([1, 2, 3, 4, 8].map(|b| AverageBatch::Half.of(b)), [1, 1, 2, 2, 4]);
    assert_eq!(AverageBatch::Same.of(4), 4);
    assert_eq!(
        [0, 1, 3, 9].map(|n| AverageBatch::Pairs(n).of(4)),
        [1, 1, 3, 4],
        "between one pair and the batch in force"
    );
    let cfg = |average_batch| TrainConfig {
        average_batch,
        average_from: 0.5,
        ..config(30, 4)
    };
    // 42 pairs in batches of 4: 11 steps an epoch; at half, 22 pairs in steps of 2.
    assert_eq!(cfg(AverageBatch::Half).epoch_plan(42, false), (42, 4));
    assert_eq!(cfg(AverageBatch::Half).epoch_plan(42, true), (22, 2));
    assert_eq!(cfg(AverageBatch::Pairs(3)).epoch_plan(42, true), (33, 3));
    assert_eq!(cfg(AverageBatch::Same).epoch_plan(42, true), (42, 4));
    assert_eq!(cfg(AverageBatch::Half).counted_pair_visits(42), 2 * 42 + 2 * 22);
    assert_eq!(cfg(AverageBatch::Same).counted_pair_visits(42), 4 * 42);

    let fit = |average_batch| {
        let mut trainer = Trainer::new(cfg(average_batch), roi(), data(42, 5)).unwrap();
        let (epochs, summary) = epochs_of(&mut trainer);
        (epochs, summary.average_batch, centre_bits(trainer.cloud()))
    };
    let (half, half_batch, half_centres) = fit(AverageBatch::Half);
    assert_eq!(
        half,
        vec![(1, 42, 11), (2, 42, 22), (3, 22, 33), (4, 22, 44)],
        "the averaged epochs (3 and 4) train on half the pairs in as many steps"
    );
    assert_eq!(half_batch, 2);
    let (same, same_batch, same_centres) = fit(AverageBatch::Same);
    assert_eq!(same, vec![(1, 42, 11), (2, 42, 22), (3, 42, 33), (4, 42, 44)]);
    assert_eq!(same_batch, 4);
    assert_ne!(
        half_centres, same_centres,
        "the averaged epochs saw other batches"
    );
    assert_eq!(
        fit(AverageBatch::Half).2,
        half_centres,
        "the same fit again, bit for bit"
    );
    // The epochs before averaging are the same steps either way: with averaging
    // from the end (never), Half changes nothing.
    let never = |average_batch| {
        let mut trainer = Trainer::new(
            TrainConfig {
                average_from: 1.0,
                ..cfg(average_batch)
            },
            roi(),
            data(42, 5),
        )
        .unwrap();
        trainer.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
        centre_bits(trainer.cloud())
    };
    assert_eq!(never(AverageBatch::Half), never(AverageBatch::Same));
}

/// Densification rounds: one after each epoch of the first half when that half holds
/// no more epochs than the rounds (a fit whose epochs are set, or a large capture),
/// and the rounds spread evenly over it when it holds more (a small capture, which the
/// step floor gives many short epochs).
#[test]
fn densification_rounds_are_spread_over_the_first_half() {
    let d = DensifySettings::default();
    assert_eq!(d.rounds, DENSIFY_ROUNDS);
    let rounds = |epochs: usize, d: &DensifySettings| -> Vec<usize> {
        (0..=epochs + 1)
            .filter(|&e| densify_after(e, epochs, d))
            .collect()
    };
    // A 1,024-pair capture at the step floor (32 epochs of 256 steps): every epoch of
    // the first half; a plan's own 16 epochs: every epoch of its first 8.
    assert_eq!(rounds(32, &d), (1..=16).collect::<Vec<_>>());
    assert_eq!(rounds(16, &d), (1..=8).collect::<Vec<_>>());
    // A 300-pair capture at the floor (110 epochs of 75 steps): 16 rounds over epochs
    // 1 to 55, three or four epochs (225–300 steps) apart, the last at 55.
    let small = rounds(110, &d);
    assert_eq!(
        small,
        vec![4, 7, 11, 14, 18, 21, 25, 28, 31, 35, 38, 42, 45, 49, 52, 55]
    );
    assert!(
        small.windows(2).all(|p| (3..=4).contains(&(p[1] - p[0]))),
        "{small:?}"
    );
    // Never before the first epoch, at or after the last, with `until` 0 or no rounds.
    assert!(!densify_after(0, 32, &d));
    assert!(!densify_after(32, 32, &d));
    assert!(rounds(1, &d).is_empty());
    assert!(rounds(32, &DensifySettings { until: 0.0, ..d }).is_empty());
    assert!(rounds(32, &DensifySettings { rounds: 0, ..d }).is_empty());
}

/// Streams `all` in batches of 30 (the first given at the start), each sent after
/// `delay`, into a fit on `threads` threads; returns the fitted cloud and the pairs seen
/// by each live epoch.
fn streamed_fit(all: &TransientSet, threads: usize, delay: Duration) -> (GaussianCloud, Vec<usize>) {
    let part = |from: usize| {
        let mut p = TransientSet::new(*all.axis()).unwrap();
        for i in from..(from + 30).min(all.len()) {
            p.push(all.pairs()[i], all.histogram(i)).unwrap();
        }
        p
    };
    on_threads(threads, || {
        let (tx, rx) = mpsc::channel();
        let parts: Vec<TransientSet> = (30..all.len()).step_by(30).map(part).collect();
        let producer = std::thread::spawn(move || {
            for p in parts {
                std::thread::sleep(delay);
                tx.send(p).unwrap();
            }
        });
        let mut trainer = Trainer::new(config(60, 3), roi(), part(0)).unwrap();
        let mut live = Vec::new();
        trainer
            .run(Some(rx), &CancelToken::new(), &mut |e| {
                if let TrainEvent::Epoch { epoch: 0, pairs, .. } = e {
                    live.push(*pairs)
                }
            })
            .unwrap();
        producer.join().unwrap();
        (trainer.cloud().clone(), live)
    })
}

#[test]
fn a_streamed_fit_is_the_same_bit_for_bit_however_fast_the_data_comes() {
    let all = data(120, 5);
    // All batches queued before the first epoch ends, or trickling in slower than
    // the epochs run; one thread or two.
    let (burst, live) = streamed_fit(&all, 1, Duration::ZERO);
    assert_eq!(live, [30, 60, 90, 120], "one live epoch per batch received");
    for (threads, delay) in [(2, Duration::from_millis(40)), (2, Duration::ZERO)] {
        let (cloud, live_again) = streamed_fit(&all, threads, delay);
        assert_eq!(live_again, live);
        assert!(
            cloud == burst,
            "{threads} threads, {delay:?} between batches: another fit"
        );
    }
}

#[test]
fn cancelling_stops_cleanly() {
    let mut trainer = Trainer::new(config(200, 10_000), roi(), data(60, 6)).unwrap();
    let cancel = CancelToken::new();
    let remote = cancel.clone();
    let canceller = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(200));
        remote.cancel();
    });
    let mut last = None;
    let summary = trainer
        .run(None, &cancel, &mut |e| last = Some(e.clone()))
        .unwrap();
    canceller.join().unwrap();
    assert!(summary.cancelled && summary.epochs < 10_000);
    assert!(matches!(last, Some(TrainEvent::Cancelled { .. })));
    assert!(all_finite(trainer.cloud()));
}

#[test]
fn backprojection_seeds_primitives_near_the_object() {
    let set = data(200, 7);
    let near = |init: Init| {
        let cfg = TrainConfig {
            init,
            ..config(400, 1)
        };
        let t = Trainer::new(cfg, roi(), set.clone()).unwrap();
        let c = t.cloud();
        (0..c.len())
            .filter(|&k| c.primitive(k).centre.distance(DVec3::new(0.05, -0.04, 0.6)) < 0.1)
            .count()
    };
    let uniform = near(Init::Uniform);
    let seeded = near(Init::Backprojection {
        grid: [24, 24, 16],
        uniform_fraction: 0.2,
    });
    assert!(
        seeded > 3 * uniform.max(1),
        "backprojection put {seeded} primitives near the object, uniform {uniform}"
    );
}

#[test]
fn pruning_drops_primitives_the_data_never_moved() {
    // With zero epochs nothing moves, so every primitive is pruned as untouched.
    let mut idle = Trainer::new(config(80, 0), roi(), data(40, 8)).unwrap();
    let mut pruned = None;
    idle.run(None, &CancelToken::new(), &mut |e| {
        if let TrainEvent::Pruned { before, kept } = e {
            pruned = Some((*before, *kept))
        }
    })
    .unwrap();
    assert_eq!(pruned, Some((80, 0)));
    assert!(idle.cloud().is_empty());

    // After training, primitives that moved and carry albedo are kept.
    let mut trained = Trainer::new(config(80, 3), roi(), data(40, 8)).unwrap();
    trained.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
    // All 80 moved and carry weight well above 2 % of the mean (measured), so the
    // default rules keep every one: pruning must not drop what the fit uses.
    let kept = trained.cloud().len();
    assert_eq!(kept, 80, "the default rules pruned primitives the fit moved");
    // Raising the weight floor to the median (the fit is deterministic, so the same
    // primitives come out of a second fit) drops about half, exactly those below it.
    let weights = |c: &GaussianCloud| {
        (0..c.len())
            .map(|k| c.primitive(k).weight())
            .collect::<Vec<f64>>()
    };
    let before = weights(trained.cloud());
    let mean = before.iter().sum::<f64>() / before.len() as f64;
    let mut sorted = before.clone();
    sorted.sort_by(f64::total_cmp);
    let floor = sorted[40] / mean;
    let cfg = TrainConfig {
        prune: PruneSettings {
            min_weight_fraction: floor,
            ..PruneSettings::default()
        },
        ..config(80, 3)
    };
    let mut strict = Trainer::new(cfg, roi(), data(40, 8)).unwrap();
    strict.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
    let want = before.iter().filter(|&&w| w >= floor * mean).count();
    assert!((30..=50).contains(&want), "{want} of 80 at or above the median");
    assert_eq!(strict.cloud().len(), want);
    let roi = roi();
    for k in 0..kept {
        let rel = ((trained.cloud().primitive(k).centre - roi.centre) / roi.half)
            .abs()
            .max_element();
        assert!(
            rel <= 0.98,
            "primitive {k} at the boundary survived pruning ({rel})"
        );
    }
}

/// A 60 × 20 mm primitive, 3 mm thin, wider than the densify tests' 10 mm target.
fn wide(rotation: DQuat) -> Primitive {
    Primitive {
        centre: DVec3::new(0.02, -0.01, 0.6),
        scale: DVec3::new(0.06, 0.02, 0.003),
        rotation,
        albedo: 1.0,
    }
}

#[test]
fn densify_splits_a_wide_bright_primitive_into_the_slot_of_a_dead_one() {
    let mut cloud = GaussianCloud::new(roi(), ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
    let wide = wide(DQuat::from_rotation_z(0.4) * DQuat::from_rotation_x(0.2));
    let small = |x: f64, s: f64| Primitive {
        centre: DVec3::new(x, 0.1, 0.55),
        scale: DVec3::new(s, s, 0.003),
        rotation: DQuat::IDENTITY,
        albedo: 1.0,
    };
    // 0: wide and carrying almost all the signal; 1 and 2: narrow, carrying next to
    // nothing (dead), 1 the lighter; 3: bright but already narrower than the target.
    cloud.push(wide).unwrap();
    cloud.push(small(-0.1, 0.004)).unwrap();
    cloud.push(small(0.1, 0.006)).unwrap();
    cloud
        .push(Primitive {
            albedo: 100.0,
            ..small(0.2, 0.009)
        })
        .unwrap();
    let before = cloud.clone();
    let mut again = cloud.clone();
    let moved = densify(&mut cloud, 0.05, 0.01, 0);
    assert_eq!(
        moved,
        vec![(0, 1)],
        "the wide primitive goes into the lightest dead slot"
    );
    assert_eq!(densify(&mut again, 0.05, 0.01, 0), moved, "deterministic");
    assert_eq!(again.centres, cloud.centres);
    for k in [2, 3] {
        assert_eq!(
            cloud.primitive(k),
            before.primitive(k),
            "primitive {k} is untouched"
        );
    }

    // The two children keep the parent's centre, its spread along the split axis,
    // its other scales and its weight.
    let (a, b) = (cloud.primitive(0), cloud.primitive(1));
    let axis = glam::DMat3::from_quat(wide.rotation).col(0);
    assert!(((a.centre + b.centre) / 2.0).distance(wide.centre) < 1e-9);
    let half_gap = (a.centre - wide.centre).dot(axis);
    let spread = (a.scale.x.powi(2) + half_gap.powi(2)).sqrt();
    assert!(
        (spread - wide.scale.x).abs() < 1e-9,
        "spread {spread} against {}",
        wide.scale.x
    );
    assert!(
        a.scale.x < 0.75 * wide.scale.x,
        "the children are narrower: {}",
        a.scale.x
    );
    assert!((a.scale.y - wide.scale.y).abs() < 1e-9 && (a.scale.z - wide.scale.z).abs() < 1e-9);
    assert_eq!(a.scale, b.scale);
    let weight = a.weight() + b.weight();
    assert!(
        (weight / wide.weight() - 1.0).abs() < 1e-9,
        "weight {weight} against {}",
        wide.weight()
    );

    // What the pair renders stays close to what the parent rendered (a pair of
    // half-width children two scales apart is not one Gaussian: 0.244 measured here,
    // for a 60 mm wide primitive; the fit takes it from there).
    let pairs = data(24, 3);
    let kernels = |c: &GaussianCloud, ks: &[usize]| ks.iter().map(|&k| c.kernel(k)).collect::<Vec<_>>();
    let parent = render_set(&kernels(&before, &[0]), &pairs, &RenderOptions::default());
    let children = render_set(&kernels(&cloud, &[0, 1]), &pairs, &RenderOptions::default());
    let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let diff: Vec<f64> = parent.iter().zip(&children).map(|(p, c)| p - c).collect();
    let rel = norm(&diff) / norm(&parent);
    assert!(
        rel < 0.3,
        "the split changes the transients by {rel:.3} (relative L2)"
    );
    eprintln!("split: transients change by {rel:.4} relative L2");

    // Nothing to split or nothing dead: nothing moves.
    let mut narrow = before.clone();
    assert!(densify(&mut narrow, 0.05, 0.1, 0).is_empty());
    assert!(densify(&mut narrow, 0.0, 0.01, 0).is_empty());
    assert_eq!(narrow.centres, before.centres);
}

/// With room to grow, `densify` appends what the dead slots cannot take: the wide
/// primitive split into a new slot, and a heavy one already at the target scale
/// cloned (its scale kept, half its albedo each, half its scale either side), never
/// more than it is allowed, in order, and the same twice.
#[test]
fn densify_grows_the_cloud_by_at_most_what_it_is_allowed() {
    let mut cloud = GaussianCloud::new(roi(), ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
    let wide = wide(DQuat::from_rotation_z(0.4));
    // Heavy (above the mean weight) but narrower than the target of 10 mm.
    let narrow = Primitive {
        centre: DVec3::new(-0.1, 0.1, 0.55),
        scale: DVec3::new(0.009, 0.004, 0.003),
        rotation: DQuat::from_rotation_x(0.3),
        albedo: 1000.0,
    };
    // Light, so the other two are above the mean.
    let faint = Primitive {
        centre: DVec3::new(0.1, 0.1, 0.5),
        scale: DVec3::splat(0.004),
        rotation: DQuat::IDENTITY,
        albedo: 1.0,
    };
    cloud.push(wide).unwrap();
    cloud.push(narrow).unwrap();
    cloud.push(faint).unwrap();
    let before = cloud.clone();
    // As the cloud holds them (its raw parameters round the last bits).
    let (wide, narrow, faint) = (before.primitive(0), before.primitive(1), before.primitive(2));
    let mean = (wide.weight() + narrow.weight() + faint.weight()) / 3.0;
    assert!(
        narrow.weight() >= mean && wide.weight() >= mean,
        "both carry signal"
    );

    // Nothing dead and no room: nothing moves, as before.
    let mut fixed = before.clone();
    assert!(densify(&mut fixed, 0.0, 0.01, 0).is_empty());
    assert_eq!(fixed, before);

    // Room for one: the split comes first, into a new slot.
    let mut one = before.clone();
    assert_eq!(densify(&mut one, 0.0, 0.01, 1), vec![(0, 3)]);
    assert_eq!(one.len(), 4);
    assert_eq!(one.primitive(1), narrow, "no room left for the clone");

    // Room for five: the split and the clone, two new primitives and no more.
    let mut grown = before.clone();
    let moved = densify(&mut grown, 0.0, 0.01, 5);
    assert_eq!(moved, vec![(0, 3), (1, 4)]);
    assert_eq!(grown.len(), 5);
    assert_eq!(grown.primitive(2), faint, "the faint one is untouched");
    let mut again = before.clone();
    assert_eq!(densify(&mut again, 0.0, 0.01, 5), moved, "deterministic");
    assert_eq!(again, grown);
    let (a, b) = (grown.primitive(1), grown.primitive(4));
    assert_eq!(
        (a.scale, b.scale),
        (narrow.scale, narrow.scale),
        "a clone keeps its scale"
    );
    assert!(((a.centre + b.centre) / 2.0).distance(narrow.centre) < 1e-9);
    let axis = glam::DMat3::from_quat(narrow.rotation).col(0);
    assert!(
        ((a.centre - narrow.centre).dot(axis) - 0.5 * narrow.scale.x).abs() < 1e-9,
        "half its scale along its widest axis"
    );
    let weight = a.weight() + b.weight();
    assert!(
        (weight / narrow.weight() - 1.0).abs() < 1e-9,
        "weight kept: {weight}"
    );
    let split = grown.primitive(0).weight() + grown.primitive(3).weight();
    assert!((split / wide.weight() - 1.0).abs() < 1e-9, "weight kept: {split}");
}

/// A fit with `grow_from` = 0.5 starts with half its primitives, grows in its rounds
/// and never past K, and is as reproducible as a fixed one: the same cloud on one
/// thread and on two. Its Adam moments follow the growth (the steps after a round
/// take the new primitives without a fault).
#[test]
fn a_fit_grows_from_half_its_primitives_to_at_most_k() {
    let cfg = TrainConfig {
        densify: DensifySettings {
            grow_from: 0.5,
            ..DensifySettings::default()
        },
        prune: PruneSettings {
            boundary_margin: 0.0,
            min_weight_fraction: 0.0,
            min_motion: 0.0,
        },
        ..config(120, 16)
    };
    let fit = |threads: usize| {
        on_threads(threads, || {
            let mut t = Trainer::new(cfg.clone(), roi(), data(60, 4)).unwrap();
            assert_eq!(t.cloud().len(), 60);
            let mut sizes = Vec::new();
            t.run(None, &CancelToken::new(), &mut |e| {
                if let TrainEvent::Epoch { primitives, .. } = e {
                    sizes.push(*primitives);
                }
            })
            .unwrap();
            (t.cloud().clone(), sizes)
        })
    };
    let (one, sizes) = fit(1);
    eprintln!("primitives after each epoch: {sizes:?}");
    assert_eq!(sizes[0], 60, "{sizes:?}");
    assert!(sizes.windows(2).all(|w| w[0] <= w[1]), "only grows: {sizes:?}");
    let most = *sizes.iter().max().unwrap();
    assert!(most > 60 && most <= 120, "{sizes:?}");
    assert!(all_finite(&one));
    assert_eq!(one.len(), most, "nothing pruned here");
    assert_eq!(fit(2).0, one, "results differ between 1 and 2 threads");
}

/// `data(n, seed)` as photon counts: each bin rounded to a whole number, plus
/// `background` counts in every bin.
fn counted(n: usize, seed: u64, background: f32) -> TransientSet {
    let clean = data(n, seed);
    let mut set = TransientSet::new(*clean.axis()).unwrap();
    for (i, pair) in clean.pairs().iter().enumerate() {
        let h: Vec<f32> = clean
            .histogram(i)
            .iter()
            .map(|&v| (v + background).round())
            .collect();
        set.push(*pair, &h).unwrap();
    }
    set
}

/// A Poisson draw of mean `mean` (Knuth's product of uniforms; small means).
fn poisson(rng: &mut ChaCha8Rng, mean: f64) -> f32 {
    let (limit, mut k, mut p) = ((-mean).exp(), 0u32, 1.0f64);
    loop {
        p *= rng.random::<f64>();
        if p <= limit {
            return k as f32;
        }
        k += 1;
    }
}

/// A faint ambient level (0.05 counts a bin, as the noisy validation capture's) is read
/// from the bins no light from the ROI reaches, without the percentile's bias: the
/// 10th percentile of the bins' sums sits 1.3 of their deviations below the mean,
/// which at this level is a third of it.
#[test]
fn the_background_is_read_without_bias_from_the_bins_the_roi_cannot_reach() {
    let clean = data(160, 3);
    let peak = (0..clean.len())
        .flat_map(|i| clean.histogram(i).to_vec())
        .fold(0.0f32, f32::max);
    let mut rng = ChaCha8Rng::seed_from_u64(54);
    let mut counts = TransientSet::new(*clean.axis()).unwrap();
    for (i, pair) in clean.pairs().iter().enumerate() {
        let h: Vec<f32> = clean
            .histogram(i)
            .iter()
            .map(|&v| poisson(&mut rng, f64::from(20.0 * v / peak) + 0.05))
            .collect();
        counts.push(*pair, &h).unwrap();
    }
    let by_roi = estimate_background(&counts, Some(&roi()));
    let by_percentile = estimate_background(&counts, None);
    assert!((by_roi / 0.05 - 1.0).abs() < 0.15, "{by_roi} against 0.05");
    assert!(
        by_percentile < 0.8 * 0.05,
        "{by_percentile}: the percentile's bias"
    );
    // A ROI whose paths fill the window leaves too few such bins: the percentile.
    let everywhere = RoiBox::from_bounds(DVec3::new(-2.0, -2.0, 0.01), DVec3::new(2.0, 2.0, 3.0)).unwrap();
    assert_eq!(estimate_background(&counts, Some(&everywhere)), by_percentile);
}

#[test]
fn non_negative_data_are_fitted_with_the_poisson_deviance_and_its_background() {
    let counts = counted(40, 3, 2.0);
    assert_eq!(first_negative(&counts), None);
    // Most bins see no primitive: the background is what they hold.
    let background = estimate_background(&counts, Some(&roi()));
    assert!((background - 2.0).abs() < 0.01, "{background}");
    assert!((estimate_background(&counts, None) - 2.0).abs() < 0.01);
    // Without any, the floor keeps the rate positive.
    let floor = estimate_background(&data(40, 3), Some(&roi()));
    assert!(floor > 0.0 && floor < 0.1, "{floor}");

    let trainer = Trainer::new(config(30, 1), roi(), counts.clone()).unwrap();
    assert_eq!(
        trainer.render_options().loss,
        Loss::Poisson { background },
        "auto picks Poisson for counts"
    );
    let trainer = Trainer::new(config(30, 1), roi(), data(40, 3)).unwrap();
    assert!(
        matches!(trainer.render_options().loss, Loss::Poisson { .. }),
        "and for non-negative intensities"
    );
    let mut signed = TransientSet::new(axis()).unwrap();
    for (i, pair) in counts.pairs().iter().enumerate() {
        let h: Vec<f32> = counts.histogram(i).iter().map(|&c| c - 2.5).collect();
        signed.push(*pair, &h).unwrap();
    }
    assert!(first_negative(&signed).is_some());
    let trainer = Trainer::new(config(30, 1), roi(), signed).unwrap();
    assert_eq!(
        trainer.render_options().loss,
        Loss::L2,
        "background-subtracted data get L2"
    );
    let l2 = TrainConfig {
        loss: LossChoice::L2,
        ..config(30, 1)
    };
    let trainer = Trainer::new(l2, roi(), counts.clone()).unwrap();
    assert_eq!(
        trainer.render_options().loss,
        Loss::L2,
        "an explicit choice stands"
    );

    // The gain is matched to the counts above the background, so the same scene with
    // and without a background of 2 gets nearly the same gain.
    let with = Trainer::new(config(30, 1), roi(), counts)
        .unwrap()
        .render_options()
        .gain;
    let without = Trainer::new(config(30, 1), roi(), counted(40, 3, 0.0))
        .unwrap()
        .render_options()
        .gain;
    assert!(
        (with / without - 1.0).abs() < 0.02,
        "gain {with} against {without}"
    );
}

#[test]
fn poisson_on_negative_data_is_refused_with_the_pair() {
    let clean = data(10, 4);
    let mut set = TransientSet::new(*clean.axis()).unwrap();
    for (i, pair) in clean.pairs().iter().enumerate() {
        let mut h = clean.histogram(i).to_vec();
        if i == 7 {
            h[3] = -1.0;
        }
        set.push(*pair, &h).unwrap();
    }
    let cfg = TrainConfig {
        loss: LossChoice::Poisson,
        ..config(30, 1)
    };
    match Trainer::new(cfg, roi(), set) {
        Err(TrainError::Config(msg)) => assert!(msg.contains("pair 7") && msg.contains("l2"), "{msg}"),
        other => panic!("expected a config error, got {:?}", other.map(|_| ())),
    }
}

/// A sign-inverted capture has a negative total, which a non-negative scene cannot
/// explain: the fit refuses it at the gain match instead of fitting an empty scene,
/// and a capture with some negative bins but a positive total still fits.
#[test]
fn a_capture_with_a_negative_total_is_refused() {
    let clean = data(10, 4);
    let flipped = |keep_positive: bool| {
        let mut set = TransientSet::new(*clean.axis()).unwrap();
        for (i, pair) in clean.pairs().iter().enumerate() {
            let h: Vec<f32> = clean
                .histogram(i)
                .iter()
                .enumerate()
                .map(|(b, v)| if keep_positive && b % 3 != 0 { *v } else { -v })
                .collect();
            set.push(*pair, &h).unwrap();
        }
        set
    };
    let cfg = || TrainConfig {
        loss: LossChoice::L2,
        ..config(30, 1)
    };
    match Trainer::new(cfg(), roi(), flipped(false)) {
        Err(e @ TrainError::NegativeTotal { total }) => {
            assert!(total < 0.0, "{total}");
            let msg = e.to_string();
            assert!(msg.contains("non-negative") && msg.contains("fbp"), "{msg}");
        }
        other => panic!("expected a negative-total error, got {:?}", other.map(|_| ())),
    }
    let mixed = flipped(true);
    assert!((0..mixed.len()).any(|i| mixed.histogram(i).iter().any(|v| *v < 0.0)));
    assert!(Trainer::new(cfg(), roi(), mixed).is_ok());
}

#[test]
fn a_poisson_fit_on_counts_stays_finite_and_lowers_its_loss() {
    let cfg = TrainConfig {
        loss: LossChoice::Poisson,
        ..config(60, 4)
    };
    let mut trainer = Trainer::new(cfg, roi(), counted(60, 5, 1.0)).unwrap();
    let mut losses = Vec::new();
    trainer
        .run(None, &CancelToken::new(), &mut |e| {
            if let TrainEvent::Epoch { loss, .. } = e {
                losses.push(*loss);
            }
        })
        .unwrap();
    assert!(losses.iter().all(|l| l.is_finite()), "{losses:?}");
    assert!(losses.last().unwrap() < &losses[0], "{losses:?}");
}

/// The fit's result is the mean of the iterates of its last third (after the
/// densification rounds): one `Averaged` event counting those steps, and a result that
/// differs from the last iterate's; `average_from = 1` keeps the last iterate.
#[test]
fn the_last_third_of_the_iterates_is_averaged() {
    let fit = |average_from: f64| {
        let cfg = TrainConfig {
            average_from,
            ..config(60, 6)
        };
        // 60 pairs in batches of 4: 15 steps an epoch.
        assert_eq!(cfg.average_start(6), Some(4).filter(|_| average_from < 1.0));
        let mut t = Trainer::new(cfg, roi(), data(60, 3)).unwrap();
        let mut averaged = Vec::new();
        t.run(None, &CancelToken::new(), &mut |e| {
            if let TrainEvent::Averaged { steps } = e {
                averaged.push(*steps);
            }
        })
        .unwrap();
        assert!(all_finite(t.cloud()));
        (t.cloud().clone(), averaged)
    };
    let (mean, events) = fit(2.0 / 3.0);
    assert_eq!(events, vec![30], "epochs 5 and 6 of 6 are averaged");
    let (last, events) = fit(1.0);
    assert!(events.is_empty());
    assert_ne!(mean, last);
    // Averaging never starts before the last densification round.
    let cfg = TrainConfig {
        average_from: 0.0,
        ..config(60, 6)
    };
    assert_eq!(cfg.average_start(6), Some(3));
}

/// `converge`: a fit whose averaged epochs have levelled off stops before its counted
/// epochs are spent, with one `Converged` event and the averaged result of the epochs
/// it ran; without the test every epoch runs.
#[test]
fn a_fit_stops_once_its_averaged_loss_levels_off() {
    let fit = |tolerance: Option<f64>| {
        let cfg = TrainConfig {
            // 15 steps an epoch; the last 10 of 30 epochs averaged, tested in windows of
            // 30 steps after at least 60.
            converge: tolerance.map(|tolerance| Convergence {
                min_steps: 60,
                window: 30,
                tolerance,
            }),
            ..config(60, 30)
        };
        let mut t = Trainer::new(cfg, roi(), data(60, 3)).unwrap();
        let (mut converged, mut epochs, mut averaged) = (Vec::new(), 0, 0);
        let summary = t
            .run(None, &CancelToken::new(), &mut |e| match e {
                TrainEvent::Converged { epoch, of, step } => converged.push((*epoch, *of, *step)),
                TrainEvent::Epoch { epoch, .. } => epochs = *epoch,
                TrainEvent::Averaged { steps } => averaged = *steps,
                _ => {}
            })
            .unwrap();
        assert!(all_finite(t.cloud()));
        (converged, epochs, averaged, summary.steps)
    };
    let (converged, epochs, averaged, steps) = fit(Some(0.5));
    assert_eq!(converged.len(), 1, "{converged:?}");
    let (epoch, of, step) = converged[0];
    assert_eq!((of, step, epoch), (30, steps, epochs));
    // The earliest test (four epochs averaged) to before the last epoch.
    assert!((24..30).contains(&epoch), "stopped after epoch {epoch}");
    assert_eq!(averaged, (epoch - 20) * 15);
    let (converged, epochs, averaged, steps) = fit(None);
    assert!(converged.is_empty(), "{converged:?}");
    assert_eq!((epochs, averaged, steps), (30, 150, 450));
}

/// `epoch_pairs`: with fewer pairs an epoch than the capture holds, each epoch trains
/// on that many (its steps and its `Epoch` event say so), and the step floor counts
/// such epochs; without it an epoch is a pass over every pair.
#[test]
fn an_epoch_of_a_large_capture_trains_on_part_of_it() {
    let fit = |epoch_pairs: usize| {
        let cfg = TrainConfig {
            epoch_pairs,
            ..config(40, 6)
        };
        let mut t = Trainer::new(cfg, roi(), data(60, 3)).unwrap();
        let (seen, summary) = epochs_of(&mut t);
        assert!(all_finite(t.cloud()));
        (seen, summary.steps)
    };
    // 16 of 60 pairs an epoch in batches of 4: 4 steps each.
    let (seen, steps) = fit(16);
    assert_eq!(steps, 24);
    assert_eq!(seen, (1..=6).map(|e| (e, 16, 4 * e)).collect::<Vec<_>>());
    let (seen, steps) = fit(0);
    assert_eq!(steps, 90);
    assert!(seen.iter().all(|&(_, pairs, _)| pairs == 60), "{seen:?}");
    // The floor counts the smaller epochs: 100 steps are 25 epochs of 16 pairs.
    let cfg = TrainConfig {
        epoch_pairs: 16,
        min_steps: 100,
        ..config(40, 6)
    };
    assert_eq!((cfg.pairs_per_epoch(60), cfg.counted_epochs(60)), (16, 25));
    assert_eq!(cfg.pairs_per_epoch(10), 10);
}

/// The gain tests' scene: two blobs 0.5–0.6 m away, and a confocal 12 × 12 grid over a
/// 1 m wall (zero transients) with its points.
fn gain_scene() -> (GaussianCloud, TransientSet, Vec<DVec3>) {
    let mut truth = GaussianCloud::new(roi(), ScaleBounds { min: 1e-3, max: 0.1 }).unwrap();
    for c in [DVec3::new(0.05, -0.04, 0.6), DVec3::new(-0.12, 0.1, 0.5)] {
        truth
            .push(Primitive {
                centre: c,
                scale: DVec3::splat(0.03),
                rotation: DQuat::IDENTITY,
                albedo: 1.0,
            })
            .unwrap();
    }
    let mut geometry = TransientSet::new(axis()).unwrap();
    let mut points = Vec::new();
    for i in 0..12 {
        for j in 0..12 {
            let x = DVec3::new(-0.5 + i as f64 / 11.0, -0.5 + j as f64 / 11.0, 0.0);
            geometry
                .push(Pair::confocal(x, DVec3::Z), &vec![0.0; axis().bins])
                .unwrap();
            points.push(x);
        }
    }
    (truth, geometry, points)
}

/// Gains from the data: on a confocal 12 × 12 grid, transients rendered from a known
/// scene times known gains (a quadratic in the logarithm: a laser's falloff) come back
/// exactly from the rendering, up to the one scale the fit's albedo carries; a point's
/// own departure from the smooth part (its albedo) comes back in part, as far as its
/// signal tells it; with a fixed laser there is nothing per illumination point to
/// estimate, and per detection point there is.
#[test]
fn pair_gains_come_back_from_the_data_and_the_rendering() {
    let (truth, geometry, points) = gain_scene();
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let smooth = |x: DVec3| (0.6 * x.x - 0.3 * x.y + 0.8 * x.x * x.x).exp();
    let own = |k: usize| if k % 7 == 3 { 1.3 } else { 1.0 };
    let bins = axis().bins;
    let make = |gain: &dyn Fn(usize) -> f64| {
        let mut set = TransientSet::new(axis()).unwrap();
        for (k, pair) in geometry.pairs().iter().enumerate() {
            let h: Vec<f32> = rendered[k * bins..(k + 1) * bins]
                .iter()
                .map(|&v| (gain(k) * v * 1e6) as f32)
                .collect();
            set.push(*pair, &h).unwrap();
        }
        set
    };
    let unit: Vec<f64> = rendered.iter().map(|v| v * 1e6).collect();
    let loss = Loss::Poisson { background: 0.0 };
    let set = make(&|k| smooth(points[k]));
    let g = estimate_pair_gains(&set, &unit, loss, PairGains::Illumination).unwrap();
    let scale = g[0] / smooth(points[0]);
    for k in 0..g.len() {
        let want = scale * smooth(points[k]);
        assert!(
            (g[k] - want).abs() < 1e-6 * want,
            "point {k}: {} against {want}",
            g[k]
        );
    }
    let set = make(&|k| smooth(points[k]) * own(k));
    let g = estimate_pair_gains(&set, &unit, loss, PairGains::Illumination).unwrap();
    let ratio: Vec<f64> = (0..g.len()).map(|k| g[k] / smooth(points[k])).collect();
    let (bright, plain): (Vec<usize>, Vec<usize>) = (0..g.len()).partition(|k| k % 7 == 3);
    let mean = |ks: &[usize]| ks.iter().map(|&k| ratio[k].ln()).sum::<f64>() / ks.len() as f64;
    let lift = mean(&bright) - mean(&plain);
    assert!(
        lift > 0.05 && lift < 1.3f64.ln() + 0.02,
        "a 30 % brighter point lifts its gain by {lift} in the log"
    );
    assert_eq!(estimate_pair_gains(&set, &unit, loss, PairGains::None), None);

    // A fixed laser: no illumination groups, one per detection point.
    let fixed: Vec<Pair> = points
        .iter()
        .map(|&x| Pair {
            xi: DVec3::ZERO,
            ni: DVec3::Z,
            xd: x,
            nd: DVec3::Z,
        })
        .collect();
    assert!(gain_groups(&fixed, PairGains::Illumination).is_none());
    let (groups, pts) = gain_groups(&fixed, PairGains::Detection).unwrap();
    assert_eq!(pts.len(), 144);
    assert_eq!(groups, (0..144).collect::<Vec<_>>());
}

/// Gains from photon counts: on the same grid, counts drawn from a known scene (about
/// 400 signal photons a transient over a background of 0.05 a bin) with every gain 1
/// give gains whose spread is a small part of the counting noise's (each point's
/// departure is noise the counts cannot tell from albedo, so it is not taken for
/// one); with ±30 % random gains, the estimate follows them.
#[test]
fn pair_gains_from_counts_take_only_what_the_counts_can_tell() {
    let (truth, geometry, _) = gain_scene();
    let bins = axis().bins;
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let n = geometry.len();
    let mean_total = rendered.iter().sum::<f64>() / n as f64;
    let unit: Vec<f64> = rendered.iter().map(|v| v * 400.0 / mean_total).collect();
    let background = 0.05;
    let mut rng = ChaCha8Rng::seed_from_u64(54);
    let draw = |rng: &mut ChaCha8Rng, gains: &[f64]| {
        let mut set = TransientSet::new(axis()).unwrap();
        for (k, pair) in geometry.pairs().iter().enumerate() {
            let h: Vec<f32> = unit[k * bins..(k + 1) * bins]
                .iter()
                .map(|&r| poisson(rng, gains[k] * r + background))
                .collect();
            set.push(*pair, &h).unwrap();
        }
        set.mark_photon_counts();
        set
    };
    let loss = Loss::Poisson { background };
    let spread = |v: &[f64]| {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / v.len() as f64).sqrt()
    };
    // Each point's own ratio: what the counts alone say, noise and all.
    let raw = |set: &TransientSet| -> Vec<f64> {
        (0..n)
            .map(|k| {
                let above: f64 = set.histogram(k).iter().map(|&v| f64::from(v) - background).sum();
                let r: f64 = unit[k * bins..(k + 1) * bins].iter().sum();
                (above.max(1.0) / r).ln()
            })
            .collect()
    };

    let set = draw(&mut rng, &vec![1.0; n]);
    let g = estimate_pair_gains(&set, &unit, loss, PairGains::Illumination).unwrap();
    let logs: Vec<f64> = g.iter().map(|g| g.ln()).collect();
    let (noise, kept) = (spread(&raw(&set)), spread(&logs));
    assert!(
        kept < 0.25 * noise,
        "gains 1: the estimate spreads {kept:.4} in the log against the counts' noise {noise:.4}"
    );

    let truth_gains: Vec<f64> = (0..n).map(|_| rng.random_range(0.7..1.3)).collect();
    let set = draw(&mut rng, &truth_gains);
    let g = estimate_pair_gains(&set, &unit, loss, PairGains::Illumination).unwrap();
    let (a, b): (Vec<f64>, Vec<f64>) = g.iter().zip(&truth_gains).map(|(g, t)| (g.ln(), t.ln())).unzip();
    let (ma, mb) = (a.iter().sum::<f64>() / n as f64, b.iter().sum::<f64>() / n as f64);
    let cov: f64 = a.iter().zip(&b).map(|(x, y)| (x - ma) * (y - mb)).sum::<f64>() / n as f64;
    let corr = cov / (spread(&a) * spread(&b));
    assert!(
        corr > 0.8,
        "±30 % gains: the estimate correlates {corr:.3} with them"
    );
}

/// `pair-gains = "auto"`, the plans' default: a scanned capture that states no gain
/// has each illumination point's gain estimated by the fit; one whose transients carry
/// known gains (a named laser falloff, the relay's albedo from its scan) and one with a
/// fixed laser keep theirs, and the fit renders nothing for gains there.
#[test]
fn auto_pair_gains_are_estimated_only_where_the_capture_states_none() {
    let (truth, geometry, points) = gain_scene();
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let bins = axis().bins;
    let smooth = |x: DVec3| (0.6 * x.x - 0.3 * x.y).exp();
    let make = |known: bool, fixed: bool| {
        let mut set = TransientSet::new(axis()).unwrap();
        for (k, pair) in geometry.pairs().iter().enumerate() {
            let g = smooth(points[k]);
            let h: Vec<f32> = rendered[k * bins..(k + 1) * bins]
                .iter()
                .map(|&v| (g * v * 1e3) as f32)
                .collect();
            let pair = if fixed {
                Pair {
                    xi: DVec3::ZERO,
                    ni: DVec3::Z,
                    ..*pair
                }
            } else {
                *pair
            };
            if known {
                set.push_with_gain(pair, &h, g as f32).unwrap();
            } else {
                set.push(pair, &h).unwrap();
            }
        }
        set
    };
    let (unknown, known, fixed) = (make(false, false), make(true, false), make(false, true));
    assert_eq!(PairGains::Auto.resolve(&unknown), PairGains::Illumination);
    assert_eq!(PairGains::Auto.resolve(&known), PairGains::None);
    assert_eq!(PairGains::Auto.resolve(&fixed), PairGains::None);
    for kind in [PairGains::None, PairGains::Illumination, PairGains::Detection] {
        assert_eq!(kind.resolve(&unknown), kind);
        assert_eq!(kind.resolve(&known), kind);
    }

    let fit = |set: TransientSet| {
        let cfg = TrainConfig {
            pair_gains: PairGains::Auto,
            ..config(40, 8)
        };
        let mut trainer = Trainer::new(cfg, roi(), set).unwrap();
        let summary = trainer.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
        (summary.pair_gains, trainer.pair_gains())
    };
    let (kind, gains) = fit(unknown);
    assert_eq!(kind, PairGains::Illumination);
    // The smooth gain spans 1.8× from one side of the wall to the other: the estimate
    // follows it (lower on the −x side than on the +x side).
    let side = |sign: f64| {
        let ks: Vec<usize> = (0..points.len()).filter(|&k| points[k].x * sign > 0.3).collect();
        ks.iter().map(|&k| gains[k].ln()).sum::<f64>() / ks.len() as f64
    };
    assert!(
        side(1.0) > side(-1.0) + 0.1,
        "+x {} against −x {}",
        side(1.0),
        side(-1.0)
    );
    for set in [known, fixed] {
        let (kind, gains) = fit(set);
        assert_eq!(kind, PairGains::None);
        assert!(gains.iter().all(|&g| g == 1.0));
    }
}

/// Zero transients on 5 mm bins for `pairs`.
fn geometry(pairs: impl IntoIterator<Item = Pair>) -> TransientSet {
    let axis = TimeAxis {
        start: 0.5,
        width: 0.005,
        bins: 64,
    };
    let mut set = TransientSet::new(axis).unwrap();
    for pair in pairs {
        set.push(pair, &[0.0; 64]).unwrap();
    }
    set
}

/// `n × n` points over `[-half, half]²` at z = 0 (the first range along x), facing +z.
fn grid(n: usize, x: [f64; 2], y: [f64; 2]) -> Vec<DVec3> {
    let at = |r: [f64; 2], i: usize| r[0] + (r[1] - r[0]) * (i as f64 + 0.5) / n as f64;
    (0..n * n)
        .map(|k| DVec3::new(at(x, k % n), at(y, k / n), 0.0))
        .collect()
}

fn pair(xi: DVec3, xd: DVec3) -> Pair {
    Pair {
        xi,
        ni: DVec3::Z,
        xd,
        nd: DVec3::Z,
    }
}

#[test]
fn a_capture_places_points_as_finely_as_its_gradients_spread() {
    let at = DVec3::new(0.0, 0.0, 0.5);
    let wall = grid(32, [-0.5, 0.5], [-0.5, 0.5]);
    // Confocal over a 1 m wall: g = 2u spreads over ±45°, s = 4 sin 45° · (cos of the
    // narrowest direction) ≈ 2.5, so 4 bins of 5 mm over it ≈ 8 mm.
    let confocal = geometry(wall.iter().map(|&x| pair(x, x)));
    let d = resolvable_separation(&confocal, at, 0.0).unwrap();
    assert!((0.006..0.010).contains(&d), "confocal wall: {d}");
    // A fixed laser at the centre: only ud moves, about half the spread.
    let fixed = geometry(wall.iter().map(|&x| pair(DVec3::ZERO, x)));
    let d_fixed = resolvable_separation(&fixed, at, 0.0).unwrap();
    assert!((0.012..0.020).contains(&d_fixed), "fixed laser: {d_fixed}");
    // Two torsos: the laser on one back, a 0.3 × 0.54 m patch of detection points on
    // the other beside the scene; across x the gradients spread over about 10°, less
    // the farther the point.
    let patch = grid(16, [0.07, 0.37], [-0.27, 0.27]);
    let backs = geometry(patch.iter().map(|&x| pair(DVec3::new(-0.22, 0.0, 0.0), x)));
    let d_backs = resolvable_separation(&backs, at, 0.0).unwrap();
    assert!((0.035..0.055).contains(&d_backs), "two backs: {d_backs}");
    let farther = resolvable_separation(&backs, DVec3::new(0.0, 0.0, 0.7), 0.0).unwrap();
    assert!(
        (0.05..0.08).contains(&farther) && farther > d_backs,
        "two backs, 0.7 m: {farther}"
    );
    // Timing jitter wider than a bin coarsens it in proportion to its full width at
    // half maximum, 2√(2 ln 2) × 10 mm.
    let jittered = resolvable_separation(&backs, at, 0.01).unwrap();
    let fwhm = 2.0 * (2.0 * 2f64.ln()).sqrt() * 0.01;
    assert!(
        (jittered / d_backs - fwhm / 0.005).abs() < 1e-9,
        "{jittered} {d_backs}"
    );
    // A point no pair sees (behind the relay) has none.
    assert_eq!(
        resolvable_separation(&backs, DVec3::new(0.0, 0.0, -0.5), 0.0),
        None
    );
}

/// The separation is the capture's, not its frame's: the same pairs and point turned
/// together about the mean gradient give the same figure. It looked across four fixed
/// directions (two axes and their diagonals) until 2026-12-08, so the two backs turned
/// by 22.5° read about 40 % finer, and a line of pairs resolved nothing across only
/// when it lay along an axis.
#[test]
fn the_separation_does_not_depend_on_how_the_relay_is_turned() {
    let at = DVec3::new(0.0, 0.0, 0.5);
    let patch = grid(16, [0.07, 0.37], [-0.27, 0.27]);
    let laser = DVec3::new(-0.22, 0.0, 0.0);
    let line: Vec<DVec3> = (0..32)
        .map(|k| DVec3::new(-0.5 + k as f64 / 31.0, 0.0, 0.0))
        .collect();
    let backs = |turn: f64| {
        let q = glam::DQuat::from_rotation_z(turn);
        geometry(patch.iter().map(|&x| pair(q * laser, q * x)))
    };
    let confocal_line = |turn: f64| {
        let q = glam::DQuat::from_rotation_z(turn);
        geometry(line.iter().map(|&x| pair(q * x, q * x)))
    };
    let straight = resolvable_separation(&backs(0.0), at, 0.0).unwrap();
    for degrees in [10.0f64, 22.5, 45.0, 67.5, 137.0] {
        let turned = resolvable_separation(&backs(degrees.to_radians()), at, 0.0).unwrap();
        assert!(
            (turned / straight - 1.0).abs() < 1e-6,
            "turned {degrees}°: {turned} against {straight}"
        );
        let across = resolvable_separation(&confocal_line(degrees.to_radians()), at, 0.0).unwrap();
        assert_eq!(
            across,
            f64::INFINITY,
            "a line turned {degrees}° resolves nothing across it"
        );
    }
    assert_eq!(
        resolvable_separation(&confocal_line(0.0), at, 0.0),
        Some(f64::INFINITY)
    );
}

#[test]
fn splits_stop_where_the_capture_stops_placing_points() {
    let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.2), DVec3::new(0.5, 0.5, 1.2)).unwrap();
    let cfg = TrainConfig {
        primitives: 2000,
        ..TrainConfig::default()
    };
    let capacity = default_target_scale(&roi, 2000);
    let wall = grid(32, [-0.5, 0.5], [-0.5, 0.5]);
    let confocal = Trainer::new(cfg.clone(), roi, geometry(wall.iter().map(|&x| pair(x, x)))).unwrap();
    assert_eq!(
        confocal.split_floor(),
        capacity,
        "a wide aperture keeps the capacity rule"
    );
    let patch = grid(16, [0.07, 0.37], [-0.27, 0.27]);
    let backs = geometry(patch.iter().map(|&x| pair(DVec3::new(-0.22, 0.0, 0.0), x)));
    let separation = resolvable_separation(&backs, roi.centre, 0.0).unwrap();
    let two_backs = Trainer::new(cfg, roi, backs).unwrap();
    let floor = two_backs.split_floor();
    assert!(floor > 2.0 * capacity, "{floor} against {capacity}");
    assert!(
        (floor - separation / 3f64.sqrt()).abs() < 1e-12,
        "children √3 σ apart, {separation} m"
    );
}

/// A fit with [`TrainConfig::coarse`] set takes its batch size and surface prior on a
/// capture whose split floor its gradients raise to twice the capacity or more (one
/// laser spot on one back, detection points on the other) and keeps its own on a
/// confocal wall; without it the two fits are configured alike.
#[test]
fn a_coarse_capture_takes_the_coarse_fit() {
    let roi = RoiBox::from_bounds(DVec3::new(-0.5, -0.5, 0.2), DVec3::new(0.5, 0.5, 1.2)).unwrap();
    let prior = SurfacePrior {
        spread: SurfacePrior::DEFAULT_SPREAD,
        cell: 0.03,
        axis: Default::default(),
    };
    let cfg = TrainConfig {
        primitives: 2000,
        densify: DensifySettings {
            grow_from: 0.5,
            ..DensifySettings::default()
        },
        average_batch: AverageBatch::Half,
        coarse: Some(CoarseFit {
            batch_size: 8,
            surface: Some(prior),
            grow_from: 1.0,
            average_batch: AverageBatch::Same,
        }),
        ..TrainConfig::default()
    };
    let wall = grid(32, [-0.5, 0.5], [-0.5, 0.5]);
    let confocal = geometry(wall.iter().map(|&x| pair(x, x)));
    let patch = grid(16, [0.07, 0.37], [-0.27, 0.27]);
    let backs = geometry(patch.iter().map(|&x| pair(DVec3::new(-0.22, 0.0, 0.0), x)));
    let on_wall = Trainer::new(cfg.clone(), roi, confocal.clone()).unwrap();
    assert_eq!(
        (on_wall.config().batch_size, on_wall.config().surface),
        (4, None),
        "a confocal wall keeps the configured fit"
    );
    assert_eq!(on_wall.cloud().len(), 1000, "and starts with half its primitives");
    assert_eq!(on_wall.config().average_batch, AverageBatch::Half);
    let on_backs = Trainer::new(cfg.clone(), roi, backs.clone()).unwrap();
    assert_eq!(
        (on_backs.config().batch_size, on_backs.config().surface),
        (8, Some(prior)),
        "two backs take the coarse fit"
    );
    assert_eq!(on_backs.cloud().len(), 2000, "with all its primitives");
    assert_eq!(
        on_backs.config().average_batch,
        AverageBatch::Same,
        "and the whole batch in its averaged epochs"
    );
    // The same places as a fit configured with all of them from the start.
    let whole = TrainConfig {
        densify: DensifySettings::default(),
        ..cfg.clone()
    };
    let at_once = Trainer::new(whole, roi, backs.clone()).unwrap();
    assert_eq!(on_backs.cloud().centres, at_once.cloud().centres);
    // Streamed: the choice waits for the first data.
    let empty = TransientSet::new(*backs.axis()).unwrap();
    let mut streamed = Trainer::new(cfg.clone(), roi, empty).unwrap();
    assert_eq!(streamed.config().batch_size, 4);
    assert_eq!(streamed.cloud().len(), 1000);
    streamed.add(&backs).unwrap();
    assert_eq!(streamed.config().batch_size, 8);
    assert_eq!(streamed.cloud().len(), 2000);
    let plain = Trainer::new(TrainConfig { coarse: None, ..cfg }, roi, backs).unwrap();
    assert_eq!((plain.config().batch_size, plain.config().surface), (4, None));
}

use std::sync::Arc;

use periscope_recon::gpu::Gpu;
use periscope_recon::gpu::testing::gpu;

/// A fit on the GPU renders its rounds of gain estimation there: on the auto test's
/// wall with a smooth gain unknown, the gains it ends with follow the CPU fit's (every
/// point's within 0.02 in the logarithm), and the fit stayed on the GPU.
#[test]
fn gain_rounds_render_on_the_fits_gpu() {
    let Some(gpu) = gpu("gain_rounds_render_on_the_fits_gpu") else {
        return;
    };
    let (truth, geometry, points) = gain_scene();
    let rendered = render_set(&truth.kernels(), &geometry, &RenderOptions::default());
    let bins = axis().bins;
    let mut set = TransientSet::new(axis()).unwrap();
    for (k, pair) in geometry.pairs().iter().enumerate() {
        let g = (0.6 * points[k].x - 0.3 * points[k].y).exp();
        let h: Vec<f32> = rendered[k * bins..(k + 1) * bins]
            .iter()
            .map(|&v| (g * v * 1e3) as f32)
            .collect();
        set.push(*pair, &h).unwrap();
    }
    let fit = |on_gpu: bool| {
        let cfg = TrainConfig {
            pair_gains: PairGains::Auto,
            ..config(40, 8)
        };
        let mut t = Trainer::new(cfg, roi(), set.clone()).unwrap();
        if on_gpu {
            t.use_gpu(gpu.clone(), true);
        }
        let summary = t.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
        assert_eq!(summary.pair_gains, PairGains::Illumination);
        assert_eq!(t.on_gpu(), on_gpu, "the fit stayed where it started");
        t.pair_gains()
    };
    let (cpu, on_gpu) = (fit(false), fit(true));
    let worst = cpu
        .iter()
        .zip(&on_gpu)
        .map(|(a, b)| (a.ln() - b.ln()).abs())
        .fold(0.0f64, f64::max);
    assert!(
        worst < 0.02,
        "the GPU fit's gains differ by up to {worst} in the log"
    );
}

/// A fit of `data` run to the end on `gpu` (strict) or the CPU, which must stay where
/// it started; with the primitives after every epoch and the last epoch's loss.
fn fit_on(cfg: TrainConfig, data: TransientSet, gpu: Option<&Arc<Gpu>>) -> (Trainer, Vec<usize>, f64) {
    let mut t = Trainer::new(cfg, roi(), data).unwrap();
    if let Some(gpu) = gpu {
        t.use_gpu(gpu.clone(), true);
    }
    let (mut sizes, mut last) = (Vec::new(), f64::NAN);
    t.run(None, &CancelToken::new(), &mut |e| {
        if let TrainEvent::Epoch { primitives, loss, .. } = e {
            sizes.push(*primitives);
            last = *loss;
        }
    })
    .unwrap();
    assert_eq!(t.on_gpu(), gpu.is_some(), "the fit stayed where it started");
    (t, sizes, last)
}

/// A fit that grows does so on the GPU too: its steps' resident buffers take the
/// cloud's new size each epoch, the fit stays on the GPU, and it grows as the CPU fit
/// does (the same sizes after every epoch, the rounds judging f32 fits alike here) to
/// a loss within 2 % of the CPU's. Its averaged epochs take half the pairs a step, as
/// the daemon's default fit does, so the GPU's steps take those smaller batches too.
#[test]
fn a_growing_fit_runs_on_the_gpu() {
    let Some(gpu) = gpu("a_growing_fit_runs_on_the_gpu") else {
        return;
    };
    let cfg = TrainConfig {
        densify: DensifySettings {
            grow_from: 0.5,
            ..DensifySettings::default()
        },
        average_batch: AverageBatch::Half,
        ..config(120, 16)
    };
    let fit = |on: Option<&Arc<Gpu>>| {
        let (t, sizes, last) = fit_on(cfg.clone(), data(60, 4), on);
        assert!(all_finite(t.cloud()));
        (sizes, last, t.steps())
    };
    let (cpu, cpu_loss, cpu_steps) = fit(None);
    let (gpu, gpu_loss, gpu_steps) = fit(Some(&gpu));
    eprintln!("sizes: CPU {cpu:?}, GPU {gpu:?}; last loss: CPU {cpu_loss}, GPU {gpu_loss}");
    assert!(cpu[0] == 60 && *cpu.last().unwrap() > 60, "{cpu:?}");
    assert_eq!(gpu, cpu);
    // 60 pairs in batches of 4 are 15 steps an epoch, averaged or not.
    assert_eq!((cpu_steps, gpu_steps), (16 * 15, 16 * 15));
    assert!(
        cpu_loss > 0.0 && (gpu_loss - cpu_loss).abs() <= 0.02 * cpu_loss,
        "GPU {gpu_loss} against CPU {cpu_loss}"
    );
}

/// A fit whose steps run on the GPU (f32) follows the CPU's (f64): after 6 epochs of
/// 15 steps on one primitive's transients, the last epoch's loss is within 1 % of the
/// CPU fit's and every centre within 0.5 mm of it, and the fit stayed on the GPU.
#[test]
fn a_fit_on_the_gpu_follows_the_cpus() {
    let Some(gpu) = gpu("a_fit_on_the_gpu_follows_the_cpus") else {
        return;
    };
    let fit = |on: Option<&Arc<Gpu>>| {
        let (t, _, last) = fit_on(config(50, 6), data(60, 1), on);
        (t.cloud().clone(), last)
    };
    let (cpu, cpu_loss) = fit(None);
    let (gpu, gpu_loss) = fit(Some(&gpu));
    eprintln!("last epoch's loss: GPU {gpu_loss}, CPU {cpu_loss}");
    assert!(
        cpu_loss > 0.0 && (gpu_loss - cpu_loss).abs() <= 0.01 * cpu_loss,
        "GPU {gpu_loss} against CPU {cpu_loss}"
    );
    assert_eq!(gpu.len(), cpu.len());
    let worst = (0..cpu.len())
        .map(|k| (gpu.primitive(k).centre - cpu.primitive(k).centre).length())
        .fold(0.0f64, f64::max);
    eprintln!("largest centre difference {worst:.2e} m");
    assert!(worst <= 5e-4, "a centre moved {worst} m from the CPU fit's");
}

/// A GPU step that fails (here a mini-batch larger than one dispatch holds) ends a
/// strict fit with the GPU's error, naming the setting to change; a fit that is not
/// strict (`[compute] device = "auto"`) goes on and ends on the CPU.
#[test]
fn a_failing_gpu_ends_a_strict_fit_and_leaves_the_others_to_the_cpu() {
    let Some(gpu) = gpu("a_failing_gpu_ends_a_strict_fit_and_leaves_the_others_to_the_cpu") else {
        return;
    };
    let axis = TimeAxis::from_seconds(0.6, 32e-12, 16);
    let mut set = TransientSet::new(axis).unwrap();
    let n = 65_600;
    for i in 0..n {
        let x = DVec3::new(
            -0.5 + (i % 256) as f64 / 256.0,
            -0.5 + (i / 256) as f64 / 257.0,
            0.0,
        );
        set.push(Pair::confocal(x, DVec3::Z), &[0.0; 16]).unwrap();
    }
    let cfg = TrainConfig {
        batch_size: n,
        ..config(4, 1)
    };
    let mut strict = Trainer::new(cfg.clone(), roi(), set.clone()).unwrap();
    strict.use_gpu(gpu.clone(), true);
    match strict.run(None, &CancelToken::new(), &mut |_| {}) {
        Err(TrainError::Gpu(e)) => assert!(e.to_string().contains("batch-size"), "{e}"),
        other => panic!("a strict fit on a failing GPU gave {other:?}"),
    }
    let mut lenient = Trainer::new(cfg, roi(), set).unwrap();
    lenient.use_gpu(gpu, false);
    let summary = lenient.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
    assert!(!summary.cancelled && summary.steps == 1, "{summary:?}");
    assert!(!lenient.on_gpu(), "the fit went on on the CPU");
    assert!(all_finite(lenient.cloud()));
}

/// `clean`'s transients as windows of 0.8 m placed at random (starting up to `latest`
/// past the axis's start, drawn from `seed`) record them, as legs that differ from
/// pair to pair place a TDC window on the hidden paths: each bin wholly inside
/// `inside(count)`, zeros elsewhere (as a rebinned capture holds). Returns that set,
/// and the same with each transient limited to its window
/// ([`TransientSet::limit_recorded`]).
fn through_windows(
    clean: &TransientSet,
    latest: f64,
    seed: u64,
    mut inside: impl FnMut(&mut ChaCha8Rng, f32) -> f32,
) -> (TransientSet, TransientSet) {
    let axis = *clean.axis();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut zeros, mut windows) = (TransientSet::new(axis).unwrap(), Vec::new());
    for (i, pair) in clean.pairs().iter().enumerate() {
        let from = axis.start + rng.random_range(0.0..latest);
        let window = (from, from + 0.8);
        let h: Vec<f32> = clean
            .histogram(i)
            .iter()
            .enumerate()
            .map(|(b, &c)| {
                let within = axis.edge(b as isize) >= window.0 && axis.edge(b as isize + 1) <= window.1;
                if within { inside(&mut rng, c) } else { 0.0 }
            })
            .collect();
        zeros.push(*pair, &h).unwrap();
        windows.push(window);
    }
    let mut limited = zeros.clone();
    for (i, &w) in windows.iter().enumerate() {
        limited.limit_recorded(i, w);
    }
    (zeros, limited)
}

/// Where each pair's TDC window records only part of the axis (0.8 m of its 2.3 m,
/// placed pair by pair at random, as legs that differ from pair to pair place a
/// window on the hidden paths; the bins past it hold zeros, as a rebinned capture's
/// do), a fit that leaves those bins out ([`TransientSet::limit_recorded`]) renders
/// the whole capture as a fit of the whole windows does, within 10 % of its light;
/// one that reads the zeros as measured loses a third of it or more.
#[test]
fn a_fit_leaves_out_what_each_pairs_window_did_not_record() {
    let full = data(80, 6);
    let (zeros, limited) = through_windows(&full, 1.3, 57, |_, c| c);
    // Light the windows miss: a fit that reads it as zeros has to dim.
    let missed = 1.0 - zeros.total_counts() / full.total_counts();
    assert!(missed > 0.3, "the windows miss {missed:.2} of the light");
    let light = |data: TransientSet| {
        let mut t = Trainer::new(config(40, 10), roi(), data).unwrap();
        t.run(None, &CancelToken::new(), &mut |_| {}).unwrap();
        let rendered: f64 = render_set(&t.cloud().kernels(), &full, t.render_options())
            .iter()
            .sum();
        rendered / full.total_counts()
    };
    let (whole, kept, read_as_zeros) = (light(full.clone()), light(limited), light(zeros));
    eprintln!(
        "light rendered over measured: whole windows {whole:.3}, recorded bins {kept:.3}, zeros read {read_as_zeros:.3}"
    );
    assert!((kept / whole - 1.0).abs() < 0.1, "{kept} against {whole}");
    assert!(read_as_zeros / whole < 0.67, "{read_as_zeros} against {whole}");
}

/// The background (2 counts a bin) is read from the bins each pair recorded: zeros
/// past a pair's window would pull it down to under a fifth, with the ROI's bins and
/// with the percentile alike.
#[test]
fn the_background_is_read_only_where_each_window_recorded() {
    let (zeros, limited) = through_windows(&data(400, 3), 1.5, 58, |rng, c| poisson(rng, f64::from(c) + 2.0));
    for roi in [Some(roi()), None] {
        let (kept, read_as_zeros) = (
            estimate_background(&limited, roi.as_ref()),
            estimate_background(&zeros, roi.as_ref()),
        );
        eprintln!(
            "ROI {}: recorded bins {kept:.3}, zeros read {read_as_zeros:.3}",
            roi.is_some()
        );
        // The percentile reads the level a little low (the test above).
        let bound = if roi.is_some() { 0.05 } else { 0.15 };
        assert!((kept / 2.0 - 1.0).abs() < bound, "{kept} against 2");
        assert!(read_as_zeros < 1.0, "{read_as_zeros}");
    }
}

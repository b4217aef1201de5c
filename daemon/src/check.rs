//! `periscope check PLAN`: what a plan will do on an instrument, how long it should
//! take, and which targets the galvos cannot reach, without touching any device.
use std::fmt::Write;

use glam::DVec3;
use periscope_drivers::{AngleLimits, GalvoPose, OpticalAngles, TdcConfig};
use periscope_recon::gtr::gain_start_epoch;
use periscope_recon::relay::Region;
use periscope_recon::transient::path_range;
use periscope_recon::{C0, Pair, TimeAxis};

use crate::budget::{GTR_EVALS_PER_S, SYNTH_EVALS_PER_S};
use crate::config::{InstrumentConfig, TdcDriver};
use crate::plan::{Method, PairMode, Plan};

/// Forward evaluations (pair × primitive) per second of a round of per-transient gain
/// estimation, which renders the whole capture (`recon.gtr.pair-gains`): on 2 cores
/// confocal_sparse's 82 rounds of 300 pairs at 2,000 primitives (49 million, as many as
/// 24 rounds of a 1,024-pair capture) added 0.8–1.0 s to its fit.
const GAIN_EVALS_PER_S: f64 = 5e7;
/// Voxel-pairs per second of the FBP of 3D-GTR's virtual scan onto the volume (the
/// scaling bench: 128² points onto 128³ and 256³ voxels, 1.7 billion a second).
const VIRTUAL_FBP_PER_S: f64 = 1.7e9;
/// Voxel-pairs per second of `method = "fbp"` on a capture's own pairs (the scaling
/// bench: 4,000 to 64,000 arbitrary pairs onto 128³ and 256³ voxels, 1.6–1.7 billion a
/// second).
const FBP_PER_S: f64 = 1.6e9;

/// Points of a plan's virtual confocal scan, for the estimate: its `virtual-grid`, or
/// without one the volume's lateral voxel columns (a scan one voxel pitch apart over
/// the volume's footprint; it grows where the relay reaches beyond it).
fn virtual_points(rc: &crate::plan::ReconSettings) -> usize {
    let most = crate::budget::MAX_VIRTUAL_RESOLUTION;
    rc.virtual_resolution.map_or(
        rc.volume.shape[0].min(most) * rc.volume.shape[1].min(most),
        |[nx, ny]| nx * ny,
    )
}

fn deg(a: OpticalAngles) -> String {
    format!("({:.2}°, {:.2}°)", a.x.to_degrees(), a.y.to_degrees())
}

fn outside(pose: &GalvoPose, limits: &AngleLimits, p: DVec3) -> Option<String> {
    match pose.angles_for(p) {
        None => Some("behind the galvo pair".into()),
        Some(a) if !limits.contains(a) => Some(format!("needs {}", deg(a))),
        Some(_) => None,
    }
}

/// What `periscope check` (and `POST /api/v1/check`) finds out about a plan.
#[derive(Clone, Debug, serde::Serialize, utoipa::ToSchema)]
pub struct Check {
    /// The plan's name.
    pub plan: String,
    /// The report as `periscope check` prints it.
    pub report: String,
    /// Pairs the plan asks for at most.
    pub pairs: usize,
    /// Estimated seconds per part: `los`, `capture`, `reconstruction`, `total`.
    pub duration_s: Duration,
    /// Memory the run needs, bytes.
    pub memory_bytes: u64,
    /// Disk the run needs, bytes.
    pub disk_bytes: u64,
    /// The instrument's memory budget, bytes.
    pub memory_limit: u64,
    /// The instrument's disk budget, bytes.
    pub disk_limit: u64,
    /// Why the plan would be refused as over budget, if it would be.
    pub over_budget: Option<String>,
    /// Targets outside the galvo limits (their pairs are left out).
    pub problems: Vec<String>,
    /// What the run may warn about or fail on that costs no pair: a TDC window that
    /// records only part of the LOS scan's first bounces or of the volume's paths, or
    /// none of them.
    pub warnings: Vec<String>,
}

/// Estimated durations, seconds.
#[derive(Clone, Copy, Debug, serde::Serialize, utoipa::ToSchema)]
#[schema(as = Durations)]
pub struct Duration {
    /// LOS scan.
    pub los: f64,
    /// NLOS capture (an adaptive one: at its whole budget).
    pub capture: f64,
    /// An adaptive capture's shortest: its stopping rule ending it at the second
    /// choice, one chosen batch measured (`None`: not adaptive, or no `stop-gain`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub capture_min: Option<f64>,
    /// Reconstruction after the capture.
    pub reconstruction: f64,
    /// The reconstruction where the relay the scan finds places points coarsely (one
    /// laser spot on one back, detection points on another), which takes a fit of
    /// twice the work ([`periscope_recon::gtr::CoarseFit`]); `None`: no other fit.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reconstruction_max: Option<f64>,
    /// All of it.
    pub total: f64,
}

/// The check report as text.
pub fn report(plan: &Plan, inst: &InstrumentConfig) -> String {
    check(plan, inst).report
}

/// Checks `plan` on `inst` without touching any device.
pub fn check(plan: &Plan, inst: &InstrumentConfig) -> Check {
    let mut out = String::new();
    let mut problems = Vec::new();
    let _ = writeln!(out, "plan `{}` on {}", plan.name, inst.summary());
    let l = &plan.los;
    let _ = writeln!(
        out,
        "  LOS scan: {}×{} SPAD angles over x [{:.1}°, {:.1}°], y [{:.1}°, {:.1}°], {:.2} ms each",
        l.grid[0],
        l.grid[1],
        l.x[0].to_degrees(),
        l.x[1].to_degrees(),
        l.y[0].to_degrees(),
        l.y[1].to_degrees(),
        l.dwell.as_secs_f64() * 1e3
    );
    for (x, y) in [
        (l.x[0], l.y[0]),
        (l.x[1], l.y[0]),
        (l.x[0], l.y[1]),
        (l.x[1], l.y[1]),
    ] {
        let a = OpticalAngles { x, y };
        if !inst.spad_arm.limits.contains(a) {
            problems.push(format!("los.angles-deg: the SPAD arm cannot reach {}", deg(a)));
        }
    }
    let r = &plan.relay;
    let _ = writeln!(
        out,
        "  relay: depth {:.2}–{:.2} m, intensity ≥ {:.0} % of the brightest, normals from {} neighbours",
        r.depth[0],
        r.depth[1],
        r.min_intensity * 100.0,
        r.neighbours
    );
    for (name, region) in [("illumination", &r.illumination), ("detection", &r.detection)] {
        if let Region::Box { min, max } = region {
            for c in 0..8 {
                let p = DVec3::new(
                    if c & 1 == 0 { min.x } else { max.x },
                    if c & 2 == 0 { min.y } else { max.y },
                    if c & 4 == 0 { min.z } else { max.z },
                );
                let (pose, limits, arm) = if name == "illumination" {
                    (&inst.laser_arm.pose, &inst.laser_arm.limits, "laser")
                } else {
                    (&inst.spad_arm.pose, &inst.spad_arm.limits, "SPAD")
                };
                if let Some(why) = outside(pose, limits, p) {
                    problems.push(format!(
                        "relay.{name}: corner {p:.3?} is outside the {arm} arm's limits ({why})"
                    ));
                }
            }
        }
    }
    if let crate::plan::PairMode::FixedLaser { laser, .. } = &plan.pairs
        && let Some(why) = outside(&inst.laser_arm.pose, &inst.laser_arm.limits, *laser)
    {
        problems.push(format!(
            "pairs.laser: ({:.3}, {:.3}, {:.3}) m is outside the laser arm's limits ({why}): no pair can be measured",
            laser.x,
            laser.y,
            laser.z
        ));
    }
    let candidates = plan.pairs.max_pairs();
    let adaptive = plan
        .adaptive
        .then(|| crate::adaptive::Sizes::of(candidates, &plan.recon.adaptive));
    let pairs = adaptive.map_or(candidates, |s| s.budget);
    match adaptive {
        None => {
            let _ = writeln!(out, "  pairs: {} (at most {pairs})", plan.pairs.describe());
        }
        Some(s) => {
            let _ = writeln!(
                out,
                "  pairs: adaptive, at most {} of the {} (at most {candidates}): {} spread over them first, {}{}",
                s.budget,
                plan.pairs.describe(),
                s.first,
                if s.rounds() == 0 {
                    "and no more (the budget ends there)".to_owned()
                } else {
                    format!("then batches of {} chosen by the running fit", s.batch)
                },
                if plan.recon.adaptive.stop_gain > 0.0 && s.rounds() > 0 {
                    format!(
                        ", ending early once a batch's expected gain falls below {} of the first's",
                        plan.recon.adaptive.stop_gain
                    )
                } else {
                    String::new()
                }
            );
        }
    }
    let a = &plan.acquisition;
    let _ = writeln!(
        out,
        "  acquisition: {:.2} ms × {} per pair, {} bins of {:.1} ps from {:.2} ns",
        a.dwell.as_secs_f64() * 1e3,
        a.repeats,
        a.bins,
        a.bin_width * 1e12,
        a.offset * 1e9
    );
    let (line, mut warnings) = window(plan, inst);
    warnings.extend(tdc_settings(plan, inst));
    // A plan that asks for a GPU is run only where one opens (the run checks before
    // its LOS scan): said here, on the machine that will run it.
    if plan.recon.compute == periscope_recon::gpu::ComputeDevice::Gpu
        && let Err(e) = periscope_recon::gpu::Compute::open(periscope_recon::gpu::ComputeDevice::Gpu)
    {
        warnings.push(format!(
            "recon.compute.device = \"gpu\": {e}; a run of this plan fails before its LOS scan"
        ));
    }
    if plan.adaptive {
        warnings.extend(crate::adaptive::Sizes::notes(candidates, &plan.recon.adaptive));
    }
    out.push_str(&line);
    let rc = &plan.recon;
    let v = &rc.volume;
    let _ = writeln!(
        out,
        "  reconstruction: {}, volume x [{:.2}, {:.2}] y [{:.2}, {:.2}] z [{:.2}, {:.2}] m on {}×{}×{} voxels",
        match rc.method {
            Method::Gtr => format!(
                "3D-GTR (K = {}, {} epochs, virtual {} confocal grid, then {})",
                rc.train.primitives,
                rc.train.counted_epochs(pairs),
                rc.virtual_resolution
                    .map_or("voxel-pitch".to_string(), |[nx, ny]| format!("{nx}×{ny}")),
                rc.solver
            ),
            Method::Solver(kind) => kind.to_string(),
        },
        v.x[0],
        v.x[1],
        v.y[0],
        v.y[1],
        v.z[0],
        v.z[1],
        v.shape[0],
        v.shape[1],
        v.shape[2]
    );
    // Duration.
    let sim = matches!(inst.backend, crate::config::Backend::Sim(_));
    let (los_s, cap_s, cap_min_s) = crate::budget::instrument_seconds(plan, inst);
    let gtr_s = |train: &periscope_recon::gtr::TrainConfig| {
        let k = train.primitives as f64;
        let points = virtual_points(rc) as f64;
        let epochs = train.counted_epochs(pairs);
        let gain_rounds = if plan.estimates_gains() {
            epochs.saturating_sub(gain_start_epoch(epochs))
        } else {
            0
        };
        train.counted_pair_visits(pairs) as f64 * k / GTR_EVALS_PER_S
            + gain_rounds as f64 * pairs as f64 * k / GAIN_EVALS_PER_S
            + points * k / SYNTH_EVALS_PER_S
            + points * v.len() as f64 / VIRTUAL_FBP_PER_S
    };
    let (recon_s, recon_max_s) = if rc.method == Method::Gtr {
        // Which fit a capture takes depends on the relay the scan finds.
        let coarse = rc
            .train
            .coarse
            .filter(|c| c.batch_size != rc.train.batch_size)
            .map(|c| {
                gtr_s(&periscope_recon::gtr::TrainConfig {
                    batch_size: c.batch_size,
                    average_batch: c.average_batch,
                    ..rc.train.clone()
                })
            });
        (gtr_s(&rc.train), coarse)
    } else {
        ((v.len() as f64 * pairs as f64 / FBP_PER_S).max(1.0), None)
    };
    let recon = match recon_max_s {
        // Epochs the plan sets take the same work in fewer, larger steps.
        Some(hi) if hi - recon_s >= 0.5 => {
            format!("{recon_s:.0} s ({hi:.0} s if the relay places points coarsely, as two backs do)")
        }
        _ => format!("{recon_s:.0} s"),
    };
    let _ = writeln!(
        out,
        "  estimated duration: LOS {:.0} s, capture {} s, reconstruction {}{}",
        los_s,
        match cap_min_s {
            Some(lo) => format!("{lo:.0} to {cap_s:.0}"),
            None => format!("{cap_s:.0}"),
        },
        recon,
        if sim {
            " (device time; the simulator's physics adds its own compute time)"
        } else {
            ""
        }
    );
    let budget = crate::budget::Budget::of_plan(plan, inst);
    let _ = writeln!(out, "  budget (per run, from the instrument's [budget]):");
    out.push_str(&budget.report(&inst.budget));
    for w in &warnings {
        let _ = writeln!(out, "  warning: {w}");
    }
    let listed = problems.clone();
    if problems.is_empty() {
        let _ = writeln!(out, "  limits: every target is within the galvo limits");
    } else {
        let _ = writeln!(
            out,
            "  limits: {} problem(s); pairs there will be left out:",
            problems.len()
        );
        for p in problems {
            let _ = writeln!(out, "    - {p}");
        }
    }
    Check {
        plan: plan.name.clone(),
        report: out,
        pairs,
        duration_s: Duration {
            los: los_s,
            capture: cap_s,
            capture_min: cap_min_s,
            reconstruction: recon_s,
            reconstruction_max: recon_max_s,
            total: los_s + cap_s + recon_s,
        },
        memory_bytes: budget.memory_bytes(),
        disk_bytes: budget.disk_bytes(),
        memory_limit: inst.budget.memory,
        disk_limit: inst.budget.disk,
        over_budget: budget.check(&inst.budget).err().map(|over| over.message),
        problems: listed,
        warnings,
    }
}

/// Relay points across `region`: a box's 9 × 9 × 3 grid, corners included; for any
/// other region, the LOS scan's cone (its SPAD angles on a 9 × 9 grid, at the near and
/// far ends and the middle of `relay.depth-m`), which holds every relay point the scan
/// can find. `true` when a box bounds them.
fn relay_samples(region: &Region, plan: &Plan, inst: &InstrumentConfig) -> (Vec<DVec3>, bool) {
    let steps = |n: usize, a: f64, b: f64| (0..n).map(move |i| a + (b - a) * i as f64 / (n - 1) as f64);
    match region {
        Region::Box { min, max } => {
            let mut out = Vec::with_capacity(243);
            for z in steps(3, min.z, max.z) {
                for y in steps(9, min.y, max.y) {
                    out.extend(steps(9, min.x, max.x).map(|x| DVec3::new(x, y, z)));
                }
            }
            (out, true)
        }
        _ => {
            let pose = &inst.spad_arm.pose;
            let (l, d) = (&plan.los, plan.relay.depth);
            let mut out = Vec::with_capacity(243);
            for depth in steps(3, d[0], d[1]) {
                for y in steps(9, l.y[0], l.y[1]) {
                    for x in steps(9, l.x[0], l.x[1]) {
                        out.push(pose.origin + depth * pose.direction(OpticalAngles { x, y }));
                    }
                }
            }
            (out, false)
        }
    }
}

/// The most bins a plan's histogram may have (`acquisition.bins`).
const MAX_PLAN_BINS: u64 = crate::plan::MAX_BINS as u64;

/// The largest `tdc.sync-divider` a suggestion names (PicoQuant's families take at
/// most 16; Periscope's USB counter any, but a period of 1,024 pulses is microseconds,
/// past any NLOS path).
const MAX_SYNC_DIVIDER: u32 = 1024;

/// The step an offset is given in and the latest the TDC and a plan take, ns: a
/// PicoQuant counter sets whole nanoseconds up to its family's largest, Periscope's
/// USB histogrammer picoseconds (suggested to a tenth of a nanosecond).
fn offset_steps(inst: &InstrumentConfig) -> (f64, f64) {
    match &inst.tdc.driver {
        TdcDriver::PicoQuant(counter) => (
            1.0,
            (counter.family.max_offset_ns() as f64).min(crate::plan::MAX_OFFSET_NS),
        ),
        TdcDriver::Usb => (0.1, crate::plan::MAX_OFFSET_NS),
    }
}

/// What the configured TDC would refuse of the plan's settings before it measures
/// anything, as warnings naming the plan's table: a PicoQuant counter takes whole
/// milliseconds and nanoseconds and its own sync dividers and histogram lengths
/// ([`Family::settings`](periscope_drivers::picoquant::Family::settings), which its
/// driver applies). Periscope's USB histogrammer takes whatever a plan may say.
fn tdc_settings(plan: &Plan, inst: &InstrumentConfig) -> Vec<String> {
    let TdcDriver::PicoQuant(counter) = &inst.tdc.driver else {
        return Vec::new();
    };
    let a = &plan.acquisition;
    let config = |dwell| TdcConfig {
        bin_width: a.bin_width,
        bins: a.bins,
        offset: a.offset,
        sync_divider: inst.tdc.sync_divider,
        acquisition: dwell,
    };
    let los = counter.family.settings(&config(plan.los.dwell)).err();
    let capture = counter.family.settings(&config(a.dwell)).err();
    let mut out = Vec::new();
    if let Some(e) = &los {
        out.push(format!(
            "los: the run will stop before its LOS scan, which the {} refuses: {e}",
            counter.family
        ));
    }
    // The same refusal (of the offset, the bins or the divider) is named once.
    if let Some(e) = capture.filter(|e| Some(e) != los.as_ref()) {
        out.push(format!(
            "acquisition: the run will stop before its first pair, whose settings the {} \
             refuses: {e}",
            counter.family
        ));
    }
    out
}

/// The TDC window against the total paths the run needs it to record, over relay points
/// sampled where the plan lets them fall ([`relay_samples`]): the LOS scan's first
/// bounces (laser galvo, relay, SPAD galvo; the scan shares the window) and the paths
/// through the volume (laser galvo to relay, through the volume, back to the relay and
/// the SPAD galvo), each widened by a margin: the run's hidden axis reaches 4 bins past
/// the volume's paths, and a pulse spreads by the jitter. The report's line, and a
/// warning where the window records part of them only, or none, with the offset and
/// bins that would record all. This is made before any device moves, over the regions
/// the relay may lie in, so it bounds: the run judges the relay its scan finds
/// (`record::run_axis`, which warns of a window short of the volume and fails when it
/// records none of it over all pairs together). Where no box bounds the relay, only a
/// window that misses even the bound is warned of.
fn window(plan: &Plan, inst: &InstrumentConfig) -> (String, Vec<String>) {
    let a = &plan.acquisition;
    let tdc = TimeAxis::of_tdc(a.offset, a.bin_width, a.bins as usize, inst.tdc.system_delay);
    let (detection, boxed_d) = relay_samples(&plan.relay.detection, plan, inst);
    let (laser, spad) = (inst.laser_arm.pose.origin, inst.spad_arm.pose.origin);
    let (illumination, boxed) = match &plan.pairs {
        PairMode::Confocal { .. } | PairMode::Mask { .. } => (Vec::new(), boxed_d),
        PairMode::FixedLaser { laser, .. } => (vec![*laser], boxed_d),
        PairMode::Scanned { .. } | PairMode::Random { .. } => {
            let (s, b) = relay_samples(&plan.relay.illumination, plan, inst);
            (s, b && boxed_d)
        }
    };
    // A pulse spreads by the jitter (three standard deviations) and is read in whole
    // bins (one); the hidden axis adds four bins of its own margin past the volume's
    // paths.
    let los_pad = tdc.width + 3.0 * C0 * inst.spad.jitter_fwhm / 2.355;
    let pad = los_pad + 4.0 * tdc.width;
    let widen = |(lo, hi): (f64, f64), x: f64| (lo.min(x), hi.max(x));
    let empty = (f64::INFINITY, f64::NEG_INFINITY);
    let los = detection
        .iter()
        .chain(&illumination)
        .fold(empty, |r, x| widen(r, x.distance(laser) + x.distance(spad)));
    let mut volume = empty;
    let mut take = |xi: DVec3, xd: DVec3| {
        let pair = Pair {
            xi,
            ni: DVec3::Z,
            xd,
            nd: DVec3::Z,
        };
        let (n, f) = path_range(&pair, &plan.recon.volume);
        let legs = xi.distance(laser) + xd.distance(spad);
        volume = widen(widen(volume, n + legs), f + legs);
    };
    for &xd in &detection {
        if illumination.is_empty() {
            take(xd, xd);
        }
        for &xi in &illumination {
            take(xi, xd);
        }
    }
    let (los, volume) = (
        (los.0 - los_pad, los.1 + los_pad),
        (volume.0 - pad, volume.1 + pad),
    );
    let (from, to) = (tdc.start, tdc.end());
    let (near, far) = (los.0.min(volume.0), los.1.max(volume.1));
    // The latest offset the TDC can be given (ns, rounded down to its step: a tenth,
    // or a whole ns on a PicoQuant counter; at least 0, at most its largest) whose
    // window starts by `near`, and the bins a window from `start` needs to reach `far`.
    let (step_ns, max_ns) = offset_steps(inst);
    let offset_ns = ((near / C0 + inst.tdc.system_delay) * 1e9 / step_ns).floor() * step_ns;
    let offset_ns = offset_ns.clamp(0.0, max_ns);
    let shown = |ns: f64| {
        if step_ns >= 1.0 {
            format!("{ns:.0}")
        } else {
            format!("{ns:.1}")
        }
    };
    let start_at = |offset_ns: f64| C0 * (offset_ns * 1e-9 - inst.tdc.system_delay);
    let bins_from = |start: f64| ((far - start) / tdc.width).ceil().max(16.0) as u64;
    let mut fix = Vec::new();
    if from > near {
        if offset_ns == 0.0 && start_at(0.0) > near {
            fix.push(format!(
                "acquisition.offset-ns 0 (the earliest offset, which starts at {:.2} m: the \
                 system delay puts the nearest paths before any offset)",
                start_at(0.0)
            ));
        } else {
            fix.push(format!("acquisition.offset-ns at most {}", shown(offset_ns)));
        }
    }
    let (start, moved) = if from > near {
        (start_at(offset_ns), true)
    } else {
        (from, false)
    };
    let bins = bins_from(start);
    // A counter times each photon from the last sync: a window past the sync period is
    // refused with the plan, so no suggestion may end past it.
    let within_period = |offset_ns: f64, bins: u64| {
        crate::config::window_past_period(
            offset_ns * 1e-9,
            u32::try_from(bins).unwrap_or(u32::MAX),
            a.bin_width,
            inst.tdc.sync_divider,
            inst.laser.repetition_rate,
        )
        .is_none()
    };
    // A window that starts well before the paths wastes bins: a later offset needs
    // fewer, and may need no more than a histogram holds where this one does.
    let later = (!moved && offset_ns > a.offset * 1e9 + step_ns / 2.0)
        .then(|| bins_from(start_at(offset_ns)))
        .filter(|&b| b < bins && b <= MAX_PLAN_BINS && within_period(offset_ns, b))
        .map(|b| format!("acquisition.offset-ns {} and bins at least {b}", shown(offset_ns)));
    let start_ns = if moved { offset_ns } else { a.offset * 1e9 };
    if bins > u64::from(a.bins) && !within_period(start_ns, bins) && later.is_none() {
        let period = f64::from(inst.tdc.sync_divider) / inst.laser.repetition_rate;
        // The least divider whose period holds the window that records the paths, of
        // those the counter takes (a PicoQuant counter, its family's; Periscope's USB
        // counter, any), where the window fits a histogram at all.
        let fits = |d: u32| {
            crate::config::window_past_period(
                start_ns * 1e-9,
                u32::try_from(bins).unwrap_or(u32::MAX),
                a.bin_width,
                d,
                inst.laser.repetition_rate,
            )
            .is_none()
        };
        let divider = (bins <= MAX_PLAN_BINS)
            .then(|| match &inst.tdc.driver {
                TdcDriver::PicoQuant(counter) => (inst.tdc.sync_divider + 1..=MAX_SYNC_DIVIDER)
                    .find(|&d| counter.family.sync_divider_ok(d) && fits(d)),
                TdcDriver::Usb => {
                    let end = start_ns * 1e-9 + bins as f64 * a.bin_width;
                    let least = (end * inst.laser.repetition_rate).ceil().max(1.0);
                    (least < f64::from(MAX_SYNC_DIVIDER))
                        .then_some(least as u32)
                        .and_then(|d| (d..d + 2).find(|&d| fits(d)))
                }
            })
            .flatten();
        fix.push(format!(
            "paths to {far:.2} m, past the {:.2} m a sync period holds (tdc.sync-divider / \
             laser.rep-rate-mhz, {:.1} ns, less the system delay): {}a [recon.volume] nearer \
             the relay",
            C0 * (period - inst.tdc.system_delay),
            period * 1e9,
            match divider {
                Some(d) => format!(
                    "tdc.sync-divider {d} (in the instrument config) and acquisition.bins at \
                     least {bins}{}, or ",
                    if moved { " from there" } else { " at this offset" }
                ),
                None => String::new(),
            }
        ));
    } else if bins > MAX_PLAN_BINS {
        match later {
            Some(later) => fix.push(later),
            None => fix.push(format!(
                "{bins} bins{}, more than the {MAX_PLAN_BINS} a histogram may have: wider bins \
                 (acquisition.bin-width-ps) or a [recon.volume] nearer the relay",
                if moved { " from there" } else { " at this offset" }
            )),
        }
    } else if bins > u64::from(a.bins) {
        // `later` is some here where the bins past this offset end past the period.
        if within_period(start_ns, bins) {
            fix.push(format!(
                "acquisition.bins at least {bins}{}",
                if moved { " from there" } else { " at this offset" }
            ));
            if let Some(later) = later {
                fix.push(format!("or {later}"));
            }
        } else if let Some(later) = later {
            fix.push(later);
        }
    }
    let fix = if fix.is_empty() {
        String::new()
    } else {
        format!(
            " To record the LOS returns and the volume's paths: {}.",
            fix.join(", ")
        )
    };
    let judge = |(lo, hi): (f64, f64)| {
        if to <= lo || from >= hi {
            "none recorded"
        } else if from > lo || to < hi {
            if boxed {
                "part recorded"
            } else {
                "perhaps part recorded"
            }
        } else {
            "all recorded"
        }
    };
    let side = |(lo, hi): (f64, f64)| match (from > lo, to < hi) {
        (true, true) => "near and far",
        (true, false) => "near",
        _ => "far",
    };
    let place = if boxed {
        "the relay regions"
    } else {
        "the relay the LOS scan can find (a bound: boxes in relay.detection, and relay.illumination \
         where the laser scans, narrow it)"
    };
    let line = format!(
        "  TDC window: total paths {from:.2}–{to:.2} m; the LOS returns from {}: {:.2}–{:.2} m, {}; \
         the volume's paths through them: {:.2}–{:.2} m, {} (margins of {:.0} and {:.0} mm)\n",
        if boxed {
            "the relay regions"
        } else {
            "the LOS cone"
        },
        los.0,
        los.1,
        judge(los),
        volume.0,
        volume.1,
        judge(volume),
        los_pad * 1e3,
        pad * 1e3,
    );
    let mut warnings = Vec::new();
    let window = format!(
        "the TDC window ({:.3} ns offset, {} bins of {:.1} ps) records total paths of {from:.2} to {to:.2} m",
        a.offset * 1e9,
        a.bins,
        a.bin_width * 1e12,
    );
    match judge(los) {
        "none recorded" => warnings.push(format!(
            "acquisition: {window}, none of the LOS scan's first bounces from {place} ({:.2} to \
             {:.2} m): the scan will find no relay and the run will fail.{fix}",
            los.0, los.1,
        )),
        "part recorded" => warnings.push(format!(
            "acquisition: {window}, part of the LOS scan's first bounces from {place} ({:.2} to \
             {:.2} m): relay points at the {} end may not be found.{fix}",
            los.0,
            los.1,
            side(los)
        )),
        _ => {}
    }
    match judge(volume) {
        "none recorded" => warnings.push(format!(
            "acquisition: {window}, none of the {:.2} to {:.2} m the volume's paths take from any \
             point of {place}: the run will fail before its first pair, or record nothing of the \
             volume.{fix} Or give a [recon.volume] the window reaches.",
            volume.0, volume.1,
        )),
        "part recorded" => warnings.push(format!(
            "acquisition: {window}, part of the {:.2} to {:.2} m the volume's paths can take through \
             {place}: pairs whose paths fall outside it record zeros there, which the reconstruction \
             leaves out, and the volume's {} side may be seen by fewer pairs or none.{fix}",
            volume.0,
            volume.1,
            side(volume)
        )),
        _ => {}
    }
    (line, warnings)
}

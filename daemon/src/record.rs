//! A stored histogram record as every reconstruction of a run sees it: the SPAD's dead
//! time and pile-up undone (when the instrument asks for it), on its total-path axis,
//! rebinned to the hidden path of its pair. The capture's streamed fit, `periscope
//! recon RUN_DIR`, the y-tal export and the tests share these.
use periscope_recon::transient::{
    TransientError, bins_within, clip_to_measured, hidden_axis, path_range, rebin_path,
};
use periscope_recon::{TimeAxis, TransientSet, VolumeGrid};

use crate::config::InstrumentConfig;
use crate::plan::{Acquisition, PlannedPair};
use crate::run_dir::RelayPoint;
use crate::store::Record;

/// Each planned pair's known gain from the relay scan: the relay's albedo at its two
/// spots, read from the LOS return's photons ([`periscope_recon::relay::RelayAlbedo`]),
/// for the model of every reconstruction of the run (the live fit, `periscope recon
/// RUN_DIR`); the counts stay as measured. `None` when the plan turns it off
/// (`relay.albedo-from-scan = false`) or the scan cannot give it (fewer than six
/// points with a return).
pub fn relay_gains(
    relay: &[RelayPoint],
    pairs: &[PlannedPair],
    inst: &InstrumentConfig,
    on: bool,
) -> Option<Vec<f32>> {
    if !on {
        return None;
    }
    // As `relay.ply` stores them (float32), so a run's live fit and `periscope recon
    // RUN_DIR` or a resumed run, which read the file back, take the same gains.
    let stored = |v: glam::DVec3| v.as_vec3().as_dvec3();
    let points: Vec<_> = relay.iter().map(|p| stored(p.x)).collect();
    let normals: Vec<_> = relay.iter().map(|p| stored(p.n)).collect();
    let photons: Vec<f64> = relay.iter().map(|p| f64::from(p.intensity as f32)).collect();
    let albedo = periscope_recon::relay::RelayAlbedo::from_scan(
        &points,
        &normals,
        &photons,
        inst.laser_arm.pose.origin,
        inst.spad_arm.pose.origin,
    )?;
    let planned: Vec<_> = pairs.iter().map(PlannedPair::pair).collect();
    let gains = albedo.pair_gains(&planned);
    let (lo, hi) = gains
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(l, h), &g| (l.min(g), h.max(g)));
    tracing::info!(
        min = lo,
        max = hi,
        "each transient's gain from the relay scan's albedo"
    );
    Some(gains.iter().map(|&g| g as f32).collect())
}

/// Undoes the SPAD's dead time and pile-up on a histogram summed over `cycles` sync
/// periods lasting `dwell` seconds in all, inverting the standard models in turn: a
/// non-paralysable dead time τ on the total count rate R (true = measured / (1 − R·τ)),
/// then Coates (1968): only the first photon of a cycle is recorded, so bin k, which saw
/// N − Σ_{j<k} n_j cycles still waiting, received λ_k = −ln(1 − n_k / (N − Σ_{j<k} n_j))
/// photons per cycle, N·λ_k in all. Returns the expected counts without either effect.
/// At low rates it changes nothing measurable (λ ≈ n/N). A bin that took every cycle
/// still waiting is read as taking all but half of one, and a dead-time loss is capped
/// at 99 %, so the answer stays finite; without a cycle count the counts are returned
/// as they are.
pub fn undo_pile_up(counts: &[u32], cycles: f64, dwell: f64, dead_time: f64) -> Vec<f32> {
    let total: f64 = counts.iter().map(|&c| f64::from(c)).sum();
    if !(cycles.is_finite() && cycles > 0.0 && dwell > 0.0) {
        return counts.iter().map(|&c| c as f32).collect();
    }
    let busy = (total / dwell * dead_time.max(0.0)).min(0.99);
    let live = 1.0 / (1.0 - busy);
    if total * live > cycles {
        // More photons than laser cycles: impossible for a first-photon TDC, so the
        // cycle count (the laser's pulse rate, the sync divider) is wrong. Undoing
        // pile-up with it would zero every later bin; the counts stay as counted.
        static SEEN: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = SEEN.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        if n.is_power_of_two() {
            tracing::warn!(
                histograms = n,
                counts = total,
                cycles,
                "a histogram holds more counts than the laser had pulses over its dwell: pile-up is left uncorrected; check laser.rep-rate-mhz and tdc.sync-divider"
            );
        }
        return counts.iter().map(|&c| c as f32).collect();
    }
    let mut waiting = cycles;
    counts
        .iter()
        .map(|&c| {
            let n = f64::from(c) * live;
            if n <= 0.0 || waiting <= 0.5 {
                return 0.0;
            }
            let taken = n.min(waiting - 0.5);
            let lambda = -(-taken / waiting).ln_1p();
            waiting -= taken;
            (cycles * lambda) as f32
        })
        .collect()
}

/// A stored record's counts as reconstructions and the export use them: with pile-up
/// and dead time undone ([`undo_pile_up`], over the record's dwell at the laser's
/// pulse rate and the sync divider) when `tdc.pile-up-correction` is on, else as
/// counted.
pub fn record_counts(rec: &Record, inst: &InstrumentConfig) -> Vec<f32> {
    corrected_counts(&rec.counts, rec.dwell_us as f64 * 1e-6, inst)
}

/// Counts summed over `dwell` seconds with pile-up and dead time undone when the
/// instrument's `tdc.pile-up-correction` is on (over `dwell` at the laser's pulse rate
/// and the sync divider), else as counted. The LOS scan and [`record_counts`] use it.
pub fn corrected_counts(counts: &[u32], dwell: f64, inst: &InstrumentConfig) -> Vec<f32> {
    if inst.tdc.pile_up_correction {
        let cycles = dwell * inst.laser.repetition_rate / f64::from(inst.tdc.sync_divider.max(1));
        undo_pile_up(counts, cycles, dwell, dead_time_across_cycles(inst))
    } else {
        counts.iter().map(|&c| c as f32).collect()
    }
}

/// The SPAD's dead time as it costs a first-photon counter beyond Coates' model: all
/// of it where a detection late in one cycle's window can leave the SPAD dead into
/// the next cycle's window (the dead time longer than the cycle's period less the
/// window's span), else none, since Coates already counts one detection a cycle. Until
/// 2026-12-07 it was always applied: with the simulated instrument's 50 ns against a
/// 100 ns cycle and a 16 ns window it raised a bright LOS return by about a quarter
/// that no counter loses.
pub fn dead_time_across_cycles(inst: &InstrumentConfig) -> f64 {
    let period = f64::from(inst.tdc.sync_divider.max(1)) / inst.laser.repetition_rate;
    let window = f64::from(inst.tdc.bins) * inst.tdc.bin_width;
    if inst.spad.dead_time > period - window {
        inst.spad.dead_time
    } else {
        0.0
    }
}

/// The transient a stored record gives its pair on the hidden-path axis, as every
/// reconstruction of a run sees it (the live fit and `periscope recon RUN_DIR`):
/// `None` for a histogram flagged overflow (a counter or the FIFO overflowed, so its
/// counts are only a lower bound: it stays in the log and the export but is not
/// fitted); pile-up and dead time undone when `tdc.pile-up-correction` is on
/// ([`undo_pile_up`]); then shifted by the legs and the system delay and rebinned onto
/// `axis` ([`rebin_path`]).
pub fn record_transient(
    rec: &Record,
    pair: &PlannedPair,
    inst: &InstrumentConfig,
    axis: &TimeAxis,
) -> Option<Vec<f32>> {
    if rec.flags.overflow {
        return None;
    }
    let tdc = record_axis(rec, inst);
    Some(rebin_path(
        record_counts(rec, inst),
        tdc.start - legs(pair, inst),
        tdc.width,
        axis,
    ))
}

/// Appends the transient `rec` gives its pair ([`record_transient`], on `set`'s axis)
/// to `set`, with `gain` its relay spots' known gain where there is one, and marks the
/// bins its own TDC window recorded ([`TransientSet::limit_recorded`]): the window
/// shifted by this pair's legs, so where the run's axis reaches past it (a pair whose
/// legs are longer than the shortest pair's, under a window that stops short of the
/// volume) the fit leaves the zeros there out. `Ok(false)` for an overflowed record,
/// which is not appended.
pub fn push_record(
    set: &mut TransientSet,
    rec: &Record,
    pair: &PlannedPair,
    inst: &InstrumentConfig,
    gain: Option<f32>,
) -> Result<bool, TransientError> {
    let Some(h) = record_transient(rec, pair, inst, set.axis()) else {
        return Ok(false);
    };
    match gain {
        Some(g) => set.push_with_gain(pair.pair(), &h, g),
        None => set.push(pair.pair(), &h),
    }?;
    let tdc = record_axis(rec, inst);
    let start = tdc.start - legs(pair, inst);
    set.limit_recorded(set.len() - 1, (start, start + tdc.bins as f64 * tdc.width));
    Ok(true)
}

/// The path a pair's light travels outside the hidden scene: from the laser galvo to
/// its illumination point, and from its detection point to the SPAD galvo.
fn legs(pair: &PlannedPair, inst: &InstrumentConfig) -> f64 {
    pair.xi.distance(inst.laser_arm.pose.origin) + pair.xd.distance(inst.spad_arm.pose.origin)
}

/// The hidden path lengths the plan's TDC window records over `pairs`, from the
/// earliest pair's first bin to the latest pair's last: each pair's window on the total
/// path (the acquisition's offset, bins and bin width, less the system delay) shifted
/// by its legs. `None` without pairs.
pub fn recorded_hidden_range(
    pairs: &[PlannedPair],
    acq: &Acquisition,
    inst: &InstrumentConfig,
) -> Option<(f64, f64)> {
    pairs
        .iter()
        .map(|p| recorded_window(p, acq, inst))
        .fold(None, |range, (a, b)| {
            let (from, to) = range.unwrap_or((f64::INFINITY, f64::NEG_INFINITY));
            Some((from.min(a), to.max(b)))
        })
}

/// The hidden path lengths the plan's TDC window records for `pair`: the window on the
/// total path (offset, bins and bin width, less the system delay) shifted by the pair's
/// legs. What [`push_record`] marks once the pair is measured, known before it is (an
/// adaptive capture weighs its candidates by it).
pub fn recorded_window(pair: &PlannedPair, acq: &Acquisition, inst: &InstrumentConfig) -> (f64, f64) {
    let tdc = TimeAxis::of_tdc(
        acq.offset,
        acq.bin_width,
        acq.bins as usize,
        inst.tdc.system_delay,
    );
    let l = legs(pair, inst);
    (tdc.start - l, tdc.end() - l)
}

/// [`recorded_window`] as the fit will read it on `axis`: the bins wholly inside it
/// ([`TransientSet::limit_recorded`]'s rule), as path lengths; an empty range where
/// there are none.
pub fn recorded_bins(
    axis: &TimeAxis,
    pair: &PlannedPair,
    acq: &Acquisition,
    inst: &InstrumentConfig,
) -> (f64, f64) {
    match bins_within(axis, recorded_window(pair, acq, inst)) {
        Some((first, end)) => (axis.edge(first as isize), axis.edge(end as isize)),
        None => (axis.start, axis.start),
    }
}

/// The hidden-path axis every reconstruction of a run puts its transients on (the live
/// fit and `periscope recon RUN_DIR` alike): the plan's bin width, spanning the paths
/// `volume` can produce ([`hidden_axis`]) where the TDC window records them
/// ([`clip_to_measured`]). Bins past the window would hold zeros nobody measured,
/// which the fit reads as "no light at this path length" and which would set the
/// Poisson loss's background estimate to its floor. An error when the window records
/// none of the volume's paths.
pub fn run_axis(
    pairs: &[PlannedPair],
    volume: &VolumeGrid,
    acq: &Acquisition,
    inst: &InstrumentConfig,
) -> Result<TimeAxis, TransientError> {
    let recon_pairs: Vec<_> = pairs.iter().map(PlannedPair::pair).collect();
    let axis = hidden_axis(&recon_pairs, volume, acq.bin_width)?;
    let Some(range) = recorded_hidden_range(pairs, acq, inst) else {
        return Ok(axis);
    };
    let needed = periscope_recon::transient::paths_needed(&recon_pairs, volume);
    let kept = clip_to_measured(&axis, range, needed).map_err(|_| {
        TransientError::Window(format!(
            "the TDC window (acquisition.offset-ns {:.3} ns, {} bins of {:.1} ps, less the \
                 system delay) records hidden paths of {:.3} to {:.3} m over the planned pairs, \
                 none of the {:.3} to {:.3} m the volume's paths need: move acquisition.offset-ns, \
                 add bins, or give a [recon.volume] the window reaches",
            acq.offset * 1e9,
            acq.bins,
            acq.bin_width * 1e12,
            range.0,
            range.1,
            needed.0,
            needed.1,
        ))
    })?;
    // Each pair's own window against its own paths: the union above can overlap where
    // no pair records any of its own (the pair with the shortest legs aimed away from
    // the volume, the one under it with longer legs). A pair is blind where no bin the
    // fit will read of it (whole bins of the kept axis inside its window) reaches its
    // paths.
    let blind = pairs
        .iter()
        .zip(&recon_pairs)
        .filter(|(p, q)| {
            let (from, to) = recorded_bins(&kept, p, acq, inst);
            let (near, far) = path_range(q, volume);
            to <= from || to <= near || from >= far
        })
        .count();
    if blind == pairs.len() {
        return Err(TransientError::Window(format!(
            "the TDC window (acquisition.offset-ns {:.3} ns, {} bins of {:.1} ps, less the system \
             delay) records none of any planned pair's own paths through the volume (each pair's \
             window shifted by its legs): move acquisition.offset-ns, add bins, or give a \
             [recon.volume] the window reaches",
            acq.offset * 1e9,
            acq.bins,
            acq.bin_width * 1e12,
        )));
    }
    if blind > 0 {
        tracing::warn!(
            blind,
            of = pairs.len(),
            "the TDC window records none of some pairs' own paths through the volume (each \
             pair's window shifted by its legs): their histograms tell the reconstruction \
             nothing (move acquisition.offset-ns or add bins)"
        );
    }
    if kept != axis {
        tracing::warn!(
            recorded_m = ?range,
            needed_m = ?(axis.start, axis.start + axis.bins as f64 * axis.width),
            bins = kept.bins,
            of = axis.bins,
            "the TDC window records only part of the hidden paths the volume can produce; the \
             reconstruction keeps the recorded bins (move acquisition.offset-ns or add bins to \
             record the rest)"
        );
    }
    Ok(kept)
}

/// A record's total-path axis (its own offset and bin width, the instrument's system
/// delay).
pub fn record_axis(rec: &Record, inst: &InstrumentConfig) -> TimeAxis {
    TimeAxis::of_tdc(
        f64::from(rec.offset_ps) * 1e-12,
        f64::from(rec.bin_width_ps) * 1e-12,
        rec.counts.len(),
        inst.tdc.system_delay,
    )
}

#[cfg(test)]
mod tests {
    use periscope_recon::C0;

    use super::*;

    fn sim_instrument() -> InstrumentConfig {
        let text = include_str!("../../configs/instrument/sim.toml");
        InstrumentConfig::from_source(&crate::config::TomlSource::from_text("sim.toml", text))
            .expect("the shipped config is valid")
    }

    #[test]
    fn a_runs_hidden_axis_keeps_to_the_tdc_window() {
        let inst = sim_instrument();
        let volume = VolumeGrid::new([-0.4, 0.4], [-0.4, 0.4], [0.3, 0.9], [16, 16, 16]).unwrap();
        let at = |x: f64, y: f64| PlannedPair {
            xi: glam::DVec3::new(x, y, 0.0),
            ni: glam::DVec3::Z,
            xd: glam::DVec3::new(x + 0.005, y, 0.0),
            nd: glam::DVec3::Z,
            laser: periscope_drivers::OpticalAngles { x: 0.0, y: 0.0 },
            spad: periscope_drivers::OpticalAngles { x: 0.0, y: 0.0 },
        };
        let pairs: Vec<PlannedPair> = [(-0.3, -0.3), (0.3, -0.3), (0.0, 0.0), (0.3, 0.3)]
            .iter()
            .map(|&(x, y)| at(x, y))
            .collect();
        let acq = |bins: u32, offset: f64| Acquisition {
            dwell: std::time::Duration::from_millis(20),
            bins,
            bin_width: 16e-12,
            offset,
            repeats: 1,
        };
        let recon: Vec<_> = pairs.iter().map(PlannedPair::pair).collect();
        let whole = hidden_axis(&recon, &volume, 16e-12).unwrap();
        let end = |a: &TimeAxis| a.start + a.bins as f64 * a.width;
        // The shipped window (1,024 bins from 12 ns) records every path: the axis as
        // the volume needs it, bit for bit the one before windows were asked.
        let wide = acq(1024, 12e-9);
        let (from, to) = recorded_hidden_range(&pairs, &wide, &inst).unwrap();
        assert!(from < whole.start && to > end(&whole), "{from} {to} {whole:?}");
        assert_eq!(run_axis(&pairs, &volume, &wide, &inst).unwrap(), whole);
        // 400 bins stop at 5.52 m of total path: the axis keeps the bins the window
        // records for some pair, on the same grid, and no bin past the last one.
        let short = acq(400, 12e-9);
        let (_, to) = recorded_hidden_range(&pairs, &short, &inst).unwrap();
        let legs = pairs.iter().map(|p| legs(p, &inst)).fold(f64::INFINITY, f64::min);
        assert!((to - (C0 * (12e-9 + 400.0 * 16e-12) - legs)).abs() < 1e-9, "{to}");
        let clipped = run_axis(&pairs, &volume, &short, &inst).unwrap();
        assert_eq!((clipped.start, clipped.width), (whole.start, whole.width));
        assert!(clipped.bins < whole.bins, "{clipped:?} {whole:?}");
        assert!(
            end(&clipped) <= to + 1e-9 && end(&clipped) > to - clipped.width,
            "{clipped:?} {to}"
        );
        // The pair with the shortest legs (the relay's centre) has counts up to the
        // axis's last bin, not zeros past what was recorded.
        let flat = |pair: u32| Record {
            pair,
            counts: vec![7; 400],
            flags: periscope_drivers::HistogramFlags::default(),
            bin_width_ps: 16,
            offset_ps: 12_000,
            dwell_us: 20_000,
            partial: false,
        };
        let h = record_transient(&flat(2), &pairs[2], &inst, &clipped).unwrap();
        assert!(h.iter().all(|&v| v > 0.0), "{h:?}");
        // Pairs with longer legs stop a few bins earlier on the one axis; each is
        // marked with the bins its own window recorded, which the fit keeps to, and
        // holds its counts there.
        let mut set = TransientSet::new(clipped).unwrap();
        for (i, p) in pairs.iter().enumerate() {
            assert!(push_record(&mut set, &flat(i as u32), p, &inst, None).unwrap());
            let kept = set.recorded(i);
            let own_end = C0 * (12e-9 + 400.0 * 16e-12) - super::legs(p, &inst);
            assert!(clipped.edge(kept.end as isize) <= own_end + 1e-9, "{i}: {kept:?}");
            assert!(
                kept.end == clipped.bins || clipped.edge(kept.end as isize + 1) > own_end,
                "{i}"
            );
            assert!(set.histogram(i)[kept.clone()].iter().all(|&v| v > 0.0), "{i}");
            // What an adaptive capture credits the pair with before measuring it.
            let (a, b) = recorded_bins(&clipped, p, &short, &inst);
            assert_eq!(
                (a, b),
                (clipped.edge(kept.start as isize), clipped.edge(kept.end as isize)),
                "{i}"
            );
        }
        assert_eq!(set.recorded(2), 0..clipped.bins);
        assert!(set.recorded(0).end < clipped.bins, "{:?}", set.recorded(0));
        // An overflowed histogram is not appended.
        let mut overflowed = flat(1);
        overflowed.flags.overflow = true;
        assert!(!push_record(&mut set, &overflowed, &pairs[1], &inst, None).unwrap());
        assert_eq!(set.len(), 4);
        // A volume off to one side: the pair with the shortest legs (the relay's centre)
        // is farther from it than one under it, whose legs are longer. A window ending
        // between their nearest paths records part of the union of the paths, but none
        // of either pair's own: refused. Ending later, the pair under the volume
        // records some of its own.
        let aside = VolumeGrid::new([0.3, 0.7], [-0.2, 0.2], [0.3, 0.9], [16, 16, 16]).unwrap();
        let two = [at(0.0, 0.0), at(0.5, 0.0)];
        let total_near = |p: &PlannedPair| path_range(&p.pair(), &aside).0 + super::legs(p, &inst);
        let (centre, under) = (total_near(&two[0]), total_near(&two[1]));
        assert!(under < centre && super::legs(&two[1], &inst) > super::legs(&two[0], &inst));
        let ending = |total: f64| {
            let bins = ((total - C0 * (12e-9 - inst.tdc.system_delay)) / (C0 * 16e-12)).floor();
            acq(bins as u32, 12e-9)
        };
        let between = ending(under - 0.01);
        let (_, union_to) = recorded_hidden_range(&two, &between, &inst).unwrap();
        let union_near = two
            .iter()
            .map(|p| path_range(&p.pair(), &aside).0)
            .fold(f64::INFINITY, f64::min);
        assert!(
            union_to > union_near,
            "the union overlaps: {union_to} {union_near}"
        );
        let e = run_axis(&two, &aside, &between, &inst).unwrap_err().to_string();
        assert!(e.contains("none of any planned pair's own paths"), "{e}");
        assert!(run_axis(&two, &aside, &ending(under + 0.05), &inst).is_ok());
        // A window wholly before the volume's paths: refused, naming the key to move.
        let early = acq(64, 12e-9);
        let e = run_axis(&pairs, &volume, &early, &inst).unwrap_err().to_string();
        assert!(
            e.contains("acquisition.offset-ns") && e.contains("[recon.volume]"),
            "{e}"
        );
    }

    /// sim.toml: 50 ns of dead time, a 100 ns cycle, a window of 1024 × 16 ps: a
    /// detection's dead time ends before the next window opens, so only Coates
    /// counts. A 25 MHz laser (a 40 ns cycle) lets it reach the next window.
    #[test]
    fn dead_time_counts_only_where_it_reaches_the_next_window() {
        let mut inst = sim_instrument();
        assert_eq!(dead_time_across_cycles(&inst), 0.0);
        inst.laser.repetition_rate = 25e6;
        assert_eq!(dead_time_across_cycles(&inst), inst.spad.dead_time);
        assert!((inst.spad.dead_time - 50e-9).abs() < 1e-15);
        // A divider lengthens the cycle again.
        inst.tdc.sync_divider = 4;
        assert_eq!(dead_time_across_cycles(&inst), 0.0);
    }

    #[test]
    fn pile_up_is_undone_by_hand_worked_figures() {
        // 1000 cycles: bin 1 took 500 of them, so λ = −ln(1 − 500/1000) = ln 2; bin 2
        // took 250 of the 500 still waiting, λ = ln 2 again.
        let got = undo_pile_up(&[0, 500, 250, 0], 1000.0, 1.0, 0.0);
        let ln2k = (1000.0 * std::f64::consts::LN_2) as f32;
        assert_eq!(got[0], 0.0);
        assert!(
            (got[1] - ln2k).abs() < 1e-3 && (got[2] - ln2k).abs() < 1e-3,
            "{got:?}"
        );
        // Dead time: 750 counts in 1 s with τ = 0.1 ms kept the SPAD busy 7.5 % of the
        // time, so every bin is scaled by 1/0.925 before Coates.
        let got = undo_pile_up(&[0, 500, 250, 0], 1e9, 1.0, 1e-4);
        assert!((got[1] - 500.0 / 0.925).abs() < 0.01, "{got:?}");
        // Low rates (21 counts in 2·10^5 cycles): under 0.02 % change.
        let got = undo_pile_up(&[3, 7, 11], 2e5, 0.02, 50e-9);
        assert!(
            got.iter()
                .zip([3.0, 7.0, 11.0])
                .all(|(g, w)| (g / w - 1.0).abs() < 2e-4),
            "{got:?}"
        );
        // Every cycle taken: finite; no cycle count: the counts as they are.
        assert!(
            undo_pile_up(&[10, 10], 10.0, 1.0, 0.0)
                .iter()
                .all(|v| v.is_finite())
        );
        assert_eq!(undo_pile_up(&[4, 5], 0.0, 1.0, 0.0), vec![4.0, 5.0]);
        // More counts than cycles (a wrong pulse rate or divider): as counted, where
        // undoing pile-up would zero every bin after the cycles run out.
        assert_eq!(
            undo_pile_up(&[30, 40, 50], 20.0, 1.0, 0.0),
            vec![30.0, 40.0, 50.0]
        );
    }
}

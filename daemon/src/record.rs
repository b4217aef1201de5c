//! A stored histogram record as every reconstruction of a run sees it: the SPAD's dead
//! time and pile-up undone (when the instrument asks for it), on its total-path axis,
//! rebinned to the hidden path of its pair. The capture's streamed fit, `periscope
//! recon RUN_DIR`, the y-tal export and the tests share these.
use periscope_recon::TimeAxis;
use periscope_recon::transient::rebin_path;

use crate::config::InstrumentConfig;
use crate::plan::PlannedPair;
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
        undo_pile_up(counts, cycles, dwell, inst.spad.dead_time)
    } else {
        counts.iter().map(|&c| c as f32).collect()
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
    let legs = pair.xi.distance(inst.laser_arm.pose.origin) + pair.xd.distance(inst.spad_arm.pose.origin);
    let tdc = record_axis(rec, inst);
    Some(rebin_path(
        record_counts(rec, inst),
        tdc.start - legs,
        tdc.width,
        axis,
    ))
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
    use super::*;

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
    }
}

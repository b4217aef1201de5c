//! NLOS acquisition: every planned pair measured through the drivers, stored in the
//! histogram log, and streamed (in hidden path length) to the 3D-GTR optimiser.
use std::collections::HashSet;
use std::sync::mpsc;

use periscope_drivers::{GalvoPair, HistogramFlags, Histogrammer, Laser, TdcConfig};
use periscope_recon::{C0, Pair, TimeAxis, TransientSet, VolumeGrid};

use super::reconstruct::{Fit, ReconInput};
use super::safety::FlagRun;
use super::{PipelineError, Run};
use crate::events::RunEvent;
use crate::plan::{Acquisition, Method, PlannedPair};
use crate::store::{HistogramLog, Record};

/// Fewest pairs per batch sent to the optimiser; a batch is also at least an eighth of
/// the plan, so a fit streams in at most a handful of batches and its live epochs (one
/// per batch, see `periscope_recon::gtr::train`) cost at most a few full epochs.
const FEED_BATCH: usize = 32;

/// Rebins a TDC histogram onto the hidden-path axis: TDC bin k covers path lengths
/// c0·(offset + k·w − t_sys) − legs onward, a fractional shift of the common axis, so
/// each bin's counts are split between the two axis bins it overlaps (area-exact).
pub fn hidden_histogram(
    counts: &[u32],
    acq_offset: f64,
    bin_width: f64,
    system_delay: f64,
    legs: f64,
    axis: &TimeAxis,
) -> Vec<f32> {
    rebin_path(
        counts.iter().map(|&c| c as f32),
        C0 * (acq_offset - system_delay) - legs,
        C0 * bin_width,
        axis,
    )
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
pub fn record_counts(rec: &Record, inst: &crate::config::InstrumentConfig) -> Vec<f32> {
    if inst.tdc.pile_up_correction {
        let dwell = rec.dwell_us as f64 * 1e-6;
        let cycles = dwell * inst.laser.repetition_rate / f64::from(inst.tdc.sync_divider.max(1));
        undo_pile_up(&rec.counts, cycles, dwell, inst.spad.dead_time)
    } else {
        rec.counts.iter().map(|&c| c as f32).collect()
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
    inst: &crate::config::InstrumentConfig,
    axis: &TimeAxis,
) -> Option<Vec<f32>> {
    if rec.flags.overflow {
        return None;
    }
    let legs = pair.xi.distance(inst.laser_arm.pose.origin) + pair.xd.distance(inst.spad_arm.pose.origin);
    let offset = f64::from(rec.offset_ps) * 1e-12;
    let width = f64::from(rec.bin_width_ps) * 1e-12;
    Some(rebin_path(
        record_counts(rec, inst),
        C0 * (offset - inst.tdc.system_delay) - legs,
        C0 * width,
        axis,
    ))
}

/// Rebins values whose bin k covers path lengths [start + k·width, start + (k+1)·width)
/// (metres) onto `axis`, splitting each bin over the axis bins it overlaps so the total
/// inside the axis is preserved (area-exact). Bins outside the axis are dropped.
pub fn rebin_path(
    values: impl IntoIterator<Item = f32>,
    start: f64,
    width: f64,
    axis: &TimeAxis,
) -> Vec<f32> {
    let mut out = vec![0.0f32; axis.bins];
    let shift = (start - axis.start) / axis.width;
    let scale = width / axis.width;
    if !(shift.is_finite() && scale.is_finite() && scale > 0.0) {
        // No overlap can be computed: nothing lands on the axis.
        return out;
    }
    for (k, c) in values.into_iter().enumerate() {
        if c == 0.0 {
            continue;
        }
        let lo = shift + k as f64 * scale;
        let hi = lo + scale;
        // Bins wholly outside the axis are skipped before any index is formed, so
        // far-off starts (hostile files) neither overflow nor loop.
        if !(hi > 0.0 && lo < axis.bins as f64) {
            continue;
        }
        let (first, last) = (lo.floor() as isize, (hi.ceil() as isize).saturating_sub(1));
        for j in first.max(0)..=last.min(axis.bins as isize - 1) {
            let overlap = (hi.min(j as f64 + 1.0) - lo.max(j as f64)).max(0.0);
            out[j as usize] += (f64::from(c) * overlap / scale) as f32;
        }
    }
    out
}

/// Interleaved passes of the capture order: pass `k` takes every `CAPTURE_PASSES`-th
/// planned pair from `k`.
const CAPTURE_PASSES: usize = 4;

/// The order in which `total` planned pairs are captured: [`CAPTURE_PASSES`] interleaved
/// passes (pairs 0, 4, 8, …, then 1, 5, 9, …). Plans list pairs along serpentine rows,
/// so each pass spans the whole detection region: the optimiser, which starts on the
/// first quarter, sees the whole aperture from its first step, and a capture stopped
/// early is a coarser scan of everything rather than a full scan of one strip. The
/// extra galvo travel is a few grid steps per move, well inside the settle time.
pub(crate) fn capture_order(total: usize) -> impl Iterator<Item = usize> {
    (0..CAPTURE_PASSES).flat_map(move |k| (k..total).step_by(CAPTURE_PASSES))
}

/// The hidden-path axis all pairs are rebinned to: the TDC's bin width, spanning the
/// shortest to the longest hidden path any pair can have to the reconstruction volume.
pub fn hidden_axis(pairs: &[Pair], volume: &VolumeGrid, bin_width: f64) -> Result<TimeAxis, String> {
    let width = C0 * bin_width;
    if !(width.is_finite() && width > 0.0) {
        return Err(format!("the bin width {bin_width} s is not a positive time"));
    }
    let (mut near, mut far) = (f64::INFINITY, 0.0f64);
    let (lo, hi) = (volume.min(), volume.max());
    for p in pairs {
        let mut corner_far = 0.0f64;
        for c in 0..8 {
            let q = glam::DVec3::new(
                if c & 1 == 0 { lo.x } else { hi.x },
                if c & 2 == 0 { lo.y } else { hi.y },
                if c & 4 == 0 { lo.z } else { hi.z },
            );
            corner_far = corner_far.max(q.distance(p.xi) + q.distance(p.xd));
        }
        far = far.max(corner_far);
        let clamp = |x: glam::DVec3| x.clamp(lo, hi);
        near = near.min(clamp(p.xi).distance(p.xi) + clamp(p.xd).distance(p.xd));
    }
    let start = ((near.max(0.0) / width).floor() - 4.0).max(0.0) * width;
    // In f64 first: hostile geometry (a tiny bin width, points far away) must be
    // refused, not wrapped or allocated.
    let bins = ((far - start) / width).ceil() + 4.0;
    if !(bins.is_finite() && start.is_finite()) || bins > MAX_AXIS_BINS as f64 {
        return Err(format!(
            "the hidden paths span {:.3e} m, {bins:.3e} bins of {width:.3e} m: more than the {MAX_AXIS_BINS} \
             bins a transient may have; check the bin width, the relay points and the volume",
            far - start
        ));
    }
    Ok(TimeAxis {
        start,
        width,
        bins: (bins as usize).max(8),
    })
}

/// Most bins a transient on the hidden-path axis may have (at 4 ps bins, 1.3 km of
/// path): beyond this a capture's geometry or bin width is wrong, not large.
pub const MAX_AXIS_BINS: usize = 1 << 20;

fn as_pair(p: &PlannedPair) -> Pair {
    Pair {
        xi: p.xi,
        ni: p.ni,
        xd: p.xd,
        nd: p.nd,
    }
}

impl Run {
    /// Measures every pair not yet stored; returns the fit that has been running
    /// alongside.
    pub(crate) fn capture(&mut self, pairs: &[PlannedPair]) -> Result<Fit, PipelineError> {
        let acq: Acquisition = self.plan.acquisition.clone();
        let (l, s) = (
            self.instrument.laser_arm.pose.origin,
            self.instrument.spad_arm.pose.origin,
        );
        let recon_pairs: Vec<Pair> = pairs.iter().map(as_pair).collect();
        let axis = hidden_axis(&recon_pairs, &self.plan.recon.volume, acq.bin_width)
            .map_err(PipelineError::Recon)?;
        let (mut log, recovered) =
            HistogramLog::recover(&self.dir).map_err(|e| PipelineError::storage(&self.dir, e))?;
        if recovered.discarded_bytes > 0 {
            tracing::warn!(
                bytes = recovered.discarded_bytes,
                ranges = ?recovered.damaged,
                kept = recovered.records.len(),
                "the histogram log held incomplete or corrupted records; they were skipped and their pairs are measured again"
            );
        }
        let input = ReconInput {
            settings: self.plan.recon.clone(),
            set: TransientSet::new(axis).map_err(|e| PipelineError::Recon(e.to_string()))?,
            detection_points: pairs.iter().map(|p| p.xd).collect(),
            viewpoint: 0.5 * (l + s),
        };
        let mut fit = Fit::new(input);
        let mut stored: HashSet<u32> = HashSet::new();
        let mut batch = TransientSet::new(axis).map_err(|e| PipelineError::Recon(e.to_string()))?;
        let instrument = self.instrument.clone();
        let push = |batch: &mut TransientSet, rec: &Record| -> Result<(), PipelineError> {
            let p = &pairs[rec.pair as usize];
            match record_transient(rec, p, &instrument, &axis) {
                Some(h) => batch
                    .push(as_pair(p), &h)
                    .map_err(|e| PipelineError::Recon(e.to_string())),
                None => Ok(()),
            }
        };
        for rec in &recovered.records {
            if (rec.pair as usize) < pairs.len() {
                stored.insert(rec.pair);
                push(&mut batch, rec)?;
            }
        }
        self.info.pairs_done = stored.len();
        let total = pairs.len();
        let streaming = self.plan.recon.method == Method::Gtr;
        // The optimiser starts once a quarter of the pairs (at least 64) are in.
        let start_at = (total / 4).max(64).min(total);
        let feed_batch = (total / 8).max(FEED_BATCH);
        let (tx, rx) = mpsc::channel::<TransientSet>();
        let mut rx = Some(rx);
        let (events, control) = (self.events.clone(), self.control.clone());
        let mut feed = |fit: &mut Fit,
                        batch: &mut TransientSet,
                        done: usize,
                        force: bool|
         -> Result<(), PipelineError> {
            if !streaming || batch.is_empty() {
                return Ok(());
            }
            let started = fit.is_training();
            if !started && done < start_at && !force {
                return Ok(());
            }
            let full = std::mem::replace(
                batch,
                TransientSet::new(axis).map_err(|e| PipelineError::Recon(e.to_string()))?,
            );
            if !started {
                fit.start_training(
                    full,
                    rx.take().expect("started once"),
                    events.clone(),
                    control.clone(),
                )?;
            } else if full.len() >= feed_batch || force {
                let _ = tx.send(full);
            } else {
                *batch = full;
            }
            Ok(())
        };
        if stored.len() < total {
            let cfg = TdcConfig {
                bin_width: acq.bin_width,
                bins: acq.bins,
                offset: acq.offset,
                sync_divider: self.instrument.tdc.sync_divider,
                acquisition: acq.dwell,
            };
            self.devices.tdc.configure(&cfg)?;
            self.devices.laser.set_diffuser(false)?;
            self.checkpoint()?;
            // The histogrammer must answer before the laser goes on.
            self.devices.tdc.status()?;
            self.devices.laser.set_emission(true)?;
            let settle = self.settle_timeout();
            let mut flagged = FlagRun::default();
            for i in capture_order(total) {
                let p = &pairs[i];
                if stored.contains(&(i as u32)) {
                    continue;
                }
                // Measured again after a suspension that cleared by itself.
                let (counts, flags) = loop {
                    self.checkpoint()?;
                    // Both arms move at once; each wait accepts only its commanded target.
                    self.devices.laser.move_to(p.laser)?;
                    self.devices.spad.move_to(p.spad)?;
                    self.devices.laser.wait_settled(settle)?;
                    self.devices.spad.wait_settled(settle)?;
                    let mut counts = vec![0u32; acq.bins as usize];
                    let mut flags = HistogramFlags::default();
                    for _ in 0..acq.repeats {
                        self.checkpoint()?;
                        let h = self.acquire()?;
                        for (c, v) in counts.iter_mut().zip(&h.counts) {
                            *c = c.saturating_add(*v);
                        }
                        flags.overflow |= h.flags.overflow;
                        flags.saturated |= h.flags.saturated;
                    }
                    match self.capture_suspension(flags, &mut flagged)? {
                        None => break (counts, flags),
                        // This pair's histograms are not kept: the light changed under them.
                        Some(s) => self.suspend(s)?,
                    }
                };
                let rec = Record {
                    pair: i as u32,
                    flags,
                    bin_width_ps: (acq.bin_width * 1e12).round() as u32,
                    offset_ps: (acq.offset * 1e12).round() as u32,
                    dwell_us: (acq.dwell.as_micros() as u64) * u64::from(acq.repeats),
                    counts,
                };
                log.append(&rec)
                    .map_err(|e| PipelineError::storage(log.path(), e))?;
                stored.insert(i as u32);
                self.info.pairs_done = stored.len();
                push(&mut batch, &rec)?;
                let (peak_bin, _) = rec
                    .counts
                    .iter()
                    .enumerate()
                    .max_by_key(|(_, c)| **c)
                    .unwrap_or((0, &0));
                self.events.emit(RunEvent::histogram(
                    i,
                    p.xi,
                    p.xd,
                    &rec.counts,
                    acq.bin_width,
                    acq.offset,
                ));
                self.events.emit(RunEvent::Pair {
                    done: stored.len(),
                    total,
                    counts: rec.counts.iter().map(|&c| u64::from(c)).sum(),
                    peak_bin,
                    flagged: flags.overflow || flags.saturated,
                });
                feed(&mut fit, &mut batch, stored.len(), false)?;
                if stored.len().is_multiple_of(64) {
                    self.save_info()?;
                }
            }
            log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
            self.devices.laser.set_emission(false)?;
        }
        self.save_info()?;
        if streaming {
            feed(&mut fit, &mut batch, stored.len(), true)?;
        }
        drop(tx);
        if !streaming {
            fit.add(&batch)?;
        }
        Ok(fit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_capture_order_visits_every_pair_once_in_interleaved_passes() {
        for total in [0, 1, 3, 4, 5, 98, 456] {
            let order: Vec<usize> = capture_order(total).collect();
            let mut sorted = order.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..total).collect::<Vec<_>>(), "{total} pairs");
        }
        let order: Vec<usize> = capture_order(10).collect();
        assert_eq!(order, [0, 4, 8, 1, 5, 9, 2, 6, 3, 7]);
        // The first quarter of a 24 × 24 serpentine grid reaches every row.
        let rows: std::collections::BTreeSet<usize> = capture_order(576).take(144).map(|i| i / 24).collect();
        assert_eq!(rows.len(), 24);
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
    }

    #[test]
    fn rebinning_preserves_counts_and_shifts_by_the_legs() {
        let mut counts = vec![0u32; 64];
        counts[20] = 1000;
        let bw = 16e-12;
        let axis = TimeAxis {
            start: 0.0,
            width: C0 * bw,
            bins: 64,
        };
        // Legs of exactly 10.25 bins: TDC bin 20 covers hidden bins [9.75, 10.75),
        // a quarter in bin 9 and three quarters in bin 10.
        let legs = 10.25 * axis.width;
        let h = hidden_histogram(&counts, 0.0, bw, 0.0, legs, &axis);
        let total: f32 = h.iter().sum();
        assert!((total - 1000.0).abs() < 1e-3, "{total}");
        assert!(
            (h[9] - 250.0).abs() < 1e-3 && (h[10] - 750.0).abs() < 1e-3,
            "{:?}",
            &h[8..12]
        );
    }
}

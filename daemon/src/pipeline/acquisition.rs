//! NLOS acquisition: every planned pair measured through the drivers, stored in the
//! histogram log, and streamed (in hidden path length) to the 3D-GTR optimiser.
use std::collections::HashSet;
use std::sync::mpsc;

use periscope_drivers::{HistogramFlags, TdcConfig};
use periscope_recon::transient::hidden_axis;
use periscope_recon::{Pair, TransientSet};

use super::reconstruct::{Fit, ReconInput};
use super::safety::FlagRun;
use super::{PipelineError, ReconError, Run};
use crate::events::RunEvent;
use crate::plan::{Acquisition, Method, PlannedPair};
use crate::record::record_transient;
use crate::store::{HistogramLog, Record};

/// Fewest pairs per batch sent to the optimiser; a batch is also at least an eighth of
/// the plan, so a fit streams in at most a handful of batches and its live epochs (one
/// per batch, see `periscope_recon::gtr::train`) cost at most a few full epochs.
const FEED_BATCH: usize = 32;

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

impl Run {
    /// Measures every pair not yet stored; returns the fit that has been running
    /// alongside and every stored record (those of earlier sessions of the run too),
    /// which the outputs stage exports without reading the log back.
    pub(crate) fn capture(&mut self, pairs: &[PlannedPair]) -> Result<(Fit, Vec<Record>), PipelineError> {
        let acq: Acquisition = self.plan.acquisition.clone();
        let (l, s) = (
            self.instrument.laser_arm.pose.origin,
            self.instrument.spad_arm.pose.origin,
        );
        let recon_pairs: Vec<Pair> = pairs.iter().map(PlannedPair::pair).collect();
        let axis =
            hidden_axis(&recon_pairs, &self.plan.recon.volume, acq.bin_width).map_err(ReconError::from)?;
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
        // The TDC's histograms are photon counts (pile-up corrected, perhaps).
        let counts = || -> Result<TransientSet, ReconError> {
            let mut set = TransientSet::new(axis)?;
            set.mark_photon_counts();
            Ok(set)
        };
        let input = ReconInput {
            settings: self.plan.recon.clone(),
            set: counts()?,
            detection_points: pairs.iter().map(|p| p.xd).collect(),
            viewpoint: 0.5 * (l + s),
        };
        let mut fit = Fit::new(input);
        let mut stored: HashSet<u32> = HashSet::new();
        let mut batch = counts()?;
        let instrument = self.instrument.clone();
        let push = |batch: &mut TransientSet, rec: &Record| -> Result<(), PipelineError> {
            let p = &pairs[rec.pair as usize];
            match record_transient(rec, p, &instrument, &axis) {
                Some(h) => Ok(batch.push(p.pair(), &h).map_err(ReconError::from)?),
                None => Ok(()),
            }
        };
        let mut held = Vec::with_capacity(pairs.len());
        for rec in recovered.records {
            if (rec.pair as usize) < pairs.len() {
                stored.insert(rec.pair);
                push(&mut batch, &rec)?;
                held.push(rec);
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
            let full = std::mem::replace(batch, counts()?);
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
            self.laser_on()?;
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
                    self.devices.laser_arm.move_to(p.laser)?;
                    self.devices.spad.move_to(p.spad)?;
                    self.devices.laser_arm.wait_settled(settle)?;
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
                    p,
                    &rec.counts,
                    rec.dwell_us,
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
                held.push(rec);
                if stored.len().is_multiple_of(64) {
                    self.save_info()?;
                }
            }
            log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
            self.devices.laser.set_emission(false)?;
            self.report_laser();
        }
        self.save_info()?;
        if streaming {
            feed(&mut fit, &mut batch, stored.len(), true)?;
        }
        drop(tx);
        if !streaming {
            fit.add(&batch)?;
        }
        Ok((fit, held))
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
}

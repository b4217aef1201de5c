//! NLOS acquisition: every planned pair measured through the drivers, stored in the
//! histogram log, and streamed (in hidden path length) to the 3D-GTR optimiser.
use std::collections::HashSet;
use std::sync::mpsc;
use std::time::Duration;

use periscope_drivers::{HistogramFlags, TdcConfig};
use periscope_recon::{Pair, TransientSet};

use super::reconstruct::{Fit, ReconInput};
use super::safety::{FlagRun, PairVerdict};
use super::{PipelineError, ReconError, Run};
use crate::adaptive::{Order, Selector};
use crate::events::RunEvent;
use crate::plan::{Acquisition, Method, PlannedPair};
use crate::record::{push_record, recorded_bins, relay_gains, run_axis};
use crate::run_dir::RelayPoint;
use crate::store::{HISTOGRAM_LOG, HistogramLog, Record};

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
    pub(crate) fn capture(
        &mut self,
        pairs: &[PlannedPair],
        relay: &[RelayPoint],
    ) -> Result<(Fit, Vec<Record>), PipelineError> {
        let (mut log, recovered) = HistogramLog::recover(&self.dir)
            .map_err(|e| PipelineError::storage(&self.dir.join(HISTOGRAM_LOG), e))?;
        if recovered.discarded_bytes > 0 {
            tracing::warn!(
                bytes = recovered.discarded_bytes,
                ranges = ?recovered.damaged,
                kept = recovered.records.len(),
                "the histogram log held incomplete or corrupted records; they were skipped and their pairs are measured again"
            );
        }
        let result = self.capture_into(&mut log, recovered.records, recovered.partial, pairs, relay);
        if result.is_err() {
            // A stop, a device error or a full disk: the laser goes off before the log
            // is synced and closed (its drop syncs, which on a stalling disk takes
            // seconds); the run's `make_safe` parks the arms after.
            if let Err(e) = self.devices.laser.set_emission(false) {
                tracing::warn!(error = %e, "switching the laser off as the capture stopped failed; the run's shutdown tries again");
            }
        }
        drop(log);
        result
    }

    /// [`Run::capture`]'s work, on the open histogram log and the records recovered
    /// from it.
    fn capture_into(
        &mut self,
        log: &mut HistogramLog,
        recovered: Vec<Record>,
        partial: Vec<Record>,
        pairs: &[PlannedPair],
        relay: &[RelayPoint],
    ) -> Result<(Fit, Vec<Record>), PipelineError> {
        // Partial sums an earlier session kept when it stopped in the middle of a
        // pair's repeats: the pair's rest is measured on top of them.
        // One that does not fit the plan stays in the log, and its pair is measured
        // afresh.
        let acq: Acquisition = self.plan.acquisition.clone();
        let mut partial: std::collections::HashMap<u32, Record> = partial
            .into_iter()
            .filter(|r| (r.pair as usize) < pairs.len() && self.fits_the_plan(r, &acq))
            .map(|r| (r.pair, r))
            .collect();
        let (l, s) = (
            self.instrument.laser_arm.pose.origin,
            self.instrument.spad_arm.pose.origin,
        );
        let recon_pairs: Vec<Pair> = pairs.iter().map(PlannedPair::pair).collect();
        let axis =
            run_axis(pairs, &self.plan.recon.volume, &acq, &self.instrument).map_err(ReconError::from)?;
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
        let mut fit = Fit::new(input)?;
        let mut stored: HashSet<u32> = HashSet::new();
        let mut batch = counts()?;
        let instrument = self.instrument.clone();
        let gains = relay_gains(relay, pairs, &instrument, self.plan.relay.albedo_from_scan);
        let push = |batch: &mut TransientSet, rec: &Record| -> Result<(), PipelineError> {
            let p = &pairs[rec.pair as usize];
            let gain = gains.as_ref().map(|g| g[rec.pair as usize]);
            push_record(batch, rec, p, &instrument, gain).map_err(ReconError::from)?;
            Ok(())
        };
        let mut held = Vec::with_capacity(pairs.len());
        for rec in recovered {
            if (rec.pair as usize) < pairs.len() {
                stored.insert(rec.pair);
                push(&mut batch, &rec)?;
                held.push(rec);
            }
        }
        self.info.pairs_done = stored.len();
        // A direct solver whose checks of the layout fail on the planned pairs would
        // fail after measuring every one of them: refused before the first (a
        // resumed run's stored pairs are reconstructed, or refused, by the solver).
        if let Method::Solver(solver) = self.plan.recon.method
            && stored.len() < pairs.len()
        {
            let s = &self.plan.recon;
            solver
                .check_layout(&recon_pairs, &axis, &s.volume, &s.solvers)
                .map_err(|source| ReconError::Unsuited {
                    solver,
                    pairs: pairs.len(),
                    source,
                })?;
        }
        if self.plan.adaptive && self.plan.recon.method == Method::Gtr {
            // An adaptive capture: the planned pairs are candidates; a first batch
            // spread over them, then each batch chosen by the fit after the last one's
            // live training, until the budget or the stopping rule ends it.
            let mut selector = Selector::new(
                recon_pairs.clone(),
                self.plan.recon.adaptive.clone(),
                Order::Adaptive,
            )
            .with_recorded(
                pairs
                    .iter()
                    .map(|p| recorded_bins(&axis, p, &acq, &self.instrument))
                    .collect(),
            );
            selector.resume(&held.iter().map(|r| r.pair as usize).collect::<Vec<_>>());
            selector.resume_batches(self.info.adaptive_batches);
            for note in crate::adaptive::Sizes::notes(pairs.len(), &self.plan.recon.adaptive) {
                tracing::warn!("{note}");
            }
            let total = selector.budget();
            self.info.pairs_total = total;
            let live_steps = self.plan.recon.adaptive.live_steps;
            if let Some(why) = self.info.adaptive_stopped.clone() {
                // Resumed after the capture had ended before its budget: it stays ended.
                tracing::info!(
                    measured = held.len(),
                    "adaptive capture resumed after it had ended: {why}"
                );
                fit.add(&batch)?;
                return Ok((fit, held));
            }
            // Pairs an earlier session stopped in the middle of are finished first:
            // their partial sums are laser time spent, which a new choice would leave
            // unused in the log.
            let mut carried: Vec<usize> = partial.keys().map(|&i| i as usize).collect();
            carried.retain(|&i| !stored.contains(&(i as u32)));
            let mut next = selector.resumed_batch(&carried);
            if next.is_none() && selector.measured().len() >= total {
                // Resumed with the budget already measured: nothing to choose.
                fit.add(&batch)?;
                return Ok((fit, held));
            }
            let (tx, rx) = mpsc::channel::<TransientSet>();
            let (model_tx, model_rx) = mpsc::channel();
            let mut start = Some((rx, model_tx));
            let settle = self.settle_timeout();
            let mut flagged = FlagRun::default();
            let mut prepared = false;
            // The time budget counts every session of a resumed capture.
            let (started, before) = (std::time::Instant::now(), self.info.adaptive_seconds);
            let spent = move || before + started.elapsed().as_secs_f64();
            loop {
                if let Some(choice) = next.take() {
                    // A pause or abort that came while the fit chose is answered before
                    // the laser goes on for the batch.
                    self.checkpoint()?;
                    self.events.emit(RunEvent::PairsChosen(choice.clone()));
                    // Counted as chosen, so that a stop in its middle (whose run.json
                    // is saved as the run stops) resumes numbering on past it.
                    self.info.adaptive_batches = selector.batches();
                    if !prepared {
                        self.prepare_capture(&acq)?;
                        prepared = true;
                    }
                    self.laser_on()?;
                    for &i in &choice.pairs {
                        if stored.contains(&(i as u32)) {
                            continue;
                        }
                        let p = &pairs[i];
                        let carried = partial.remove(&(i as u32));
                        let rec = self.measure(i, p, &acq, settle, &mut flagged, log, carried)?;
                        self.store(log, &mut stored, &rec)?;
                        push(&mut batch, &rec)?;
                        self.announce(i, p, &rec, &acq, stored.len(), total);
                        held.push(rec);
                    }
                    // The laser is off while the fit chooses the next batch (seconds of
                    // training with nothing to measure), and before the disk is waited on.
                    self.devices.laser.set_emission(false)?;
                    self.report_laser();
                    log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
                    self.info.adaptive_seconds = spent();
                    self.info.adaptive_batches = selector.batches();
                    self.save_info()?;
                }
                let full = std::mem::replace(&mut batch, counts()?);
                let budget_s = self.plan.recon.adaptive.seconds;
                let out_of_time = |spent: f64| budget_s > 0.0 && spent >= budget_s;
                let measured_all = selector.measured().len() >= total;
                if measured_all || out_of_time(spent()) {
                    // Nothing more is chosen: the last batch goes to the refit as it
                    // is, not through a live training that no choice needs. Once the
                    // budget is measured that is no stop before the budget, however
                    // long the capture took.
                    if !measured_all {
                        selector.stop(over_time(spent(), budget_s));
                    }
                    fit.add(&full)?;
                    break;
                }
                if start.is_some() && full.is_empty() {
                    // Nothing to fit yet (every histogram flagged and left out): spread
                    // another batch instead of waiting for a fit that cannot start.
                    next = selector.spread();
                    if next.is_none() {
                        break;
                    }
                    continue;
                }
                match start.take() {
                    Some((rx, model_tx)) => fit.start_training(
                        full,
                        rx,
                        self.events.clone(),
                        self.control.clone(),
                        Some((model_tx, live_steps)),
                    )?,
                    None => {
                        let _ = tx.send(full);
                    }
                }
                // The fit's model once the batch has had its live training; a stop or
                // pause is answered while waiting. A fit that ended sends nothing more
                // (`refit` reports why).
                let model = loop {
                    self.checkpoint()?;
                    match model_rx.recv_timeout(MODEL_POLL) {
                        Ok(m) => break Some(m),
                        Err(mpsc::RecvTimeoutError::Timeout) => continue,
                        Err(mpsc::RecvTimeoutError::Disconnected) => break None,
                    }
                };
                let Some(model) = model else { break };
                if out_of_time(spent()) {
                    // The live training ran the time out: this batch is the last.
                    selector.stop(over_time(spent(), budget_s));
                }
                match selector.next(&model, &axis) {
                    Some(c) => next = Some(c),
                    None => break,
                }
            }
            if let Some(why) = selector.stopped() {
                tracing::info!(
                    measured = stored.len(),
                    budget = total,
                    "adaptive capture ended before its budget: {why}"
                );
                self.info.adaptive_stopped = Some(why.to_owned());
            }
            self.info.adaptive_seconds = spent();
            log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
            self.save_info()?;
            drop(tx);
            return Ok((fit, held));
        }
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
                    None,
                )?;
            } else if full.len() >= feed_batch || force {
                let _ = tx.send(full);
            } else {
                *batch = full;
            }
            Ok(())
        };
        if stored.len() < total {
            self.prepare_capture(&acq)?;
            self.laser_on()?;
            let settle = self.settle_timeout();
            let mut flagged = FlagRun::default();
            for i in capture_order(total) {
                let p = &pairs[i];
                if stored.contains(&(i as u32)) {
                    continue;
                }
                let carried = partial.remove(&(i as u32));
                let rec = self.measure(i, p, &acq, settle, &mut flagged, log, carried)?;
                self.store(log, &mut stored, &rec)?;
                push(&mut batch, &rec)?;
                self.announce(i, p, &rec, &acq, stored.len(), total);
                feed(&mut fit, &mut batch, stored.len(), false)?;
                held.push(rec);
                if stored.len().is_multiple_of(64) {
                    // The count run.json records is of records on the disk: the log
                    // first, so a power cut never leaves run.json counting records
                    // the log lost.
                    log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
                    self.save_info()?;
                }
            }
            self.devices.laser.set_emission(false)?;
            self.report_laser();
            log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
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

/// How many of the plan's dwells partial sum `r` holds.
fn repeats_in(r: &Record, acq: &Acquisition) -> u32 {
    (r.dwell_us / (acq.dwell.as_micros() as u64).max(1)) as u32
}

/// Why an adaptive capture that ran `spent` seconds against its time budget ended.
fn over_time(spent: f64, budget_s: f64) -> String {
    format!("the capture has run {spent:.0} s, its time budget (adaptive.seconds = {budget_s})")
}

/// How often a capture waiting for the fit's choice checks for a stop or pause.
const MODEL_POLL: Duration = Duration::from_millis(50);

impl Run {
    /// Configures the histogrammer for the plan's acquisition and takes the diffuser
    /// out; the histogrammer must answer before the laser goes on.
    fn prepare_capture(&mut self, acq: &Acquisition) -> Result<(), PipelineError> {
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
        self.devices.tdc.status()?;
        Ok(())
    }

    /// Measures pair `i` (`p`): both arms moved and settled, the plan's repeats summed
    /// (on top of `carried`, an earlier session's partial sum of them, which
    /// [`Run::fits_the_plan`]); measured again after a suspension that cleared by itself. A pause or
    /// abort in the middle of the repeats keeps those summed ([`Run::keep_partial`]).
    #[allow(clippy::too_many_arguments)]
    fn measure(
        &mut self,
        i: usize,
        p: &PlannedPair,
        acq: &Acquisition,
        settle: Duration,
        flagged: &mut FlagRun,
        log: &mut HistogramLog,
        carried: Option<Record>,
    ) -> Result<Record, PipelineError> {
        let (counts, flags) = loop {
            self.checkpoint()?;
            // Both arms move at once; each wait accepts only its commanded target.
            self.devices.laser_arm.move_to(p.laser)?;
            self.devices.spad.move_to(p.spad)?;
            self.devices.laser_arm.wait_settled(settle)?;
            self.devices.spad.wait_settled(settle)?;
            let (mut counts, mut flags, done) = match &carried {
                Some(r) => (r.counts.clone(), r.flags, repeats_in(r, acq)),
                None => (vec![0u32; acq.bins as usize], HistogramFlags::default(), 0),
            };
            for summed in done..acq.repeats {
                let h = match self.checkpoint().and_then(|()| self.acquire()) {
                    Ok(h) => h,
                    Err(e) => return Err(self.keep_partial(i, acq, (counts, flags), (summed, done), e, log)),
                };
                // A sum past a bin's 2³² − 1 is clipped, and the histogram flagged as
                // overflowed like a counter's own (its counts only a lower bound).
                for (c, v) in counts.iter_mut().zip(&h.counts) {
                    *c = c.checked_add(*v).unwrap_or_else(|| {
                        flags.overflow = true;
                        u32::MAX
                    });
                }
                flags.overflow |= h.flags.overflow;
                flags.saturated |= h.flags.saturated;
            }
            match self.capture_suspension(flags, flagged)? {
                PairVerdict::Keep => break (counts, flags),
                // This pair's histograms are not kept: the sync was in doubt under them.
                PairVerdict::Again => {}
                // Nor here: the light changed under them.
                PairVerdict::Suspend(s) => self.suspend(s, Some(&mut *log))?,
            }
        };
        Ok(self.record(i, acq, counts, flags, acq.repeats, false))
    }

    /// Pair `i`'s record of `counts` summed over `repeats` dwells.
    fn record(
        &self,
        i: usize,
        acq: &Acquisition,
        counts: Vec<u32>,
        flags: HistogramFlags,
        repeats: u32,
        partial: bool,
    ) -> Record {
        Record {
            pair: i as u32,
            flags,
            bin_width_ps: (acq.bin_width * 1e12).round() as u32,
            offset_ps: (acq.offset * 1e12).round() as u32,
            dwell_us: (acq.dwell.as_micros() as u64) * u64::from(repeats),
            counts,
            partial,
        }
    }

    /// Whether an earlier session's partial sum `r` can be continued under the plan:
    /// its bins, bin width and offset the plan's, and a whole number of the plan's
    /// dwells, fewer than its repeats. One that cannot is left in the log, and the
    /// pair's whole record, measured afresh, supersedes it.
    fn fits_the_plan(&self, r: &Record, acq: &Acquisition) -> bool {
        let blank = self.record(
            r.pair as usize,
            acq,
            Vec::new(),
            HistogramFlags::default(),
            0,
            true,
        );
        let dwell_us = acq.dwell.as_micros() as u64;
        let fits = r.counts.len() == acq.bins as usize
            && (r.bin_width_ps, r.offset_ps) == (blank.bin_width_ps, blank.offset_ps)
            && dwell_us > 0
            && r.dwell_us.is_multiple_of(dwell_us)
            && (1..u64::from(acq.repeats)).contains(&(r.dwell_us / dwell_us));
        if !fits {
            tracing::warn!(
                pair = r.pair,
                "the pair's partial sum from an earlier session does not fit the plan's acquisition; it stays in the log and the pair is measured afresh"
            );
        }
        fits
    }

    /// A stop `e` that came after `summed` of pair `i`'s repeats, `done` of them an
    /// earlier session's: where this session summed some and the stop is the
    /// operator's pause or abort, the sum so far is appended as a partial record
    /// ([`Record::partial`]) and a resume measures the rest on top of it (until
    /// 2026-12-07 every stop in the middle of a pair dropped the repeats summed).
    /// Kept only where the pair's own checks would keep it so far
    /// ([`Run::capture_suspension`]'s, read now): the laser still on with the interlock
    /// closed (only the run switches it on, so then every repeat summed was lit
    /// throughout; an e-stop or a signal switches it off out of band as it asks the
    /// stop, and a dwell that ended in between may have been partly dark), the
    /// detector's rate within `suspend.max-count-rate-hz`, and the sync as the config
    /// says once the rate meter shows it; else, as after a device error, the pair is
    /// measured again whole. The laser goes off before the record is written, and the
    /// record is synced with the log after (never waiting on the disk with the laser
    /// on). Returns `e`.
    fn keep_partial(
        &mut self,
        i: usize,
        acq: &Acquisition,
        (counts, flags): (Vec<u32>, HistogramFlags),
        (summed, done): (u32, u32),
        e: PipelineError,
        log: &mut HistogramLog,
    ) -> PipelineError {
        if summed == done || !matches!(e, PipelineError::Paused(_) | PipelineError::Aborted(_)) {
            return e;
        }
        let lit = matches!(self.devices.laser.laser_state(), Ok(s) if s.emission && s.interlock_closed);
        let rates = lit
            .then(|| self.devices.tdc.status())
            .and_then(Result::ok)
            .map(|s| s.rates);
        let after = self.devices.tdc.sync_after_divider();
        let sync_shown = self.sync.from.is_some_and(|t| std::time::Instant::now() >= t);
        let keep = rates.is_some_and(|r| {
            r.detector <= self.plan.suspend.max_count_rate
                && (!sync_shown || self.instrument.sync_fault(r.sync, after).is_none())
        });
        if let Err(err) = self.devices.laser.set_emission(false) {
            tracing::warn!(error = %err, "switching the laser off as the capture stopped failed; the run's shutdown tries again");
        }
        if !keep {
            return e;
        }
        let rec = self.record(i, acq, counts, flags, summed, true);
        match log.append_unsynced(&rec) {
            Ok(()) => tracing::info!(
                pair = i,
                summed,
                repeats = acq.repeats,
                "stopped in the middle of a pair's repeats: those summed are kept, and a resume measures the rest on top of them"
            ),
            Err(err) => tracing::warn!(
                pair = i,
                error = %err,
                "stopped in the middle of a pair's repeats, and their sum could not be kept: a resume measures the pair again"
            ),
        }
        e
    }

    /// Appends a measured pair's record to the histogram log and counts it stored.
    fn store(
        &mut self,
        log: &mut HistogramLog,
        stored: &mut HashSet<u32>,
        rec: &Record,
    ) -> Result<(), PipelineError> {
        log.append(rec)
            .map_err(|e| PipelineError::storage(log.path(), e))?;
        stored.insert(rec.pair);
        self.info.pairs_done = stored.len();
        self.blind_resumes = 0;
        Ok(())
    }

    /// The live displays' events for a stored pair: its histogram and the progress.
    fn announce(
        &self,
        i: usize,
        p: &PlannedPair,
        rec: &Record,
        acq: &Acquisition,
        done: usize,
        total: usize,
    ) {
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
            done,
            total,
            counts: rec.counts.iter().map(|&c| u64::from(c)).sum(),
            peak_bin,
            flagged: rec.flags.overflow || rec.flags.saturated,
        });
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

//! What keeps a run safe while it measures: acquisitions that a pause, abort or e-stop
//! stops within the driver's poll interval, and the suspenders that switch the laser
//! off when the interlock opens, emission drops out, frames keep overflowing or the
//! detector sees too much light.
use std::time::{Duration, Instant};

use periscope_drivers::{Error, ErrorKind, Histogram, HistogramFlags};

use super::{PipelineError, Run};
use crate::events::RunEvent;
use crate::plan::SuspendResume;

/// How often a suspended run looks at its condition and its checkpoint.
const SUSPENDED_POLL: Duration = Duration::from_millis(20);

/// Automatic resumes running, with no pair stored between them, from a condition only
/// a new measurement can judge (the count rate, flagged frames, emission lost), after
/// which the run stops paused for the operator: a limit the scene can never meet (a
/// count-rate limit under the detector's dark counts) switched the laser on and off
/// thousands of times a second, for good, filling `events.jsonl`.
pub(crate) const MAX_BLIND_RESUMES: u32 = 5;

/// The least wait before the second of such resumes running; it doubles with each
/// after it (0.25, 0.5, 1 and 2 s, whatever `clear-for-s` asks below them), so a
/// passing condition (someone walking through the beam) has time to pass.
const BLIND_RESUME_BACKOFF: Duration = Duration::from_millis(250);

/// A condition that suspends measuring.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Suspension {
    /// The interlock loop is open; clears when it closes.
    Interlock,
    /// Emission stopped although it was wanted (a watchdog trip, a controller reset).
    EmissionLost,
    /// Consecutive flagged frames.
    Flagged(u32),
    /// The detector count rate, hertz, above the limit.
    Rate(f64, f64),
}

impl Suspension {
    fn reason(&self) -> String {
        match self {
            Suspension::Interlock => "the interlock loop opened".into(),
            Suspension::EmissionLost => {
                "laser emission stopped although it was wanted (the controller's watchdog tripped or it was reset)".into()
            }
            Suspension::Flagged(n) => {
                format!("{n} consecutive histograms were flagged overflow or saturated")
            }
            Suspension::Rate(rate, max) => format!(
                "the detector count rate {:.3e} Hz is above the plan's limit {max:.3e} Hz (suspend.max-count-rate-hz): something bright in the path?",
                rate
            ),
        }
    }
}

/// How many times running one pair may be measured again because its sync read off
/// and then right ([`PairVerdict::Again`]) before the run fails.
const MAX_SYNC_AGAINS: u32 = 3;

/// What a sync reading says ([`Run::sync_verdict`]).
#[derive(Debug)]
enum SyncVerdict {
    /// As configured.
    Right,
    /// Off, then right after the rate meter's latency: what was measured under the
    /// first reading is measured again.
    Again,
    /// The laser stopped meanwhile: the suspenders' to handle.
    Laser(Suspension),
}

/// What a measured pair's histograms are worth ([`Run::capture_suspension`]).
#[derive(Debug)]
pub(crate) enum PairVerdict {
    /// Keep them.
    Keep,
    /// Measure the pair again at once (the sync read off while it was measured).
    Again,
    /// Suspend, then measure it again.
    Suspend(Suspension),
}

/// Counts consecutive flagged histograms.
#[derive(Default)]
pub(crate) struct FlagRun(u32);

impl FlagRun {
    pub(crate) fn record(&mut self, flags: HistogramFlags) -> u32 {
        self.0 = if flags.overflow || flags.saturated {
            self.0 + 1
        } else {
            0
        };
        self.0
    }
}

/// How long a run whose laser switch-on an emergency off refused waits for the stop
/// request that comes with it.
const STOP_REQUEST_WAIT: Duration = Duration::from_millis(100);

impl Run {
    /// One histogram, stopped (and aborted on the device) as soon as the run is asked
    /// to pause or abort.
    pub(crate) fn acquire(&mut self) -> Result<Histogram, PipelineError> {
        let control = self.control.clone();
        match self.devices.tdc.acquire_until(&|| control.stopping()) {
            Ok(h) => Ok(h),
            Err(e) if e.kind() == ErrorKind::Interrupted => {
                self.checkpoint()?;
                Err(e.into())
            }
            Err(e) => Err(e.into()),
        }
    }

    /// The panic hook switches every laser in the process off and latches its driver,
    /// whichever thread panicked (a fit's, an API handler's). A laser found off, or a
    /// switch-on refused, after such a panic is a bug's doing, not the controller's or
    /// an operator's: the run fails as the internal error it is, naming the panic,
    /// instead of waiting paused for a laser the latch keeps off.
    fn panicked_elsewhere(&self) -> Result<(), PipelineError> {
        match crate::signals::panicked_since(self.opened_at) {
            Some(p) => Err(PipelineError::Panicked {
                stage: self.stage.name(),
                message: format!("{p}; the panic hook switched the laser off"),
            }),
            None => Ok(()),
        }
    }

    /// Switches the laser on to measure. After an emergency off (the e-stop, a signal,
    /// a shutdown) the driver refuses for good, however the two raced: the run then
    /// stops as the stop asked (aborted or paused), or, if nothing asked, is held
    /// paused with the reason.
    pub(crate) fn laser_on(&mut self) -> Result<(), PipelineError> {
        let on = self.devices.laser.set_emission(true);
        self.report_laser();
        match on {
            Err(e) if e.kind() == ErrorKind::Interrupted => {
                // Every emergency off comes with a stop request (a signal's right after
                // the off): give it a moment to arrive, so the run ends as it asked.
                self.await_stop_request();
                self.checkpoint()?;
                self.panicked_elsewhere()?;
                Err(PipelineError::Suspended {
                    reason: e.to_string(),
                    pairs: self.info.pairs_done,
                })
            }
            r => r.map_err(Into::into),
        }?;
        self.sync.from = Some(Instant::now() + self.devices.tdc.rate_latency());
        if !self.sync.verified {
            self.sync.verified = self.verify_sync()?;
        }
        Ok(())
    }

    /// With the laser just switched on, until one such check has passed this session:
    /// waits out the counter's rate meter (answering a stop), then reads the sync rate
    /// and fails the run if it is none or not the configured one ([`Run::sync_verdict`]),
    /// before anything is measured. Whether it judged: an interlock that opened or
    /// emission that dropped while it waited is left to the suspenders at the first
    /// reading, and the next switch-on judges. Later switch-ons (after a suspension,
    /// between adaptive batches) do not wait: [`Run::capture_suspension`] checks every
    /// reading that shows the sync since.
    fn verify_sync(&mut self) -> Result<bool, PipelineError> {
        let until = self.sync.from.unwrap_or_else(Instant::now);
        self.wait_answering_stops(until.saturating_duration_since(Instant::now()))?;
        if self.laser_suspension()?.is_some() {
            return Ok(false);
        }
        let first = self.devices.tdc.status()?.rates.sync;
        Ok(!matches!(self.sync_verdict(first)?, SyncVerdict::Laser(_)))
    }

    /// The sync reading `first` (hertz) against the instrument config
    /// ([`crate::config::InstrumentConfig::sync_fault`]). A reading off is read again
    /// after the counter's rate-meter latency before it is believed (a counter reopened
    /// or reconfigured in between reads its old rate, or none, that long): off again,
    /// the run fails; right now, what was measured under the first is measured again.
    /// An interlock that opened or emission that dropped during the wait is handed to
    /// the suspenders instead.
    fn sync_verdict(&mut self, first: f64) -> Result<SyncVerdict, PipelineError> {
        let after = self.devices.tdc.sync_after_divider();
        if self.instrument.sync_fault(first, after).is_none() {
            return Ok(SyncVerdict::Right);
        }
        self.wait_answering_stops(self.devices.tdc.rate_latency())?;
        if let Some(s) = self.laser_suspension()? {
            return Ok(SyncVerdict::Laser(s));
        }
        let second = self.devices.tdc.status()?.rates.sync;
        match self.instrument.sync_fault(second, after) {
            Some(fault) => Err(PipelineError::Sync(fault)),
            None => {
                tracing::warn!(
                    first_hz = first,
                    then_hz = second,
                    "the counter's sync read off the config, then right after its rate meter's latency: a pair measured under the first reading is measured again"
                );
                Ok(SyncVerdict::Again)
            }
        }
    }

    /// Sleeps `d` in slices of [`SUSPENDED_POLL`], returning the pause or abort asked
    /// for in the meantime (each checkpoint feeds the laser's stall watchdog as well).
    fn wait_answering_stops(&self, d: Duration) -> Result<(), PipelineError> {
        let until = Instant::now() + d;
        loop {
            self.checkpoint()?;
            let left = until.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(());
            }
            std::thread::sleep(left.min(SUSPENDED_POLL));
        }
    }

    /// Waits (at most [`STOP_REQUEST_WAIT`]) for the stop request that comes with an
    /// emergency off.
    fn await_stop_request(&self) {
        let since = Instant::now();
        while !self.control.stopping() && since.elapsed() < STOP_REQUEST_WAIT {
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    /// Reads the laser's state and reports it to the live displays (errors are left
    /// to the next check that needs the state).
    pub(crate) fn report_laser(&mut self) {
        if let Ok(state) = self.devices.laser.laser_state() {
            self.emit_safety(state);
        }
    }

    fn emit_safety(&self, state: periscope_drivers::LaserState) {
        self.events.emit(RunEvent::Safety {
            emission: state.emission,
            interlock_closed: state.interlock_closed,
            diffuser_in: state.diffuser_in,
            unix_ms: crate::run_dir::unix_now() * 1e3,
        });
    }

    pub(crate) fn laser_suspension(&mut self) -> Result<Option<Suspension>, PipelineError> {
        let state = self.devices.laser.laser_state()?;
        self.emit_safety(state);
        Ok(if !state.interlock_closed {
            Some(Suspension::Interlock)
        } else if !state.emission {
            Some(Suspension::EmissionLost)
        } else {
            None
        })
    }

    /// After a pair's histograms: every suspender, in order of urgency.
    pub(crate) fn capture_suspension(
        &mut self,
        flags: HistogramFlags,
        flagged: &mut FlagRun,
    ) -> Result<PairVerdict, PipelineError> {
        if let Some(s) = self.laser_suspension()? {
            return Ok(PairVerdict::Suspend(s));
        }
        let rates = self.devices.tdc.status()?.rates;
        // The laser is on (checked above); once the rate meter shows the sync since
        // it went on, a sync that stops or changes fails the run.
        if self.sync.from.is_some_and(|t| Instant::now() >= t) {
            match self.sync_verdict(rates.sync)? {
                SyncVerdict::Right => self.sync.agains = 0,
                SyncVerdict::Again => {
                    // A sync or a counter link that keeps dropping out would have the
                    // pair measured again for ever.
                    self.sync.agains += 1;
                    if self.sync.agains >= MAX_SYNC_AGAINS {
                        return Err(PipelineError::Sync(format!(
                            "the counter's sync read off, then right after its rate meter's latency, {MAX_SYNC_AGAINS} times running on one pair: the laser's sync, or the counter's link to this host, keeps dropping out"
                        )));
                    }
                    return Ok(PairVerdict::Again);
                }
                SyncVerdict::Laser(s) => {
                    self.sync.agains = 0;
                    return Ok(PairVerdict::Suspend(s));
                }
            }
        }
        let n = flagged.record(flags);
        let limit = self.plan.suspend.flagged_frames;
        if limit > 0 && n >= limit {
            *flagged = FlagRun::default();
            return Ok(PairVerdict::Suspend(Suspension::Flagged(n)));
        }
        let rate = rates.detector;
        let max = self.plan.suspend.max_count_rate;
        if rate > max {
            return Ok(PairVerdict::Suspend(Suspension::Rate(rate, max)));
        }
        Ok(PairVerdict::Keep)
    }

    /// Switches the laser off and holds the run: with `resume = "operator"` the run
    /// stops as paused (error [`PipelineError::Suspended`]); with `"auto"` it waits,
    /// answering pause, abort and e-stop, until the condition has stayed clear for the
    /// plan's time, then switches the laser back on and returns.
    pub(crate) fn suspend(
        &mut self,
        s: Suspension,
        log: Option<&mut crate::store::HistogramLog>,
    ) -> Result<(), PipelineError> {
        self.devices.laser.set_emission(false)?;
        self.report_laser();
        // A suspension may last until someone closes the door: the records appended
        // since the last sync are made durable now, with the laser already off.
        if let Some(log) = log {
            log.sync().map_err(|e| PipelineError::storage(log.path(), e))?;
        }
        // Emission lost is what an emergency off looks like from here: the e-stop
        // asks the run to abort before it switches the laser off, a signal right
        // after. A stop asked for ends the run as it asked (aborted, not held paused).
        if matches!(s, Suspension::EmissionLost) {
            self.await_stop_request();
        }
        self.checkpoint()?;
        if matches!(s, Suspension::EmissionLost) {
            self.panicked_elsewhere()?;
        }
        let reason = s.reason();
        let mode = self.plan.suspend.resume;
        tracing::warn!(reason = %reason, "suspended: laser off");
        self.events.emit(RunEvent::Suspended {
            reason: reason.clone(),
            resume: match mode {
                SuspendResume::Operator => "operator".into(),
                SuspendResume::Auto { .. } => "auto".into(),
            },
        });
        let SuspendResume::Auto { mut clear_for } = mode else {
            return Err(PipelineError::Suspended {
                reason,
                pairs: self.info.pairs_done,
            });
        };
        if !matches!(s, Suspension::Interlock) {
            self.blind_resumes += 1;
            let n = self.blind_resumes;
            if n > MAX_BLIND_RESUMES {
                return Err(PipelineError::Suspended {
                    reason: format!(
                        "{reason}, {n} times running with no pair stored between: it does not clear, so the run waits for the operator (check the scene, or the plan's [suspend] limits)"
                    ),
                    pairs: self.info.pairs_done,
                });
            }
            if n >= 2 {
                clear_for = clear_for.max(BLIND_RESUME_BACKOFF * (1 << (n - 2)));
            }
        }
        let mut clear_since: Option<Instant> = None;
        loop {
            self.checkpoint()?;
            let clear = match s {
                Suspension::Interlock => self.devices.laser.interlock_closed()?,
                // Rate, flags and dropped emission can only be judged with the laser
                // on: wait the clear time out, then measure again.
                _ => true,
            };
            if clear {
                let since = *clear_since.get_or_insert_with(Instant::now);
                if since.elapsed() >= clear_for {
                    break;
                }
            } else {
                clear_since = None;
            }
            std::thread::sleep(SUSPENDED_POLL);
        }
        self.events.emit(RunEvent::SuspendCleared {
            reason: reason.clone(),
        });
        tracing::info!(reason = %reason, "suspension cleared: laser on again");
        self.laser_on()?;
        Ok(())
    }
}

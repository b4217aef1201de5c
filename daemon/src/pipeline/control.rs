//! What a running pipeline is asked to do and how it answers: the operator's pause and
//! abort read at every checkpoint, the run's sign of life for the laser's keepalive,
//! the record of how the run left the instrument, and (with the `test-hooks` feature)
//! injected faults.
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};

use periscope_recon::gtr::CancelToken;

use super::PipelineError;
use crate::events::Stage;

/// What a running pipeline is asked to do, read at its checkpoints.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Request {
    /// Carry on.
    Run,
    /// Pause (laser off, arms parked, data kept; resume continues).
    Pause,
    /// Abort (laser off, arms parked, data kept; the run ends).
    Abort,
}

#[derive(Default)]
struct ControlInner {
    state: AtomicU8,
    /// Cancel tokens of optimisers working for this run: a pause or an abort stops
    /// them at once instead of at their next event.
    cancels: Mutex<Vec<CancelToken>>,
    /// Testing aid: the stage in which the next checkpoint panics (stage index + 1).
    #[cfg(feature = "test-hooks")]
    panic_in: AtomicU8,
    /// Testing aid: the stage in which the next checkpoint hangs, and for how long.
    #[cfg(feature = "test-hooks")]
    hang_in: Mutex<Option<(Stage, std::time::Duration)>>,
    /// How the run's last attempt to make the instrument safe went (laser off, arms
    /// parked): `None` until it has tried, the first failure as text.
    made_safe: Mutex<Option<Result<(), String>>>,
    /// The run's sign of life for the laser's keepalive, beaten at every checkpoint
    /// and stop poll ([`Control::progress`]).
    progress: Mutex<Option<periscope_drivers::Progress>>,
    /// Who asked the run to pause or abort (a key's name, `estop`, `shutdown`), and
    /// whether the run has taken the request at a checkpoint: the run records it with
    /// the state it stops in.
    requested_by: Mutex<Requester>,
}

/// Who asked the run to stop, and whether the run has taken the request.
#[derive(Default)]
struct Requester {
    by: Option<String>,
    /// A checkpoint has turned the request into the run's stop ([`Control::check`]):
    /// from then on the run is winding down to the state it names, and a later
    /// request would be answered as taken when it is not.
    taken: bool,
}

/// Operator requests a running pipeline honours at its checkpoints: between devices
/// while opening, at every LOS point and pair, every 5 ms inside a dwell, between the
/// relay and planning steps, and at every optimiser step.
#[derive(Clone, Default)]
pub struct Control(Arc<ControlInner>);

impl Control {
    const RUN: u8 = 0;
    const PAUSE: u8 = 1;
    const ABORT: u8 = 2;

    /// A control that never interrupts.
    pub fn new() -> Control {
        Control::default()
    }
    /// How the run's last attempt to make the instrument safe went: `Some(Ok(()))`
    /// once it has switched the laser off and parked both arms, `Some(Err(why))` if a
    /// step failed, `None` if it has not tried (it never opened the devices). The
    /// e-stop believes a run only on `Some(Ok(()))`.
    pub fn made_safe(&self) -> Option<Result<(), String>> {
        self.0.made_safe.lock().unwrap_or_else(|p| p.into_inner()).clone()
    }
    pub(super) fn record_made_safe(&self, result: Result<(), String>) {
        *self.0.made_safe.lock().unwrap_or_else(|p| p.into_inner()) = Some(result);
    }
    /// Asks the run to pause at the next checkpoint ([`Control::pause_by`] with nobody
    /// named).
    pub fn pause(&self) {
        self.ask(Self::PAUSE, None);
    }
    /// Who asked the run to stop, if recorded.
    pub fn requested_by(&self) -> Option<String> {
        self.0
            .requested_by
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .by
            .clone()
    }

    /// Whether the run has taken a pause or abort at a checkpoint and is winding down
    /// to it (making the instrument safe, writing its state): [`Control::pause_by`] and
    /// [`Control::abort_by`] then change nothing, and a caller that must see its request
    /// through waits for the run to be handed back and acts on its stored state.
    pub fn stop_taken(&self) -> bool {
        self.0
            .requested_by
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .taken
    }

    /// [`Control::pause`] asked by `by` (a key's name, `estop`, `shutdown`, a signal's
    /// name), recorded only if this request is the one that pauses the run: a pause
    /// asked of a run already asked to pause or abort changes nothing, and so does not
    /// take the stop from whoever asked first. The request and its record change
    /// together (under the record's lock), so a pause and an abort asked at once from
    /// two threads leave the abort's requester with the abort. Returns whether it
    /// paused the run.
    pub fn pause_by(&self, by: &str) -> bool {
        self.ask(Self::PAUSE, Some(by))
    }

    /// Asks the run to abort at the next checkpoint ([`Control::abort_by`] with nobody
    /// named).
    pub fn abort(&self) {
        self.ask(Self::ABORT, None);
    }

    /// [`Control::abort`] asked by `by`, recorded unless the run was already asked to
    /// abort (an abort overrides a pause, and its requester the pause's) or has taken a
    /// pause at a checkpoint ([`Control::stop_taken`]: it stops paused, and the abort
    /// is the caller's to apply to the paused run). Returns whether this request
    /// changed what the run is asked to do.
    pub fn abort_by(&self, by: &str) -> bool {
        self.ask(Self::ABORT, Some(by))
    }

    /// Moves the request on to `to` (a pause only from running, an abort from anything
    /// short of an abort) unless the run has taken its stop, recording `by` with the
    /// change; the request and its record change together, under the record's lock.
    fn ask(&self, to: u8, by: Option<&str>) -> bool {
        let mut who = self.0.requested_by.lock().unwrap_or_else(|p| p.into_inner());
        let changed = !who.taken
            && match to {
                Self::PAUSE => self
                    .0
                    .state
                    .compare_exchange(Self::RUN, Self::PAUSE, Ordering::SeqCst, Ordering::SeqCst)
                    .is_ok(),
                _ => self.0.state.swap(Self::ABORT, Ordering::SeqCst) != Self::ABORT,
            };
        if changed {
            who.by = by.map(str::to_owned);
        }
        drop(who);
        self.cancel_optimisers();
        changed
    }
    /// What the run is asked to do.
    pub fn requested(&self) -> Request {
        match self.0.state.load(Ordering::SeqCst) {
            Self::RUN => Request::Run,
            Self::PAUSE => Request::Pause,
            _ => Request::Abort,
        }
    }
    /// Whether the run is asked to stop (pause or abort). Asking is a sign of life
    /// ([`Control::progress`]).
    pub fn stopping(&self) -> bool {
        self.beat();
        self.requested() != Request::Run
    }
    /// Whether the run is asked to stop, asked from a thread other than the run's own
    /// (the trainer's): no sign of life, so a capture that hangs with the laser on
    /// loses the keepalive after `[laser] stall-ms` however busy the trainer is.
    pub fn stop_requested(&self) -> bool {
        self.requested() != Request::Run
    }
    /// The run's sign of life for its laser's keepalive, alive for `limit` after each
    /// checkpoint or stop poll; a new one (just beaten) replaces the last.
    pub fn progress(&self, limit: std::time::Duration) -> periscope_drivers::Progress {
        let p = periscope_drivers::Progress::new(limit);
        *self.0.progress.lock().unwrap_or_else(|p| p.into_inner()) = Some(p.clone());
        p
    }
    fn beat(&self) {
        if let Some(p) = &*self.0.progress.lock().unwrap_or_else(|p| p.into_inner()) {
            p.beat();
        }
    }
    /// Registers an optimiser's cancel token; cancelled at once if already stopping.
    pub(crate) fn watch(&self, token: &CancelToken) {
        self.0
            .cancels
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .push(token.clone());
        if self.stop_requested() {
            token.cancel();
        }
    }
    fn cancel_optimisers(&self) {
        for t in self.0.cancels.lock().unwrap_or_else(|p| p.into_inner()).iter() {
            t.cancel();
        }
    }
    /// Testing aid (fault injection): the next checkpoint reached in `stage` panics,
    /// as a bug there would. The safety tests use it to show that a panic anywhere
    /// leaves the laser off and the run resumable. Built only with the `test-hooks`
    /// feature, which the release binary does not have.
    #[cfg(feature = "test-hooks")]
    pub fn inject_panic(&self, stage: Stage) {
        self.0.panic_in.store(stage as u8 + 1, Ordering::SeqCst);
    }
    /// Testing aid (fault injection): the next checkpoint reached in `stage` hangs for
    /// `duration`, deaf to pause, abort and e-stop, as a worker stuck in a call would.
    /// The safety tests use it to show that an e-stop does not need the worker.
    /// Built only with the `test-hooks` feature.
    #[cfg(feature = "test-hooks")]
    pub fn inject_hang(&self, stage: Stage, duration: std::time::Duration) {
        *self.0.hang_in.lock().unwrap_or_else(|p| p.into_inner()) = Some((stage, duration));
    }
    /// The faults injected for `stage`: a panic, or a hang deaf to every request.
    #[cfg(feature = "test-hooks")]
    fn injected_faults(&self, stage: Stage) {
        if self.0.panic_in.load(Ordering::SeqCst) == stage as u8 + 1 {
            self.0.panic_in.store(0, Ordering::SeqCst);
            panic!("injected panic in stage {}", stage.name());
        }
        let hang = {
            let mut h = self.0.hang_in.lock().unwrap_or_else(|p| p.into_inner());
            h.filter(|(s, _)| *s == stage).and_then(|_| h.take())
        };
        if let Some((_, duration)) = hang {
            std::thread::sleep(duration);
        }
    }
    /// Marks the run's stop taken when it stops for a reason of its own (a suspension,
    /// a device error, a panic), not at a checkpoint, and says what it is asked to do
    /// then: an abort asked before this is the run's to record, one asked after it
    /// is the caller's to apply to the stored run ([`Control::stop_taken`]).
    pub(crate) fn take_stop(&self) -> Request {
        let mut who = self.0.requested_by.lock().unwrap_or_else(|p| p.into_inner());
        who.taken = true;
        self.requested()
    }
    /// The error a checkpoint returns for the current request, if any.
    pub(crate) fn check(&self, stage: Stage, pairs: usize) -> Result<(), PipelineError> {
        #[cfg(feature = "test-hooks")]
        self.injected_faults(stage);
        // Only the injected faults depend on the stage.
        #[cfg(not(feature = "test-hooks"))]
        let _ = stage;
        self.beat();
        if self.requested() == Request::Run {
            return Ok(());
        }
        // Taken under the requester's lock, so no request slips between the state read
        // and the mark: the run stops as this says, recorded with this requester.
        let mut who = self.0.requested_by.lock().unwrap_or_else(|p| p.into_inner());
        who.taken = true;
        match self.requested() {
            Request::Run => Ok(()),
            Request::Pause => Err(PipelineError::Paused(pairs)),
            Request::Abort => Err(PipelineError::Aborted(pairs)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// The record names whoever stopped the run. Until 2026-12-07 every request
    /// overwrote it, taken or not: an abort followed by another key's pause (which the
    /// aborting run ignores) was recorded as that key's abort.
    #[test]
    fn the_requester_recorded_is_the_one_whose_request_was_taken() {
        let control = Control::new();
        assert!(control.abort_by("alice"));
        assert!(!control.pause_by("bob"));
        assert!(!control.abort_by("carol"));
        assert_eq!(control.requested(), Request::Abort);
        assert_eq!(control.requested_by().as_deref(), Some("alice"));

        // A pause's requester stays against a second pause; an abort takes over both.
        let control = Control::new();
        assert!(control.pause_by("alice"));
        assert!(!control.pause_by("shutdown"));
        assert_eq!(control.requested(), Request::Pause);
        assert_eq!(control.requested_by().as_deref(), Some("alice"));
        assert!(control.abort_by("estop"));
        assert_eq!(control.requested(), Request::Abort);
        assert_eq!(control.requested_by().as_deref(), Some("estop"));
    }

    /// Once a checkpoint has turned a pause into the run's stop, the run winds down
    /// paused whatever is asked after: a later abort changes nothing and says so (the
    /// service then waits for the paused run and aborts it as stored), and the record
    /// keeps the pause's requester. Until 2026-12-07 an abort in that window was
    /// accepted, recorded as the pause's author, and lost.
    #[test]
    fn a_request_after_the_run_has_taken_its_stop_changes_nothing() {
        let control = Control::new();
        assert!(control.check(Stage::Capture, 3).is_ok());
        assert!(!control.stop_taken());
        assert!(control.pause_by("alice"));
        assert!(matches!(
            control.check(Stage::Capture, 3),
            Err(PipelineError::Paused(3))
        ));
        assert!(control.stop_taken());
        assert!(!control.abort_by("bob"));
        control.abort();
        assert_eq!(control.requested(), Request::Pause);
        assert_eq!(control.requested_by().as_deref(), Some("alice"));
        // The checkpoint the fit's cancellation asks again says the same.
        assert!(matches!(
            control.check(Stage::Reconstruction, 3),
            Err(PipelineError::Paused(3))
        ));
    }

    /// A pause and an abort asked at once, from many threads: whatever the order, the
    /// run is asked to abort and the record is an abort's requester.
    #[test]
    fn a_pause_racing_an_abort_never_takes_the_aborts_record() {
        for _ in 0..200 {
            let control = Control::new();
            let barrier = std::sync::Arc::new(std::sync::Barrier::new(4));
            let threads: Vec<_> = ["pauser-1", "aborter-1", "pauser-2", "aborter-2"]
                .into_iter()
                .map(|who| {
                    let (control, barrier) = (control.clone(), barrier.clone());
                    std::thread::spawn(move || {
                        barrier.wait();
                        if who.starts_with("pauser") {
                            control.pause_by(who);
                        } else {
                            control.abort_by(who);
                        }
                    })
                })
                .collect();
            for t in threads {
                t.join().unwrap();
            }
            assert_eq!(control.requested(), Request::Abort);
            let by = control.requested_by().unwrap();
            assert!(by.starts_with("aborter"), "recorded {by} for an abort");
        }
    }

    /// The trainer asks whether to stop at every event of its fit, from its own
    /// thread: that is no sign of the run's life, so a capture that hangs with the
    /// laser on loses the keepalive after its stall limit however often the trainer
    /// asks. Until 2026-12-06 the trainer's asking beat the run's progress.
    #[test]
    fn another_threads_asking_is_no_sign_of_the_runs_life() {
        let control = Control::new();
        let progress = control.progress(Duration::from_millis(50));
        let asking = {
            let control = control.clone();
            std::thread::spawn(move || {
                for _ in 0..30 {
                    assert!(!control.stop_requested());
                    std::thread::sleep(Duration::from_millis(5));
                }
            })
        };
        asking.join().unwrap();
        assert!(!progress.alive(), "the trainer's asking kept the run alive");
        // The run's own poll is one.
        assert!(!control.stopping());
        assert!(progress.alive());
        control.pause();
        assert!(control.stop_requested());
    }
}

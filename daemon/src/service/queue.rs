//! The run queue: submitting and checking plans, listing runs, and the operator's
//! pause, resume and abort. The queue's order is persisted in `RUNS_DIR/queue.json`
//! after every change.
use super::*;

impl Service {
    pub(super) fn persist(&self, s: &Shared) -> Result<(), ServiceError> {
        let path = self.runs_dir.join(QUEUE_FILE);
        let ids: Vec<&String> = s.queue.iter().collect();
        write_atomic(
            &path,
            serde_json::to_string_pretty(&ids).expect("serialises").as_bytes(),
        )
        .map_err(ServiceError::storage(&path))
    }

    /// Writes queue.json after a request has already changed the queue and a run's
    /// run.json: a failure is logged, not returned, because the change has been made
    /// and holds (a client told "failed" would submit again and queue a duplicate).
    /// The next start rebuilds what queue.json missed from the runs' own run.json
    /// (queued and running runs missing from it are queued again).
    pub(super) fn persist_after_change(&self, s: &Shared) {
        if let Err(e) = self.persist(s) {
            tracing::error!(
                "{e}: the queue in memory is right, and the next start queues again the runs queue.json misses"
            );
        }
    }

    pub(super) fn dir(&self, id: &str) -> Result<PathBuf, ServiceError> {
        let valid = !id.is_empty()
            && id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
        let dir = self.runs_dir.join(id);
        if valid && RunDir::holds_run(&dir) {
            Ok(dir)
        } else {
            Err(ServiceError::UnknownRun(id.to_owned()))
        }
    }

    pub(super) fn info(&self, id: &str) -> Result<RunInfo, ServiceError> {
        let dir = self.dir(id)?;
        RunInfo::load(&dir).map_err(ServiceError::storage(dir.join(file::RUN)))
    }

    pub(super) fn set_state(
        &self,
        id: &str,
        state: RunState,
        error: Option<String>,
        by: &str,
    ) -> Result<(), ServiceError> {
        let dir = self.dir(id)?;
        let mut info = self.info(id)?;
        info.state = state;
        info.acting = Some(by.to_owned());
        if error.is_some() {
            info.error = error;
        }
        info.save(&dir)
            .map_err(ServiceError::storage(dir.join(file::RUN)))?;
        self.touch(id);
        Ok(())
    }

    /// Holds a place in the queue for a run about to be made (released by decrementing
    /// `admitting` once it is queued or refused): 429 when the queue is full. Returns
    /// the e-stops' count as it is now, for [`Service::queue_admitted`].
    pub(super) fn reserve_place(&self) -> Result<u64, ServiceError> {
        let mut s = self.lock();
        let max = self.instrument.api.max_queue;
        if s.queue.len() + s.admitting >= max {
            return Err(ServiceError::QueueFull(format!(
                "the queue holds {max} runs, the most this daemon keeps ([api] max-queue); \
                 wait for runs to finish or abort queued ones"
            )));
        }
        s.admitting += 1;
        Ok(s.estop_holds)
    }

    /// Queues run `id`, admitted since its place was reserved when the e-stops' count
    /// was `seen`. An e-stop in between held every queued run, and would have held
    /// this one, already `queued` on disk, had it been in the queue: it is held now,
    /// as the e-stop would have held it, so no capture starts after an e-stop until an
    /// operator resumes it (until 2026-12-07 a submission in flight started right
    /// after one). Returns whether it was held.
    pub(super) fn queue_admitted(&self, s: &mut Shared, id: &str, seen: u64) -> bool {
        s.queue.push_back(id.to_owned());
        // An e-stop still under way (waiting for its run, parking the arms) holds
        // what reaches the queue meanwhile, too.
        if s.estop_holds == seen && self.estops.load(std::sync::atomic::Ordering::SeqCst) == 0 {
            return false;
        }
        s.held.insert(id.to_owned());
        if let Err(e) = self.set_state(
            id,
            RunState::Paused,
            Some("held by an emergency stop pressed while it was submitted; resume it to run".into()),
            "estop",
        ) {
            tracing::warn!(run = %id, error = %e, "a run submitted during an e-stop is held (the worker will not start it), but its run.json could not record it");
        }
        true
    }

    /// Validates a plan (TOML text) and queues it. Returns the new run's status.
    /// In-process callers (tests, benches) submit as `local`.
    pub fn submit(&self, text: String) -> Result<RunStatus, ServiceError> {
        self.submit_as(text, "local", None)
    }

    /// Validates a plan and queues it as submitted by `by` (an API key's name),
    /// recording the run it repeats, if any.
    pub fn submit_as(
        &self,
        text: String,
        by: &str,
        again_of: Option<&str>,
    ) -> Result<RunStatus, ServiceError> {
        let src = TomlSource::from_text("request body", text);
        let plan = Plan::from_source(&src, &self.instrument).map_err(ServiceError::InvalidPlan)?;
        crate::budget::Budget::of_plan(&plan, &self.instrument)
            .check(&self.instrument.budget)
            .map_err(|over| ServiceError::OverBudget(over.message))?;
        // A place in the queue is reserved before the run directory is made, so a
        // flood of submissions never makes more directories than the queue takes.
        let seen = self.reserve_place()?;
        let admitted = self.admit(&src, &plan, by, again_of);
        let mut s = self.lock();
        s.admitting -= 1;
        let id = admitted?;
        self.queue_admitted(&mut s, &id, seen);
        self.persist_after_change(&s);
        self.wake.notify_all();
        drop(s);
        tracing::info!(run = %id, plan = %plan.name, by, "run queued");
        self.index_now(&id);
        self.status(&id)
    }

    /// Makes a submitted plan's run directory; returns its id.
    pub(super) fn admit(
        &self,
        src: &TomlSource,
        plan: &Plan,
        by: &str,
        again_of: Option<&str>,
    ) -> Result<String, ServiceError> {
        let dir = crate::run_dir::new_run_dir(&self.runs_dir, &plan.name)
            .map_err(ServiceError::storage(&self.runs_dir))?;
        let src = TomlSource::from_text(dir.join(file::PLAN), src.text().to_owned());
        pipeline::prepare(&src, &self.instrument_src, Some(&dir), by).map_err(|e| match e {
            PipelineError::Config(c) => ServiceError::InvalidPlan(c),
            other => ServiceError::Prepare(other),
        })?;
        if let Some(of) = again_of {
            let mut info = RunInfo::load(&dir).map_err(ServiceError::storage(dir.join(file::RUN)))?;
            info.again_of = Some(of.to_owned());
            info.save(&dir)
                .map_err(ServiceError::storage(dir.join(file::RUN)))?;
        }
        Ok(dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default())
    }

    /// Every run in the runs directory, oldest first (read from the directories, not
    /// the catalogue: the reference the catalogue is checked against).
    pub fn list(&self) -> Result<Vec<RunStatus>, ServiceError> {
        let mut ids: Vec<String> = std::fs::read_dir(&self.runs_dir)
            .map_err(ServiceError::storage(&self.runs_dir))?
            .filter_map(Result::ok)
            .filter(|e| RunDir::holds_run(&e.path()))
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        ids.sort();
        Ok(ids.iter().filter_map(|id| self.status(id).ok()).collect())
    }

    /// One run's status: its run.json, live progress if it is running, its queue place.
    pub fn status(&self, id: &str) -> Result<RunStatus, ServiceError> {
        let dir = self.dir(id)?;
        let info = self.info(id)?;
        let s = self.lock();
        let mut st = RunStatus {
            id: info.id.clone(),
            plan: info.plan.clone(),
            state: info.state,
            stage: info.stage.clone(),
            pairs_total: info.pairs_total,
            pairs_done: info.pairs_done,
            progress: 0.0,
            eta_s: None,
            queue_position: None,
            loss: None,
            error: info.error.clone(),
            timings: info.timings.clone(),
            files: Vec::new(),
            imported: info.import.as_ref().map(|i| i.capture.clone()),
        };
        if s.current.as_ref().is_some_and(|(c, _)| c == id) && s.live.id == id {
            let live = &s.live;
            st.stage = live.stage.clone();
            st.pairs_done = live.pairs_done.max(st.pairs_done);
            st.pairs_total = live.pairs_total.max(st.pairs_total);
            st.loss = live.loss;
            if let Some((t0, done0)) = live.capture_started {
                let rate =
                    (live.pairs_done.saturating_sub(done0)) as f64 / t0.elapsed().as_secs_f64().max(1e-3);
                if rate > 0.0 && live.stage == "capture" {
                    st.eta_s = Some(live.pairs_total.saturating_sub(live.pairs_done) as f64 / rate);
                }
            }
        }
        // Run files are read with the lock released: the worker and the capture's
        // events take it too.
        let queue: Vec<String> = if st.state == RunState::Queued {
            s.queue.iter().cloned().collect()
        } else {
            Vec::new()
        };
        drop(s);
        if st.state == RunState::Queued {
            st.queue_position = queue
                .iter()
                .filter(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                .position(|q| q == id);
        }
        if st.pairs_total > 0 {
            st.progress = (st.pairs_done as f64 / st.pairs_total as f64).min(1.0);
        }
        if st.state == RunState::Completed {
            st.progress = 1.0;
            // The fit's final loss, from the outputs (method gtr).
            st.loss = crate::store::read_text_capped(&dir.join(file::VOLUME_JSON), 1 << 20)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .and_then(|v| v.get("final_loss").and_then(serde_json::Value::as_f64));
        }
        st.files = crate::run_dir::DOWNLOADS
            .iter()
            .filter(|(name, _)| dir.join(name).is_file())
            .map(|(name, _)| (*name).to_owned())
            .collect();
        Ok(st)
    }

    /// Asks the running run to pause at its next checkpoint.
    pub fn pause(&self, id: &str) -> Result<RunStatus, ServiceError> {
        self.pause_as(id, "local")
    }

    /// [`Service::pause`] by `by` (recorded in the run's state history when it stops).
    pub fn pause_as(&self, id: &str, by: &str) -> Result<RunStatus, ServiceError> {
        {
            let s = self.lock();
            let info = self.info(id)?;
            match &s.current {
                Some((c, control)) if c == id => {
                    control.pause_by(by);
                }
                _ => {
                    return Err(ServiceError::Conflict(format!(
                        "run {id} is {}, not running: only a running run can be paused",
                        state_name(info.state)
                    )));
                }
            }
        }
        self.status(id)
    }

    /// Queues a paused, failed or interrupted run again; it continues from its last
    /// stored pair when the instrument is free.
    pub fn resume(&self, id: &str) -> Result<RunStatus, ServiceError> {
        self.resume_as(id, "local")
    }

    /// [`Service::resume`] by `by` (recorded in the run's state history).
    pub fn resume_as(&self, id: &str, by: &str) -> Result<RunStatus, ServiceError> {
        // run.json is read under the lock: the worker and other requests change it
        // under the same lock, so the state checked is the state changed.
        let s = self.lock();
        let mut s = self.await_hand_back(s, id);
        let info = self.info(id)?;
        if s.current.as_ref().is_some_and(|(c, _)| c == id) {
            return Err(ServiceError::Conflict(format!(
                "run {id} is running; there is nothing to resume"
            )));
        }
        // A run an e-stop held whose run.json could not record the hold reads queued.
        let held = s.held.contains(id);
        let stale = s.stale.contains(id);
        match info.state {
            RunState::Paused | RunState::Failed => {}
            RunState::Queued if held || stale => {}
            RunState::Running if stale => {}
            other => {
                return Err(ServiceError::Conflict(format!(
                    "run {id} is {}: only a paused or failed run can be resumed",
                    state_name(other)
                )));
            }
        }
        // The marks go only once the new state is written: a resume refused by the
        // disk leaves a held run held (it started by itself once writes came back,
        // until 2026-12-06) and a stale one resumable.
        self.set_state(id, RunState::Queued, None, by)?;
        s.held.remove(id);
        s.stale.remove(id);
        if !s.queue.iter().any(|q| q == id) {
            s.queue.push_back(id.to_owned());
        }
        self.persist_after_change(&s);
        self.wake.notify_all();
        drop(s);
        self.status(id)
    }

    /// Waits (at most [`HAND_BACK_WAIT`]) while run `id` is still the worker's current
    /// run but has already written a final or paused state: the pipeline records its
    /// state on its way out, before the worker takes the lock to let the run go. A
    /// request in that gap saw the run `paused` in its status yet was refused as
    /// running (resume), or was sent to a pipeline that had already stopped and lost
    /// (abort). It waits, too, for a run that has taken a stop at its checkpoint and is
    /// still `running` while it makes the instrument safe ([`Control::stop_taken`]): a
    /// request then would reach a pipeline that no longer listens.
    pub(super) fn await_hand_back<'a>(
        &'a self,
        mut s: MutexGuard<'a, Shared>,
        id: &str,
    ) -> MutexGuard<'a, Shared> {
        let deadline = Instant::now() + HAND_BACK_WAIT;
        while s
            .current
            .as_ref()
            .is_some_and(|(c, control)| c == id && (stopping_short_of_abort(control) || self.has_stopped(id)))
            && Instant::now() < deadline
        {
            s = self
                .wake
                .wait_timeout(s, Duration::from_millis(5))
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
        s
    }

    /// Aborts a run: a running one at its next checkpoint (the instrument is made safe
    /// and what was captured is kept), a queued or paused one at once.
    pub fn abort(&self, id: &str) -> Result<RunStatus, ServiceError> {
        self.abort_as(id, "local")
    }

    /// [`Service::abort`] by `by` (recorded in the run's state history when the abort
    /// is immediate; a running run records its own end).
    pub fn abort_as(&self, id: &str, by: &str) -> Result<RunStatus, ServiceError> {
        let s = self.lock();
        // A run that has already stopped at a checkpoint would not see the request.
        let mut s = self.await_hand_back(s, id);
        let info = self.info(id)?;
        if let Some((c, control)) = &s.current
            && c == id
        {
            // Refused only by a run that took a pause at its checkpoint and has not
            // been handed back within the wait: answered as a conflict, not as an
            // abort under way that never happens (until 2026-12-07 it was accepted,
            // and the run stopped paused).
            if !control.abort_by(by) && stopping_short_of_abort(control) {
                return Err(ServiceError::Conflict(format!(
                    "run {id} is stopping (it is making the instrument safe and writing its state): abort it again once it has stopped"
                )));
            }
            drop(s);
            return self.status(id);
        }
        let stale = s.stale.contains(id);
        match info.state {
            RunState::Queued | RunState::Paused | RunState::Failed => {}
            RunState::Running if stale => {}
            other => {
                return Err(ServiceError::Conflict(format!(
                    "run {id} is {}; there is nothing to abort",
                    state_name(other)
                )));
            }
        }
        self.set_state(
            id,
            RunState::Aborted,
            Some("aborted by the operator before it ran again".into()),
            by,
        )?;
        s.held.remove(id);
        s.stale.remove(id);
        s.queue.retain(|q| q != id);
        // Its event stream (clients waiting for it to start) ends here.
        s.channels.remove(id);
        self.persist_after_change(&s);
        drop(s);
        self.status(id)
    }

    /// What `periscope check` says about a plan (TOML text), as JSON-ready data; an
    /// invalid plan is refused with the same message `submit` would give.
    pub fn check(&self, text: String) -> Result<crate::check::Check, ServiceError> {
        let src = TomlSource::from_text("request body", text);
        let plan = Plan::from_source(&src, &self.instrument).map_err(ServiceError::InvalidPlan)?;
        Ok(crate::check::check(&plan, &self.instrument))
    }
}

/// A run found `running` when the daemon starts was interrupted by its stop: it is
/// held as paused (its data is intact) until an operator resumes it.
pub(super) fn hold_interrupted(dir: &Path, id: &str, info: &mut RunInfo) -> Result<(), ServiceError> {
    info.state = RunState::Paused;
    info.error = Some(format!(
        "interrupted: the daemon stopped during stage {}; POST /api/v1/runs/{id}/resume continues it",
        info.stage
    ));
    info.save(dir).map_err(ServiceError::storage(dir.join(file::RUN)))
}

/// Whether the run has taken a stop other than an abort (a pause at its checkpoint, a
/// suspension, a failure) and is winding down to it: an abort is then applied to the
/// run as stored, once it is handed back (a taken abort needs nobody's wait: it ends
/// aborted whatever is asked).
fn stopping_short_of_abort(control: &Control) -> bool {
    control.stop_taken() && control.requested() != crate::pipeline::Request::Abort
}

impl Service {
    /// Whether run `id`'s stored state is no longer `running` or `queued`.
    fn has_stopped(&self, id: &str) -> bool {
        self.info(id)
            .is_ok_and(|i| !matches!(i.state, RunState::Running | RunState::Queued))
    }
}

/// How long a resume or abort waits for a run that has stopped at its checkpoint to be
/// handed back by the worker ([`Service::await_hand_back`]).
pub(super) const HAND_BACK_WAIT: Duration = Duration::from_secs(5);

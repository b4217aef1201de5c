//! Queue operations beyond submit/pause/resume/abort (reorder, move, batch submit,
//! run again, the maintenance lock), annotations, and the service's side of the run
//! catalogue and the audit trail: the indexer thread that keeps the catalogue in step
//! with the run directories without ever making the worker wait on SQLite.
use super::*;
use crate::catalogue::{AuditEntry, Catalogue, RunPage, RunQuery};
use crate::run_dir::Annotations;

/// Why an annotation edit failed: the request's values, or the file.
enum AnnotateError {
    Invalid(String),
    Io(std::io::Error),
}

impl From<std::io::Error> for AnnotateError {
    fn from(e: std::io::Error) -> AnnotateError {
        AnnotateError::Io(e)
    }
}

/// The lock file in the runs directory (present while the queue is locked).
pub const LOCK_FILE: &str = "queue-lock.json";

/// The queue's maintenance lock (Bluesky's lock, for the queue): while it is held no
/// queued run starts, and requests that change the queue are refused unless they carry
/// the lock key. A running run finishes.
#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize, ToSchema)]
pub struct QueueLock {
    /// Who locked it.
    pub by: String,
    /// Why.
    pub reason: String,
    /// Since when (Unix seconds).
    pub since_unix_s: f64,
    /// SHA-256 of the lock key (the key itself is never stored).
    #[serde(skip_serializing_if = "String::is_empty", default)]
    #[schema(ignore)]
    pub key_sha256: String,
}

/// The queue as `GET /api/v1/queue` shows it.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct QueueView {
    /// The running run, if any.
    pub running: Option<String>,
    /// Queued and paused runs in the queue, in order (queued ones start in this order).
    pub order: Vec<String>,
    /// The maintenance lock, if held (its key's digest left out).
    pub lock: Option<QueueLock>,
}

impl Service {
    /// Starts the indexer thread: it syncs the catalogue with the run directories,
    /// then re-reads each run it is told of. The worker and the API only queue run
    /// ids for it, so neither waits on SQLite.
    pub(super) fn start_indexer(self: &Arc<Self>) {
        let (tx, rx) = std::sync::mpsc::channel::<String>();
        *self.indexer.lock().unwrap_or_else(|p| p.into_inner()) = Some(tx);
        let cat = Arc::clone(&self.catalogue);
        let spawned = std::thread::Builder::new()
            .name("catalogue".into())
            .spawn(move || {
                match cat.sync() {
                    Ok(r) => tracing::info!(
                        runs = r.runs,
                        indexed = r.indexed,
                        removed = r.removed,
                        "run catalogue in step with the run directories"
                    ),
                    Err(e) => tracing::error!("{e}; the catalogue may miss runs until the next start"),
                }
                while let Ok(first) = rx.recv() {
                    // Requests that arrived meanwhile are taken together, each run once.
                    let mut ids = std::collections::BTreeSet::from([first]);
                    ids.extend(rx.try_iter());
                    for id in ids {
                        if let Err(e) = cat.index(&id) {
                            tracing::warn!(run = %id, "run catalogue: {e}");
                        }
                    }
                }
            });
        if let Err(e) = spawned {
            tracing::error!("no thread for the run catalogue ({e}); it is synced at the next start");
        }
    }

    /// Asks the indexer to read run `id` again (never blocks).
    pub(super) fn touch(&self, id: &str) {
        if let Some(tx) = &*self.indexer.lock().unwrap_or_else(|p| p.into_inner()) {
            let _ = tx.send(id.to_owned());
        }
    }

    /// Indexes run `id` now, on the caller's thread (API requests, after a change the
    /// caller will read back).
    pub(super) fn index_now(&self, id: &str) {
        if let Err(e) = self.catalogue.index(id) {
            tracing::warn!(run = %id, "run catalogue: {e}");
        }
    }

    /// The run catalogue.
    pub fn catalogue(&self) -> &Catalogue {
        &self.catalogue
    }

    /// The API keys.
    pub fn keys(&self) -> &crate::access::KeyStore {
        &self.keys
    }

    /// The metrics.
    pub fn metrics(&self) -> &crate::metrics::Metrics {
        &self.metrics
    }

    /// The metrics as Prometheus text, with the gauges read off the service's state
    /// now.
    pub fn metrics_text(&self) -> String {
        let mut snap = crate::metrics::Snapshot {
            status_interval_s: self.instrument.api.status_interval.as_secs_f64(),
            ..Default::default()
        };
        {
            let s = self.lock();
            if let Some(r) = &s.reading {
                snap.reading_age_s = Some(r.at.elapsed().as_secs_f64());
                if let Ok(d) = &r.devices {
                    let flag = |p: &str| d.pointer(p).and_then(serde_json::Value::as_bool);
                    snap.emission = flag("/laser/emission");
                    snap.interlock_closed = flag("/laser/interlock_closed");
                    snap.diffuser_in = flag("/laser/diffuser_in");
                    let rate = |p: &str| d.pointer(p).and_then(serde_json::Value::as_f64);
                    snap.rates = rate("/tdc_status/rates/sync").zip(rate("/tdc_status/rates/detector"));
                }
            }
            // A run holds the devices and reads the laser at every pair: while it
            // runs, its reading is the current one, not the worker's from before it.
            // (An imported capture's run holds no device: the worker's reading stands.)
            let running = s.current.as_ref().is_some_and(|(c, _)| *c == s.live.id);
            if running && !s.live.import {
                let live = s.live.laser.as_ref();
                snap.emission = live.map(|l| l.0.emission);
                snap.interlock_closed = live.map(|l| l.0.interlock_closed);
                snap.diffuser_in = live.map(|l| l.0.diffuser_in);
                if let Some(l) = live {
                    snap.reading_age_s = Some(l.1.elapsed().as_secs_f64());
                }
                // The worker's count rates are from before the run: not shown beside
                // a fresh age (the run's own rate is the capture's counts rate).
                snap.rates = None;
            }
            // As `GET /instrument` says: an imported capture's run holds no device, and
            // the worker goes on reading them (so the stale-reading alert, which a
            // busy instrument silences, keeps watching).
            snap.busy = s.current.is_some() && !s.live.import;
            if s.current.is_some()
                && s.live.stage == "capture"
                && let Some((t0, done0)) = s.live.capture_started
            {
                let dt = t0.elapsed().as_secs_f64().max(1e-3);
                snap.pair_rate = s.live.pairs_done.saturating_sub(done0) as f64 / dt;
                snap.capture_counts_rate = s.live.counts as f64 / dt;
            }
            snap.queue_length = s
                .queue
                .iter()
                .filter(|q| s.current.as_ref().is_none_or(|(c, _)| c != *q))
                .count();
            snap.queue_locked = s.lock.is_some();
        }
        match self.catalogue.state_counts() {
            Ok(runs) => snap.runs = runs,
            Err(e) => tracing::warn!("metrics: runs per state: {e}"),
        }
        self.metrics.encode(&snap)
    }

    /// Records an audit entry; a failure to record is logged, never returned (the
    /// action it records has happened).
    pub fn audit(&self, entry: AuditEntry) {
        if let Err(e) = self.catalogue.record(&entry) {
            tracing::error!(action = %entry.action, actor = %entry.actor, "audit trail: {e}");
        }
    }

    /// A page of runs from the catalogue, with live progress for the running run and
    /// queue places for queued ones.
    pub fn query(&self, q: &RunQuery) -> Result<(RunPage, Vec<RunStatus>), ServiceError> {
        let page = self.catalogue.query(q).map_err(ServiceError::Catalogue)?;
        let statuses = page
            .runs
            .iter()
            .map(|r| {
                let mut st = RunStatus {
                    id: r.id.clone(),
                    plan: r.plan.clone(),
                    state: r.state,
                    stage: r.stage.clone(),
                    pairs_total: r.pairs_total as usize,
                    pairs_done: r.pairs_done as usize,
                    progress: 0.0,
                    eta_s: None,
                    queue_position: None,
                    loss: r.final_loss,
                    error: r.error.clone(),
                    timings: r.timings.clone(),
                    files: r.outputs.iter().map(|o| o.name.clone()).collect(),
                    imported: r.imported.clone(),
                };
                if st.pairs_total > 0 {
                    st.progress = (st.pairs_done as f64 / st.pairs_total as f64).min(1.0);
                }
                if st.state == RunState::Completed {
                    st.progress = 1.0;
                }
                st
            })
            .collect::<Vec<_>>();
        // Runs that are queued or running: their live state beats the catalogue's.
        let statuses = statuses
            .into_iter()
            .map(|st| {
                if matches!(st.state, RunState::Queued | RunState::Running) {
                    self.status(&st.id).unwrap_or(st)
                } else {
                    st
                }
            })
            .collect();
        Ok((page, statuses))
    }

    /// Sets run `id`'s tags and note.
    pub fn annotate(
        &self,
        id: &str,
        add: &[String],
        remove: &[String],
        note: Option<&str>,
    ) -> Result<Annotations, ServiceError> {
        let dir = self.dir(id)?;
        // Under the annotations' file lock, which the CLI takes too: two edits never
        // lose one another's tags.
        let path = dir.join(file::ANNOTATIONS);
        let a = Annotations::update(&dir, |a| {
            a.edit(add, remove, note).map_err(AnnotateError::Invalid)
        })
        .map_err(|e| match e {
            AnnotateError::Invalid(m) => ServiceError::Invalid(m),
            AnnotateError::Io(source) => ServiceError::Storage { path, source },
        })?;
        self.index_now(id);
        Ok(a)
    }

    /// The queue: the running run, the order, the lock.
    pub fn queue(&self) -> QueueView {
        let s = self.lock();
        QueueView {
            running: s.current.as_ref().map(|(id, _)| id.clone()),
            order: s
                .queue
                .iter()
                .filter(|q| s.current.as_ref().is_none_or(|(c, _)| c != *q))
                .cloned()
                .collect(),
            lock: s.lock.clone().map(|mut l| {
                l.key_sha256.clear();
                l
            }),
        }
    }

    /// Refuses a change to the queue while it is locked, unless `key` is the lock's.
    pub fn check_lock(&self, key: Option<&str>) -> Result<(), ServiceError> {
        let s = self.lock();
        match &s.lock {
            Some(l) if key.is_none_or(|k| crate::access::digest(k) != l.key_sha256) => {
                Err(ServiceError::Locked(format!(
                    "the queue is locked for maintenance by {} since {}: {}; wait for the unlock, or send the lock key in X-Periscope-Lock-Key",
                    l.by,
                    crate::access::format_time(l.since_unix_s),
                    l.reason
                )))
            }
            _ => Ok(()),
        }
    }

    /// Locks the queue for maintenance with `key` (needed to unlock it and to change
    /// the queue meanwhile).
    pub fn lock_queue(&self, by: &str, reason: &str, key: &str) -> Result<QueueView, ServiceError> {
        // The key travels in a header (`X-Periscope-Lock-Key`), where only visible
        // ASCII arrives as sent.
        if key.len() < 8 || !key.bytes().all(|b| b.is_ascii_graphic()) {
            return Err(ServiceError::Invalid(
                "the lock key must have at least 8 characters, each a visible ASCII one (letters, digits, punctuation; no spaces): it is sent in the X-Periscope-Lock-Key header"
                    .into(),
            ));
        }
        {
            let mut s = self.lock();
            if let Some(l) = &s.lock {
                return Err(ServiceError::Conflict(format!(
                    "the queue is already locked by {} ({})",
                    l.by, l.reason
                )));
            }
            let lock = QueueLock {
                by: by.to_owned(),
                reason: reason.to_owned(),
                since_unix_s: crate::run_dir::unix_now(),
                key_sha256: crate::access::digest(key),
            };
            let path = self.runs_dir.join(LOCK_FILE);
            write_atomic(
                &path,
                serde_json::to_string_pretty(&lock)
                    .expect("serialises")
                    .as_bytes(),
            )
            .map_err(ServiceError::storage(&path))?;
            s.lock = Some(lock);
        }
        Ok(self.queue())
    }

    /// Unlocks the queue: with its key, or `force`d (by an admin who lost it).
    pub fn unlock_queue(&self, key: Option<&str>, force: bool) -> Result<QueueView, ServiceError> {
        {
            let mut s = self.lock();
            let Some(l) = &s.lock else {
                return Err(ServiceError::Conflict("the queue is not locked".into()));
            };
            if !force && key.is_none_or(|k| crate::access::digest(k) != l.key_sha256) {
                return Err(ServiceError::Locked(
                    "the lock key is missing or wrong; give the key the queue was locked with, or force the unlock".into(),
                ));
            }
            let path = self.runs_dir.join(LOCK_FILE);
            match std::fs::remove_file(&path) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(ServiceError::storage(&path)(e)),
            }
            s.lock = None;
            self.wake.notify_all();
        }
        Ok(self.queue())
    }

    /// Puts the queue's waiting runs in `order`, which must name each of them once.
    pub fn reorder(&self, order: &[String]) -> Result<QueueView, ServiceError> {
        self.reorder_in(&mut self.lock(), order)?;
        Ok(self.queue())
    }

    /// [`Service::reorder`] under the lock the caller holds.
    fn reorder_in(&self, s: &mut Shared, order: &[String]) -> Result<(), ServiceError> {
        let running = s.current.as_ref().map(|(id, _)| id.clone());
        let waiting: Vec<String> = s
            .queue
            .iter()
            .filter(|q| Some(*q) != running.as_ref())
            .cloned()
            .collect();
        let mut a = waiting.clone();
        let mut b = order.to_vec();
        a.sort();
        b.sort();
        if a != b {
            return Err(ServiceError::Invalid(format!(
                "the order must name each waiting run once: {}",
                waiting.join(", ")
            )));
        }
        s.queue = running.into_iter().chain(order.iter().cloned()).collect();
        self.persist_after_change(s);
        self.wake.notify_all();
        Ok(())
    }

    /// Moves waiting run `id` to `position` (0 = next) among the waiting runs. The
    /// queue is read and reordered under one lock: a run starting or a submission in
    /// between made the move fail with "the order must name each waiting run once".
    pub fn move_run(&self, id: &str, position: usize) -> Result<QueueView, ServiceError> {
        {
            let mut s = self.lock();
            let mut order: Vec<String> = s
                .queue
                .iter()
                .filter(|q| s.current.as_ref().is_none_or(|(c, _)| c != *q))
                .cloned()
                .collect();
            let Some(at) = order.iter().position(|q| q == id) else {
                return Err(ServiceError::Conflict(format!(
                    "run {id} is not waiting in the queue; only queued or paused runs there can be moved"
                )));
            };
            let run = order.remove(at);
            order.insert(position.min(order.len()), run);
            self.reorder_in(&mut s, &order)?;
        }
        Ok(self.queue())
    }

    /// Validates every plan, then queues them all in order; one invalid plan refuses
    /// the whole batch (its place in the batch named) and queues none.
    pub fn submit_batch(&self, texts: Vec<String>, by: &str) -> Result<Vec<RunStatus>, ServiceError> {
        if texts.is_empty() {
            return Err(ServiceError::Invalid("the batch holds no plans".into()));
        }
        let mut plans = Vec::with_capacity(texts.len());
        for (i, text) in texts.iter().enumerate() {
            let src = TomlSource::from_text(format!("batch plan {}", i + 1), text.clone());
            let plan = Plan::from_source(&src, &self.instrument).map_err(ServiceError::InvalidPlan)?;
            crate::budget::Budget::of_plan(&plan, &self.instrument)
                .check(&self.instrument.budget)
                .map_err(|m| ServiceError::OverBudget(format!("batch plan {}: {m}", i + 1)))?;
            plans.push((src, plan));
        }
        // The whole batch's places are reserved at once, so no submission in between
        // can make it fail half-way for want of room.
        let seen = {
            let mut s = self.lock();
            let max = self.instrument.api.max_queue;
            if s.queue.len() + s.admitting + plans.len() > max {
                return Err(ServiceError::QueueFull(format!(
                    "the batch of {} does not fit: the queue holds {} of at most {max} runs ([api] max-queue)",
                    plans.len(),
                    s.queue.len()
                )));
            }
            s.admitting += plans.len();
            s.estop_holds
        };
        let mut ids = Vec::with_capacity(plans.len());
        let mut failed = None;
        for (src, plan) in &plans {
            let admitted = if failed.is_none() {
                self.admit(src, plan, by, None)
            } else {
                Err(ServiceError::Invalid(String::new()))
            };
            let mut s = self.lock();
            s.admitting -= 1;
            match admitted {
                Ok(id) => {
                    self.queue_admitted(&mut s, &id, seen);
                    ids.push(id);
                }
                Err(e) => {
                    if failed.is_none() {
                        failed = Some(e);
                    }
                }
            }
        }
        {
            let s = self.lock();
            self.persist_after_change(&s);
            self.wake.notify_all();
        }
        for id in &ids {
            self.index_now(id);
        }
        if let Some(e) = failed {
            // A storage failure half-way: the runs queued before it stay (they are
            // valid and stored); the error names them.
            return Err(match e {
                ServiceError::Storage { path, source } if !ids.is_empty() => ServiceError::Storage {
                    path,
                    source: std::io::Error::new(
                        source.kind(),
                        format!("{source} (queued before it: {})", ids.join(", ")),
                    ),
                },
                other => other,
            });
        }
        ids.iter().map(|id| self.status(id)).collect()
    }

    /// Queues run `id`'s stored plan again as a new run.
    pub fn again(&self, id: &str, by: &str) -> Result<RunStatus, ServiceError> {
        let dir = self.dir(id)?;
        if let Some(source) = self.info(id)?.import {
            return Err(ServiceError::Conflict(format!(
                "run {id} reconstructed an imported capture ({}), not a plan: import the file again (with other \
                 settings in its `recon` part), or reconstruct it offline with `periscope recon {}`",
                source.capture,
                dir.display()
            )));
        }
        let path = dir.join(file::PLAN);
        let text = crate::store::read_text_capped(&path, self.instrument.api.body_limit as u64)
            .map_err(ServiceError::storage(&path))?;
        self.submit_as(text, by, Some(id))
    }
}

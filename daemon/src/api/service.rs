//! The instrument service behind the HTTP API: the run queue (persisted in
//! `RUNS_DIR/queue.json`), the worker thread that owns the instrument and runs one plan
//! at a time, and the live state the endpoints read.
//!
//! Everything here is synchronous and quick (a mutex held for microseconds, small file
//! writes); the HTTP handlers call the slower parts through `spawn_blocking`. Runs
//! execute on the dedicated worker thread, never on the async runtime.
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::sync::broadcast;
use utoipa::ToSchema;

use crate::config::{InstrumentConfig, TomlSource};
use crate::events::{EventSink, RunEvent};
use crate::pipeline::{self, Control, PipelineError, Run};
use crate::plan::Plan;
use crate::run_dir::{RunDir, file};
use crate::store::{RunInfo, RunState, write_atomic};
use periscope_drivers::galvo::EmergencyOff;
use periscope_sim::devices::Rig;

/// The queue file in the runs directory.
pub const QUEUE_FILE: &str = "queue.json";

/// Pair and LOS-point events are forwarded to event-stream clients at most this often
/// (plus the last one); stage, optimiser and output events always are.
const PAIR_EVENT_INTERVAL: Duration = Duration::from_millis(50);

/// Events buffered per run for slow stream clients before they are told they lagged.
const EVENT_BUFFER: usize = 1024;

/// An event as sent to stream clients: its name and JSON.
#[derive(Clone, Debug)]
pub struct StreamEvent {
    /// The SSE event name: the event's `event` field (`stage-started`, `pair`,
    /// `epoch`, `output`, ...).
    pub name: Arc<str>,
    /// The event as JSON.
    pub json: Arc<str>,
}

/// A run as the API reports it.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct RunStatus {
    /// Run id.
    pub id: String,
    /// Plan name.
    pub plan: String,
    /// State.
    pub state: RunState,
    /// Current or last stage.
    pub stage: String,
    /// Pairs planned (0 until planned).
    pub pairs_total: usize,
    /// Pairs stored.
    pub pairs_done: usize,
    /// Fraction of the capture done, 0 to 1.
    pub progress: f64,
    /// Estimated seconds until the capture finishes (running captures only).
    pub eta_s: Option<f64>,
    /// Place in the queue (0 = next), for queued runs.
    pub queue_position: Option<usize>,
    /// Last optimiser loss, when fitting.
    pub loss: Option<f64>,
    /// Last error.
    pub error: Option<String>,
    /// Seconds per finished stage.
    pub timings: Vec<(String, f64)>,
    /// Files available for download.
    pub files: Vec<String>,
}

/// Why a request on a run was refused. Each variant keeps the error it came from, and
/// the API's status code follows the kind (`api::ApiError::from`).
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// No such run.
    #[error("no run `{0}`: list runs with GET /api/v1/runs")]
    UnknownRun(String),
    /// The request does not fit the run's state.
    #[error("{0}")]
    Conflict(String),
    /// The plan is invalid; the config error names the key and what it expects.
    #[error(transparent)]
    InvalidPlan(crate::config::ConfigError),
    /// A file or directory under the runs directory could not be read or written.
    #[error("{}: {source}", path.display())]
    Storage {
        /// The file or directory.
        path: PathBuf,
        /// What the filesystem said.
        #[source]
        source: std::io::Error,
    },
    /// `queue.json` is not a list of run ids.
    #[error(
        "{}: {source}; fix or delete the file (runs themselves are kept in their directories)",
        path.display()
    )]
    QueueFile {
        /// The queue file.
        path: PathBuf,
        /// Why it does not parse.
        #[source]
        source: serde_json::Error,
    },
    /// A run's stored files could not be loaded.
    #[error(transparent)]
    RunFiles(#[from] crate::run_dir::RunDirError),
    /// Preparing a submitted run's directory failed; the pipeline's error kind decides
    /// the status (a config error is the plan's fault, a storage error the daemon's).
    #[error(transparent)]
    Prepare(PipelineError),
    /// A run's capture could not be exported as y-tal HDF5.
    #[error("run {id}: capture export: {source}")]
    Export {
        /// The run.
        id: String,
        /// Why.
        #[source]
        source: periscope_recon::io::ytal::YtalError,
    },
    /// The instrument config is invalid.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    /// The queue is full.
    #[error("{0}")]
    QueueFull(String),
    /// The plan needs more memory or disk than the instrument's budget allows.
    #[error("{0}")]
    OverBudget(String),
}

impl ServiceError {
    /// A storage error on `path`.
    fn storage(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> ServiceError {
        let path = path.into();
        move |source| ServiceError::Storage { path, source }
    }
}

/// A run file to send: small ones in memory, the rest streamed from disk.
#[derive(Debug)]
pub enum Download {
    /// The whole body.
    Bytes(Vec<u8>),
    /// An open file and its length.
    File(std::fs::File, u64),
}

/// The devices as the worker last read them.
struct Reading {
    /// When it was taken.
    at: Instant,
    /// The same, as Unix seconds.
    unix_s: f64,
    /// The devices' report, or why they could not be read.
    devices: Result<serde_json::Value, String>,
}

/// Live progress of the running run, fed by its events.
#[derive(Default)]
struct Live {
    id: String,
    stage: String,
    pairs_done: usize,
    pairs_total: usize,
    capture_started: Option<(Instant, usize)>,
    loss: Option<f64>,
}

struct Shared {
    /// Run ids waiting or paused, in submission order.
    queue: VecDeque<String>,
    /// The running run and its control.
    current: Option<(String, Control)>,
    /// The running run's direct way to its laser, once its devices are open.
    laser_off: Option<EmergencyOff>,
    live: Live,
    /// Event channels of runs that are running (or were, until a client drops them).
    channels: HashMap<String, broadcast::Sender<StreamEvent>>,
    /// The instrument's state as the last run or e-stop left it.
    last_safe: Option<String>,
    /// The worker's last reading of the devices (`GET /instrument` serves it).
    reading: Option<Reading>,
    /// Asks the worker for a fresh reading (after a run or an e-stop).
    refresh: bool,
    /// Submissions between their queue-length check and their place in the queue.
    admitting: usize,
    /// Queued runs an e-stop held (as `paused` in their run.json, where the store
    /// lets it): the worker skips them whatever their run.json says, until an operator
    /// resumes or aborts them, so a hold the disk refused still holds.
    held: std::collections::HashSet<String>,
    /// Runs whose end neither the pipeline nor the worker could record: their run.json
    /// still reads queued or running though nothing works on them. Resume and abort
    /// take them as failed (a `running` run.json of any other run is left alone: it
    /// may be a `periscope run` of another process in the same directory).
    stale: std::collections::HashSet<String>,
    shutdown: bool,
}

/// The service: configuration, queue and worker.
pub struct Service {
    runs_dir: PathBuf,
    instrument_src: TomlSource,
    instrument: InstrumentConfig,
    /// The simulated instrument (back-end `sim`), kept for the daemon's life so that
    /// runs, e-stops and status all see the same devices.
    rig: Option<Rig>,
    token: Option<String>,
    shared: Mutex<Shared>,
    wake: Condvar,
    /// Held while a capture export is written.
    exporting: Mutex<()>,
    /// Held while the service itself has devices open outside a run (the worker's
    /// reading, the idle e-stop), so the two never open one serial port at once: an
    /// e-stop waits for a reading in progress (milliseconds) instead of failing to
    /// open the laser controller.
    devices: Mutex<()>,
}

impl Service {
    /// Opens the service on `runs_dir`, restoring the queue. A run that was running when
    /// the daemon stopped is marked paused (its data is intact), so an operator decides
    /// whether to resume it; queued runs stay queued.
    pub fn open(instrument_src: TomlSource, token: Option<String>) -> Result<Arc<Service>, ServiceError> {
        let instrument = InstrumentConfig::from_source(&instrument_src)?;
        let rig = crate::devices::sim_rig(&instrument)?;
        let runs_dir = instrument.api.runs_dir.clone();
        std::fs::create_dir_all(&runs_dir).map_err(ServiceError::storage(&runs_dir))?;
        let mut queue = VecDeque::new();
        let qpath = runs_dir.join(QUEUE_FILE);
        if qpath.is_file() {
            let text = std::fs::read_to_string(&qpath).map_err(ServiceError::storage(&qpath))?;
            let ids: Vec<String> = serde_json::from_str(&text).map_err(|source| ServiceError::QueueFile {
                path: qpath.clone(),
                source,
            })?;
            for id in ids {
                let dir = runs_dir.join(&id);
                let Ok(mut info) = RunInfo::load(&dir) else {
                    tracing::warn!(
                        "queue.json names run {id}, which has no readable run.json; dropped from the queue"
                    );
                    continue;
                };
                match info.state {
                    RunState::Running => {
                        hold_interrupted(&dir, &id, &mut info)?;
                        queue.push_back(id);
                    }
                    RunState::Queued | RunState::Paused => queue.push_back(id),
                    _ => {}
                }
            }
        }
        // A run whose directory was made but whose place in queue.json was never saved
        // (the daemon stopped in between) is queued again rather than stranded.
        let mut orphans: Vec<String> = std::fs::read_dir(&runs_dir)
            .map_err(ServiceError::storage(&runs_dir))?
            .filter_map(Result::ok)
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .filter(|id| !queue.contains(id))
            .filter(|id| {
                RunInfo::load(&runs_dir.join(id))
                    .is_ok_and(|i| matches!(i.state, RunState::Queued | RunState::Running))
            })
            .collect();
        orphans.sort();
        for id in orphans {
            let dir = runs_dir.join(&id);
            if let Ok(mut info) = RunInfo::load(&dir)
                && info.state == RunState::Running
            {
                hold_interrupted(&dir, &id, &mut info)?;
            }
            tracing::warn!(run = %id, "run {id} was missing from queue.json; queued again");
            queue.push_back(id);
        }
        let service = Arc::new(Service {
            runs_dir,
            instrument_src,
            instrument,
            rig,
            token,
            shared: Mutex::new(Shared {
                queue,
                current: None,
                laser_off: None,
                live: Live::default(),
                channels: HashMap::new(),
                last_safe: None,
                reading: None,
                refresh: true,
                admitting: 0,
                held: Default::default(),
                stale: Default::default(),
                shutdown: false,
            }),
            wake: Condvar::new(),
            exporting: Mutex::new(()),
            devices: Mutex::new(()),
        });
        service.persist(&service.lock())?;
        Ok(service)
    }

    /// Starts the worker thread that runs queued plans, one at a time.
    pub fn start_worker(self: &Arc<Self>) -> std::thread::JoinHandle<()> {
        let me = Arc::clone(self);
        std::thread::Builder::new()
            .name("instrument".into())
            .spawn(move || me.worker())
            .expect("the worker thread starts")
    }

    /// Shuts down: the running run's laser off at once through its direct path, the
    /// run paused at its next checkpoint (so it resumes after a restart), every event
    /// stream ended, and the worker told to stop.
    pub fn shutdown(&self) {
        let mut s = self.lock();
        s.shutdown = true;
        if let Some((_, control)) = &s.current {
            control.pause();
        }
        if let Some(off) = &s.laser_off
            && let Err(e) = off.laser_off()
        {
            tracing::warn!(error = %e, "shutdown: direct laser off failed; the run switches it off at its checkpoint");
        }
        // Dropping the senders ends every event stream after what it has buffered.
        s.channels.clear();
        self.wake.notify_all();
    }

    /// Switches the running run's laser off through its direct path, if a run holds
    /// the devices (for signal handlers: quick, waits for nothing but a mutex).
    pub fn laser_off_now(&self) {
        if let Some(off) = self.lock().laser_off.clone()
            && let Err(e) = off.laser_off()
        {
            tracing::warn!(error = %e, "direct laser off failed");
        }
    }

    /// The simulated instrument, for back-end `sim`.
    pub fn rig(&self) -> Option<&Rig> {
        self.rig.as_ref()
    }

    /// Testing aid (fault injection): the running run panics at its next checkpoint
    /// in `stage` (see [`Control::inject_panic`]). Returns whether a run was running.
    pub fn inject_panic(&self, stage: crate::events::Stage) -> bool {
        let s = self.lock();
        s.current.as_ref().map(|(_, c)| c.inject_panic(stage)).is_some()
    }

    /// Testing aid (fault injection): the running run hangs at its next checkpoint in
    /// `stage` for `duration` (see [`Control::inject_hang`]). Returns whether a run
    /// was running.
    pub fn inject_hang(&self, stage: crate::events::Stage, duration: Duration) -> bool {
        let s = self.lock();
        s.current
            .as_ref()
            .map(|(_, c)| c.inject_hang(stage, duration))
            .is_some()
    }

    fn lock(&self) -> MutexGuard<'_, Shared> {
        self.shared.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The bearer token mutating requests must carry.
    pub fn token(&self) -> Option<&str> {
        self.token.as_deref()
    }

    /// The instrument config.
    pub fn instrument(&self) -> &InstrumentConfig {
        &self.instrument
    }

    /// The runs directory.
    pub fn runs_dir(&self) -> &Path {
        &self.runs_dir
    }

    fn persist(&self, s: &Shared) -> Result<(), ServiceError> {
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
    fn persist_after_change(&self, s: &Shared) {
        if let Err(e) = self.persist(s) {
            tracing::error!(
                "{e}: the queue in memory is right, and the next start queues again the runs queue.json misses"
            );
        }
    }

    fn dir(&self, id: &str) -> Result<PathBuf, ServiceError> {
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

    fn info(&self, id: &str) -> Result<RunInfo, ServiceError> {
        let dir = self.dir(id)?;
        RunInfo::load(&dir).map_err(ServiceError::storage(dir.join(file::RUN)))
    }

    fn set_state(&self, id: &str, state: RunState, error: Option<String>) -> Result<(), ServiceError> {
        let dir = self.dir(id)?;
        let mut info = self.info(id)?;
        info.state = state;
        if error.is_some() {
            info.error = error;
        }
        info.save(&dir)
            .map_err(ServiceError::storage(dir.join(file::RUN)))
    }

    /// Validates a plan (TOML text) and queues it. Returns the new run's status.
    pub fn submit(&self, text: String) -> Result<RunStatus, ServiceError> {
        let src = TomlSource::from_text("request body", text);
        let plan = Plan::from_source(&src, &self.instrument).map_err(ServiceError::InvalidPlan)?;
        crate::budget::Budget::of_plan(&plan)
            .check(&self.instrument.budget)
            .map_err(ServiceError::OverBudget)?;
        // A place in the queue is reserved before the run directory is made, so a
        // flood of submissions never makes more directories than the queue takes.
        {
            let mut s = self.lock();
            let max = self.instrument.api.max_queue;
            if s.queue.len() + s.admitting >= max {
                return Err(ServiceError::QueueFull(format!(
                    "the queue holds {max} runs, the most this daemon keeps ([api] max-queue); \
                     wait for runs to finish or abort queued ones"
                )));
            }
            s.admitting += 1;
        }
        let admitted = self.admit(&src, &plan);
        let mut s = self.lock();
        s.admitting -= 1;
        let id = admitted?;
        s.queue.push_back(id.clone());
        self.persist_after_change(&s);
        self.wake.notify_all();
        drop(s);
        tracing::info!(run = %id, plan = %plan.name, "run queued");
        self.status(&id)
    }

    /// Makes a submitted plan's run directory; returns its id.
    fn admit(&self, src: &TomlSource, plan: &Plan) -> Result<String, ServiceError> {
        let dir = crate::store::new_run_dir(&self.runs_dir, &plan.name)
            .map_err(ServiceError::storage(&self.runs_dir))?;
        let src = TomlSource::from_text(dir.join(file::PLAN), src.text().to_owned());
        pipeline::prepare(&src, &self.instrument_src, Some(&dir)).map_err(|e| match e {
            PipelineError::Config(c) => ServiceError::InvalidPlan(c),
            other => ServiceError::Prepare(other),
        })?;
        Ok(dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default())
    }

    /// Every run in the runs directory, oldest first.
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
        if st.state == RunState::Queued {
            st.queue_position = s
                .queue
                .iter()
                .filter(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                .position(|q| q == id);
        }
        drop(s);
        if st.pairs_total > 0 {
            st.progress = (st.pairs_done as f64 / st.pairs_total as f64).min(1.0);
        }
        if st.state == RunState::Completed {
            st.progress = 1.0;
        }
        st.files = super::DOWNLOADS
            .iter()
            .filter(|(name, _)| dir.join(name).is_file())
            .map(|(name, _)| (*name).to_owned())
            .collect();
        Ok(st)
    }

    /// Asks the running run to pause at its next checkpoint.
    pub fn pause(&self, id: &str) -> Result<RunStatus, ServiceError> {
        {
            let s = self.lock();
            let info = self.info(id)?;
            match &s.current {
                Some((c, control)) if c == id => control.pause(),
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
        let held = s.held.remove(id);
        let stale = s.stale.remove(id);
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
        self.set_state(id, RunState::Queued, None)?;
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
    /// (abort).
    fn await_hand_back<'a>(&'a self, mut s: MutexGuard<'a, Shared>, id: &str) -> MutexGuard<'a, Shared> {
        let deadline = Instant::now() + HAND_BACK_WAIT;
        while s.current.as_ref().is_some_and(|(c, _)| c == id)
            && self
                .info(id)
                .is_ok_and(|i| !matches!(i.state, RunState::Running | RunState::Queued))
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
        let s = self.lock();
        // A run that has already stopped at a checkpoint would not see the request.
        let mut s = self.await_hand_back(s, id);
        let info = self.info(id)?;
        if let Some((c, control)) = &s.current
            && c == id
        {
            control.abort();
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

    /// Emergency stop. In this order: the laser off through the running run's direct
    /// path (an out-of-band `LASER OFF` to the laser controller that nothing pending
    /// can hold up), the run aborted (it parks both arms on its way out), queued runs
    /// held as paused. With no run holding the devices, or if the direct path fails,
    /// the laser controller is opened on its own (neither the SPAD arm nor the
    /// histogrammer is needed) and switched off, then each arm parked. Nothing stops
    /// it half-way: every step is tried, and the report says what was done.
    pub fn estop(&self) -> Result<EstopReport, ServiceError> {
        let t = Instant::now();
        let mut report = EstopReport::default();
        let (running, direct) = {
            let s = self.lock();
            (s.current.clone(), s.laser_off.clone())
        };
        // 1. The laser, directly. The run is told to abort first (an atomic store), so
        //    that a `LASER ON` the latched switch refuses it reads as the abort.
        if let Some((_, control)) = &running {
            control.abort();
        }
        let mut laser_off = false;
        if let Some(off) = &direct {
            match off.laser_off() {
                Ok(()) => {
                    laser_off = true;
                    report.laser = "off: out-of-band LASER OFF to the laser controller".into();
                    report.laser_off_s = Some(t.elapsed().as_secs_f64());
                }
                Err(e) => report.warnings.push(format!("direct laser off failed: {e}")),
            }
        }
        // 2. The run (asked above).
        if let Some((id, _)) = &running {
            report.aborted = Some(id.clone());
        }
        // 3. Queued runs are held (under the lock, so no resume or worker pick races it).
        //    A run the worker took from the queue since step 1 is held through its
        //    control (it stops at its next checkpoint, paused): its pipeline alone writes
        //    its run.json, and a state written here would race the pipeline's own.
        {
            let mut s = self.lock();
            if let Some((id, control)) = s.current.as_ref()
                && running.as_ref().is_none_or(|(r, _)| r != id)
            {
                control.pause();
                report.held.push(id.clone());
            }
            let running_id = s.current.as_ref().map(|(id, _)| id.clone());
            let queued: Vec<String> = s
                .queue
                .iter()
                .filter(|q| Some(*q) != running_id.as_ref())
                .filter(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                .cloned()
                .collect();
            for id in queued {
                s.held.insert(id.clone());
                if let Err(e) = self.set_state(
                    &id,
                    RunState::Paused,
                    Some("held by an emergency stop; resume it to run".into()),
                ) {
                    report.warnings.push(format!(
                        "queued run {id} is held (the worker will not start it), but its run.json could not record it: {e}; resume or abort it once the disk is fixed"
                    ));
                }
                report.held.push(id);
            }
        }
        // 4. Wait (bounded) for the run to reach its checkpoint: it parks the arms and
        //    confirms the laser off on its way out.
        if let Some((id, control)) = &running {
            let deadline = Instant::now() + ESTOP_RUN_WAIT;
            let mut s = self.lock();
            while s.current.as_ref().is_some_and(|(c, _)| c == id) && Instant::now() < deadline {
                s = self
                    .wake
                    .wait_timeout(s, Duration::from_millis(5))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
            if s.current.as_ref().is_some_and(|(c, _)| c == id) {
                report.warnings.push(format!(
                    "run {id} did not reach its checkpoint within {} s; the devices were opened directly",
                    ESTOP_RUN_WAIT.as_secs_f64()
                ));
            } else {
                // Only a run that says it made the instrument safe is believed; one
                // whose make-safe failed, or that never held the devices, leaves it
                // to step 5.
                match control.made_safe() {
                    Some(Ok(())) => {
                        report.parked = true;
                        if !laser_off {
                            laser_off = true;
                            report.laser = "off: the run switched it off on its way out".into();
                            report.laser_off_s = Some(t.elapsed().as_secs_f64());
                        }
                    }
                    Some(Err(e)) => report.warnings.push(format!(
                        "run {id} could not make the instrument safe on its way out ({e}); the devices were opened directly"
                    )),
                    None => {}
                }
            }
        }
        // 5. No run (or one that did not stop): each controller opened on its own.
        if !report.parked {
            match self.laser_controller_off() {
                Ok(()) => {
                    if !laser_off {
                        report.laser =
                            "off: LASER OFF through the laser controller, opened for the e-stop".into();
                        report.laser_off_s = Some(t.elapsed().as_secs_f64());
                        laser_off = true;
                    }
                }
                Err(e) => report.warnings.push(format!("laser controller: {e}")),
            }
            match self.park_spad() {
                Ok(()) => report.parked = true,
                Err(e) => report.warnings.push(format!("SPAD arm: {e}")),
            }
        }
        if !laser_off {
            report.laser = "UNCONFIRMED: no path to the laser controller answered; the controller's watchdog ends emission within its timeout, or switch the laser off at the interlock".into();
        }
        report.seconds = t.elapsed().as_secs_f64();
        {
            let mut s = self.lock();
            s.last_safe = Some(format!("{} (e-stop)", report.laser));
            s.refresh = true;
            self.wake.notify_all();
        }
        tracing::warn!(laser = %report.laser, parked = report.parked, seconds = report.seconds, "emergency stop");
        Ok(report)
    }

    /// Opens the laser controller alone: laser off, then park.
    fn laser_controller_off(&self) -> Result<(), String> {
        let _devices = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let mut controller = crate::devices::Devices::laser_controller(&self.instrument, self.rig.as_ref())
            .map_err(|e| e.to_string())?;
        let off = controller.laser.set_emission(false).map_err(|e| e.to_string());
        let park = controller.arm.park().map_err(|e| e.to_string());
        off?;
        park
    }

    /// Opens the SPAD arm's controller alone and parks it.
    fn park_spad(&self) -> Result<(), String> {
        let _devices = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let mut spad = crate::devices::Devices::spad_controller(&self.instrument, self.rig.as_ref())
            .map_err(|e| e.to_string())?;
        spad.park().map_err(|e| e.to_string())
    }

    /// The instrument's status, without touching the hardware: the worker's last
    /// reading of the devices with its age (it reads them when it starts, after every
    /// run and e-stop, and every `[api] status-interval-s` while idle), and the running
    /// run's stage while one holds the instrument.
    pub fn instrument_status(&self) -> InstrumentStatus {
        let s = self.lock();
        let (reading, devices, error) = match &s.reading {
            Some(r) => {
                let age = ReadingAge {
                    taken_unix_s: r.unix_s,
                    age_s: r.at.elapsed().as_secs_f64(),
                };
                match &r.devices {
                    Ok(d) => (Some(age), Some(d.clone()), None),
                    Err(e) => (Some(age), None, Some(e.clone())),
                }
            }
            None => (None, None, None),
        };
        let run = s.current.as_ref().map(|(id, _)| RunStage {
            id: id.clone(),
            stage: s.live.stage.clone(),
        });
        InstrumentStatus {
            name: self.instrument.name.clone(),
            summary: self.instrument.summary(),
            busy: run.is_some(),
            note: run
                .as_ref()
                .map(|_| "the running run holds the devices; their live state is in its event stream"),
            run,
            devices,
            reading,
            error,
            last_safe: s.last_safe.clone(),
        }
    }

    /// Reads the devices (worker thread only: it owns the instrument between runs).
    fn take_reading(&self) {
        let _devices = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let devices = crate::devices::Devices::open_on(&self.instrument, self.rig.clone(), &|| false)
            .and_then(|mut d| d.report())
            .map(|r| serde_json::to_value(r).unwrap_or_default())
            .map_err(|e| e.to_string());
        let unix_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        self.lock().reading = Some(Reading {
            at: Instant::now(),
            unix_s,
            devices,
        });
    }

    /// A run file for download. `instrument.toml` is served with its secrets cut out
    /// (runs stored before they were cut out at the source included); `capture.hdf5`
    /// of a run that has not finished is exported from what is stored so far, once per
    /// stored pair count, into a cache file beside the run; the rest stream from disk.
    pub fn download(&self, id: &str, name: &str) -> Result<Download, ServiceError> {
        let dir = self.dir(id)?;
        let missing = |_| {
            ServiceError::Conflict(format!(
                "run {id} has no {name} (yet): outputs appear when the run completes"
            ))
        };
        let path = dir.join(name);
        if name == file::INSTRUMENT {
            let text = crate::store::read_text_capped(&path, 1 << 20).map_err(missing)?;
            return Ok(Download::Bytes(crate::config::redact_secrets(&text).into_bytes()));
        }
        if !path.is_file() && name == crate::ytal::CAPTURE_FILE {
            return self.export_capture(id, &dir);
        }
        let file = std::fs::File::open(&path).map_err(missing)?;
        let len = file.metadata().map_err(missing)?.len();
        Ok(Download::File(file, len))
    }

    fn export_capture(&self, id: &str, dir: &Path) -> Result<Download, ServiceError> {
        // One export at a time: concurrent requests wait for it and share its file.
        let _one = self.exporting.lock().unwrap_or_else(|p| p.into_inner());
        let done = RunInfo::load(dir).map(|i| i.pairs_done).unwrap_or(0);
        let records = std::fs::metadata(dir.join(crate::store::HISTOGRAM_LOG)).map_or(0, |m| m.len());
        let cache = dir.join(file::EXPORT_CACHE);
        let stamp = dir.join(format!("{}.stamp", file::EXPORT_CACHE));
        let key = format!("{done} {records}");
        let fresh = std::fs::read_to_string(&stamp).is_ok_and(|k| k == key) && cache.is_file();
        if !fresh {
            let not_yet = |e: &dyn std::fmt::Display| {
                ServiceError::Conflict(format!("run {id} has no capture to export yet: {e}"))
            };
            let capture = crate::capture::RunCapture::load(dir)
                .map_err(|e| not_yet(&e))?
                .to_ytal()
                .map_err(|e| not_yet(&e))?;
            capture.write(&cache).map_err(|source| ServiceError::Export {
                id: id.to_owned(),
                source,
            })?;
            write_atomic(&stamp, key.as_bytes()).map_err(ServiceError::storage(&stamp))?;
        }
        let file = std::fs::File::open(&cache).map_err(ServiceError::storage(&cache))?;
        let len = file.metadata().map_err(ServiceError::storage(&cache))?.len();
        Ok(Download::File(file, len))
    }

    /// What `periscope check` says about a plan (TOML text), as JSON-ready data; an
    /// invalid plan is refused with the same message `submit` would give.
    pub fn check(&self, text: String) -> Result<crate::check::Check, ServiceError> {
        let src = TomlSource::from_text("request body", text);
        let plan = Plan::from_source(&src, &self.instrument).map_err(ServiceError::InvalidPlan)?;
        Ok(crate::check::check(&plan, &self.instrument))
    }

    /// A run's geometry for 3-D views: the relay points the LOS scan kept, the planned
    /// illumination and detection points (each thinned to at most [`GEOMETRY_POINTS`]),
    /// the reconstruction volume and the instrument's viewpoint, in metres. Parts the
    /// run has not made yet are empty.
    pub fn geometry(&self, id: &str) -> Result<Geometry, ServiceError> {
        let dir = self.dir(id)?;
        let storage = ServiceError::RunFiles;
        let run = RunDir::new(&dir);
        let (_, plan, inst) = run.load().map_err(storage)?;
        let relay: Vec<[f64; 3]> = run
            .relay()
            .map_err(storage)?
            .unwrap_or_default()
            .iter()
            .map(|p| p.x.to_array())
            .collect();
        let pairs = run.planned_pairs().map_err(storage)?.unwrap_or_default();
        let unique = |pick: fn(&crate::plan::PlannedPair) -> glam::DVec3| {
            let mut seen = std::collections::HashSet::new();
            let points: Vec<[f64; 3]> = pairs
                .iter()
                .map(pick)
                .filter(|p| seen.insert(p.to_array().map(f64::to_bits)))
                .map(|p| p.to_array())
                .collect();
            thin(points)
        };
        let v = &plan.recon.volume;
        let viewpoint = 0.5 * (inst.laser_arm.pose.origin + inst.spad_arm.pose.origin);
        Ok(Geometry {
            relay: thin(relay),
            illumination: unique(|p| p.xi),
            detection: unique(|p| p.xd),
            pairs: pairs.len(),
            volume: VolumeBox {
                x: v.x,
                y: v.y,
                z: v.z,
            },
            viewpoint: viewpoint.to_array(),
        })
    }

    /// Subscribes to a run's events: a running run's, or a queued or paused one's from
    /// when it (re)starts. `None` when the run has finished (its past events are in
    /// `events.jsonl`). The stream ends when the run stops.
    pub fn subscribe(&self, id: &str) -> Result<Option<broadcast::Receiver<StreamEvent>>, ServiceError> {
        self.dir(id)?;
        let mut s = self.lock();
        let waiting = s.current.as_ref().is_some_and(|(c, _)| c == id) || s.queue.iter().any(|q| q == id);
        if !waiting || s.shutdown {
            return Ok(None);
        }
        Ok(Some(
            s.channels
                .entry(id.to_owned())
                .or_insert_with(|| broadcast::channel(EVENT_BUFFER).0)
                .subscribe(),
        ))
    }

    fn worker(self: Arc<Self>) {
        loop {
            let (id, control) = {
                let mut s = self.lock();
                loop {
                    if s.shutdown {
                        return;
                    }
                    let next = s
                        .queue
                        .iter()
                        .filter(|q| !s.held.contains(*q))
                        .find(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                        .cloned();
                    let Some(id) = next else {
                        let interval = self.instrument.api.status_interval;
                        let stale = s.reading.as_ref().is_none_or(|r| r.at.elapsed() >= interval);
                        if s.refresh || stale {
                            s.refresh = false;
                            drop(s);
                            self.take_reading();
                            s = self.lock();
                        } else {
                            let wait = s
                                .reading
                                .as_ref()
                                .map_or(interval, |r| interval.saturating_sub(r.at.elapsed()));
                            s = self
                                .wake
                                .wait_timeout(s, wait.max(Duration::from_millis(10)))
                                .unwrap_or_else(|p| p.into_inner())
                                .0;
                        }
                        continue;
                    };
                    let control = Control::new();
                    s.current = Some((id.clone(), control.clone()));
                    s.live = Live {
                        id: id.clone(),
                        stage: "starting".into(),
                        ..Live::default()
                    };
                    s.channels
                        .entry(id.clone())
                        .or_insert_with(|| broadcast::channel(EVENT_BUFFER).0);
                    break (id, control);
                }
            };
            tracing::info!(run = %id, "run starting");
            // The pipeline catches its own panics; this catches the rest (the worker's
            // own code), so a bug never freezes the queue or strands the e-stop.
            let result = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                self.execute(&id, control.clone())
            })) {
                Ok(r) => r,
                Err(payload) => {
                    let e = PipelineError::Panicked {
                        stage: "worker",
                        message: pipeline::panic_message(payload.as_ref()),
                    };
                    self.lock().laser_off = None;
                    if let Err(off) = self.laser_controller_off() {
                        tracing::error!("after a panic, the laser controller could not be reached: {off}");
                    }
                    if let Err(park) = self.park_spad() {
                        tracing::error!("after a panic, the SPAD arm could not be parked: {park}");
                    }
                    let dir = self.runs_dir.join(&id);
                    if let Ok(mut info) = RunInfo::load(&dir) {
                        info.state = RunState::Failed;
                        info.error = Some(e.to_string());
                        let _ = info.save(&dir);
                    }
                    Err(e)
                }
            };
            let stale = result.as_ref().is_err_and(|e| self.record_unrecorded_end(&id, e));
            let mut s = self.lock();
            if stale {
                s.stale.insert(id.clone());
            }
            s.current = None;
            s.laser_off = None;
            s.refresh = true;
            s.channels.remove(&id);
            match &result {
                Ok(()) | Err(PipelineError::Aborted(_)) => {
                    s.queue.retain(|q| q != &id);
                    match control.made_safe() {
                        Some(Ok(())) => {
                            s.last_safe = Some(format!("laser off, arms parked (end of run {id})"))
                        }
                        Some(Err(e)) => {
                            tracing::error!(run = %id, "the run could not make the instrument safe: {e}")
                        }
                        None => {}
                    }
                }
                // Paused or suspended: resumable, it keeps its place.
                Err(PipelineError::Paused(_) | PipelineError::Suspended { .. }) => {}
                Err(_) => {
                    s.queue.retain(|q| q != &id);
                }
            }
            if let Err(e) = self.persist(&s) {
                tracing::error!("{e}");
            }
            self.wake.notify_all();
            drop(s);
            match result {
                Ok(()) => tracing::info!(run = %id, "run completed"),
                Err(e) => tracing::warn!(run = %id, "run stopped: {e}"),
            }
        }
    }

    /// After a run stopped with `e` (worker thread, the run still current so nothing
    /// else writes its run.json): if its run.json still says queued or running, the
    /// pipeline could not record its end (the store refused, or it failed before it
    /// could), so it is recorded here as failed, resumable, with the error, rather
    /// than left looking queued or running with nothing working on it. Returns
    /// whether it still reads so (the store refused this too).
    fn record_unrecorded_end(&self, id: &str, e: &PipelineError) -> bool {
        let dir = self.runs_dir.join(id);
        match RunInfo::load(&dir) {
            Ok(mut info) if matches!(info.state, RunState::Queued | RunState::Running) => {
                info.state = RunState::Failed;
                info.error = Some(e.to_string());
                if let Err(io) = info.save(&dir) {
                    tracing::error!(run = %id, "could not record the run's end ({e}) in {}: {io}", dir.display());
                    return true;
                }
                false
            }
            Ok(_) => false,
            Err(io) => {
                tracing::error!(run = %id, "could not read {}: {io}", dir.display());
                false
            }
        }
    }

    fn execute(self: &Arc<Self>, id: &str, control: Control) -> Result<(), PipelineError> {
        let dir = self.runs_dir.join(id);
        let events = EventSink::open(&dir).map_err(|e| PipelineError::Storage {
            path: dir.clone(),
            source: e,
        })?;
        let me = Arc::clone(self);
        let run_id = id.to_owned();
        let mut last_sent = [Instant::now() - PAIR_EVENT_INTERVAL; 2];
        events.listen(move |ev| me.on_event(&run_id, ev, &mut last_sent));
        // Run::open records a run that never started (paused, aborted or failed,
        // resumable) itself.
        let run = Run::open(&dir, control, Some(events), self.rig.clone())?;
        self.lock().laser_off = Some(run.emergency_off());
        run.execute().map(|_| ())
    }

    fn on_event(&self, id: &str, ev: &RunEvent, last_sent: &mut [Instant; 2]) {
        let mut s = self.lock();
        if s.live.id == id {
            let live = &mut s.live;
            match ev {
                RunEvent::StageStarted { stage } => {
                    live.stage = stage.name().into();
                    if stage.name() == "capture" {
                        live.capture_started = Some((Instant::now(), live.pairs_done));
                    }
                }
                RunEvent::Planned { pairs, .. } => live.pairs_total = *pairs,
                RunEvent::Pair { done, total, .. } => {
                    live.pairs_done = *done;
                    live.pairs_total = *total;
                    if live.capture_started.is_none() {
                        live.capture_started = Some((Instant::now(), *done));
                    }
                }
                RunEvent::Train(t) => {
                    if let Some(loss) = train_loss(t) {
                        live.loss = Some(loss);
                    }
                }
                _ => {}
            }
        }
        let Some(tx) = s.channels.get(id) else {
            return;
        };
        if tx.receiver_count() == 0 {
            return;
        }
        // Per-pair and per-LOS-point progress is forwarded at a display rate (and the
        // last one always), so clients cost the capture nothing measurable.
        // Histograms likewise, on their own clock (each forwarded one is the newest).
        let progress = match ev {
            RunEvent::Pair { done, total, .. } | RunEvent::LosPoint { done, total } => {
                Some((0, done == total))
            }
            RunEvent::Histogram { .. } => Some((1, false)),
            _ => None,
        };
        if let Some((clock, last)) = progress {
            if !last && last_sent[clock].elapsed() < PAIR_EVENT_INTERVAL {
                return;
            }
            last_sent[clock] = Instant::now();
        }
        let value = serde_json::to_value(ev).unwrap_or_default();
        let name = event_name(&value);
        // A send fails only when no client listens; that is fine.
        let _ = tx.send(StreamEvent {
            name,
            json: value.to_string().into(),
        });
    }
}

/// The most points of each kind [`Service::geometry`] returns.
pub const GEOMETRY_POINTS: usize = 20_000;

/// Every k-th point, so at most [`GEOMETRY_POINTS`] remain, rounded to 0.1 mm.
fn thin(points: Vec<[f64; 3]>) -> Vec<[f64; 3]> {
    let step = points.len().div_ceil(GEOMETRY_POINTS).max(1);
    points
        .into_iter()
        .step_by(step)
        .map(|p| p.map(|c| (c * 1e4).round() / 1e4))
        .collect()
}

/// A run found `running` when the daemon starts was interrupted by its stop: it is
/// held as paused (its data is intact) until an operator resumes it.
fn hold_interrupted(dir: &Path, id: &str, info: &mut RunInfo) -> Result<(), ServiceError> {
    info.state = RunState::Paused;
    info.error = Some(format!(
        "interrupted: the daemon stopped during stage {}; POST /api/v1/runs/{id}/resume continues it",
        info.stage
    ));
    info.save(dir).map_err(ServiceError::storage(dir.join(file::RUN)))
}

/// How long an e-stop waits for a running run to reach its checkpoint (and park)
/// before it opens the controllers itself.
const ESTOP_RUN_WAIT: Duration = Duration::from_secs(2);

/// How long a resume or abort waits for a run that has stopped at its checkpoint to be
/// handed back by the worker ([`Service::await_hand_back`]).
const HAND_BACK_WAIT: Duration = Duration::from_secs(5);

/// What `GET /api/v1/instrument` reports: the worker's last reading of the devices,
/// never a fresh one.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct InstrumentStatus {
    /// The instrument config's name.
    pub name: String,
    /// One line on the instrument config.
    pub summary: String,
    /// Whether a run holds the instrument.
    pub busy: bool,
    /// The run holding the instrument, and its stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub run: Option<RunStage>,
    /// Where to look for the devices' live state while a run holds them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<&'static str>,
    /// The last reading of the devices, as `periscope devices --json` prints it
    /// (`null` until one succeeded).
    #[schema(value_type = Option<Object>)]
    pub devices: Option<serde_json::Value>,
    /// When that reading was taken (`null`: none yet).
    pub reading: Option<ReadingAge>,
    /// Why the last reading failed, if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The last time the instrument was made safe, and by what.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_safe: Option<String>,
}

/// A run and its stage.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct RunStage {
    /// Run id.
    pub id: String,
    /// Its current stage.
    pub stage: String,
}

/// When a device reading was taken.
#[derive(Clone, Copy, Debug, Serialize, ToSchema)]
pub struct ReadingAge {
    /// Unix time of the reading, seconds.
    pub taken_unix_s: f64,
    /// Its age, seconds.
    pub age_s: f64,
}

/// A run's geometry for 3-D views, metres, world frame.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct Geometry {
    /// Relay points of the LOS scan (thinned).
    pub relay: Vec<[f64; 3]>,
    /// Planned illumination points, each once (thinned).
    pub illumination: Vec<[f64; 3]>,
    /// Planned detection points, each once (thinned).
    pub detection: Vec<[f64; 3]>,
    /// Planned pairs.
    pub pairs: usize,
    /// The reconstruction volume.
    pub volume: VolumeBox,
    /// Midway between the two galvo pairs.
    pub viewpoint: [f64; 3],
}

/// An axis-aligned box, metres.
#[derive(Clone, Copy, Debug, Serialize, ToSchema)]
pub struct VolumeBox {
    /// x range.
    pub x: [f64; 2],
    /// y range.
    pub y: [f64; 2],
    /// z range.
    pub z: [f64; 2],
}

/// What an e-stop did.
#[derive(Debug, Default, Serialize, ToSchema)]
pub struct EstopReport {
    /// The run that was aborted, if one was running.
    pub aborted: Option<String>,
    /// What happened to the laser, and by which path.
    pub laser: String,
    /// Seconds from the request until LASER OFF was sent (`null`: not confirmed).
    pub laser_off_s: Option<f64>,
    /// Whether both arms were parked.
    pub parked: bool,
    /// Queued runs held as paused.
    pub held: Vec<String>,
    /// Steps that failed (each was tried regardless).
    pub warnings: Vec<String>,
    /// Seconds from the request until every step was done.
    pub seconds: f64,
}

fn train_loss(t: &periscope_recon::gtr::TrainEvent) -> Option<f64> {
    match t {
        periscope_recon::gtr::TrainEvent::Epoch { loss, .. } => Some(*loss),
        _ => None,
    }
}

fn event_name(v: &serde_json::Value) -> Arc<str> {
    v.get("event").and_then(|e| e.as_str()).unwrap_or("event").into()
}

/// A run state's name as the API spells it.
pub fn state_name(s: RunState) -> &'static str {
    match s {
        RunState::Queued => "queued",
        RunState::Running => "running",
        RunState::Paused => "paused",
        RunState::Completed => "completed",
        RunState::Aborted => "aborted",
        RunState::Failed => "failed",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The service on the shipped simulated instrument, its runs in `runs`, no worker.
    fn service(runs: &Path) -> Arc<Service> {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/instrument/sim.toml");
        let mut text = std::fs::read_to_string(&path).unwrap();
        text.push_str(&format!("\n[api]\nruns-dir = \"{}\"\n", runs.display()));
        Service::open(TomlSource::from_text(path, text), None).unwrap()
    }

    /// Run `id` as the pipeline leaves it when it stops at a checkpoint: its state
    /// (`state`) written, still the worker's current run; the worker takes it back
    /// after `delay`.
    fn stopping(
        svc: &Arc<Service>,
        id: &str,
        state: RunState,
        delay: Duration,
    ) -> std::thread::JoinHandle<()> {
        svc.set_state(id, state, None).unwrap();
        let control = Control::new();
        svc.lock().current = Some((id.to_owned(), control));
        let svc = Arc::clone(svc);
        std::thread::spawn(move || {
            std::thread::sleep(delay);
            let mut s = svc.lock();
            s.current = None;
            svc.wake.notify_all();
        })
    }

    #[test]
    fn a_run_paused_at_its_checkpoint_resumes_and_aborts_while_the_worker_lets_it_go() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let plan = include_str!("../../../tests/data/plans/small-fbp.toml");
        let id = svc.submit(plan.to_owned()).unwrap().id;
        // Resume in the gap: queued again, not refused as running.
        let worker = stopping(&svc, &id, RunState::Paused, Duration::from_millis(100));
        let st = svc.resume(&id).unwrap();
        assert_eq!(st.state, RunState::Queued);
        worker.join().unwrap();
        // Abort in the gap: the paused run is aborted, not left paused.
        let worker = stopping(&svc, &id, RunState::Paused, Duration::from_millis(100));
        let st = svc.abort(&id).unwrap();
        assert_eq!(st.state, RunState::Aborted);
        worker.join().unwrap();
        // A run still running is refused at once, whatever the worker does.
        let id = svc.submit(plan.to_owned()).unwrap().id;
        let worker = stopping(&svc, &id, RunState::Running, Duration::from_millis(300));
        let t = Instant::now();
        assert!(matches!(svc.resume(&id), Err(ServiceError::Conflict(_))));
        assert!(t.elapsed() < Duration::from_millis(250));
        worker.join().unwrap();
    }
}

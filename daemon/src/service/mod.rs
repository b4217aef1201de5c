//! The run service: the run queue (persisted in `RUNS_DIR/queue.json`), the worker
//! thread that owns the instrument and runs one plan at a time, the e-stop, and the
//! live state that the HTTP API and the CLI read. It knows the devices only through
//! their backend ([`DeviceBackend`]), and nothing of HTTP: `crate::api` is the HTTP
//! face of it.
//!
//! | file | what it holds |
//! |---|---|
//! | `mod.rs` | the [`Service`], its shared state, opening (restoring the queue), shutdown |
//! | `queue.rs` | submit, check, list, status, pause, resume, abort |
//! | `estop.rs` | the e-stop and its report |
//! | `status.rs` | the instrument's status, run geometry, downloads, event subscriptions |
//! | `worker.rs` | the worker thread, a run's execution and its event forwarding |
//! | `ops.rs` | reorder, move, batch, run again, the queue lock, annotations; the catalogue's indexer and the audit trail |
//!
//! Everything here is synchronous and quick (a mutex held for microseconds, small file
//! writes); the HTTP handlers call the slower parts through `spawn_blocking`. Runs
//! execute on the dedicated worker thread, never on the async runtime.
use std::collections::{HashMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::sync::broadcast;
use utoipa::ToSchema;

use crate::config::{InstrumentConfig, TomlSource};
use crate::devices::DeviceBackend;
use crate::events::{EventSink, RunEvent};
use crate::pipeline::{self, Control, PipelineError, Run};
use crate::plan::Plan;
use crate::run_dir::{RunDir, file};
use crate::run_dir::{RunInfo, RunState};
use crate::store::write_atomic;
use periscope_drivers::{EmergencyOff, EmergencyPark};

mod estop;
mod import;
mod ops;
mod queue;
mod status;
mod worker;

pub use estop::EstopReport;
pub use import::{ImportTicket, MAX_FILE_NAME, STAGING_DIR, Upload, stored_name};
pub use ops::{LOCK_FILE, QueueLock, QueueView};
use queue::hold_interrupted;
pub use status::{
    GEOMETRY_POINTS, Geometry, InstrumentStatus, RUN_STALE_S, ReadingAge, RunStage, Safety, VolumeBox,
};

/// The queue file in the runs directory.
pub const QUEUE_FILE: &str = "queue.json";

/// Pair and LOS-point events are forwarded to event-stream clients at most this often
/// (plus the last one); stage, optimiser and output events always are.
const PAIR_EVENT_INTERVAL: Duration = Duration::from_millis(50);

/// Events buffered per run for slow stream clients before they are told they lagged.
pub const EVENT_BUFFER: usize = 1024;

/// Events queued from a run to its forwarder thread at most (a few MB of histograms).
const EVENT_QUEUE: usize = 4096;

/// Bytes of display-only events (a fit's snapshots, histograms, safety readings) the
/// event streams may hold for clients that have not read them yet, over every run:
/// past it they are not sent until clients catch up (the next one goes out then). The
/// events a display cannot do without (stages, progress, epochs, outputs) are always
/// sent, and the ring of [`EVENT_BUFFER`] bounds them.
pub const STREAM_DISPLAY_BYTES: usize = 16 << 20;

/// An event as sent to stream clients: its name and JSON.
#[derive(Clone, Debug)]
pub struct StreamEvent {
    /// The SSE event name: the event's `event` field (`stage-started`, `pair`,
    /// `epoch`, `output`, ...).
    pub name: Arc<str>,
    /// The event as JSON.
    pub json: Arc<HeldJson>,
}

/// An event's JSON, counted in the service's stream bytes until the last client has
/// read it (or the ring has dropped it).
#[derive(Debug)]
pub struct HeldJson {
    text: Box<str>,
    held: Arc<AtomicUsize>,
}

impl HeldJson {
    /// `text`, counted in `held` while it lives.
    fn new(text: String, held: &Arc<AtomicUsize>) -> HeldJson {
        held.fetch_add(text.len(), Ordering::Relaxed);
        HeldJson {
            text: text.into(),
            held: Arc::clone(held),
        }
    }
}

impl std::ops::Deref for HeldJson {
    type Target = str;

    fn deref(&self) -> &str {
        &self.text
    }
}

impl Drop for HeldJson {
    fn drop(&mut self) {
        self.held.fetch_sub(self.text.len(), Ordering::Relaxed);
    }
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
    /// Last optimiser loss while fitting; the final loss once completed (method gtr).
    pub loss: Option<f64>,
    /// Last error.
    pub error: Option<String>,
    /// Seconds per finished stage.
    pub timings: Vec<(String, f64)>,
    /// Files available for download.
    pub files: Vec<String>,
    /// The capture file an imported capture's run reconstructs (`POST /imports`);
    /// absent for a capture run.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub imported: Option<String>,
}

/// Why a request on a run was refused. Each variant keeps the error it came from, and
/// the API's status code follows the kind (`crate::api::ApiError::from`).
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
    /// Another daemon serves this runs directory.
    #[error(
        "another Periscope daemon serves {}: one daemon per runs directory (stop that one, or give this one another [api] runs-dir)",
        .0.display()
    )]
    RunsDirInUse(PathBuf),
    /// The plan needs more memory or disk than the instrument's budget allows.
    #[error("{0}")]
    OverBudget(String),
    /// The request's values are not acceptable (a tag, an order, a lock key).
    #[error("{0}")]
    Invalid(String),
    /// The queue is locked for maintenance.
    #[error("{0}")]
    Locked(String),
    /// The work asked for is already under way for another request; retry shortly.
    #[error("{0}")]
    Busy(String),
    /// An import's upload is not a capture, or its settings are invalid.
    #[error("{0}")]
    InvalidImport(String),
    /// The run catalogue failed.
    #[error(transparent)]
    Catalogue(#[from] crate::catalogue::CatalogueError),
}

impl ServiceError {
    /// A storage error on `path`.
    fn storage(path: impl Into<PathBuf>) -> impl FnOnce(std::io::Error) -> ServiceError {
        let path = path.into();
        move |source| ServiceError::Storage { path, source }
    }
}

/// A key the request asks for that does not fit the keys there is the request's fault
/// (422); a keys file that cannot be read or written is the daemon's (500 `storage`).
impl From<crate::access::KeysError> for ServiceError {
    fn from(e: crate::access::KeysError) -> ServiceError {
        match e {
            crate::access::KeysError::Io { path, source } => ServiceError::Storage { path, source },
            crate::access::KeysError::Invalid(m) => ServiceError::Invalid(m),
        }
    }
}

/// A run file to send: small ones in memory, the rest streamed from disk.
#[derive(Debug)]
pub enum Download {
    /// The whole body.
    Bytes(Vec<u8>),
    /// A regular file, served from disk with its validators.
    Path(PathBuf),
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
    /// Photon counts since the capture (re)started, for the counts-rate metric.
    counts: u64,
    loss: Option<f64>,
    /// The laser as the run last read it, and when.
    laser: Option<(periscope_drivers::LaserState, Instant, f64)>,
    /// The arms' angles (degrees), the signal rate (counts/s) and the pair index of
    /// the run's latest histogram, and when it arrived.
    histogram: Option<LiveHistogram>,
    /// The run reconstructs an imported capture: it holds no device.
    import: bool,
}

/// What the live safety bar takes from a run's latest histogram.
#[derive(Clone, Copy, Debug)]
struct LiveHistogram {
    laser_deg: [f64; 2],
    spad_deg: [f64; 2],
    signal_rate: f64,
    pair: usize,
    at: Instant,
}

struct Shared {
    /// Run ids waiting or paused, in submission order.
    queue: VecDeque<String>,
    /// The running run and its control.
    current: Option<(String, Control)>,
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
    /// E-stops that have held the queue so far: a submission notes it when it reserves
    /// its place and is held too if another has held the queue before the run is
    /// queued ([`Service::queue_admitted`]).
    estop_holds: u64,
    /// Queued runs an e-stop held (as `paused` in their run.json, where the store
    /// lets it): the worker skips them whatever their run.json says, until an operator
    /// resumes or aborts them, so a hold the disk refused still holds.
    held: std::collections::HashSet<String>,
    /// Runs whose end neither the pipeline nor the worker could record: their run.json
    /// still reads queued or running though nothing works on them. Resume and abort
    /// take them as failed (a `running` run.json of any other run is left alone: it
    /// may be a `periscope run` of another process in the same directory).
    stale: std::collections::HashSet<String>,
    /// The queue's maintenance lock (`queue-lock.json` while held).
    lock: Option<QueueLock>,
    shutdown: bool,
}

/// The running run's stop path ([`Service::direct`]).
#[derive(Default)]
struct Direct {
    /// The running run and its control (as `Shared::current`, set and cleared with it).
    run: Option<(String, Control)>,
    /// The running run's direct way to its laser, once its devices are open.
    laser_off: Option<EmergencyOff>,
    /// The running run's direct way to park its arms (laser arm, SPAD arm), once its
    /// devices are open.
    park: Option<[EmergencyPark; 2]>,
    /// The running run reconstructs an imported capture: it holds no device, so an
    /// e-stop opens the laser controller at once, as with no run.
    import: bool,
}

/// The service: configuration, queue and worker.
pub struct Service {
    runs_dir: PathBuf,
    instrument_src: TomlSource,
    instrument: InstrumentConfig,
    /// The way to the devices, kept for the daemon's life so that runs, e-stops and
    /// status readings all reach the same devices (one simulated instrument, for
    /// `sim`).
    backend: Arc<dyn DeviceBackend>,
    /// The API keys (and the daemon's single token, as an admin key).
    keys: crate::access::KeyStore,
    /// The run catalogue and audit trail.
    catalogue: Arc<crate::catalogue::Catalogue>,
    /// The catalogue's indexer thread's queue ([`Service::touch`]).
    indexer: Mutex<Option<std::sync::mpsc::Sender<String>>>,
    /// Counters and histograms for `/metrics`.
    metrics: crate::metrics::Metrics,
    /// The catalogue's lock, held shared for the service's life (no rebuild under it).
    _catalogue_hold: std::fs::File,
    /// This daemon's hold on its runs directory (one daemon a runs directory).
    _runs_hold: crate::run_dir::RunHold,
    shared: Mutex<Shared>,
    wake: Condvar,
    /// E-stops under way: the worker starts no run while one parks the arms and
    /// switches the laser off (it opens the devices a run would take).
    estops: std::sync::atomic::AtomicUsize,
    /// The running run's stop path, apart from `shared`, whose holders write files
    /// (fsyncs, on a disk that may stall): the e-stop, the signal thread and shutdown
    /// reach the laser without waiting for them.
    direct: Mutex<Direct>,
    /// Bytes of event JSON the event streams hold for clients yet to read them.
    stream_bytes: Arc<AtomicUsize>,
    /// Of which display-only events may hold at most this many
    /// ([`STREAM_DISPLAY_BYTES`]; tests set less).
    stream_display_budget: AtomicUsize,
    /// Held while a capture export is written.
    exporting: Mutex<()>,
    /// The geometry of the runs viewed last, each with the stamps of the files it was
    /// made from, so a view polled by many clients does not read a run's whole pair
    /// list again each time.
    geometries: Mutex<status::GeometryCache>,
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
        let backend = crate::devices::backend(&instrument)?;
        let runs_dir = instrument.api.runs_dir.clone();
        std::fs::create_dir_all(&runs_dir).map_err(ServiceError::storage(&runs_dir))?;
        // One daemon per runs directory: a second would rewrite queue.json under the
        // first and take its running run for an interrupted one.
        let runs_hold = match crate::run_dir::RunHold::take(&runs_dir) {
            Ok(Some(h)) => h,
            Ok(None) => return Err(ServiceError::RunsDirInUse(runs_dir)),
            Err(e) => return Err(ServiceError::storage(&runs_dir)(e)),
        };
        Service::clear_staging(&runs_dir);
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
                if crate::run_dir::RunHold::held(&dir) {
                    tracing::warn!(
                        "run {id} is being written by another Periscope process (`periscope run` or `resume`); left out of the queue, and left as it is"
                    );
                    continue;
                }
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
            // A `periscope run` under way in this runs directory is that process's (asked
            // of run directories only: never a lock on the daemon's own files).
            .filter(|id| !crate::run_dir::RunHold::held(&runs_dir.join(id)))
            .collect();
        orphans.sort();
        let lock_path = runs_dir.join(LOCK_FILE);
        let lock = match std::fs::read_to_string(&lock_path) {
            Ok(text) => Some(serde_json::from_str::<QueueLock>(&text).unwrap_or_else(|e| {
                // A damaged lock file still locks: maintenance was going on.
                tracing::warn!(
                    "{}: {e}; the queue stays locked (unlock it with force)",
                    lock_path.display()
                );
                QueueLock {
                    by: "unknown".into(),
                    reason: format!("{} could not be read", lock_path.display()),
                    since_unix_s: 0.0,
                    key_sha256: String::new(),
                }
            })),
            Err(_) => None,
        };
        // The hold first: a `periscope catalogue rebuild` under way (it holds the lock
        // exclusively while it replaces the file) finishes before the daemon opens the
        // catalogue, so the daemon never keeps a connection to the file it replaced.
        let catalogue_hold = crate::catalogue::hold(&runs_dir)
            .map_err(ServiceError::storage(runs_dir.join(crate::catalogue::LOCK_FILE)))?;
        let catalogue = Arc::new(crate::catalogue::Catalogue::open_unsynced(&runs_dir)?);
        let keys = crate::access::KeyStore::open(&runs_dir, token);
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
            backend,
            keys,
            catalogue,
            indexer: Mutex::new(None),
            metrics: crate::metrics::Metrics::new(),
            stream_bytes: Arc::new(AtomicUsize::new(0)),
            stream_display_budget: AtomicUsize::new(STREAM_DISPLAY_BYTES),
            _catalogue_hold: catalogue_hold,
            _runs_hold: runs_hold,
            shared: Mutex::new(Shared {
                queue,
                current: None,
                live: Live::default(),
                channels: HashMap::new(),
                last_safe: None,
                reading: None,
                refresh: true,
                admitting: 0,
                estop_holds: 0,
                held: Default::default(),
                stale: Default::default(),
                lock,
                shutdown: false,
            }),
            wake: Condvar::new(),
            estops: std::sync::atomic::AtomicUsize::new(0),
            direct: Mutex::new(Direct::default()),
            exporting: Mutex::new(()),
            geometries: Mutex::default(),
            devices: Mutex::new(()),
        });
        service.persist(&service.lock())?;
        service.start_indexer();
        Ok(service)
    }

    /// Shuts down: the running run's laser off at once through its direct path, the
    /// run paused at its next checkpoint (so it resumes after a restart), every event
    /// stream ended, and the worker told to stop.
    pub fn shutdown(&self) {
        // Through the stop path's own lock, not under the service's (which a request
        // writing files may hold for a while): the run told to pause first (so a
        // `LASER ON` the latched switch refuses reads as the pause), then its laser off.
        let (running, off) = {
            let d = self.direct();
            (d.run.clone(), d.laser_off.clone())
        };
        if let Some((_, control)) = &running {
            control.pause_by("shutdown");
        }
        if let Some(off) = off
            && let Err(e) = off.laser_off()
        {
            tracing::warn!(error = %e, "shutdown: direct laser off failed; the run switches it off at its checkpoint");
        }
        let mut s = self.lock();
        s.shutdown = true;
        // A run the worker took since.
        if let Some((id, control)) = &s.current
            && running.as_ref().is_none_or(|(r, _)| r != id)
        {
            control.pause_by("shutdown");
        }
        // Dropping the senders ends every event stream after what it has buffered.
        s.channels.clear();
        // And the catalogue's indexer ends after what it was told of.
        *self.indexer.lock().unwrap_or_else(|p| p.into_inner()) = None;
        self.wake.notify_all();
    }

    /// Whether [`Service::shutdown`] was called.
    pub fn is_shut_down(&self) -> bool {
        self.lock().shutdown
    }

    /// The way to the devices (tests reach the simulated instrument through it:
    /// `devices::sim::rig_of`).
    pub fn backend(&self) -> &dyn DeviceBackend {
        self.backend.as_ref()
    }

    /// Testing aid (fault injection): the running run panics at its next checkpoint
    /// in `stage` (see [`Control::inject_panic`]). Returns whether a run was running.
    /// Built only with the `test-hooks` feature.
    #[cfg(feature = "test-hooks")]
    pub fn inject_panic(&self, stage: crate::events::Stage) -> bool {
        let s = self.lock();
        s.current.as_ref().map(|(_, c)| c.inject_panic(stage)).is_some()
    }

    /// Bytes of event JSON the event streams hold now for clients yet to read them.
    pub fn stream_bytes(&self) -> usize {
        self.stream_bytes.load(Ordering::Relaxed)
    }

    /// Testing aid: display-only events are held back past `bytes` of held events
    /// instead of [`STREAM_DISPLAY_BYTES`]. Built only with the `test-hooks` feature.
    #[cfg(feature = "test-hooks")]
    pub fn set_stream_display_budget(&self, bytes: usize) {
        self.stream_display_budget.store(bytes, Ordering::Relaxed);
    }

    /// Testing aid (fault injection): the running run hangs at its next checkpoint in
    /// `stage` for `duration` (see [`Control::inject_hang`]). Returns whether a run
    /// was running. Built only with the `test-hooks` feature.
    #[cfg(feature = "test-hooks")]
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

    /// The stop path's lock: held for a clone or an assignment, never while another
    /// lock is taken or a file written.
    fn direct(&self) -> MutexGuard<'_, Direct> {
        self.direct.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Sets (or clears) the running run, in `s` and in the stop path.
    fn set_current(&self, s: &mut Shared, run: Option<(String, Control)>) {
        let mut d = self.direct();
        if run.is_none() {
            d.laser_off = None;
            d.park = None;
            d.import = false;
        }
        d.run.clone_from(&run);
        s.current = run;
    }

    /// The instrument config.
    pub fn instrument(&self) -> &InstrumentConfig {
        &self.instrument
    }

    /// The runs directory.
    pub fn runs_dir(&self) -> &Path {
        &self.runs_dir
    }
}

pub use crate::run_dir::state_name;

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
        svc.set_state(id, state, None, "test").unwrap();
        let control = Control::new();
        svc.set_current(&mut svc.lock(), Some((id.to_owned(), control)));
        let svc = Arc::clone(svc);
        std::thread::spawn(move || {
            std::thread::sleep(delay);
            svc.set_current(&mut svc.lock(), None);
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

    /// Run `id` running under `control`, which has taken its stop, and the pipeline's
    /// wind-down on a thread: its state written paused by `by` after 100 ms, the run
    /// handed back 50 ms after that.
    fn winding_down_to_paused(
        svc: &Arc<Service>,
        id: &str,
        control: Control,
        by: &'static str,
    ) -> std::thread::JoinHandle<()> {
        svc.set_state(id, RunState::Running, None, "test").unwrap();
        svc.set_current(&mut svc.lock(), Some((id.to_owned(), control)));
        let (svc, id) = (Arc::clone(svc), id.to_owned());
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(100));
            svc.set_state(&id, RunState::Paused, None, by).unwrap();
            std::thread::sleep(Duration::from_millis(50));
            svc.set_current(&mut svc.lock(), None);
            svc.wake.notify_all();
        })
    }

    /// A run that has taken a pause at its checkpoint still reads `running` while it
    /// makes the instrument safe; an abort then waits for the paused run and aborts it.
    /// Until 2026-12-07 it was answered as under way and lost: the run stopped paused.
    #[test]
    fn an_abort_while_a_run_winds_down_to_its_pause_aborts_the_paused_run() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let plan = include_str!("../../../tests/data/plans/small-fbp.toml");
        let id = svc.submit(plan.to_owned()).unwrap().id;
        let control = Control::new();
        assert!(control.pause_by("alice"));
        assert!(control.check(crate::events::Stage::Capture, 4).is_err());
        let worker = winding_down_to_paused(&svc, &id, control, "alice");
        let st = svc.abort_as(&id, "bob").unwrap();
        worker.join().unwrap();
        assert_eq!(st.state, RunState::Aborted);
        let info = crate::run_dir::RunInfo::load(&svc.dir(&id).unwrap()).unwrap();
        let by: Vec<_> = info
            .history
            .iter()
            .map(|c| (state_name(c.state), c.by.clone().unwrap_or_default()))
            .collect();
        assert_eq!(
            by[by.len() - 2..],
            [("paused", "alice".to_owned()), ("aborted", "bob".to_owned())],
            "{by:?}"
        );
    }

    /// The same for a run that stopped for a reason of its own (a suspension, a device
    /// error) and winds down to paused: the abort waits for it and aborts the stored
    /// run, which leaves the queue. Until 2026-12-08 it was answered as under way and
    /// the run stayed paused and queued, to be resumed.
    #[test]
    fn an_abort_while_a_run_winds_down_from_a_stop_of_its_own_aborts_the_stored_run() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let plan = include_str!("../../../tests/data/plans/small-fbp.toml");
        let id = svc.submit(plan.to_owned()).unwrap().id;
        let control = Control::new();
        assert_eq!(control.take_stop(), crate::pipeline::Request::Run);
        let worker = winding_down_to_paused(&svc, &id, control, "interlock");
        let st = svc.abort_as(&id, "bob").unwrap();
        worker.join().unwrap();
        assert_eq!(st.state, RunState::Aborted);
        assert!(!svc.queue().order.contains(&id), "{:?}", svc.queue().order);
    }

    /// A submission whose place was reserved before an e-stop and which reaches the
    /// queue after it (its run already `queued` on disk when the e-stop held the
    /// queue) is held as the e-stop held the others, not started right after it.
    #[test]
    fn a_submission_in_flight_during_an_estop_is_held() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let text = include_str!("../../../tests/data/plans/small-fbp.toml");
        let src = TomlSource::from_text("request body", text.to_owned());
        let plan = crate::plan::Plan::from_source(&src, &svc.instrument).unwrap();
        let seen = svc.reserve_place().unwrap();
        let id = svc.admit(&src, &plan, "alice", None).unwrap();
        svc.estop().unwrap();
        let held = {
            let mut s = svc.lock();
            s.admitting -= 1;
            svc.queue_admitted(&mut s, &id, seen)
        };
        assert!(held);
        assert!(svc.lock().held.contains(&id));
        assert_eq!(svc.status(&id).unwrap().state, RunState::Paused);
        // One submitted after the e-stop is queued as usual.
        let after = svc.submit(text.to_owned()).unwrap();
        assert_eq!(after.state, RunState::Queued);
        assert!(!svc.lock().held.contains(&after.id));
    }

    #[test]
    fn a_capture_export_under_way_answers_a_second_one_busy_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let plan = include_str!("../../../tests/data/plans/small-fbp.toml");
        let id = svc.submit(plan.to_owned()).unwrap().id;
        let run = svc.dir(&id).unwrap();
        let one = svc.exporting.lock().unwrap();
        let t = Instant::now();
        assert!(matches!(
            svc.export_capture(&id, &run),
            Err(ServiceError::Busy(_))
        ));
        assert!(t.elapsed() < Duration::from_millis(100));
        drop(one);
        // Free again, it is judged on the run: a queued run has nothing to export.
        assert!(matches!(
            svc.export_capture(&id, &run),
            Err(ServiceError::Conflict(_))
        ));
    }

    #[test]
    fn a_runs_geometry_is_kept_until_its_files_change() {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path());
        let plan = include_str!("../../../tests/data/plans/small-fbp.toml");
        let ids: Vec<String> = (0..=status::GEOMETRY_CACHE)
            .map(|_| svc.submit(plan.to_owned()).unwrap().id)
            .collect();
        let g = svc.geometry(&ids[0]).unwrap();
        assert_eq!((g.pairs, g.illumination.len()), (0, 0));
        // The run plans: its pairs appear, not the geometry kept from before.
        let pair = |x: f64| crate::plan::PlannedPair {
            xi: glam::DVec3::new(x, 0.0, 0.0),
            ni: glam::DVec3::Z,
            xd: glam::DVec3::new(0.0, x, 0.0),
            nd: glam::DVec3::Z,
            laser: periscope_drivers::OpticalAngles { x: 0.0, y: 0.0 },
            spad: periscope_drivers::OpticalAngles { x: 0.0, y: 0.0 },
        };
        let pairs = svc.dir(&ids[0]).unwrap().join(crate::run_dir::file::PAIRS);
        std::fs::write(&pairs, serde_json::to_vec(&[pair(0.1), pair(0.2)]).unwrap()).unwrap();
        let g = svc.geometry(&ids[0]).unwrap();
        assert_eq!((g.pairs, g.illumination.len(), g.detection.len()), (2, 2, 2));
        // Kept while the file stands: a read of it again would fail on this.
        let stamp = std::fs::metadata(&pairs).unwrap().modified().unwrap();
        let same_length = vec![b' '; std::fs::metadata(&pairs).unwrap().len() as usize];
        std::fs::write(&pairs, &same_length).unwrap();
        std::fs::File::options()
            .write(true)
            .open(&pairs)
            .unwrap()
            .set_modified(stamp)
            .unwrap();
        assert_eq!(svc.geometry(&ids[0]).unwrap().pairs, 2);
        // At most GEOMETRY_CACHE runs are kept: viewing the others drops the first.
        for id in &ids[1..] {
            svc.geometry(id).unwrap();
        }
        assert!(matches!(svc.geometry(&ids[0]), Err(ServiceError::RunFiles(_))));
    }
}

//! The capture pipeline: LOS scan → relay → pair plan → NLOS acquisition (stored and
//! streamed to the 3D-GTR optimiser, which starts before the capture ends) →
//! reconstruction → outputs, in a run directory that a crash never corrupts and
//! `periscope resume` continues.
//!
//! Everything here is blocking: device I/O and compute run on the calling thread and a
//! trainer thread, never on an async runtime (the HTTP server calls this from
//! `spawn_blocking`).
mod acquisition;
mod los;
mod output;
mod reconstruct;
mod safety;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use periscope_drivers::{DeviceError, EmergencyOff};
use periscope_recon::gtr::CancelToken;

use crate::run_dir::{RunDir, file};

pub use crate::record::{record_axis, record_counts, record_transient, undo_pile_up};
pub use crate::run_dir::{RelayPoint, parse_relay_ply, read_relay_ply};
pub use crate::signals::panic_message;
pub use los::{first_bounce_range, peak};
pub use output::{RELAY_PLY, RunOutputs, write_outputs};
pub use reconstruct::{MAX_VIRTUAL_RESOLUTION, ReconInput, ReconResult, reconstruct};

use crate::capture::RunCapture;
use crate::config::{ConfigError, InstrumentConfig, TomlSource};
use crate::devices::{DeviceBackend, Devices, OpenError};
use crate::events::{EventSink, RunEvent, Stage};
use crate::plan::{Plan, PlannedPair};
use crate::run_dir::{RunInfo, RunState};

/// Why the relay surface could not be extracted from the LOS scan.
#[derive(Debug, thiserror::Error)]
pub enum RelayError {
    /// Too few LOS points passed the plan's relay thresholds.
    #[error(
        "only {kept} of {total} LOS points passed relay.depth-m {depth:?} and relay.min-intensity {min_intensity}: widen them, or check that los.angles-deg covers the relay"
    )]
    TooFewPoints {
        /// Points kept.
        kept: usize,
        /// Points scanned.
        total: usize,
        /// The depth window, metres.
        depth: [f64; 2],
        /// The intensity floor, a fraction of the brightest return.
        min_intensity: f64,
    },
    /// Outlier rejection or normal estimation failed on the points kept.
    #[error(transparent)]
    Geometry(#[from] periscope_recon::relay::GeometryError),
}

/// Why a reconstruction failed, with the recon crate's own error as its source.
#[derive(Debug, thiserror::Error)]
pub enum ReconError {
    /// Transients or their time axis were rejected.
    #[error(transparent)]
    Transient(#[from] periscope_recon::TransientError),
    /// The 3D-GTR fit failed.
    #[error(transparent)]
    Train(#[from] periscope_recon::gtr::TrainError),
    /// A solver failed or does not suit the data.
    #[error(transparent)]
    Solver(#[from] periscope_recon::solver::SolverError),
    /// The virtual relay could not be built.
    #[error(transparent)]
    Geometry(#[from] periscope_recon::relay::GeometryError),
    /// The volume is not a box.
    #[error(transparent)]
    Roi(#[from] periscope_recon::RoiError),
    /// An output file could not be written.
    #[error("{}: {source}", path.display())]
    Output {
        /// The file.
        path: PathBuf,
        /// Why.
        source: periscope_recon::io::IoError,
    },
    /// There is nothing to reconstruct.
    #[error("no transients to reconstruct from")]
    Empty,
    /// The solver produced a volume with a value that is not finite (data whose scale
    /// overflows the arithmetic): nothing is written.
    #[error(
        "the reconstructed volume has a value that is not finite ({value} at voxel {index}); nothing \
         was written: check the capture's counts (a huge or degenerate scale) and report it"
    )]
    NotFinite {
        /// The first such voxel (C order).
        index: usize,
        /// Its value.
        value: f32,
    },
    /// The optimiser thread could not start or panicked.
    #[error("the optimiser thread {0}")]
    Thread(String),
}

impl ReconError {
    /// Whether the error is the user's to fix by choosing another method or other
    /// settings (the data do not suit the solver, a setting is out of range, no pair
    /// sees the volume, the arrays would exceed the memory cap, no plane fits the relay
    /// points for 3D-GTR's virtual scan), as against a failure of the run itself. The
    /// CLI exits with 2 for these, as for any other configuration error.
    pub fn is_settings(&self) -> bool {
        use periscope_recon::gtr::TrainError;
        use periscope_recon::relay::GeometryError;
        use periscope_recon::solver::SolverError;
        match self {
            ReconError::Solver(e) => !matches!(e, SolverError::Volume(_)),
            ReconError::Train(e) => matches!(
                e,
                TrainError::Config(_) | TrainError::NothingVisible | TrainError::NegativeTotal { .. }
            ),
            ReconError::Geometry(e) => matches!(e, GeometryError::NoPlane { .. }),
            ReconError::Roi(_) | ReconError::Empty => true,
            ReconError::Transient(_)
            | ReconError::Output { .. }
            | ReconError::Thread(_)
            | ReconError::NotFinite { .. } => false,
        }
    }
}

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// A config or plan is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The devices could not be opened.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// A device failed (a galvo controller, the laser, the histogrammer).
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The relay could not be extracted.
    #[error("relay: {0}")]
    Relay(#[from] RelayError),
    /// No pair could be planned: the plan's relay regions and pair grid, with the
    /// galvo limits, leave none.
    #[error(
        "pair planning: no pair could be planned from {relay_points} relay points ({unreachable} outside the galvo limits): check relay.illumination, relay.detection and the pairs grid"
    )]
    NoPairs {
        /// Relay points there were.
        relay_points: usize,
        /// Pairs outside the galvo limits.
        unreachable: usize,
    },
    /// The run's y-tal capture could not be written.
    #[error("{}: capture export: {source}", path.display())]
    Export {
        /// The capture file.
        path: PathBuf,
        /// Why.
        source: crate::ytal::ExportError,
    },
    /// Reconstruction failed.
    #[error("reconstruction: {0}")]
    Recon(#[from] ReconError),
    /// The run directory could not be written or read.
    #[error("run directory {path}: {source}")]
    Storage {
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The operator aborted the run (captured data is kept).
    #[error("the run was aborted; the {0} pairs captured so far are kept")]
    Aborted(usize),
    /// The operator paused the run; `periscope resume` continues it.
    #[error("the run was paused after {0} pairs; resume it to continue")]
    Paused(usize),
    /// A suspender tripped and the plan leaves resuming to the operator.
    #[error(
        "{reason}: the laser is off and the run paused after {pairs} pairs; resume it when the condition has cleared"
    )]
    Suspended {
        /// What tripped.
        reason: String,
        /// Pairs stored.
        pairs: usize,
    },
    /// A bug: code in the pipeline panicked. The instrument was made safe and the
    /// data kept; the run can be resumed.
    #[error(
        "internal error in stage {stage}: {message}; the instrument was made safe and the data kept (resume continues the run; please report this)"
    )]
    Panicked {
        /// The stage it happened in.
        stage: &'static str,
        /// The panic's message.
        message: String,
    },
}

impl From<crate::run_dir::RunDirError> for PipelineError {
    fn from(e: crate::run_dir::RunDirError) -> PipelineError {
        match e {
            crate::run_dir::RunDirError::Io { path, source } => PipelineError::Storage { path, source },
            crate::run_dir::RunDirError::Config(c) => PipelineError::Config(c),
        }
    }
}

impl PipelineError {
    pub(crate) fn storage(path: &Path, source: std::io::Error) -> PipelineError {
        PipelineError::Storage {
            path: path.to_owned(),
            source,
        }
    }
}

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
    fn record_made_safe(&self, result: Result<(), String>) {
        *self.0.made_safe.lock().unwrap_or_else(|p| p.into_inner()) = Some(result);
    }
    /// Asks the run to pause at the next checkpoint.
    pub fn pause(&self) {
        let _ = self
            .0
            .state
            .compare_exchange(Self::RUN, Self::PAUSE, Ordering::SeqCst, Ordering::SeqCst);
        self.cancel_optimisers();
    }
    /// Asks the run to abort at the next checkpoint.
    pub fn abort(&self) {
        self.0.state.store(Self::ABORT, Ordering::SeqCst);
        self.cancel_optimisers();
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
        if self.stopping() {
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
    /// The error a checkpoint returns for the current request, if any.
    pub(crate) fn check(&self, stage: Stage, pairs: usize) -> Result<(), PipelineError> {
        #[cfg(feature = "test-hooks")]
        self.injected_faults(stage);
        // Only the injected faults depend on the stage.
        #[cfg(not(feature = "test-hooks"))]
        let _ = stage;
        self.beat();
        match self.requested() {
            Request::Run => Ok(()),
            Request::Pause => Err(PipelineError::Paused(pairs)),
            Request::Abort => Err(PipelineError::Aborted(pairs)),
        }
    }
}

/// A run in progress.
pub struct Run {
    dir: PathBuf,
    plan: Plan,
    instrument: InstrumentConfig,
    devices: Devices,
    events: EventSink,
    info: RunInfo,
    control: Control,
    /// The stage in progress (for checkpoints and panic reports).
    stage: Stage,
}

/// The result of a finished run.
#[derive(Clone, Debug)]
pub struct RunSummary {
    /// The run directory.
    pub dir: PathBuf,
    /// Seconds per stage.
    pub timings: Vec<(String, f64)>,
    /// Pairs measured.
    pub pairs: usize,
    /// Outputs and reconstruction statistics.
    pub outputs: RunOutputs,
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> Result<(), PipelineError> {
    let path = dir.join(name);
    crate::store::write_atomic(&path, bytes).map_err(|e| PipelineError::storage(&path, e))
}

/// Starts a new run of `plan` on `instrument`: creates the run directory (under
/// `runs/` unless `out` is given) with the plan and instrument config as provenance.
pub fn prepare(
    plan_src: &TomlSource,
    instrument_src: &TomlSource,
    out: Option<&Path>,
) -> Result<(PathBuf, Plan, InstrumentConfig), PipelineError> {
    let instrument = InstrumentConfig::from_source(instrument_src)?;
    let plan = Plan::from_source(plan_src, &instrument)?;
    crate::budget::Budget::of_plan(&plan)
        .check(&instrument.budget)
        .map_err(|m| PipelineError::Config(plan_src.invalid("pairs", m)))?;
    let dir = match out {
        Some(dir) => {
            std::fs::create_dir_all(dir).map_err(|e| PipelineError::storage(dir, e))?;
            if RunDir::holds_run(dir) {
                return Err(PipelineError::storage(
                    dir,
                    std::io::Error::new(
                        std::io::ErrorKind::AlreadyExists,
                        "already holds a run: use `periscope resume` to continue it, or choose another --out",
                    ),
                ));
            }
            dir.to_owned()
        }
        None => crate::run_dir::new_run_dir(Path::new("runs"), &plan.name)
            .map_err(|e| PipelineError::storage(Path::new("runs"), e))?,
    };
    write(&dir, file::PLAN, plan_src.text().as_bytes())?;
    // The token stays in the process: the stored copy (served as a download) has it
    // cut out, and the service never reads it back from a run.
    write(
        &dir,
        file::INSTRUMENT,
        crate::config::redact_secrets(instrument_src.text()).as_bytes(),
    )?;
    let info = RunInfo {
        id: dir
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        plan: plan.name.clone(),
        state: RunState::Queued,
        stage: "queued".into(),
        instrument_path: std::path::absolute(instrument_src.path())
            .unwrap_or_else(|_| instrument_src.path().to_owned()),
        pairs_total: 0,
        pairs_done: 0,
        error: None,
        timings: Vec::new(),
    };
    info.save(&dir).map_err(|e| PipelineError::storage(&dir, e))?;
    Ok((dir, plan, instrument))
}

/// Records why a run stopped before its devices were open (a pause, an abort, a
/// device that would not open, a panic): the run stays resumable.
fn stopped_before_start(
    dir: &Path,
    info: &mut RunInfo,
    events: &EventSink,
    e: PipelineError,
) -> PipelineError {
    match &e {
        PipelineError::Paused(_) => info.state = RunState::Paused,
        PipelineError::Aborted(_) => info.state = RunState::Aborted,
        e => {
            info.state = RunState::Failed;
            info.error = Some(e.to_string());
            events.emit(RunEvent::Failed {
                message: e.to_string(),
            });
        }
    }
    if let Err(io) = info.save(dir) {
        tracing::error!(error = %io, "could not record the run's state in {}", dir.display());
    }
    e
}

/// Removes what atomic writes of an earlier process left in the run directory when it
/// was killed between writing a temporary file and renaming it
/// (`<name>.<pid>-<n>.tmp`, [`periscope_recon::io::temporary_beside`]): the file it was
/// replacing is intact, the temporary is garbage. Only this process's run holds the
/// directory now, so no other writer's temporary is touched.
fn remove_stale_temporaries(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.filter_map(Result::ok) {
        let name = entry.file_name().to_string_lossy().into_owned();
        let stale = name
            .strip_suffix(".tmp")
            .and_then(|s| s.rsplit_once('.'))
            .and_then(|(_, tag)| tag.split_once('-'))
            .is_some_and(|(pid, n)| {
                !pid.is_empty()
                    && !n.is_empty()
                    && pid.chars().all(|c| c.is_ascii_digit())
                    && n.chars().all(|c| c.is_ascii_digit())
                    && pid != std::process::id().to_string()
            });
        if stale && entry.file_type().is_ok_and(|t| t.is_file()) {
            match std::fs::remove_file(entry.path()) {
                Ok(()) => tracing::info!("removed {name}, left by an interrupted write"),
                Err(e) => tracing::warn!(error = %e, "could not remove {name}, left by an interrupted write"),
            }
        }
    }
}

impl Run {
    /// Opens the devices for a prepared (or interrupted) run: stage `opening`, which a
    /// pause or abort interrupts between devices. `backend` is the way to the devices
    /// (the run service keeps one for the daemon's life); `None` opens the backend the
    /// run's instrument config names (a fresh simulated instrument for `sim`).
    pub fn open(
        dir: &Path,
        control: Control,
        events: Option<EventSink>,
        backend: Option<&dyn DeviceBackend>,
    ) -> Result<Run, PipelineError> {
        let (mut info, plan, instrument) = RunDir::new(dir).load()?;
        remove_stale_temporaries(dir);
        let events = match events {
            Some(e) => e,
            None => EventSink::open(dir).map_err(|e| PipelineError::storage(dir, e))?,
        };
        info.stage = Stage::Opening.name().into();
        info.state = RunState::Running;
        if let Err(e) = info.save(dir) {
            // Recorded as failed (resumable) if the store lets it be, so the run is not
            // left looking queued or running with nothing working on it.
            return Err(stopped_before_start(
                dir,
                &mut info,
                &events,
                PipelineError::storage(dir, e),
            ));
        }
        events.emit(RunEvent::StageStarted {
            stage: Stage::Opening,
        });
        let pairs = info.pairs_done;
        let opened = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            control.check(Stage::Opening, pairs)?;
            let own;
            let backend = match backend {
                Some(b) => b,
                None => {
                    own = crate::devices::backend(&instrument)?;
                    own.as_ref()
                }
            };
            Devices::open(backend, &|| control.stopping()).map_err(|e| match e {
                OpenError::Interrupted => match control.check(Stage::Opening, pairs) {
                    Err(stop) => stop,
                    Ok(()) => PipelineError::Open(e),
                },
                e => PipelineError::Open(e),
            })
        }));
        let mut devices = match opened {
            Ok(Ok(devices)) => devices,
            Ok(Err(e)) => return Err(stopped_before_start(dir, &mut info, &events, e)),
            Err(payload) => {
                let e = PipelineError::Panicked {
                    stage: Stage::Opening.name(),
                    message: panic_message(payload.as_ref()),
                };
                return Err(stopped_before_start(dir, &mut info, &events, e));
            }
        };
        crate::signals::register_laser(devices.laser.emergency_off());
        // The laser's keepalive feeds the controller's watchdog only while this run
        // beats (at its checkpoints and stop polls): a run stuck with the laser on
        // loses it within `[laser] stall-ms` plus the watchdog's timeout.
        devices
            .laser
            .watch_progress(control.progress(instrument.laser.stall));
        Ok(Run {
            dir: dir.to_owned(),
            plan,
            instrument,
            devices,
            events,
            info,
            control,
            stage: Stage::Opening,
        })
    }

    /// A handle that switches this run's laser off from any thread, whatever the run
    /// is doing (the e-stop's and the signal handlers' direct path).
    pub fn emergency_off(&self) -> EmergencyOff {
        self.devices.laser.emergency_off()
    }

    /// A checkpoint: the pause or abort asked for, as the error that stops the run.
    pub(crate) fn checkpoint(&self) -> Result<(), PipelineError> {
        self.control.check(self.stage, self.info.pairs_done)
    }

    /// The event sink (to attach listeners).
    pub fn events(&self) -> &EventSink {
        &self.events
    }

    /// The run directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn settle_timeout(&self) -> Duration {
        (self
            .instrument
            .laser_arm
            .settle
            .max(self.instrument.spad_arm.settle)
            * 20)
            .max(Duration::from_millis(200))
    }

    fn set_stage(&mut self, stage: Stage) -> Result<(), PipelineError> {
        self.stage = stage;
        self.checkpoint()?;
        self.info.stage = stage.name().into();
        self.info.state = RunState::Running;
        self.save_info()?;
        self.events.emit(RunEvent::StageStarted { stage });
        Ok(())
    }

    fn save_info(&self) -> Result<(), PipelineError> {
        self.info
            .save(&self.dir)
            .map_err(|e| PipelineError::storage(&self.dir, e))
    }

    fn finish_stage(&mut self, stage: Stage, started: Instant) {
        let seconds = started.elapsed().as_secs_f64();
        self.info.timings.retain(|(s, _)| s != stage.name());
        self.info.timings.push((stage.name().into(), seconds));
        self.events.emit(RunEvent::StageFinished { stage, seconds });
    }

    /// Runs (or continues) the pipeline to the end. On any error the laser is switched
    /// off and the galvos parked, the run is marked failed (or paused, or aborted) with
    /// its data intact, and the error is returned.
    pub fn execute(mut self) -> Result<RunSummary, PipelineError> {
        // A panic anywhere in the stages is caught here, so the instrument is made safe
        // and the run marked as for any other failure (the optimiser thread's panics
        // arrive as errors already).
        let result = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.stages())) {
            Ok(r) => r,
            Err(payload) => Err(PipelineError::Panicked {
                stage: self.stage.name(),
                message: panic_message(payload.as_ref()),
            }),
        };
        let safe = self.devices.make_safe();
        self.control
            .record_made_safe(safe.as_ref().map(|_| ()).map_err(|e| e.to_string()));
        match &result {
            // An earlier stop's error (a pause, a suspender, a failure) is history once
            // the run has completed.
            Ok(_) => {
                self.info.state = RunState::Completed;
                self.info.error = None;
            }
            Err(PipelineError::Paused(_)) => self.info.state = RunState::Paused,
            Err(e @ PipelineError::Suspended { .. }) => {
                self.info.state = RunState::Paused;
                self.info.error = Some(e.to_string());
            }
            Err(PipelineError::Aborted(_)) => self.info.state = RunState::Aborted,
            Err(e) => {
                self.info.state = RunState::Failed;
                self.info.error = Some(e.to_string());
                self.events.emit(RunEvent::Failed {
                    message: e.to_string(),
                });
            }
        }
        if let Err(e) = safe {
            tracing::error!(error = %e, "could not make the instrument safe: switch the laser off by hand");
        }
        // A run that stopped keeps its own error if its state cannot be recorded (the
        // API's worker records it then, or holds it at the next start).
        if let Err(e) = self.save_info() {
            tracing::error!(error = %e, "could not record the run's end");
            if result.is_ok() {
                return Err(e);
            }
        }
        if result.is_ok() {
            self.events.emit(RunEvent::Completed);
        }
        result
    }

    fn stages(&mut self) -> Result<RunSummary, PipelineError> {
        self.checkpoint()?;
        let relay = match self.load_relay()? {
            Some(r) => r,
            None => {
                let t = Instant::now();
                self.set_stage(Stage::LosScan)?;
                let returns = self.los_scan()?;
                self.finish_stage(Stage::LosScan, t);
                let t = Instant::now();
                self.set_stage(Stage::Relay)?;
                let relay = self.extract_relay(&returns)?;
                self.checkpoint()?;
                self.events.emit(RunEvent::Relay {
                    returns: returns.len(),
                    kept: relay.len(),
                });
                crate::run_dir::write_relay_ply(&self.dir, &relay)?;
                self.finish_stage(Stage::Relay, t);
                relay
            }
        };
        let pairs = match self.load_pairs()? {
            Some(p) => p,
            None => {
                let t = Instant::now();
                self.set_stage(Stage::Planning)?;
                let pairs = self.plan_pairs(&relay)?;
                self.checkpoint()?;
                self.finish_stage(Stage::Planning, t);
                pairs
            }
        };
        self.info.pairs_total = pairs.len();
        let t = Instant::now();
        self.set_stage(Stage::Capture)?;
        let (fit, records) = self.capture(&pairs)?;
        self.finish_stage(Stage::Capture, t);
        let t = Instant::now();
        self.set_stage(Stage::Reconstruction)?;
        let result = fit.finish(&self.events, &self.control)?;
        self.checkpoint()?;
        self.finish_stage(Stage::Reconstruction, t);
        let t = Instant::now();
        self.set_stage(Stage::Outputs)?;
        let mut outputs = output::write_outputs(&self.dir, &result, &self.events)?;
        // The measured histograms as a y-tal capture, for y-tal, h5py and other labs,
        // from what the run holds.
        let measured = pairs.len();
        let p = self.dir.join(crate::ytal::CAPTURE_FILE);
        let capture = RunCapture::new(
            &self.dir,
            self.info.clone(),
            self.plan.clone(),
            self.instrument.clone(),
            pairs,
            records,
        );
        capture
            .to_ytal()
            .and_then(|c| c.write(&p).map_err(crate::ytal::ExportError::from))
            .map_err(|source| PipelineError::Export { path: p, source })?;
        self.events.emit(RunEvent::Output {
            name: crate::ytal::CAPTURE_FILE.into(),
        });
        outputs.files.push(crate::ytal::CAPTURE_FILE.into());
        self.finish_stage(Stage::Outputs, t);
        Ok(RunSummary {
            dir: self.dir.clone(),
            timings: self.info.timings.clone(),
            pairs: measured,
            outputs,
        })
    }

    fn plan_pairs(&mut self, relay: &[RelayPoint]) -> Result<Vec<PlannedPair>, PipelineError> {
        let points: Vec<_> = relay.iter().map(|r| r.x).collect();
        let normals: Vec<_> = relay.iter().map(|r| r.n).collect();
        let view = crate::plan::RelayView {
            points: &points,
            normals: &normals,
        };
        let i = &self.instrument;
        let (pairs, unreachable) = crate::plan::plan_pairs(
            &self.plan.pairs,
            &view,
            &self.plan.relay.illumination,
            &self.plan.relay.detection,
            [
                (&i.laser_arm.pose, &i.laser_arm.limits),
                (&i.spad_arm.pose, &i.spad_arm.limits),
            ],
        );
        self.events.emit(RunEvent::Planned {
            pairs: pairs.len(),
            unreachable,
        });
        if pairs.is_empty() {
            return Err(PipelineError::NoPairs {
                relay_points: relay.len(),
                unreachable,
            });
        }
        let json = serde_json::to_vec(&pairs).expect("pairs serialise");
        write(&self.dir, file::PAIRS, &json)?;
        Ok(pairs)
    }

    fn load_relay(&self) -> Result<Option<Vec<RelayPoint>>, PipelineError> {
        Ok(RunDir::new(&self.dir).relay()?)
    }

    fn load_pairs(&self) -> Result<Option<Vec<PlannedPair>>, PipelineError> {
        Ok(RunDir::new(&self.dir).planned_pairs()?)
    }
}

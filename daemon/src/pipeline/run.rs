//! A run: its state, the devices it holds, and its life from opening the devices to
//! the last stage. The stages themselves are `impl Run` blocks beside the code they
//! drive: `los.rs` (the LOS scan and the relay), `acquisition.rs` (planning and the
//! capture, streamed to the optimiser), `output.rs` (writing the results), `safety.rs`
//! (the suspenders and device-error handling at every measurement); this file holds
//! what every stage shares (opening, checkpoints, stage bookkeeping, `execute`).
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use periscope_drivers::{EmergencyOff, EmergencyPark};

use super::{PipelineError, panic_message};
use crate::capture::RunCapture;
use crate::config::{InstrumentConfig, TomlSource};
use crate::devices::{DeviceBackend, Devices, OpenError};
use crate::events::{EventSink, RunEvent, Stage};
use crate::plan::{Plan, PlannedPair};
use crate::run_dir::{RunDir, RunInfo, RunState, file};

use super::Control;
use super::output::{self, RunOutputs};
use crate::run_dir::RelayPoint;

/// A run in progress.
pub struct Run {
    pub(super) dir: PathBuf,
    pub(super) plan: Plan,
    pub(super) instrument: InstrumentConfig,
    pub(super) devices: Devices,
    pub(super) events: EventSink,
    pub(super) info: RunInfo,
    pub(super) control: Control,
    /// The stage in progress (for checkpoints and panic reports).
    pub(super) stage: Stage,
    /// When the stage in progress started, until it finishes: a run that stops in it
    /// (a pause, a failure) records the part it ran, so a resumed stage's time is the
    /// sum of its parts.
    pub(super) stage_started: Option<Instant>,
    /// When the run's laser was registered with the panic hook: a panic elsewhere in
    /// the process since then, whose hook switched this laser off, fails the run as the
    /// internal error it is ([`crate::signals::panicked_since`]).
    pub(super) opened_at: Instant,
    /// The sync as the counter reads it since the laser last went on: from when its
    /// readings show it (the rate meter's latency after the switch-on), and whether
    /// this session has already waited for one and checked it.
    pub(super) sync: SyncWatch,
    /// Automatic resumes since the last stored pair from a suspension only a new
    /// measurement can judge (the count rate, flagged frames, emission lost): a
    /// condition that never clears would otherwise switch the laser on and off for
    /// good ([`super::safety::MAX_BLIND_RESUMES`]).
    pub(super) blind_resumes: u32,
    /// This process's hold on the run directory, for as long as the run is open: the
    /// last field, so it is let go after everything else is dropped (the histogram
    /// log synced, the devices closed).
    _hold: crate::run_dir::RunHold,
}

/// The least distance from the plan's `pairs.laser` the relay point a fixed laser
/// lights may lie at, metres ([`fixed_laser_reach`]).
const FIXED_LASER_REACH: f64 = 0.05;

/// How far from the plan's `pairs.laser` the relay point a fixed laser lights may lie:
/// three of the relay's point spacings (the median distance to the nearest other
/// point, over up to 256 points spread through the relay), and at least
/// [`FIXED_LASER_REACH`]. A coarse LOS grid leaves its points far apart; a target
/// farther off than that is not on the relay.
fn fixed_laser_reach(points: &[glam::DVec3]) -> f64 {
    let step = points.len().div_ceil(256).max(1);
    let mut nearest: Vec<f64> = points
        .iter()
        .step_by(step)
        .map(|a| {
            points
                .iter()
                .filter(|b| *b != a)
                .map(|b| a.distance(*b))
                .fold(f64::INFINITY, f64::min)
        })
        .filter(|d| d.is_finite())
        .collect();
    nearest.sort_by(f64::total_cmp);
    let spacing = nearest.get(nearest.len() / 2).copied().unwrap_or(0.0);
    (3.0 * spacing).max(FIXED_LASER_REACH)
}

/// See [`Run::sync`].
#[derive(Clone, Copy, Debug, Default)]
pub(super) struct SyncWatch {
    /// Status readings from this instant on show the sync since the laser went on.
    pub(super) from: Option<Instant>,
    /// The first switch-on of this session waited for a reading and checked it.
    pub(super) verified: bool,
    /// Times running the pair being measured was measured again because its sync
    /// read off and then right.
    pub(super) agains: u32,
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
/// `runs/` unless `out` is given) with the plan and instrument config as provenance,
/// and `submitted_by` (an API key's name, or `cli`) as its submitter.
pub fn prepare(
    plan_src: &TomlSource,
    instrument_src: &TomlSource,
    out: Option<&Path>,
    submitted_by: &str,
) -> Result<(PathBuf, Plan, InstrumentConfig), PipelineError> {
    let instrument = InstrumentConfig::from_source(instrument_src)?;
    let plan = Plan::from_source(plan_src, &instrument)?;
    crate::budget::Budget::of_plan(&plan, &instrument)
        .check(&instrument.budget)
        .map_err(|over| PipelineError::Config(plan_src.invalid(over.key, over.message)))?;
    let dir = match out {
        Some(dir) => {
            crate::store::create_dir_durably(dir).map_err(|e| PipelineError::storage(dir, e))?;
            // Why `dir` cannot take a new run, if it cannot.
            let taken = if RunDir::holds_run(dir) {
                Some(
                    "already holds a run: use `periscope resume` to continue it, or choose another --out"
                        .to_owned(),
                )
            } else if let Some(found) = RunDir::leftover_data(dir) {
                // A run's data without its run.json (deleted, or a copy that left it
                // out): a new run would recover that log as its own and keep pairs it
                // never measured under another plan's name.
                Some(format!(
                    "holds a run's data ({found}) but no run.json: a new run would take those records for its own; move them aside or choose another --out"
                ))
            } else {
                RunDir::file_a_run_would_replace(dir).map(|found| {
                    format!(
                        "holds {found} but no run.json: a new run writes its own {found} there and would replace it; give a new or empty --out"
                    )
                })
            };
            if let Some(why) = taken {
                return Err(PipelineError::storage(
                    dir,
                    std::io::Error::new(std::io::ErrorKind::AlreadyExists, why),
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
    let mut info = RunInfo {
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
        created_unix_s: Some(crate::run_dir::unix_now()),
        submitted_by: Some(submitted_by.to_owned()),
        again_of: None,
        import: None,
        history: Vec::new(),
        adaptive_seconds: 0.0,
        adaptive_stopped: None,
        adaptive_batches: 0,
        acting: Some(submitted_by.to_owned()),
    };
    info.save(&dir).map_err(|e| PipelineError::run_json(&dir, e))?;
    Ok((dir, plan, instrument))
}

/// Records why a run stopped before its devices were open (a pause, an abort, a
/// device that would not open, a panic): the run stays resumable, unless it was
/// asked to abort.
fn stopped_before_start(
    dir: &Path,
    info: &mut RunInfo,
    events: &EventSink,
    control: &Control,
    e: PipelineError,
) -> PipelineError {
    // As [`Run::execute`] takes a stop of the run's own: an abort asked before it ends
    // the run aborted, keeping the error.
    let e = match e {
        e @ (PipelineError::Paused(_) | PipelineError::Aborted(_)) => e,
        e if control.take_stop() == super::Request::Abort => {
            info.error = Some(e.to_string());
            PipelineError::Aborted(info.pairs_done)
        }
        e => e,
    };
    match &e {
        // Named in the state history as a stop at a later checkpoint is (until
        // 2026-12-07 a run paused or aborted while opening, an e-stop's hold the most
        // common, recorded nobody).
        PipelineError::Paused(_) => {
            info.state = RunState::Paused;
            info.acting = control.requested_by();
        }
        PipelineError::Aborted(_) => {
            info.state = RunState::Aborted;
            info.acting = control.requested_by();
        }
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
/// directory now ([`crate::run_dir::RunHold`]), so no other writer's temporary is
/// touched.
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
        // Before anything is read or written: a run another process is writing is left
        // as it is, its run.json included.
        let hold = match crate::run_dir::RunHold::take(dir) {
            Ok(Some(h)) => h,
            Ok(None) => return Err(PipelineError::InUse(dir.to_owned())),
            Err(e) => return Err(PipelineError::storage(dir, e)),
        };
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
                &control,
                PipelineError::run_json(dir, e),
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
            Ok(Err(e)) => return Err(stopped_before_start(dir, &mut info, &events, &control, e)),
            Err(payload) => {
                let e = PipelineError::Panicked {
                    stage: Stage::Opening.name(),
                    message: panic_message(payload.as_ref()),
                };
                return Err(stopped_before_start(dir, &mut info, &events, &control, e));
            }
        };
        // From here the panic hook can switch this run's laser off.
        let opened_at = Instant::now();
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
            stage_started: None,
            opened_at,
            sync: SyncWatch::default(),
            blind_resumes: 0,
            _hold: hold,
        })
    }

    /// A handle that switches this run's laser off from any thread, whatever the run
    /// is doing (the e-stop's and the signal handlers' direct path).
    pub fn emergency_off(&self) -> EmergencyOff {
        self.devices.laser.emergency_off()
    }

    /// Handles that park this run's arms (laser arm, SPAD arm) from any thread,
    /// whatever the run is doing: the e-stop's path when the run does not reach its
    /// checkpoint, since the devices it holds are closed to anyone else.
    pub fn emergency_park(&self) -> [EmergencyPark; 2] {
        [
            self.devices.laser_arm.emergency_park(),
            self.devices.spad.emergency_park(),
        ]
    }

    /// A checkpoint: the pause or abort asked for, as the error that stops the run.
    pub(super) fn checkpoint(&self) -> Result<(), PipelineError> {
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

    pub(super) fn settle_timeout(&self) -> Duration {
        (self
            .instrument
            .laser_arm
            .settle
            .max(self.instrument.spad_arm.settle)
            * 20)
            .max(Duration::from_millis(200))
    }

    pub(super) fn set_stage(&mut self, stage: Stage) -> Result<(), PipelineError> {
        self.stage = stage;
        self.stage_started = None;
        self.checkpoint()?;
        self.stage_started = Some(Instant::now());
        self.info.stage = stage.name().into();
        self.info.state = RunState::Running;
        self.save_info()?;
        self.events.emit(RunEvent::StageStarted { stage });
        Ok(())
    }

    pub(super) fn save_info(&mut self) -> Result<(), PipelineError> {
        self.info
            .save(&self.dir)
            .map_err(|e| PipelineError::run_json(&self.dir, e))
    }

    pub(super) fn finish_stage(&mut self, stage: Stage, started: Instant) {
        let seconds = started.elapsed().as_secs_f64();
        self.stage_started = None;
        self.add_timing(stage, seconds);
        self.events.emit(RunEvent::StageFinished { stage, seconds });
    }

    /// Adds `seconds` to `stage`'s time: a stage run in parts (paused and resumed,
    /// suspended, failed and resumed) is timed over all its parts, not only its last.
    fn add_timing(&mut self, stage: Stage, seconds: f64) {
        match self.info.timings.iter_mut().find(|(s, _)| s == stage.name()) {
            Some((_, total)) => *total += seconds,
            None => self.info.timings.push((stage.name().into(), seconds)),
        }
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
        // A stop of the run's own (a suspension, a device error, a panic) is taken now,
        // as a checkpoint takes a pause: an abort asked before it (an operator's, the
        // e-stop's, as the run wound down) ends the run aborted, and one asked after it
        // finds the stop taken and is applied to the run as stored. Until 2026-12-08
        // such an abort was answered as under way while the run stopped paused, or
        // failed, and stayed resumable.
        // The error that stopped it is kept with the abort.
        let mut stopped_by = None;
        let result = match result {
            Err(e) if !matches!(e, PipelineError::Paused(_) | PipelineError::Aborted(_)) => {
                if self.control.take_stop() == super::Request::Abort {
                    tracing::warn!(error = %e, "the run stopped as it was asked to abort: it ends aborted");
                    stopped_by = Some(e.to_string());
                    Err(PipelineError::Aborted(self.info.pairs_done))
                } else {
                    Err(e)
                }
            }
            r => r,
        };
        // The part of the stage that ran before the run stopped in it.
        if let Some(t) = self.stage_started.take() {
            self.add_timing(self.stage, t.elapsed().as_secs_f64());
        }
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
            Err(PipelineError::Paused(_)) => {
                self.info.state = RunState::Paused;
                self.info.acting = self.control.requested_by();
            }
            Err(e @ PipelineError::Suspended { .. }) => {
                self.info.state = RunState::Paused;
                self.info.error = Some(e.to_string());
            }
            Err(PipelineError::Aborted(_)) => {
                self.info.state = RunState::Aborted;
                self.info.acting = self.control.requested_by();
                if let Some(e) = stopped_by {
                    self.info.error = Some(e);
                }
            }
            Err(e) => {
                self.info.state = RunState::Failed;
                self.info.error = Some(e.to_string());
                self.events.emit(RunEvent::Failed {
                    message: e.to_string(),
                });
            }
        }
        if let Err(e) = safe {
            tracing::error!("could not make the instrument safe: {e}");
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

    pub(super) fn stages(&mut self) -> Result<RunSummary, PipelineError> {
        self.checkpoint()?;
        // A plan that asks for a GPU where none opens would measure every pair and fail
        // at the reconstruction: it fails now, before the laser goes on (the GPU opened
        // here is the one the reconstruction takes; it is opened once a process).
        if self.plan.recon.compute == periscope_recon::gpu::ComputeDevice::Gpu {
            periscope_recon::gpu::Compute::open(periscope_recon::gpu::ComputeDevice::Gpu)
                .map_err(|e| PipelineError::Recon(super::ReconError::Gpu(e)))?;
        }
        let relay = match self.load_relay()? {
            Some(r) => r,
            None => {
                let t = Instant::now();
                self.set_stage(Stage::LosScan)?;
                let returns = self.los_scan().inspect_err(|e| {
                    if matches!(e, PipelineError::Relay(_)) {
                        self.set_aside_los_rows();
                    }
                })?;
                self.finish_stage(Stage::LosScan, t);
                let t = Instant::now();
                self.set_stage(Stage::Relay)?;
                let relay = self
                    .extract_relay(&returns)
                    .inspect_err(|_| self.set_aside_los_rows())?;
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
        let (fit, records) = self.capture(&pairs, &relay)?;
        self.finish_stage(Stage::Capture, t);
        let t = Instant::now();
        self.set_stage(Stage::Reconstruction)?;
        let result = if self.plan.adaptive {
            fit.refit(&self.events, &self.control)?
        } else {
            fit.finish(&self.events, &self.control)?
        };
        self.checkpoint()?;
        self.finish_stage(Stage::Reconstruction, t);
        let t = Instant::now();
        self.set_stage(Stage::Outputs)?;
        let mut outputs = output::write_outputs(&self.dir, &result, &self.events)?;
        // The measured histograms as a y-tal capture, for y-tal, h5py and other labs,
        // from what the run holds.
        // The pairs measured, not the planned (an adaptive capture measures a budget of
        // its candidates).
        let measured = records
            .iter()
            .map(|r| r.pair)
            .collect::<std::collections::HashSet<_>>()
            .len();
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
        // The API's export of the capture while it ran is superseded by the whole
        // capture beside it, and would otherwise hold as much disk again for good
        // (a download reading it keeps its open file).
        for cache in [
            file::EXPORT_CACHE.to_owned(),
            format!("{}.stamp", file::EXPORT_CACHE),
        ] {
            match std::fs::remove_file(self.dir.join(&cache)) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => {
                    tracing::warn!(file = %self.dir.join(&cache).display(), error = %e, "could not remove the superseded export of the unfinished capture")
                }
            }
        }
        self.finish_stage(Stage::Outputs, t);
        Ok(RunSummary {
            dir: self.dir.clone(),
            timings: self.info.timings.clone(),
            pairs: measured,
            outputs,
        })
    }

    pub(super) fn plan_pairs(&mut self, relay: &[RelayPoint]) -> Result<Vec<PlannedPair>, PipelineError> {
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
        // A fixed laser aims at the relay point nearest the plan's; one far from it is
        // not what the plan asked for (a point 70 m off the wall lit its corner).
        if let (crate::plan::PairMode::FixedLaser { laser, .. }, Some(p)) = (&self.plan.pairs, pairs.first())
            && p.xi.distance(*laser) > fixed_laser_reach(&points)
        {
            let path = self.dir.join(file::PLAN);
            let src = crate::config::TomlSource::load(&path)
                .unwrap_or_else(|_| crate::config::TomlSource::from_text(path, String::new()));
            return Err(PipelineError::Config(src.invalid(
                "pairs.laser",
                format!(
                    "({:.3}, {:.3}, {:.3}) m is {:.3} m from the nearest relay point the scan found ({:.3}, {:.3}, {:.3}), more than {:.3} m (three of the relay's point spacings, at least {FIXED_LASER_REACH} m): aim it at the relay (relay.illumination permitting)",
                    laser.x,
                    laser.y,
                    laser.z,
                    p.xi.distance(*laser),
                    p.xi.x,
                    p.xi.y,
                    p.xi.z,
                    fixed_laser_reach(&points),
                ),
            )));
        }
        let requested = self.plan.pairs.max_pairs();
        self.events.emit(RunEvent::Planned {
            pairs: pairs.len(),
            unreachable,
            requested,
        });
        let empty = requested.saturating_sub(pairs.len() + unreachable);
        if empty > 0 {
            // Not an error (a relay smaller than the grid still gives what it has), but
            // never silent: the layout measured is not the one the plan drew.
            tracing::warn!(
                planned = pairs.len(),
                requested,
                "{empty} of the {requested} pairs the plan asks for have no relay point: the cells of pairs.grid (or pairs.laser-grid) the relay the LOS scan found leaves empty ({} relay points); a finer los.grid, a coarser pairs grid, or relay regions that match the relay fill them",
                relay.len()
            );
        }
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

    pub(super) fn load_relay(&self) -> Result<Option<Vec<RelayPoint>>, PipelineError> {
        Ok(RunDir::new(&self.dir).relay()?)
    }

    pub(super) fn load_pairs(&self) -> Result<Option<Vec<PlannedPair>>, PipelineError> {
        Ok(RunDir::new(&self.dir).planned_pairs()?)
    }
}

//! The capture pipeline: LOS scan → relay → pair plan → NLOS acquisition (stored and
//! streamed to the 3D-GTR optimiser, which starts before the capture ends) →
//! reconstruction → outputs, in a run directory that a crash never corrupts and
//! `periscope resume` continues.
//!
//! Everything here is blocking: device I/O and compute run on the calling thread and a
//! trainer thread, never on an async runtime (the HTTP server calls this from
//! `spawn_blocking`).
mod capture;
mod los;
mod output;
mod reconstruct;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::{Duration, Instant};

use periscope_drivers::galvo::GalvoError;
use periscope_drivers::tdc::TdcError;

pub use capture::{hidden_axis, hidden_histogram, rebin_path};
pub use los::RelayPoint;
pub use output::{RELAY_PLY, RunOutputs, write_outputs};
pub use reconstruct::{ReconInput, ReconResult, reconstruct};

use crate::config::{ConfigError, InstrumentConfig, TomlSource};
use crate::devices::{Devices, OpenError};
use crate::events::{EventSink, RunEvent, Stage};
use crate::plan::{Plan, PlannedPair};
use crate::store::{RunInfo, RunState};

/// Why a run stopped.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    /// A config or plan is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The devices could not be opened.
    #[error(transparent)]
    Open(#[from] OpenError),
    /// A galvo controller failed.
    #[error(transparent)]
    Galvo(#[from] GalvoError),
    /// The histogrammer failed.
    #[error(transparent)]
    Tdc(#[from] TdcError),
    /// The relay could not be extracted.
    #[error("relay: {0}")]
    Relay(String),
    /// No pair could be planned.
    #[error("pair planning: {0}")]
    Planning(String),
    /// Reconstruction failed.
    #[error("reconstruction: {0}")]
    Recon(String),
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
}

impl PipelineError {
    pub(crate) fn storage(path: &Path, source: std::io::Error) -> PipelineError {
        PipelineError::Storage {
            path: path.to_owned(),
            source,
        }
    }
}

/// Operator requests a running pipeline honours at its next checkpoint (between pairs,
/// between LOS rows, between epochs).
#[derive(Clone, Default)]
pub struct Control(Arc<AtomicU8>);

impl Control {
    const RUN: u8 = 0;
    const PAUSE: u8 = 1;
    const ABORT: u8 = 2;

    /// A control that never interrupts.
    pub fn new() -> Control {
        Control::default()
    }
    /// Asks the run to pause at the next checkpoint.
    pub fn pause(&self) {
        let _ = self
            .0
            .compare_exchange(Self::RUN, Self::PAUSE, Ordering::SeqCst, Ordering::SeqCst);
    }
    /// Asks the run to abort at the next checkpoint.
    pub fn abort(&self) {
        self.0.store(Self::ABORT, Ordering::SeqCst);
    }
    pub(crate) fn requested(&self) -> u8 {
        self.0.load(Ordering::SeqCst)
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
    let dir = match out {
        Some(dir) => {
            std::fs::create_dir_all(dir).map_err(|e| PipelineError::storage(dir, e))?;
            if dir.join("run.json").exists() {
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
        None => crate::store::new_run_dir(Path::new("runs"), &plan.name)
            .map_err(|e| PipelineError::storage(Path::new("runs"), e))?,
    };
    write(&dir, "plan.toml", plan_src.text().as_bytes())?;
    write(&dir, "instrument.toml", instrument_src.text().as_bytes())?;
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

/// Loads a run directory's plan and instrument back (for resume and offline recon).
pub fn load_run(dir: &Path) -> Result<(RunInfo, Plan, InstrumentConfig), PipelineError> {
    let info = RunInfo::load(dir).map_err(|e| PipelineError::storage(&dir.join("run.json"), e))?;
    let read = |name: &str| {
        let path = dir.join(name);
        std::fs::read_to_string(&path).map_err(|e| PipelineError::storage(&path, e))
    };
    // The stored text is what ran; scene paths in it resolve against where it was.
    let instrument = InstrumentConfig::from_source(&TomlSource::from_text(
        info.instrument_path.clone(),
        read("instrument.toml")?,
    ))?;
    let plan = Plan::from_source(
        &TomlSource::from_text(dir.join("plan.toml"), read("plan.toml")?),
        &instrument,
    )?;
    Ok((info, plan, instrument))
}

impl Run {
    /// Opens the devices for a prepared (or interrupted) run.
    pub fn open(dir: &Path, control: Control, events: Option<EventSink>) -> Result<Run, PipelineError> {
        let (info, plan, instrument) = load_run(dir)?;
        let devices = Devices::open(&instrument)?;
        let events = match events {
            Some(e) => e,
            None => EventSink::open(dir).map_err(|e| PipelineError::storage(dir, e))?,
        };
        Ok(Run {
            dir: dir.to_owned(),
            plan,
            instrument,
            devices,
            events,
            info,
            control,
        })
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
        let result = self.stages();
        let safe = self.devices.make_safe();
        match &result {
            Ok(_) => self.info.state = RunState::Completed,
            Err(PipelineError::Paused(_)) => self.info.state = RunState::Paused,
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
        self.save_info()?;
        if result.is_ok() {
            self.events.emit(RunEvent::Completed);
        }
        result
    }

    fn stages(&mut self) -> Result<RunSummary, PipelineError> {
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
                self.events.emit(RunEvent::Relay {
                    returns: returns.len(),
                    kept: relay.len(),
                });
                output::write_relay_ply(&self.dir, &relay)?;
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
                self.finish_stage(Stage::Planning, t);
                pairs
            }
        };
        self.info.pairs_total = pairs.len();
        let t = Instant::now();
        self.set_stage(Stage::Capture)?;
        let fit = self.capture(&pairs)?;
        self.finish_stage(Stage::Capture, t);
        let t = Instant::now();
        self.set_stage(Stage::Reconstruction)?;
        let result = fit.finish(&self.events, &self.control)?;
        self.finish_stage(Stage::Reconstruction, t);
        let t = Instant::now();
        self.set_stage(Stage::Outputs)?;
        let mut outputs = output::write_outputs(&self.dir, &result, &self.events)?;
        // The measured histograms as a y-tal capture, for y-tal, h5py and other labs.
        let p = self.dir.join(crate::ytal::CAPTURE_FILE);
        crate::ytal::YtalCapture::from_run(&self.dir)
            .and_then(|c| Ok(c.write(&p)?))
            .map_err(|e| PipelineError::storage(&p, std::io::Error::other(e.to_string())))?;
        self.events.emit(RunEvent::Output {
            name: crate::ytal::CAPTURE_FILE.into(),
        });
        outputs.files.push(crate::ytal::CAPTURE_FILE.into());
        self.finish_stage(Stage::Outputs, t);
        Ok(RunSummary {
            dir: self.dir.clone(),
            timings: self.info.timings.clone(),
            pairs: pairs.len(),
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
            return Err(PipelineError::Planning(format!(
                "no pair could be planned from {} relay points ({unreachable} outside the galvo limits): check relay.illumination, relay.detection and the pairs grid",
                relay.len()
            )));
        }
        let json = serde_json::to_vec(&pairs).expect("pairs serialise");
        write(&self.dir, "pairs.json", &json)?;
        Ok(pairs)
    }

    fn load_pairs(&self) -> Result<Option<Vec<PlannedPair>>, PipelineError> {
        let path = self.dir.join("pairs.json");
        if !path.exists() {
            return Ok(None);
        }
        let bytes = std::fs::read(&path).map_err(|e| PipelineError::storage(&path, e))?;
        serde_json::from_slice(&bytes).map(Some).map_err(|e| {
            PipelineError::storage(&path, std::io::Error::new(std::io::ErrorKind::InvalidData, e))
        })
    }

    fn load_relay(&self) -> Result<Option<Vec<RelayPoint>>, PipelineError> {
        output::read_relay_ply(&self.dir)
    }
}

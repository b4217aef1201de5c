//! An imported capture's run (`POST /api/v1/imports`): a capture file of any public
//! format, uploaded into a run directory, read and reconstructed as a queue item, so it
//! never competes with a capture for the CPU and its results are a run's like any
//! other (the dashboard's results view, downloads, the catalogue). No device is opened:
//! stages `reading` (the file into transients), `reconstruction` and `outputs`.
use std::path::Path;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use super::{Control, PipelineError, ReconInput, panic_message, reconstruct, write_outputs};
use crate::capture::Capture;
use crate::config::TomlSource;
use crate::events::{EventSink, RunEvent, Stage};
use crate::run_dir::{RunInfo, RunState, file};

/// An imported capture's geometry for 3-D views (`geometry.json`, written when the
/// file is read; the API's `GET /runs/{id}/geometry` serves it), metres.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ImportGeometry {
    /// The relay points the transients were measured at (detection side, and the
    /// laser's points where it is scanned).
    pub relay: Vec<[f64; 3]>,
    /// Illumination points, each once.
    pub illumination: Vec<[f64; 3]>,
    /// Detection points, each once.
    pub detection: Vec<[f64; 3]>,
    /// Transients in the file.
    pub pairs: usize,
    /// The reconstruction volume, `[lo, hi]` per axis.
    pub volume: [[f64; 2]; 3],
    /// A point on the instrument's side of the relay.
    pub viewpoint: [f64; 3],
}

/// Reads, reconstructs and writes an imported capture's run at `dir`, recording its
/// state in `run.json` as a capture run does (running, then completed, paused, aborted
/// or failed with the error; a paused or failed import reads its file afresh when
/// resumed). Its stored files are never changed: a failure leaves the upload as it
/// came.
pub fn execute_import(dir: &Path, control: Control, events: EventSink) -> Result<(), PipelineError> {
    let mut info = RunInfo::load(dir).map_err(|e| PipelineError::run_json(dir, e))?;
    let mut timings = std::mem::take(&mut info.timings);
    let mut stage = Stage::Reading;
    let mut started: Option<Instant> = None;
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        stages(
            dir,
            &mut info,
            &control,
            &events,
            &mut stage,
            &mut started,
            &mut timings,
        )
    }))
    .unwrap_or_else(|payload| {
        Err(PipelineError::Panicked {
            stage: stage.name(),
            message: panic_message(payload.as_ref()),
        })
    });
    // As [`super::Run::execute`] takes a stop of the run's own (a failure, a panic): an
    // abort asked before it ends the import aborted, with the error kept, and one asked
    // after it is the caller's to apply to the stored run. Until 2026-12-08 an abort
    // that reached an import as it failed was answered as under way, and the import
    // stayed failed and resumable.
    let mut stopped_by = None;
    let result = match result {
        Err(e) if !matches!(e, PipelineError::Paused(_) | PipelineError::Aborted(_)) => {
            if control.take_stop() == super::Request::Abort {
                tracing::warn!(error = %e, "the import stopped as it was asked to abort: it ends aborted");
                stopped_by = Some(e.to_string());
                Err(PipelineError::Aborted(info.pairs_done))
            } else {
                Err(e)
            }
        }
        r => r,
    };
    if let Some(t) = started {
        add_timing(&mut timings, stage, t.elapsed().as_secs_f64());
    }
    info.timings = timings;
    match &result {
        Ok(()) => {
            info.state = RunState::Completed;
            info.error = None;
        }
        Err(PipelineError::Paused(_)) => {
            info.state = RunState::Paused;
            info.acting = control.requested_by();
        }
        Err(PipelineError::Aborted(_)) => {
            info.state = RunState::Aborted;
            info.acting = control.requested_by();
            if let Some(e) = stopped_by {
                info.error = Some(e);
            }
        }
        Err(e) => {
            info.state = RunState::Failed;
            info.error = Some(e.to_string());
            events.emit(RunEvent::Failed {
                message: e.to_string(),
            });
        }
    }
    if let Err(e) = info.save(dir) {
        tracing::error!(error = %e, "could not record the imported capture's end in {}", dir.display());
        if result.is_ok() {
            return Err(PipelineError::run_json(dir, e));
        }
    }
    if result.is_ok() {
        events.emit(RunEvent::Completed);
    }
    result
}

fn add_timing(timings: &mut Vec<(String, f64)>, stage: Stage, seconds: f64) {
    match timings.iter_mut().find(|(s, _)| s == stage.name()) {
        Some((_, total)) => *total += seconds,
        None => timings.push((stage.name().into(), seconds)),
    }
}

#[allow(clippy::too_many_arguments)]
fn stages(
    dir: &Path,
    info: &mut RunInfo,
    control: &Control,
    events: &EventSink,
    stage: &mut Stage,
    started: &mut Option<Instant>,
    timings: &mut Vec<(String, f64)>,
) -> Result<(), PipelineError> {
    let source = info.import.clone().ok_or_else(|| {
        PipelineError::storage(
            &dir.join(file::RUN),
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "the run is not an imported capture",
            ),
        )
    })?;
    let mut enter = |next: Stage, info: &mut RunInfo, timings: &mut Vec<(String, f64)>, pairs: usize| {
        finish_stage(*stage, started, timings, events);
        *stage = next;
        control.check(next, pairs)?;
        *started = Some(Instant::now());
        info.stage = next.name().into();
        info.state = RunState::Running;
        info.timings = timings.clone();
        info.save(dir).map_err(|e| PipelineError::run_json(dir, e))?;
        events.emit(RunEvent::StageStarted { stage: next });
        Ok::<(), PipelineError>(())
    };
    enter(Stage::Reading, info, timings, 0)?;
    let path = dir.join(file::IMPORT_DIR).join(&source.capture);
    let capture = Capture::open(&path)?;
    let settings = if source.recon {
        let src = TomlSource::load(&dir.join(file::RECON))?;
        capture.recon_from::<PipelineError>(&src)?
    } else {
        capture.default_recon()?
    };
    let t = capture.transients(&settings.volume, settings.laser_falloff)?;
    tracing::info!(run = %info.id, "{}", capture.describe());
    let pairs = t.set.len();
    info.pairs_total = pairs;
    info.pairs_done = pairs;
    events.emit(RunEvent::Planned {
        pairs,
        unreachable: 0,
        requested: pairs,
    });
    write_geometry(dir, &capture, &t, &settings.volume, pairs)?;
    enter(Stage::Reconstruction, info, timings, pairs)?;
    let input = ReconInput {
        settings,
        set: t.set,
        detection_points: t.detection_points,
        viewpoint: t.viewpoint,
    };
    let result = reconstruct(input, events, control)?;
    enter(Stage::Outputs, info, timings, pairs)?;
    write_outputs(dir, &result, events)?;
    // The capture as y-tal HDF5, whatever format it came in: for y-tal, h5py and
    // `periscope recon` elsewhere.
    if let Capture::Ytal { capture, .. } = &capture {
        let out = dir.join(crate::ytal::CAPTURE_FILE);
        capture.write(&out).map_err(|e| PipelineError::Export {
            path: out.clone(),
            source: crate::ytal::ExportError::from(e),
        })?;
        events.emit(RunEvent::Output {
            name: crate::ytal::CAPTURE_FILE.into(),
        });
    }
    finish_stage(*stage, started, timings, events);
    Ok(())
}

/// Ends `stage` if it was started: its time added to `timings`, its end sent.
fn finish_stage(
    stage: Stage,
    started: &mut Option<Instant>,
    timings: &mut Vec<(String, f64)>,
    events: &EventSink,
) {
    if let Some(t) = started.take() {
        let seconds = t.elapsed().as_secs_f64();
        add_timing(timings, stage, seconds);
        events.emit(RunEvent::StageFinished { stage, seconds });
    }
}

/// Writes `geometry.json`: the capture's relay points, the volume and the viewpoint.
fn write_geometry(
    dir: &Path,
    capture: &Capture,
    t: &crate::capture::Transients,
    volume: &periscope_recon::VolumeGrid,
    pairs: usize,
) -> Result<(), PipelineError> {
    let unique = |points: &mut dyn Iterator<Item = glam::DVec3>| {
        let mut seen = std::collections::HashSet::new();
        points
            .filter(|p| seen.insert(p.to_array().map(f64::to_bits)))
            .map(|p| p.to_array())
            .collect::<Vec<_>>()
    };
    let (illumination, detection) = match capture {
        Capture::Ytal { capture, .. } => (
            unique(&mut capture.laser_grid.points.iter().copied()),
            unique(&mut capture.sensor_grid.points.iter().copied()),
        ),
        Capture::Run(_) => (
            unique(&mut t.set.pairs().iter().map(|p| p.xi)),
            unique(&mut t.set.pairs().iter().map(|p| p.xd)),
        ),
    };
    let g = ImportGeometry {
        relay: unique(&mut t.detection_points.iter().copied()),
        illumination,
        detection,
        pairs,
        volume: [volume.x, volume.y, volume.z],
        viewpoint: t.viewpoint.to_array(),
    };
    let path = dir.join(file::GEOMETRY);
    crate::store::write_atomic(&path, &serde_json::to_vec(&g).expect("plain data"))
        .map_err(|e| PipelineError::storage(&path, e))
}

//! The run's typed progress events: written to `events.jsonl` in the run directory,
//! shown by the CLI's progress bars, and (with the HTTP API) streamed to clients. One
//! enum for all of them, so they cannot drift apart.
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;
use std::sync::{Arc, Mutex};

use periscope_recon::gtr::TrainEvent;
use serde::Serialize;

/// A pipeline stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Opening and identifying the devices.
    Opening,
    /// LOS first-bounce scan of the relay.
    LosScan,
    /// Relay point cloud, thresholds and normals.
    Relay,
    /// Pair planning.
    Planning,
    /// NLOS acquisition (the optimiser runs alongside).
    Capture,
    /// Fit completion, synthesis and solver.
    Reconstruction,
    /// Writing volumes and images.
    Outputs,
}

impl Stage {
    /// The stage's name as written in `run.json` and events.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Opening => "opening",
            Stage::LosScan => "los-scan",
            Stage::Relay => "relay",
            Stage::Planning => "planning",
            Stage::Capture => "capture",
            Stage::Reconstruction => "reconstruction",
            Stage::Outputs => "outputs",
        }
    }
}

/// Something that happened in a run.
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum RunEvent {
    /// A stage started.
    StageStarted {
        /// Which.
        stage: Stage,
    },
    /// A stage finished.
    StageFinished {
        /// Which.
        stage: Stage,
        /// Seconds it took.
        seconds: f64,
    },
    /// A suspender tripped: the laser is off and the run waits (or pauses) until the
    /// condition clears.
    Suspended {
        /// What tripped and what was measured.
        reason: String,
        /// `auto` (the run goes on by itself once the condition has cleared) or
        /// `operator` (the run pauses; resume it).
        resume: String,
    },
    /// A suspender's condition cleared and the run goes on.
    SuspendCleared {
        /// What had tripped.
        reason: String,
    },
    /// LOS scan progress.
    LosPoint {
        /// Points scanned.
        done: usize,
        /// Points in the scan.
        total: usize,
    },
    /// The relay was extracted.
    Relay {
        /// LOS points with a return.
        returns: usize,
        /// Points kept after thresholds and outlier removal, with normals.
        kept: usize,
    },
    /// Pairs were planned.
    Planned {
        /// Pairs to measure.
        pairs: usize,
        /// Pairs left out (outside the galvo limits).
        unreachable: usize,
    },
    /// A pair was measured and stored.
    Pair {
        /// Pairs stored.
        done: usize,
        /// Pairs planned.
        total: usize,
        /// Photon counts in its histogram.
        counts: u64,
        /// Peak bin of its histogram.
        peak_bin: usize,
        /// Whether a flag (overflow, saturation) was set.
        flagged: bool,
    },
    /// Optimiser progress.
    Train(TrainEvent),
    /// An output was written.
    Output {
        /// File name in the run directory.
        name: String,
    },
    /// A device error stopped the run (it can be resumed).
    Failed {
        /// The error.
        message: String,
    },
    /// The run finished.
    Completed,
}

/// Where events go: the run's `events.jsonl` and any number of listeners.
#[derive(Clone)]
pub struct EventSink {
    inner: Arc<Mutex<Inner>>,
}

type Listener = Box<dyn FnMut(&RunEvent) + Send>;

struct Inner {
    file: Option<File>,
    listeners: Vec<Listener>,
}

impl EventSink {
    /// Appends to `dir/events.jsonl`.
    pub fn open(dir: &Path) -> std::io::Result<EventSink> {
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .open(dir.join("events.jsonl"))?;
        Ok(EventSink {
            inner: Arc::new(Mutex::new(Inner {
                file: Some(file),
                listeners: Vec::new(),
            })),
        })
    }

    /// Adds a listener (the CLI progress display, the HTTP event stream).
    pub fn listen(&self, f: impl FnMut(&RunEvent) + Send + 'static) {
        self.lock().listeners.push(Box::new(f));
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records an event.
    pub fn emit(&self, event: RunEvent) {
        let mut inner = self.lock();
        if let Some(f) = inner.file.as_mut() {
            let t = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            let mut line = serde_json::json!({ "time": t });
            if let (Some(obj), Ok(serde_json::Value::Object(ev))) =
                (line.as_object_mut(), serde_json::to_value(&event))
            {
                obj.extend(ev);
            }
            // Events are a log, not data: a full disk must not stop the capture.
            let _ = writeln!(f, "{line}");
        }
        for l in inner.listeners.iter_mut() {
            l(&event);
        }
    }
}

//! The capture pipeline: LOS scan → relay → pair plan → NLOS acquisition (stored and
//! streamed to the 3D-GTR optimiser, which starts before the capture ends) →
//! reconstruction → outputs, in a run directory that a crash never corrupts and
//! `periscope resume` continues.
//!
//! Everything here is blocking: device I/O and compute run on the calling thread and a
//! trainer thread, never on an async runtime (the HTTP server calls this from
//! `spawn_blocking`).
mod acquisition;
mod control;
mod import;
mod los;
mod output;
mod reconstruct;
mod run;
mod safety;

use std::path::{Path, PathBuf};

use periscope_drivers::DeviceError;

pub use crate::record::{record_axis, record_counts, record_transient, undo_pile_up};
pub use crate::run_dir::{RelayPoint, parse_relay_ply, read_relay_ply};
pub use crate::signals::panic_message;
pub use control::{Control, Request};
pub use import::{ImportGeometry, execute_import};
pub use los::{first_bounce_range, peak};
pub use output::{RELAY_PLY, RunOutputs, write_outputs};
pub(crate) use reconstruct::Fit;
pub use reconstruct::{MAX_VIRTUAL_RESOLUTION, ReconInput, ReconResult, reconstruct};
pub use run::{Run, RunSummary, prepare};

use crate::config::ConfigError;
use crate::devices::OpenError;

/// Why the relay surface could not be extracted from the LOS scan.
#[derive(Debug, thiserror::Error)]
pub enum RelayError {
    /// No LOS point had a return inside the histogrammer's window.
    #[error(
        "none of the {scanned} LOS points had a return inside the TDC window (total paths {:.2} to {:.2} m, from acquisition.offset-ns, acquisition.bins and bin-width-ps): the window must reach the relay's first bounces, and los.angles-deg must cover the relay; `periscope check` names the acquisition settings that record them",
        window[0],
        window[1]
    )]
    NoReturns {
        /// Points scanned.
        scanned: usize,
        /// The total path lengths the window records, metres.
        window: [f64; 2],
    },
    /// Too few LOS points passed the plan's relay thresholds.
    #[error(
        "only {kept} of the {total} LOS points with a return passed relay.depth-m {depth:?} and relay.min-intensity {min_intensity}: widen them, or check that los.angles-deg covers the relay"
    )]
    TooFewPoints {
        /// Points kept.
        kept: usize,
        /// Points with a return.
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
    /// An output file could not be written (the error names the file).
    #[error("{source}")]
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
         was written. The solvers compute in single precision: counts of about 1e20 or more (a y-tal file's \
         `H`, or a capture scaled by a large factor) overflow it, and f-k squares them; divide the counts \
         by a constant and reconstruct again. If the counts are ordinary, please report it"
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
    /// `[compute] device = "gpu"` and no GPU is usable, or the GPU failed.
    #[error(transparent)]
    Gpu(#[from] periscope_recon::gpu::GpuError),
    /// The plan's solver cannot reconstruct the pairs planned on the relay the LOS scan
    /// found: refused before they are measured.
    #[error(
        "recon.method = \"{solver}\" cannot reconstruct the {pairs} pairs planned on the relay the LOS scan \
         found, and the capture stopped before measuring any more of them: {source}"
    )]
    Unsuited {
        /// The plan's solver.
        solver: periscope_recon::solver::SolverKind,
        /// Pairs planned.
        pairs: usize,
        /// What the solver's check found.
        source: periscope_recon::solver::SolverError,
    },
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
            ReconError::Solver(e) => !matches!(e, SolverError::Volume(_) | SolverError::Gpu(_)),
            // No GPU where one was asked for is the settings' to fix; a GPU failing
            // while it runs is not.
            ReconError::Gpu(e) => !matches!(e, periscope_recon::gpu::GpuError::Run { .. }),
            ReconError::Train(e) => matches!(
                e,
                TrainError::Config(_) | TrainError::NothingVisible | TrainError::NegativeTotal { .. }
            ),
            ReconError::Geometry(e) => matches!(e, GeometryError::NoPlane { .. }),
            ReconError::Unsuited { source, .. } => {
                !matches!(source, SolverError::Volume(_) | SolverError::Gpu(_))
            }
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
    /// An imported capture's file could not be read, or does not fit its settings.
    #[error("imported capture: {0}")]
    Import(#[from] crate::capture::CaptureError),
    /// A file of the run (or of a reconstruction's output directory) could not be
    /// written or read.
    #[error("{}: {source}{}", path.display(), storage_remedy(source))]
    Storage {
        /// The file or directory.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Another process holds the run directory ([`crate::run_dir::RunHold`]): it is
    /// writing the run now. Nothing was written.
    #[error(
        "run directory {}: another Periscope process (a daemon, or `periscope run` or `resume`) is writing this run now; nothing was changed. Wait for it to finish, or pause or stop it there, then resume the run",
        .0.display()
    )]
    InUse(PathBuf),
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
    /// The counter's sync rate, read with the laser on, is none or not what the
    /// instrument config says the laser pulses at
    /// ([`crate::config::InstrumentConfig::sync_fault`]).
    #[error(
        "{0}. The laser is off and the run kept what it measured: resume it once the laser is put right; a run keeps the instrument config it started with, so for a config put right submit the plan again as a new run"
    )]
    Sync(String),
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
    /// The run's `run.json` in `dir` could not be written (or read).
    pub(crate) fn run_json(dir: &Path, source: std::io::Error) -> PipelineError {
        PipelineError::storage(&dir.join(crate::run_dir::file::RUN), source)
    }

    pub(crate) fn storage(path: &Path, source: std::io::Error) -> PipelineError {
        PipelineError::Storage {
            path: path.to_owned(),
            source,
        }
    }
}

/// What to do about a file the disk would not write, where the error says enough to
/// know: a full disk, a read-only file system, a directory the daemon may not write.
/// Nothing already stored is lost by such an error (histograms are appended and
/// synced, every other file replaced atomically), so the remedy ends in trying again.
fn storage_remedy(e: &std::io::Error) -> &'static str {
    match e.kind() {
        std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded => {
            "; the disk is full: free space on it, then resume the run (or run the command again); what was stored before is kept"
        }
        std::io::ErrorKind::ReadOnlyFilesystem => {
            "; the file system is read-only: remount it writable, then resume the run (or run the command again); what was stored before is kept"
        }
        std::io::ErrorKind::PermissionDenied => {
            "; Periscope may not write there: give its user write access, then resume the run (or run the command again)"
        }
        _ => "",
    }
}

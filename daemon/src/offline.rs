//! `periscope recon CAPTURE`: reconstruct a stored run again, with other settings or
//! another method, without the instrument; or a y-tal HDF5 capture (a public dataset,
//! or another lab's).
use std::path::{Path, PathBuf};

use periscope_recon::{Pair, TransientError, TransientSet};

use crate::config::{ConfigError, TomlSource};
use crate::events::EventSink;
use crate::pipeline::{self, Control, PipelineError, ReconInput};
use crate::plan::{default_recon, load_recon};
use crate::run_dir::{RunDir, RunDirError};
use crate::ytal::{YtalCapture, YtalError, is_hdf5_path};

/// Why `periscope recon CAPTURE` failed; every variant names the capture or file.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// The capture path does not exist.
    #[error("capture {} does not exist: give a run directory or a y-tal .hdf5/.h5 file", .0.display())]
    Missing(PathBuf),
    /// A directory without `run.json`.
    #[error("{} is not a run directory (no run.json)", .0.display())]
    NotRun(PathBuf),
    /// A file that is not `.hdf5` or `.h5`.
    #[error(
        "{} is a file but not a y-tal capture (.hdf5 or .h5); give a capture file or a run directory",
        .0.display()
    )]
    NotCapture(PathBuf),
    /// A run that stored no histogram.
    #[error("{} holds no measured pairs", .0.display())]
    NoPairs(PathBuf),
    /// A run whose every histogram overflowed.
    #[error("{}: every stored histogram is flagged overflow; nothing to reconstruct from", .0.display())]
    AllOverflowed(PathBuf),
    /// A y-tal capture with no signal inside the volume's time range.
    #[error("{}: every transient is empty inside the reconstruction volume's time range", .0.display())]
    NothingInWindow(PathBuf),
    /// The capture's transients or time axis do not fit the volume.
    #[error("{}: {source}", path.display())]
    Transients {
        /// The capture.
        path: PathBuf,
        /// Why.
        source: TransientError,
    },
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The RECON.toml is invalid.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The stored run could not be read.
    #[error(transparent)]
    Run(#[from] RunDirError),
    /// The y-tal capture could not be read.
    #[error(transparent)]
    Ytal(#[from] YtalError),
    /// The reconstruction or its outputs failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

impl OfflineError {
    /// Whether a configuration is at fault: the RECON.toml, the stored run's plan or
    /// instrument, or settings the data cannot support (exit code 2).
    pub fn is_config(&self) -> bool {
        match self {
            OfflineError::Config(_)
            | OfflineError::Run(RunDirError::Config(_))
            | OfflineError::Ytal(YtalError::Run(RunDirError::Config(_)))
            | OfflineError::Pipeline(PipelineError::Config(_)) => true,
            OfflineError::Pipeline(PipelineError::Recon(e)) => e.is_settings(),
            _ => false,
        }
    }
}

fn transients(path: &Path) -> impl Fn(TransientError) -> OfflineError + '_ {
    move |source| OfflineError::Transients {
        path: path.to_path_buf(),
        source,
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> OfflineError + '_ {
    move |source| OfflineError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reconstructs `capture` (a run directory) into `out`.
pub fn recon(capture: &Path, config: Option<&Path>, out: &Path) -> Result<(), OfflineError> {
    if !capture.exists() {
        return Err(OfflineError::Missing(capture.to_path_buf()));
    }
    if capture.is_file() {
        return recon_ytal(capture, config, out);
    }
    if !RunDir::holds_run(capture) {
        return Err(OfflineError::NotRun(capture.to_path_buf()));
    }
    let run = RunDir::new(capture);
    let (_info, plan, inst) = run.load()?;
    let pairs = run.pairs()?;
    let settings = match config {
        Some(path) => load_recon(&TomlSource::load(path)?, Some(plan.recon.volume))?,
        None => plan.recon.clone(),
    };
    let records = crate::store::read_log(capture).map_err(io(capture))?;
    if records.records.is_empty() {
        return Err(OfflineError::NoPairs(capture.to_path_buf()));
    }
    let (l, s) = (inst.laser_arm.pose.origin, inst.spad_arm.pose.origin);
    let recon_pairs: Vec<Pair> = pairs
        .iter()
        .map(|p| Pair {
            xi: p.xi,
            ni: p.ni,
            xd: p.xd,
            nd: p.nd,
        })
        .collect();
    let axis =
        periscope_recon::transient::hidden_axis(&recon_pairs, &settings.volume, plan.acquisition.bin_width)
            .map_err(transients(capture))?;
    let mut set = TransientSet::new(axis).map_err(transients(capture))?;
    let mut used = Vec::new();
    let mut overflowed = 0usize;
    for r in &records.records {
        let Some(p) = pairs.get(r.pair as usize) else {
            continue;
        };
        match pipeline::record_transient(r, p, &inst, &axis) {
            Some(h) => {
                set.push(recon_pairs[r.pair as usize], &h)
                    .map_err(transients(capture))?;
                used.push(p.xd);
            }
            None => overflowed += 1,
        }
    }
    if overflowed > 0 {
        println!(
            "{}: {overflowed} histograms flagged overflow left out (their counts are only a lower bound)",
            capture.display()
        );
    }
    if set.is_empty() {
        return Err(OfflineError::AllOverflowed(capture.to_path_buf()));
    }
    let input = ReconInput {
        settings,
        set,
        detection_points: used,
        viewpoint: 0.5 * (l + s),
    };
    finish(input, out)
}

/// Reconstructs a y-tal HDF5 capture.
fn recon_ytal(capture: &Path, config: Option<&Path>, out: &Path) -> Result<(), OfflineError> {
    if !is_hdf5_path(capture) {
        return Err(OfflineError::NotCapture(capture.to_path_buf()));
    }
    let ytal = YtalCapture::read(capture)?;
    let settings = match config {
        Some(path) => load_recon(&TomlSource::load(path)?, ytal.default_volume().ok())?,
        None => default_recon(ytal.default_volume()?),
    };
    let set = ytal.transients(&settings.volume)?;
    if set.is_empty() {
        return Err(OfflineError::NothingInWindow(capture.to_path_buf()));
    }
    println!(
        "{}: {} transients ({}), {} bins of {:.4} m{}",
        capture.display(),
        ytal.len(),
        ytal.h_format.name(),
        ytal.bins(),
        ytal.delta_t,
        if ytal.t_accounts_first_and_last_bounces {
            ", first and last legs removed"
        } else {
            ""
        }
    );
    let input = ReconInput {
        settings,
        set,
        detection_points: ytal.sensor_grid.points.clone(),
        viewpoint: ytal.viewpoint(),
    };
    finish(input, out)
}

/// Runs the reconstruction and writes its outputs to `out`.
fn finish(input: ReconInput, out: &Path) -> Result<(), OfflineError> {
    std::fs::create_dir_all(out).map_err(io(out))?;
    let events = EventSink::open(out).map_err(io(out))?;
    crate::progress::attach(&events);
    let t = std::time::Instant::now();
    let result = pipeline::reconstruct(input, &events, &Control::new())?;
    let outputs = pipeline::write_outputs(out, &result, &events)?;
    println!(
        "reconstructed {} pairs in {:.1} s",
        result.pairs,
        t.elapsed().as_secs_f64()
    );
    for f in &outputs.files {
        println!("  {}", out.join(f).display());
    }
    Ok(())
}

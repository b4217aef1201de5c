//! `periscope recon CAPTURE`: reconstruct a stored run again, with other settings or
//! another method, without the instrument; or a y-tal HDF5 capture (a public dataset,
//! or another lab's).
use std::path::{Path, PathBuf};

use crate::capture::{Capture, CaptureError};
use crate::config::{ConfigError, TomlSource};
use crate::events::EventSink;
use crate::pipeline::{self, Control, PipelineError, ReconInput};
use crate::plan::load_recon;

/// Why `periscope recon CAPTURE` failed; every variant names the capture or file.
#[derive(Debug, thiserror::Error)]
pub enum OfflineError {
    /// The capture could not be opened or give its transients.
    #[error(transparent)]
    Capture(#[from] CaptureError),
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
    /// The reconstruction or its outputs failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
}

impl OfflineError {
    /// Whether a configuration is at fault: the RECON.toml, the stored run's plan or
    /// instrument, or settings the data cannot support (exit code 2).
    pub fn is_config(&self) -> bool {
        match self {
            OfflineError::Config(_) | OfflineError::Pipeline(PipelineError::Config(_)) => true,
            OfflineError::Capture(e) => e.is_config(),
            OfflineError::Pipeline(PipelineError::Recon(e)) => e.is_settings(),
            OfflineError::Io { .. } | OfflineError::Pipeline(_) => false,
        }
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> OfflineError + '_ {
    move |source| OfflineError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Reconstructs `capture` (a run directory or a y-tal file) into `out`, with the
/// settings of the RECON.toml at `config`, or else the run's plan's (the defaults
/// derived for the capture, for a y-tal file).
pub fn recon(capture: &Path, config: Option<&Path>, out: &Path) -> Result<(), OfflineError> {
    let capture = Capture::open(capture)?;
    let settings = match config {
        Some(path) => load_recon(&TomlSource::load(path)?, capture.default_volume().ok())?,
        None => capture.default_recon()?,
    };
    let t = capture.transients(&settings.volume, settings.laser_falloff)?;
    println!("{}", capture.describe());
    if let Some(f) = &t.falloff {
        println!(
            "  laser falloff divided out: cos θ / d² from the laser at ({:.3}, {:.3}, {:.3}) m, each histogram \
             scaled by {:.2} to {:.2} ({}; laser-falloff = \"none\" keeps the counts as they are)",
            f.laser.x, f.laser.y, f.laser.z, f.range.0, f.range.1, f.why
        );
    }
    if t.overflowed > 0 {
        println!(
            "  {} histograms flagged overflow left out (their counts are only a lower bound)",
            t.overflowed
        );
    }
    let input = ReconInput {
        settings,
        set: t.set,
        detection_points: t.detection_points,
        viewpoint: t.viewpoint,
    };
    finish(input, out)
}

/// The process's peak resident memory (`VmHWM` of /proc/self/status), bytes; `None`
/// where /proc is not there (not Linux).
fn peak_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib = status.lines().find_map(|l| l.strip_prefix("VmHWM:"))?;
    Some(kib.trim().trim_end_matches("kB").trim().parse::<u64>().ok()? * 1024)
}

/// Runs the reconstruction and writes its outputs to `out`.
fn finish(input: ReconInput, out: &Path) -> Result<(), OfflineError> {
    std::fs::create_dir_all(out).map_err(io(out))?;
    let events = EventSink::open(out).map_err(io(out))?;
    crate::progress::attach(&events);
    let t = std::time::Instant::now();
    let result = pipeline::reconstruct(input, &events, &Control::new())?;
    let outputs = pipeline::write_outputs(out, &result, &events)?;
    let peak = peak_memory_bytes().map_or(String::new(), |b| {
        format!(", peak memory {:.0} MiB", b as f64 / (1u64 << 20) as f64)
    });
    println!(
        "reconstructed {} pairs in {:.1} s{peak}",
        result.pairs,
        t.elapsed().as_secs_f64()
    );
    for f in &outputs.files {
        println!("  {}", out.join(f).display());
    }
    Ok(())
}

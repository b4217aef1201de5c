//! The tracing subscriber for the binary: human-readable or JSON lines on stderr,
//! filtered by `RUST_LOG` (default `info`), optionally mirrored as JSON to a file.
//!
//! Libraries only emit `tracing` events; this is the one place a subscriber is made.
use std::fs::File;
use std::path::Path;
use std::sync::Mutex;

use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{EnvFilter, Layer, fmt};

/// How log lines on stderr are written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// One readable line per event.
    #[default]
    Text,
    /// One JSON object per event (for log collectors).
    Json,
}

/// Whether stderr carries JSON lines (set by [`init`]).
static JSON: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// A message for the operator on stderr: a plain line, or with `--log-format json`
/// an info event, so that stderr stays one JSON object per line.
pub fn notice(message: &str) {
    if JSON.load(std::sync::atomic::Ordering::Relaxed) {
        tracing::info!("{message}");
    } else {
        eprintln!("{message}");
    }
}

/// The error a command ended with, on stderr: `error: ...`, or an error event in JSON.
pub fn report_error(message: &str) {
    if JSON.load(std::sync::atomic::Ordering::Relaxed) {
        tracing::error!("{message}");
    } else {
        eprintln!("error: {message}");
    }
}

/// Extensions of files Periscope reads or writes as data: an existing file named so is
/// not taken as a log (appending log lines would corrupt it).
const DATA_EXTENSIONS: &[&str] = &[
    "toml", "json", "jsonl", "bin", "hdf5", "h5", "mat", "npy", "ply", "png", "obj", "csv", "py",
];

/// Opens `path` for `--log-file`: appended to, never truncated, and made if missing.
/// Refused: anything but a regular file (a FIFO would block the command before it
/// starts, a device or directory is no log), a file in a run directory (the run's
/// files are its only copy of what it measured), and an existing file named as data
/// (`plan.toml`, `capture.hdf5`, ...).
fn open_log_file(path: &Path) -> std::io::Result<File> {
    use std::io::{Error, ErrorKind};
    use std::os::unix::fs::OpenOptionsExt;
    let refuse = |why: &str| {
        Error::new(
            ErrorKind::InvalidInput,
            format!(
                "--log-file {}: {why}; give a new file or an existing log",
                path.display()
            ),
        )
    };
    let parent = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if parent.join("run.json").exists() || parent.join("histograms.bin").exists() {
        return Err(refuse("lies in a run directory, whose files are the run's"));
    }
    if let Ok(meta) = std::fs::symlink_metadata(path) {
        if !meta.file_type().is_file() {
            return Err(refuse(
                "exists and is not a regular file (a FIFO, device, directory or link)",
            ));
        }
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        if DATA_EXTENSIONS.contains(&ext.as_str()) {
            return Err(refuse(&format!(
                "exists and is named as data (.{ext}), not a log"
            )));
        }
    }
    // Without blocking, and checked once open: a FIFO put there since would block.
    let file = std::fs::OpenOptions::new()
        .append(true)
        .create(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOFOLLOW)
        .open(path)?;
    if !file.metadata()?.file_type().is_file() {
        return Err(refuse("is not a regular file"));
    }
    Ok(file)
}

/// Installs the global subscriber. Fails only when the log file cannot be opened:
/// it is appended to, and refused if it is not a regular file, lies in a run
/// directory, or exists under a data file's name.
pub fn init(format: LogFormat, log_file: Option<&Path>) -> std::io::Result<()> {
    JSON.store(format == LogFormat::Json, std::sync::atomic::Ordering::Relaxed);
    let filter = || EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let stderr = match format {
        LogFormat::Text => fmt::layer()
            .with_writer(std::io::stderr)
            .with_target(false)
            .boxed(),
        LogFormat::Json => fmt::layer().json().with_writer(std::io::stderr).boxed(),
    };
    let file = log_file.map(open_log_file).transpose()?.map(|f| {
        fmt::layer()
            .json()
            .with_ansi(false)
            .with_writer(Mutex::new(f))
            .with_filter(filter())
    });
    // A second init (tests calling twice) is harmless: keep the first subscriber.
    let _ = tracing_subscriber::registry()
        .with(stderr.with_filter(filter()))
        .with(file)
        .try_init();
    Ok(())
}

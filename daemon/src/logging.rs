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

/// Installs the global subscriber. Fails only when the log file cannot be created.
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
    let file = log_file.map(File::create).transpose()?.map(|f| {
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

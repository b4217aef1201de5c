//! What run directories add to y-tal HDF5 captures. The format itself (the reader, the
//! writer, `YtalCapture` with its flags and size limits) is the recon crate's
//! [`periscope_recon::io::ytal`], usable without the daemon. A run becomes a capture
//! through [`crate::capture::RunCapture::to_ytal`], which may refuse the run before
//! any HDF5 is written: [`ExportError`] says whether the run or the file failed.
use std::path::PathBuf;

use periscope_recon::io::ytal::YtalError;

/// The capture file a run writes next to its other outputs.
pub const CAPTURE_FILE: &str = crate::run_dir::file::CAPTURE;

/// Why a run could not be exported as a y-tal capture.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The capture could not be encoded or written.
    #[error(transparent)]
    Ytal(#[from] YtalError),
    /// A run's histograms cannot be exported (none stored, or too many).
    #[error("{path}: {message}")]
    Refused {
        /// The run directory.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

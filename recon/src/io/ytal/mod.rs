//! y-tal HDF5 captures: the interchange format of the y-tal NLOS toolkit
//! (`tal.io.read_capture` / `tal.io.write_capture`) and of the public datasets it
//! converts (Z-NLOS, phasor-field captures).
//!
//! A capture is one HDF5 file of top-level datasets:
//!
//! | dataset | meaning |
//! |---|---|
//! | `H` | transients, time first: `(T, Sx, Sy)`, `(T, Si)`, `(T, Li, Si)` or `(T, Lx, Ly, Sx, Sy)` |
//! | `H_format` | enum: `T_Sx_Sy` = 1, `T_Lx_Ly_Sx_Sy` = 2, `T_Si` = 3, `T_Li_Si` = 4 |
//! | `sensor_grid_xyz`, `laser_grid_xyz` | relay points, `(N, 3)` or `(X, Y, 3)` |
//! | `sensor_grid_normals`, `laser_grid_normals` | unit normals toward the hidden scene, same shapes |
//! | `sensor_grid_format`, `laser_grid_format` | enum: `N_3` = 1, `X_Y_3` = 2 |
//! | `sensor_xyz`, `laser_xyz` | SPAD and laser origins (may be empty) |
//! | `delta_t`, `t_start` | bin width and start of bin 0, metres of optical path |
//! | `t_accounts_first_and_last_bounces` | whether path lengths include the legs from the laser and to the SPAD |
//! | `scene_info` | YAML text (may be empty) |
//!
//! Bin k covers path lengths `[t_start + k·delta_t, t_start + (k+1)·delta_t)`. With
//! `T_Sx_Sy` / `T_Si`, the laser grid either matches the sensor grid point for point
//! (confocal or paired captures) or holds one point (a fixed laser). Missing values are
//! HDF5 empty (null) datasets, as h5py writes `None`.
//!
//! y-tal's reader refuses datasets it does not know, so Periscope's histogram flags
//! travel inside `scene_info`, as two YAML lists of transient indices (columns of `H`):
//! `periscope_overflow: [..]` and `periscope_saturated: [..]`.
//!
//! The reader and writer live here, in the recon crate, beside the transients they
//! feed, so a program that uses `periscope-recon` as a library reads and writes y-tal
//! captures without the daemon; the daemon adds only what run directories need (the
//! export of a run, `daemon::capture::RunCapture::to_ytal`). The module is split by
//! concern: `dataset` reads one dataset safely (the size checks against hostile
//! files), `read` decodes and validates a capture, `transients` turns it into relay
//! pairs and rebinned transients, `write` encodes it as y-tal does.
//!
//! ```no_run
//! use std::path::Path;
//! use periscope_recon::io::ytal::YtalCapture;
//!
//! # fn main() -> Result<(), periscope_recon::io::ytal::YtalError> {
//! let capture = YtalCapture::read(Path::new("scene.hdf5"))?;
//! let volume = capture.default_volume()?;
//! let transients = capture.transients(&volume)?;
//! println!("{} of {} transients in the volume's window", transients.len(), capture.len());
//! capture.write(Path::new("copy.hdf5"))?;
//! # Ok(())
//! # }
//! ```
use std::path::{Path, PathBuf};

use glam::DVec3;

mod dataset;
mod read;

pub(crate) use dataset::{Reader, unit};
pub(crate) use read::{file_memory_check, guarded, memory_check};
mod transients;
mod write;

#[cfg(test)]
mod tests;

/// What can go wrong reading or writing a y-tal capture.
#[derive(Debug, thiserror::Error)]
pub enum YtalError {
    /// The file could not be opened, parsed or written as HDF5.
    #[error("{path}: {message}")]
    Hdf5 {
        /// The file.
        path: PathBuf,
        /// What the HDF5 layer said.
        message: String,
    },
    /// The file is HDF5 but not a y-tal capture we can use.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong, naming the dataset.
        message: String,
    },
}

impl YtalError {
    /// The error with `path` named where it came from a capture held in memory (whose
    /// methods do not know the file it was read from).
    pub fn at(self, path: &std::path::Path) -> YtalError {
        match self {
            YtalError::Format { path: p, message } if p.as_os_str() == UNNAMED => YtalError::Format {
                path: path.to_owned(),
                message,
            },
            e => e,
        }
    }
}

/// What a capture's own errors call it until the caller names the file
/// ([`YtalError::at`]).
/// `text` as a YAML double-quoted scalar that any YAML reader takes back as it was
/// (what goes into a `scene_info`):
/// quotes and backslashes escaped, and every character outside printable ASCII
/// written as a `\u` or `\U` escape, since YAML readers (y-tal's PyYAML among them)
/// refuse control characters in a document, and a plan stored before they were
/// refused may hold one.
pub fn yaml_string(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            ' '..='~' => out.push(c),
            c if u32::from(c) <= 0xFFFF => out.push_str(&format!("\\u{:04x}", u32::from(c))),
            c => out.push_str(&format!("\\U{:08x}", u32::from(c))),
        }
    }
    out.push('"');
    out
}

pub(crate) const UNNAMED: &str = "<capture>";

/// How `H` is laid out (y-tal's `HFormat`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HFormat {
    /// `(T, Sx, Sy)`: confocal, paired or single-laser, on a sensor grid.
    TSxSy = 1,
    /// `(T, Lx, Ly, Sx, Sy)`: every laser grid point with every sensor grid point.
    TLxLySxSy = 2,
    /// `(T, Si)`: confocal, paired or single-laser, on a sensor point list.
    TSi = 3,
    /// `(T, Li, Si)`: every laser point with every sensor point.
    TLiSi = 4,
}

impl HFormat {
    fn from_code(code: i64) -> Option<HFormat> {
        Some(match code {
            1 => HFormat::TSxSy,
            2 => HFormat::TLxLySxSy,
            3 => HFormat::TSi,
            4 => HFormat::TLiSi,
            _ => return None,
        })
    }

    /// y-tal's name for it.
    pub fn name(self) -> &'static str {
        match self {
            HFormat::TSxSy => "T_Sx_Sy",
            HFormat::TLxLySxSy => "T_Lx_Ly_Sx_Sy",
            HFormat::TSi => "T_Si",
            HFormat::TLiSi => "T_Li_Si",
        }
    }

    fn is_product(self) -> bool {
        matches!(self, HFormat::TLxLySxSy | HFormat::TLiSi)
    }
}

/// How a grid of relay points is laid out (y-tal's `GridFormat`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GridFormat {
    /// `(N, 3)`: a point list.
    N3 = 1,
    /// `(X, Y, 3)`: a grid.
    XY3 = 2,
}

/// Relay points and normals of one side (laser or sensor).
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    /// Points, flattened in C order.
    pub points: Vec<DVec3>,
    /// Unit normals toward the hidden scene.
    pub normals: Vec<DVec3>,
    /// Layout in the file.
    pub format: GridFormat,
    /// Shape without the trailing 3: `[N]` or `[X, Y]`.
    pub shape: Vec<usize>,
}

/// A y-tal capture in memory.
#[derive(Debug, Clone, PartialEq)]
pub struct YtalCapture {
    /// Transients, C order, time first.
    pub h: Vec<f32>,
    /// Shape of `h`.
    pub h_shape: Vec<usize>,
    /// Layout of `h`.
    pub h_format: HFormat,
    /// Sensor-side relay points.
    pub sensor_grid: Grid,
    /// Laser-side relay points.
    pub laser_grid: Grid,
    /// SPAD origin, if recorded.
    pub sensor_xyz: Option<DVec3>,
    /// Laser origin, if recorded.
    pub laser_xyz: Option<DVec3>,
    /// Bin width, metres of path.
    pub delta_t: f64,
    /// Path length at the start of bin 0, metres.
    pub t_start: f64,
    /// Whether path lengths include the first and last legs.
    pub t_accounts_first_and_last_bounces: bool,
    /// YAML text, if any.
    pub scene_info: Option<String>,
    /// Periscope's histogram flags, one per transient in `H`'s order (bit 0 overflow: a
    /// counter overflowed and the counts are only a lower bound; bit 1 saturated), in
    /// captures Periscope exported; `None` in others. Stored in the file as the
    /// `scene_info` keys `periscope_overflow` and `periscope_saturated` (lists of
    /// transient indices), which [`YtalCapture::read`] takes out of `scene_info` again.
    pub flags: Option<Vec<u8>>,
}

/// Flag bit: a counter or the FIFO overflowed.
pub const FLAG_OVERFLOW: u8 = 1;
/// Flag bit: the detector rate exceeded 5 % of the sync rate.
pub const FLAG_SATURATED: u8 = 2;

/// The `scene_info` keys that carry the flags, with their bits.
const FLAG_KEYS: [(&str, u8); 2] = [
    ("periscope_overflow", FLAG_OVERFLOW),
    ("periscope_saturated", FLAG_SATURATED),
];

/// Largest dataset a capture may declare, bytes in memory (8 GiB of `H` is about
/// 2,000 million bins, twenty times the largest published captures).
pub const MAX_DATASET_BYTES: u64 = 8 << 30;

/// Largest capture file read, bytes: the HDF5 layer reads the file whole.
pub const MAX_FILE_BYTES: u64 = 16 << 30;

impl YtalCapture {
    /// How many transients carry the overflow flag ([`FLAG_OVERFLOW`]), which
    /// [`YtalCapture::transients`] leaves out, and of how many.
    pub fn overflowed(&self) -> (usize, usize) {
        self.flags.as_ref().map_or((0, 0), |f| {
            (f.iter().filter(|&&b| b & FLAG_OVERFLOW != 0).count(), f.len())
        })
    }

    /// The renderer that made the capture, if `scene_info` says it was rendered: a
    /// top-level `renderer` entry (mitransient's harnesses), or y-tal's documented
    /// `config` entry, which `tal render` writes (its scene configuration). Measured
    /// captures carry neither. Rendered lasers are point sources (the daemon's
    /// `laser-falloff = "auto"` divides their falloff out of such captures with
    /// [`crate::TransientSet::compensate_laser_falloff`]).
    pub fn rendered_by(&self) -> Option<String> {
        let info = self.scene_info.as_deref()?;
        let top = |key: &str| {
            info.lines().find_map(|l| {
                l.strip_prefix(key)
                    .and_then(|rest| rest.strip_prefix(':'))
                    .map(|v| v.trim().trim_matches(['\'', '"']).to_string())
            })
        };
        match (top("renderer"), top("config")) {
            (Some(r), _) if !r.is_empty() => Some(r),
            (_, Some(_)) => Some("y-tal's `tal render`".into()),
            _ => None,
        }
    }

    /// Time bins per transient.
    pub fn bins(&self) -> usize {
        self.h_shape[0]
    }

    /// Number of transients (laser/sensor pairs).
    pub fn len(&self) -> usize {
        self.h_shape[1..].iter().product()
    }

    /// Whether the capture holds no transients.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Whether `path` names an HDF5 file by its extension.
pub fn is_hdf5_path(path: &Path) -> bool {
    matches!(
        path.extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref(),
        Some("hdf5" | "h5")
    )
}

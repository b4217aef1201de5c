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
use std::path::{Path, PathBuf};

use glam::DVec3;
use hdf5_pure::{Datatype, EnumTypeBuilder, File, FileBuilder, make_i8_type, make_i32_type};
use periscope_recon::{C0, Pair, TimeAxis, TransientSet, VolumeGrid};

use periscope_recon::transient::{clip_to_measured, hidden_axis, rebin_path};

/// The capture file a run writes next to its other outputs.
pub const CAPTURE_FILE: &str = crate::run_dir::file::CAPTURE;

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
    /// A run's histograms cannot be exported (none stored, or too many).
    #[error("{path}: {message}")]
    Export {
        /// The run directory.
        path: PathBuf,
        /// Why.
        message: String,
    },
}

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

/// Splits the flag lists out of a `scene_info` text: the text without them, and the
/// (index, bit) pairs they name. `Err` names a malformed list.
fn take_flags(info: &str) -> Result<(String, Vec<(usize, u8)>), String> {
    let mut rest = String::new();
    let mut marks = Vec::new();
    for line in info.lines() {
        match FLAG_KEYS.iter().find_map(|(key, bit)| {
            line.strip_prefix(key)
                .and_then(|l| l.strip_prefix(':'))
                .map(|l| (key, *bit, l))
        }) {
            Some((key, bit, list)) => {
                let inner = list
                    .trim()
                    .strip_prefix('[')
                    .and_then(|l| l.strip_suffix(']'))
                    .ok_or_else(|| {
                        format!("`scene_info` key `{key}` should be a list like [3, 17], it is {list:?}")
                    })?;
                for item in inner.split(',').map(str::trim).filter(|s| !s.is_empty()) {
                    let i = item.parse::<usize>().map_err(|_| {
                        format!("`scene_info` key `{key}` lists {item:?}, not a transient index")
                    })?;
                    marks.push((i, bit));
                }
            }
            None => {
                rest.push_str(line);
                rest.push('\n');
            }
        }
    }
    Ok((rest, marks))
}

/// A dataset's values (as f64) and shape.
type Values = (Vec<f64>, Vec<usize>);

struct Reader<'a> {
    file: File,
    path: &'a Path,
    /// Length of the file, bytes.
    file_len: u64,
}

/// Largest dataset a capture may declare, bytes in memory (8 GiB of `H` is about
/// 2,000 million bins, twenty times the largest published captures).
pub const MAX_DATASET_BYTES: u64 = 8 << 30;

/// Largest capture file read, bytes: the HDF5 layer reads the file whole.
pub const MAX_FILE_BYTES: u64 = 16 << 30;

/// Best compression ratio deflate can reach: a chunked dataset cannot hold more than
/// this times the file's length.
const MAX_GZIP_RATIO: u64 = 1032;

/// Most chunks a dataset may be split into.
const MAX_CHUNKS: u64 = 1 << 22;

/// Largest chunk, bytes (h5py aims at 1 MiB at most): the HDF5 layer sizes its
/// decompression buffers by the declared chunk, whatever the data.
const MAX_CHUNK_BYTES: u64 = 64 << 20;

/// Most bytes the rebinned transients of a capture may take in memory (the default
/// run budget).
const MAX_TRANSIENT_BYTES: u64 = 16 << 30;

impl Reader<'_> {
    /// A dataset's shape, after checking that reading it is safe: the declared size
    /// (as `out_width`-byte values in memory) fits [`MAX_DATASET_BYTES`] and what the
    /// file can hold (its length, times the best gzip ratio for chunked data), and a
    /// chunked layout has a sane chunk count. A small file that declares a huge shape
    /// (an "HDF5 bomb") is refused here, before the HDF5 layer allocates for it.
    fn checked_shape(
        &self,
        ds: &hdf5_pure::Dataset,
        name: &str,
        out_width: u64,
    ) -> Result<Vec<usize>, YtalError> {
        let err = |m: String| self.format(format!("dataset `{name}`: {m}"));
        let shape = ds.shape().map_err(|e| err(e.to_string()))?;
        let elements = shape
            .iter()
            .try_fold(1u64, |a, &d| a.checked_mul(d))
            .ok_or_else(|| err(format!("its shape {shape:?} overflows")))?;
        let stored = ds
            .element_size()
            .ok()
            .and_then(|w| elements.checked_mul(w))
            .ok_or_else(|| err(format!("its shape {shape:?} overflows")))?;
        let declared = stored.max(elements.saturating_mul(out_width));
        if declared > MAX_DATASET_BYTES {
            return Err(err(format!(
                "its shape {shape:?} declares {declared} bytes, more than the {MAX_DATASET_BYTES} a capture dataset may have"
            )));
        }
        let chunked = matches!(ds.layout(), Ok(hdf5_pure::Layout::Chunked { .. }));
        let holds = if chunked {
            self.file_len.saturating_mul(MAX_GZIP_RATIO)
        } else {
            self.file_len
        };
        if stored > holds {
            return Err(err(format!(
                "its shape {shape:?} declares {stored} bytes but the file has {} bytes: it is truncated or forged",
                self.file_len
            )));
        }
        if let Ok(Some(chunk)) = ds.chunk_shape() {
            let count = shape
                .iter()
                .zip(&chunk)
                .try_fold(1u64, |a, (&d, &c)| a.checked_mul(d.div_ceil(c.max(1))));
            let chunk_bytes = chunk
                .iter()
                .try_fold(ds.element_size().unwrap_or(8).max(1), |a, &c| a.checked_mul(c));
            if chunk.len() != shape.len()
                || chunk.contains(&0)
                || count.is_none_or(|n| n > MAX_CHUNKS)
                || chunk_bytes.is_none_or(|b| b > MAX_CHUNK_BYTES)
            {
                return Err(err(format!(
                    "its chunk shape {chunk:?} does not fit its shape {shape:?}, makes too many chunks, \
                     or makes chunks over {MAX_CHUNK_BYTES} bytes"
                )));
            }
        }
        // Every stored chunk must lie inside the file and inside the dataset: the HDF5
        // layer trusts a chunk's recorded size and offset when it reads (the fuzzer
        // found a 160 KB file whose chunk record made it allocate 3.4 GB).
        if chunked && let Ok(chunks) = ds.chunks() {
            for c in &chunks {
                let inside_file = c
                    .address
                    .checked_add(c.storage_size)
                    .is_some_and(|end| end <= self.file_len);
                let inside_data =
                    c.offset.len() == shape.len() && c.offset.iter().zip(&shape).all(|(o, d)| o < d);
                if !inside_file || !inside_data {
                    return Err(err(format!(
                        "a chunk (at {:?}, {} bytes at byte {}) lies outside the dataset or beyond the end of the file",
                        c.offset, c.storage_size, c.address
                    )));
                }
            }
        }
        shape
            .into_iter()
            .map(|d| usize::try_from(d).map_err(|_| err("a dimension does not fit this machine".into())))
            .collect()
    }

    fn format(&self, message: String) -> YtalError {
        YtalError::Format {
            path: self.path.to_path_buf(),
            message,
        }
    }

    fn has(&self, name: &str) -> bool {
        self.file.dataset(name).is_ok()
    }

    /// Values and shape; `None` for a missing or empty (null) dataset.
    fn floats(&self, name: &str) -> Result<Option<Values>, YtalError> {
        let Ok(ds) = self.file.dataset(name) else {
            return Ok(None);
        };
        let shape = self.checked_shape(&ds, name, 8)?;
        let values = ds
            .read_f64()
            .map_err(|e| self.format(format!("dataset `{name}` is not numeric: {e}")))?;
        if values.is_empty() {
            return Ok(None);
        }
        Ok(Some((values, shape)))
    }

    fn scalar(&self, name: &str) -> Result<Option<f64>, YtalError> {
        match self.floats(name)? {
            None => Ok(None),
            Some((v, _)) if v.len() == 1 => Ok(Some(v[0])),
            Some((v, _)) => Err(self.format(format!(
                "dataset `{name}` should hold one value, it holds {}",
                v.len()
            ))),
        }
    }

    fn required_scalar(&self, name: &str) -> Result<f64, YtalError> {
        self.scalar(name)?
            .ok_or_else(|| self.format(format!("dataset `{name}` is missing or empty")))
    }

    fn point(&self, name: &str) -> Result<Option<DVec3>, YtalError> {
        match self.floats(name)? {
            None => Ok(None),
            Some((v, _)) if v.len() == 3 && v.iter().all(|x| x.is_finite()) => {
                Ok(Some(DVec3::new(v[0], v[1], v[2])))
            }
            Some((v, _)) => Err(self.format(format!(
                "dataset `{name}` should hold a point (3 finite values), it holds {v:?}"
            ))),
        }
    }

    fn grid(&self, side: &str) -> Result<Grid, YtalError> {
        let xyz_name = format!("{side}_grid_xyz");
        let (xyz, shape) = self
            .floats(&xyz_name)?
            .ok_or_else(|| self.format(format!("dataset `{xyz_name}` is missing or empty")))?;
        if shape.last() != Some(&3) || !(shape.len() == 2 || shape.len() == 3) {
            return Err(self.format(format!(
                "dataset `{xyz_name}` has shape {shape:?}; expected (N, 3) or (X, Y, 3)"
            )));
        }
        let format = if shape.len() == 2 {
            GridFormat::N3
        } else {
            GridFormat::XY3
        };
        let points = to_points(&xyz);
        let normals_name = format!("{side}_grid_normals");
        let normals = match self.floats(&normals_name)? {
            Some((n, nshape)) => {
                if nshape.iter().product::<usize>() == 3 {
                    // One normal for the whole grid.
                    vec![to_points(&n)[0].normalize_or_zero(); points.len()]
                } else if nshape == shape {
                    to_points(&n).into_iter().map(DVec3::normalize_or_zero).collect()
                } else {
                    return Err(self.format(format!(
                        "dataset `{normals_name}` has shape {nshape:?} but `{xyz_name}` has {shape:?}"
                    )));
                }
            }
            None => {
                tracing::warn!(
                    "{}: no `{normals_name}`; assuming the y-tal convention, a relay facing +z",
                    self.path.display()
                );
                vec![DVec3::Z; points.len()]
            }
        };
        if let Some(i) = normals.iter().position(|n| *n == DVec3::ZERO || !n.is_finite()) {
            return Err(self.format(format!(
                "dataset `{normals_name}`: normal {i} is zero or not finite"
            )));
        }
        if let Some(i) = points.iter().position(|p| !p.is_finite()) {
            return Err(self.format(format!("dataset `{xyz_name}`: point {i} is not finite")));
        }
        Ok(Grid {
            points,
            normals,
            format,
            shape: shape[..shape.len() - 1].to_vec(),
        })
    }
}

/// Runs a decode, turning a panic inside the HDF5 layer into an error that names the
/// file. The fuzzer found malformed chunk layouts that make hdf5-pure 0.47 overflow
/// an offset (`chunked_read.rs`, `copy_chunk_to_output`): a malformed file must be
/// an error for the user, never a crash of `recon` or of the daemon.
fn guarded(
    path: &Path,
    decode: impl FnOnce() -> Result<YtalCapture, YtalError>,
) -> Result<YtalCapture, YtalError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(decode)).unwrap_or_else(|payload| {
        Err(YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: format!(
                "is malformed: the HDF5 decoder failed on it ({}); it is not a capture that can be read",
                crate::signals::panic_message(payload.as_ref())
            ),
        })
    })
}

fn to_points(v: &[f64]) -> Vec<DVec3> {
    v.chunks_exact(3).map(|c| DVec3::new(c[0], c[1], c[2])).collect()
}

impl YtalCapture {
    /// Reads a capture written by y-tal (or by [`YtalCapture::write`]).
    pub fn read(path: &Path) -> Result<YtalCapture, YtalError> {
        let file_len = std::fs::metadata(path)
            .map_err(|e| YtalError::Hdf5 {
                path: path.to_path_buf(),
                message: format!("cannot be read ({e})"),
            })?
            .len();
        if file_len > MAX_FILE_BYTES {
            return Err(YtalError::Hdf5 {
                path: path.to_path_buf(),
                message: format!(
                    "is {file_len} bytes, more than the {MAX_FILE_BYTES} a capture file may have here"
                ),
            });
        }
        guarded(path, || {
            let file = File::open(path).map_err(|e| YtalError::Hdf5 {
                path: path.to_path_buf(),
                message: format!(
                    "cannot be read as HDF5 ({e}); give a y-tal capture (.hdf5/.h5) or a run directory"
                ),
            })?;
            YtalCapture::decode(file, path, file_len)
        })
    }

    /// Reads a capture held in memory (`name` is used in messages), with the same
    /// checks as [`YtalCapture::read`].
    pub fn from_bytes(bytes: Vec<u8>, name: &Path) -> Result<YtalCapture, YtalError> {
        let file_len = bytes.len() as u64;
        guarded(name, || {
            let file = File::from_bytes(bytes).map_err(|e| YtalError::Hdf5 {
                path: name.to_path_buf(),
                message: format!("cannot be read as HDF5 ({e})"),
            })?;
            YtalCapture::decode(file, name, file_len)
        })
    }

    fn decode(file: File, path: &Path, file_len: u64) -> Result<YtalCapture, YtalError> {
        let r = Reader { file, path, file_len };
        if !r.has("H") {
            let hint = ["data", "data_t", "dataset", "rect_data"]
                .iter()
                .find(|k| r.has(k))
                .map(|k| {
                    format!(
                        " It has `{k}`, so it is in another NLOS format: convert it with y-tal first \
                         (`tal.io.write_capture(out, tal.io.read_capture(file))`)."
                    )
                })
                .unwrap_or_default();
            return Err(r.format(format!("no dataset `H`; this is not a y-tal capture.{hint}")));
        }
        let code = r.required_scalar("H_format")?;
        let integral = code.is_finite() && code.fract() == 0.0 && code.abs() < 1e6;
        let h_format = HFormat::from_code(if integral { code as i64 } else { -1 }).ok_or_else(|| {
            r.format(format!(
                "`H_format` is {code}; expected 1 to 4 (T_Sx_Sy … T_Li_Si)"
            ))
        })?;
        let ds = r
            .file
            .dataset("H")
            .map_err(|e| r.format(format!("dataset `H`: {e}")))?;
        let h_shape = r.checked_shape(&ds, "H", 4)?;
        let rank = match h_format {
            HFormat::TSxSy | HFormat::TLiSi => 3,
            HFormat::TSi => 2,
            HFormat::TLxLySxSy => 5,
        };
        if h_shape.len() != rank || h_shape.contains(&0) {
            return Err(r.format(format!(
                "`H` has shape {h_shape:?} but `H_format` {} needs {rank} non-empty dimensions",
                h_format.name()
            )));
        }
        let h = ds
            .read_f32()
            .map_err(|e| r.format(format!("dataset `H` is not numeric: {e}")))?;
        if let Some(i) = h.iter().position(|v| !v.is_finite()) {
            return Err(r.format(format!("`H` value {i} is not finite")));
        }
        let delta_t = r.required_scalar("delta_t")?;
        if !(delta_t > 0.0 && delta_t <= 10.0) {
            return Err(r.format(format!(
                "`delta_t` is {delta_t}; it must be a positive path length in metres (at most 10)"
            )));
        }
        let t_accounts = match r.scalar("t_accounts_first_and_last_bounces")? {
            None => false,
            Some(v) if v == 0.0 || v == 1.0 => v == 1.0,
            Some(v) => {
                return Err(r.format(format!(
                    "`t_accounts_first_and_last_bounces` is {v}; it must be true or false"
                )));
            }
        };
        let t_start = match r.scalar("t_start")? {
            Some(t) if t.is_finite() && t.abs() <= 1e4 => t,
            Some(t) => {
                return Err(r.format(format!(
                    "`t_start` is {t}; it must be a path length in metres (within ±10 km)"
                )));
            }
            None if t_accounts => {
                return Err(r.format(
                    "`t_start` is empty but `t_accounts_first_and_last_bounces` is true; \
                     the time origin is unknown"
                        .into(),
                ));
            }
            None => 0.0,
        };
        let scene_info = r
            .file
            .dataset("scene_info")
            .ok()
            .filter(|d| r.checked_shape(d, "scene_info", 1 << 16).is_ok())
            .and_then(|d| d.read_string().ok())
            .and_then(|v| v.into_iter().next());
        let mut capture = YtalCapture {
            h,
            h_shape,
            h_format,
            sensor_grid: r.grid("sensor")?,
            laser_grid: r.grid("laser")?,
            sensor_xyz: r.point("sensor_xyz")?,
            laser_xyz: r.point("laser_xyz")?,
            delta_t,
            t_start,
            t_accounts_first_and_last_bounces: t_accounts,
            scene_info,
            flags: None,
        };
        if let Some(info) = &capture.scene_info
            && FLAG_KEYS.iter().any(|(k, _)| info.contains(k))
        {
            let (rest, marks) = take_flags(info).map_err(|m| r.format(m))?;
            let columns = capture.len();
            let mut flags = vec![0u8; columns];
            for (i, bit) in marks {
                let f = flags.get_mut(i).ok_or_else(|| {
                    r.format(format!("`scene_info` flags transient {i}, but `H` has {columns}"))
                })?;
                *f |= bit;
            }
            capture.scene_info = Some(rest);
            capture.flags = Some(flags);
        }
        capture.check().map_err(|m| r.format(m))?;
        Ok(capture)
    }

    /// Checks that `H`, the grids and the origins fit together.
    fn check(&self) -> Result<(), String> {
        let columns: usize = self.h_shape[1..]
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .ok_or("the shape of `H` overflows")?;
        // Grids stored as (X, Y, 3) must match `H`'s own dimensions, not only in count:
        // a transposed grid would put every transient at the wrong point.
        let dims: Vec<(&str, &Grid, &[usize])> = match self.h_format {
            HFormat::TSxSy => vec![("sensor", &self.sensor_grid, &self.h_shape[1..3])],
            HFormat::TLxLySxSy => vec![
                ("laser", &self.laser_grid, &self.h_shape[1..3]),
                ("sensor", &self.sensor_grid, &self.h_shape[3..5]),
            ],
            HFormat::TSi | HFormat::TLiSi => Vec::new(),
        };
        for (side, grid, want) in dims {
            if grid.format == GridFormat::XY3 && grid.shape != want {
                return Err(format!(
                    "`{side}_grid_xyz` is a {:?} grid but `H` ({}) has {want:?} there",
                    grid.shape,
                    self.h_format.name()
                ));
            }
        }
        let (ns, nl) = (self.sensor_grid.points.len(), self.laser_grid.points.len());
        if self.h_format.is_product() {
            if columns != nl * ns {
                return Err(format!(
                    "`H` ({}) has {columns} transients but the laser grid has {nl} points and the \
                     sensor grid {ns}",
                    self.h_format.name()
                ));
            }
        } else {
            if columns != ns {
                return Err(format!(
                    "`H` ({}) has {columns} transients but `sensor_grid_xyz` has {ns} points",
                    self.h_format.name()
                ));
            }
            if nl != ns && nl != 1 {
                return Err(format!(
                    "`laser_grid_xyz` has {nl} points: with `H_format` {} it must have one (a fixed \
                     laser) or one per sensor point ({ns})",
                    self.h_format.name()
                ));
            }
        }
        if self.t_accounts_first_and_last_bounces && (self.laser_xyz.is_none() || self.sensor_xyz.is_none()) {
            return Err(
                "`t_accounts_first_and_last_bounces` is true but `laser_xyz` or `sensor_xyz` is \
                        empty, so the first and last legs cannot be subtracted"
                    .into(),
            );
        }
        if let Some(flags) = &self.flags
            && flags.len() != columns
        {
            return Err(format!(
                "the capture has {} histogram flags but `H` has {columns} transients",
                flags.len()
            ));
        }
        if Some(self.h.len()) != self.bins().checked_mul(columns) {
            return Err(format!(
                "`H` holds {} values, its shape {:?} says otherwise",
                self.h.len(),
                self.h_shape
            ));
        }
        Ok(())
    }

    /// The renderer that made the capture, if `scene_info` says it was rendered: a
    /// top-level `renderer` entry (mitransient's harnesses), or y-tal's documented
    /// `config` entry, which `tal render` writes (its scene configuration). Measured
    /// captures carry neither. Rendered lasers are point sources
    /// ([`crate::plan::LaserFalloff::Auto`]).
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

    /// Laser and sensor point indices of transient `c`.
    pub fn indices(&self, c: usize) -> (usize, usize) {
        let ns = self.sensor_grid.points.len();
        if self.h_format.is_product() {
            (c / ns, c % ns)
        } else if self.laser_grid.points.len() == 1 {
            (0, c)
        } else {
            (c, c)
        }
    }

    /// The relay pair of transient `c`.
    pub fn pair(&self, c: usize) -> Pair {
        let (l, s) = self.indices(c);
        Pair {
            xi: self.laser_grid.points[l],
            ni: self.laser_grid.normals[l],
            xd: self.sensor_grid.points[s],
            nd: self.sensor_grid.normals[s],
        }
    }

    /// Transient `c`, time bins in order.
    pub fn transient(&self, c: usize) -> impl Iterator<Item = f32> + '_ {
        let stride = self.len();
        self.h.iter().skip(c).step_by(stride).copied()
    }

    /// Path length at the start of transient `c`'s bin 0, in hidden path length (legs
    /// from the laser and to the SPAD removed when the file includes them).
    pub fn hidden_start(&self, c: usize) -> f64 {
        if !self.t_accounts_first_and_last_bounces {
            return self.t_start;
        }
        let p = self.pair(c);
        let legs = match (self.laser_xyz, self.sensor_xyz) {
            (Some(l), Some(s)) => p.xi.distance(l) + p.xd.distance(s),
            _ => 0.0, // excluded by `check`
        };
        self.t_start - legs
    }

    /// All transients rebinned onto the hidden-path axis for `volume`, at the file's bin
    /// width, where the file recorded it (the axis stops where the last transient's time
    /// window ends, and starts no earlier than the first one's begins, even when the
    /// volume's paths reach further: [`clip_to_measured`]). Transients with no counts
    /// are left out, and so are those the flags mark overflowed (their counts are only
    /// a lower bound), as in a run's own reconstruction.
    pub fn transients(&self, volume: &VolumeGrid) -> Result<TransientSet, YtalError> {
        let pairs: Vec<Pair> = (0..self.len()).map(|c| self.pair(c)).collect();
        let axis: TimeAxis =
            hidden_axis(&pairs, volume, self.delta_t / C0).map_err(|e| self.error(e.to_string()))?;
        // Only the paths some transient recorded: beyond the file's time window the
        // rebinned histograms would hold zeros nobody measured.
        let span = self.bins() as f64 * self.delta_t;
        let measured = (0..self.len())
            .map(|c| self.hidden_start(c))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| {
                (lo.min(s), hi.max(s + span))
            });
        let axis = clip_to_measured(&axis, measured).map_err(|e| self.error(e.to_string()))?;
        let bytes = (pairs.len() as u64)
            .saturating_mul(axis.bins as u64)
            .saturating_mul(8);
        if bytes > MAX_TRANSIENT_BYTES {
            return Err(self.error(format!(
                "{} transients of {} bins would take {bytes} bytes, more than {MAX_TRANSIENT_BYTES}: \
                 give a smaller [volume] or a coarser capture",
                pairs.len(),
                axis.bins
            )));
        }
        let mut set = TransientSet::new(axis).map_err(|e| self.error(e.to_string()))?;
        // Whole non-negative numbers throughout: a photon-counting capture.
        let mut whole = true;
        for (c, pair) in pairs.into_iter().enumerate() {
            if self.flags.as_ref().is_some_and(|f| f[c] & FLAG_OVERFLOW != 0) {
                continue;
            }
            whole &= self.transient(c).all(|v| v >= 0.0 && v.fract() == 0.0);
            let h = rebin_path(self.transient(c), self.hidden_start(c), self.delta_t, &axis);
            if h.iter().any(|&v| v != 0.0) {
                set.push(pair, &h).map_err(|e| self.error(e.to_string()))?;
            }
        }
        if whole {
            set.mark_photon_counts();
        }
        Ok(set)
    }

    fn error(&self, message: String) -> YtalError {
        YtalError::Format {
            path: PathBuf::from("<capture>"),
            message,
        }
    }

    /// A reconstruction volume for a capture that comes with none: over the relay
    /// points' extent, from 5 cm in front of the relay out to the depth the time axis
    /// reaches (at most 3 m), on the side the normals face.
    pub fn default_volume(&self) -> Result<VolumeGrid, YtalError> {
        let pts: Vec<DVec3> = self
            .sensor_grid
            .points
            .iter()
            .chain(&self.laser_grid.points)
            .copied()
            .collect();
        let normal = self
            .sensor_grid
            .normals
            .iter()
            .fold(DVec3::ZERO, |a, &n| a + n)
            .normalize_or_zero();
        if normal == DVec3::ZERO {
            return Err(self.error("the sensor normals cancel out; give a RECON.toml with a [volume]".into()));
        }
        let (lo, hi) = pts.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(a, b), &p| (a.min(p), b.max(p)),
        );
        let reach = (0..self.len())
            .map(|c| self.hidden_start(c))
            .fold(f64::NEG_INFINITY, f64::max)
            + self.delta_t * self.bins() as f64;
        let depth = (0.5 * reach).clamp(0.2, 3.0);
        let (near, far) = (lo + normal * 0.05, hi + normal * depth);
        let (a, b) = (near.min(far).min(lo), near.max(far).max(hi));
        // Keep the relay itself out of the volume along the normal axis.
        let axis = normal.abs().max_element();
        let mut min = a;
        let mut max = b;
        for k in 0..3 {
            if normal[k].abs() == axis {
                if normal[k] > 0.0 {
                    min[k] = hi[k] + 0.05;
                    max[k] = hi[k] + depth;
                } else {
                    max[k] = lo[k] - 0.05;
                    min[k] = lo[k] - depth;
                }
            }
        }
        VolumeGrid::new([min.x, max.x], [min.y, max.y], [min.z, max.z], [64, 64, 64])
            .map_err(|e| self.error(e.to_string()))
    }

    /// A point on the side of the relay the normals face (orients the virtual relay).
    pub fn viewpoint(&self) -> DVec3 {
        let n = self.sensor_grid.points.len() as f64;
        let centre = self.sensor_grid.points.iter().fold(DVec3::ZERO, |a, &p| a + p) / n;
        let normal = self.sensor_grid.normals.iter().fold(DVec3::ZERO, |a, &p| a + p) / n;
        centre + normal
    }

    /// Writes the capture in y-tal's own layout (what `tal.io.write_capture` writes), so
    /// y-tal and h5py read it. The file is replaced atomically.
    pub fn write(&self, path: &Path) -> Result<(), YtalError> {
        let bytes = self.to_bytes().map_err(|e| YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: format!("cannot be encoded: {e}"),
        })?;
        crate::store::write_atomic(path, &bytes).map_err(|e| YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: format!("cannot be written: {e}"),
        })
    }

    /// The capture as the bytes of a y-tal HDF5 file (what [`YtalCapture::write`] stores).
    pub fn to_bytes(&self) -> Result<Vec<u8>, hdf5_pure::Error> {
        let h_type = enum_type(
            make_i32_type(),
            &[
                ("UNKNOWN", 0),
                ("T_Sx_Sy", 1),
                ("T_Lx_Ly_Sx_Sy", 2),
                ("T_Si", 3),
                ("T_Li_Si", 4),
            ],
        )?;
        let grid_type = enum_type(make_i32_type(), &[("UNKNOWN", 0), ("N_3", 1), ("X_Y_3", 2)])?;
        // numpy booleans, as h5py stores them.
        let bool_type = enum_type(make_i8_type(), &[("FALSE", 0), ("TRUE", 1)])?;
        let shape = |s: &[usize]| s.iter().map(|&d| d as u64).collect::<Vec<u64>>();
        let mut b = FileBuilder::new();
        b.create_dataset("H")
            .with_f32_data(&self.h)
            .with_shape(&shape(&self.h_shape))
            .with_chunks(&chunks(&self.h_shape))
            .with_deflate(4);
        b.create_dataset("H_format")
            .with_enum_i32_data(h_type, &[self.h_format as i32]);
        for (side, grid) in [("sensor", &self.sensor_grid), ("laser", &self.laser_grid)] {
            let mut gshape = shape(&grid.shape);
            gshape.push(3);
            let flat = |v: &[DVec3]| {
                v.iter()
                    .flat_map(|p| [p.x as f32, p.y as f32, p.z as f32])
                    .collect::<Vec<f32>>()
            };
            b.create_dataset(&format!("{side}_grid_xyz"))
                .with_f32_data(&flat(&grid.points))
                .with_shape(&gshape);
            b.create_dataset(&format!("{side}_grid_normals"))
                .with_f32_data(&flat(&grid.normals))
                .with_shape(&gshape);
            b.create_dataset(&format!("{side}_grid_format"))
                .with_enum_i32_data(grid_type.clone(), &[grid.format as i32]);
        }
        // An unknown origin is left out, which y-tal reads as `None`.
        for (name, origin) in [("sensor_xyz", self.sensor_xyz), ("laser_xyz", self.laser_xyz)] {
            if let Some(p) = origin {
                b.create_dataset(name)
                    .with_f32_data(&[p.x as f32, p.y as f32, p.z as f32]);
            }
        }
        b.create_dataset("delta_t")
            .with_f64_data(&[self.delta_t])
            .with_shape(&[]);
        b.create_dataset("t_start")
            .with_f64_data(&[self.t_start])
            .with_shape(&[]);
        b.create_dataset("t_accounts_first_and_last_bounces")
            .with_enum_u8_data(bool_type, &[u8::from(self.t_accounts_first_and_last_bounces)])
            .with_shape(&[]);
        let mut info = self.scene_info.clone();
        if let Some(flags) = &self.flags {
            let text = info.get_or_insert_with(String::new);
            if !(text.is_empty() || text.ends_with('\n')) {
                text.push('\n');
            }
            for (key, bit) in FLAG_KEYS {
                let list: Vec<String> = (0..flags.len())
                    .filter(|&i| flags[i] & bit != 0)
                    .map(|i| i.to_string())
                    .collect();
                text.push_str(&format!("{key}: [{}]\n", list.join(", ")));
            }
        }
        if let Some(info) = &info {
            b.create_dataset("scene_info")
                .with_vlen_strings(&[info])
                .with_shape(&[]);
        }
        b.finish()
    }
}

fn enum_type(base: Datatype, members: &[(&str, i32)]) -> Result<Datatype, hdf5_pure::FormatError> {
    members
        .iter()
        .fold(EnumTypeBuilder::with_base(base), |b, &(name, v)| b.value(name, v))
        .build()
}

/// Chunks of about 256 KiB for `H`: whole time axis, as many transients as fit.
fn chunks(shape: &[usize]) -> Vec<u64> {
    let t = shape[0].max(1);
    let mut left = (65_536 / t).max(1);
    let mut out = vec![t as u64];
    for &d in shape[1..].iter().rev() {
        let take = d.min(left).max(1);
        out.push(take as u64);
        left = (left / take).max(1);
    }
    out[1..].reverse();
    out
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

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> YtalCapture {
        let points: Vec<DVec3> = (0..6)
            .map(|i| DVec3::new(0.1 * i as f64, -0.05 * i as f64, 0.0))
            .collect();
        let grid = |points: Vec<DVec3>, shape: Vec<usize>, format| Grid {
            normals: vec![DVec3::Z; points.len()],
            points,
            format,
            shape,
        };
        YtalCapture {
            h: (0..5 * 6 * 2).map(|v| v as f32 * 0.5).collect(),
            h_shape: vec![5, 2, 6],
            h_format: HFormat::TLiSi,
            sensor_grid: grid(points.clone(), vec![2, 3], GridFormat::XY3),
            laser_grid: grid(points[..2].to_vec(), vec![2], GridFormat::N3),
            sensor_xyz: Some(DVec3::new(0.2, 0.0, 1.0)),
            laser_xyz: None,
            delta_t: 0.004,
            t_start: 1.5,
            t_accounts_first_and_last_bounces: false,
            scene_info: Some("original_format: test\n".into()),
            flags: Some(vec![0, 1, 2, 3, 0, 0, 0, 0, 0, 0, 0, 0]),
        }
    }

    #[test]
    fn a_rendered_capture_is_told_from_its_scene_info() {
        let with = |info: Option<&str>| YtalCapture {
            scene_info: info.map(str::to_string),
            ..sample()
        };
        // The validation harness's mitransient captures.
        let harness = "description: a letter\nrenderer: 'mitransient 1.3.1 / mitsuba 3.9.1'\nspp: 262144\n";
        assert_eq!(
            with(Some(harness)).rendered_by().as_deref(),
            Some("mitransient 1.3.1 / mitsuba 3.9.1")
        );
        // `tal render`'s, as PyYAML dumps them (keys sorted, the config a mapping).
        let tal =
            "args:\n  threads: 2\nconfig:\n  laser_x: -0.5\n  scan_type: confocal\ntal_version: 0.20.0\n";
        assert_eq!(
            with(Some(tal)).rendered_by().as_deref(),
            Some("y-tal's `tal render`")
        );
        // Measured or exported captures, and keys that only mention a renderer.
        for info in [
            None,
            Some(""),
            Some("original_format: periscope\nrun: 'x'\n"),
            Some("original_format: HDF5_ZNLOS\nvolume:\n  config: 1\n"),
            Some("notes: the renderer: was not used\n"),
        ] {
            assert_eq!(with(info).rendered_by(), None, "{info:?}");
        }
    }

    #[test]
    fn a_written_capture_reads_back_identically() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("c.hdf5");
        let c = sample();
        c.write(&path).unwrap();
        let back = YtalCapture::read(&path).unwrap();
        // Points go through f32 in the file, as y-tal stores them.
        let round = |g: &Grid| Grid {
            points: g.points.iter().map(|p| p.as_vec3().as_dvec3()).collect(),
            ..g.clone()
        };
        assert_eq!(back.sensor_grid, round(&c.sensor_grid));
        assert_eq!(back.laser_grid, round(&c.laser_grid));
        assert_eq!(back.h, c.h);
        assert_eq!(back.h_shape, c.h_shape);
        assert_eq!(back.h_format, c.h_format);
        assert_eq!(back.laser_xyz, None);
        assert_eq!(back.sensor_xyz, c.sensor_xyz.map(|p| p.as_vec3().as_dvec3()));
        assert_eq!((back.delta_t, back.t_start), (c.delta_t, c.t_start));
        assert!(!back.t_accounts_first_and_last_bounces);
        assert_eq!(back.scene_info, c.scene_info);
    }

    #[test]
    fn transients_are_indexed_laser_major_and_time_first() {
        let c = sample();
        // H is (T=5, L=2, S=6): transient c = l·6 + s, value at (t, c) = h[t·12 + c].
        assert_eq!(c.indices(7), (1, 1));
        let t: Vec<f32> = c.transient(7).collect();
        assert_eq!(t, (0..5).map(|k| (k * 12 + 7) as f32 * 0.5).collect::<Vec<_>>());
        assert_eq!(c.pair(7).xi, c.laser_grid.points[1]);
        assert_eq!(c.pair(7).xd, c.sensor_grid.points[1]);
    }

    #[test]
    fn legs_are_subtracted_when_the_file_includes_them() {
        let mut c = sample();
        c.t_accounts_first_and_last_bounces = true;
        c.laser_xyz = Some(DVec3::new(0.0, 0.0, 1.0));
        let p = c.pair(3);
        let legs = p.xi.distance(c.laser_xyz.unwrap()) + p.xd.distance(c.sensor_xyz.unwrap());
        assert!((c.hidden_start(3) - (1.5 - legs)).abs() < 1e-12);
        c.laser_xyz = None;
        assert!(c.check().unwrap_err().contains("laser_xyz"));
    }

    /// The hidden axis stops where the file's recording does: a volume whose far paths
    /// reach beyond the time window gets no bins past it (they would be zeros nobody
    /// measured), the recorded counts all land on the axis, and a volume the window
    /// does not reach is refused with the file and the remedy named.
    #[test]
    fn the_hidden_axis_keeps_to_the_recorded_window() {
        // 64 bins of 1 cm from 0.5 m: paths 0.5 to 1.14 m, seen confocally from six
        // points with no legs in the times.
        let mut c = sample();
        c.h_format = HFormat::TSi;
        c.h_shape = vec![64, 6];
        c.laser_grid = c.sensor_grid.clone();
        c.delta_t = 0.01;
        c.t_start = 0.5;
        c.h = (0..64 * 6).map(|v| (v % 7) as f32).collect();
        c.flags = None;
        c.check().unwrap();
        // Paths from 2 × 0.2 m to past 2 m: beyond the recording at both ends.
        let deep = VolumeGrid::new([-0.3, 0.3], [-0.3, 0.3], [0.2, 1.0], [8, 8, 8]).unwrap();
        let set = c.transients(&deep).unwrap();
        let axis = *set.axis();
        assert!(axis.start >= 0.5 - 1e-9, "{axis:?}");
        assert!(axis.end() <= 1.14 + 1e-9, "{axis:?}");
        assert_eq!(axis.bins, 64, "every recorded bin is kept: {axis:?}");
        let recorded: f64 = c.h.iter().map(|&v| f64::from(v)).sum();
        let kept: f64 = (0..set.len())
            .map(|i| set.histogram(i).iter().map(|&v| f64::from(v)).sum::<f64>())
            .sum();
        assert!(
            (kept - recorded).abs() < 1e-6 * recorded,
            "{kept} of {recorded} counts"
        );
        // A volume 3 m away: its paths start beyond the recording's end.
        let far = VolumeGrid::new([-0.3, 0.3], [-0.3, 0.3], [3.0, 3.5], [8, 8, 8]).unwrap();
        let e = c.transients(&far).unwrap_err().to_string();
        assert!(e.contains("do not reach") && e.contains("[volume]"), "{e}");
    }

    #[test]
    fn mismatched_grids_are_refused_with_the_dataset_named() {
        let mut c = sample();
        c.h_format = HFormat::TSi;
        c.h_shape = vec![5, 12];
        let e = c.check().unwrap_err();
        assert!(e.contains("sensor_grid_xyz") && e.contains("12"), "{e}");
        let mut c = sample();
        c.laser_grid.points.push(DVec3::ZERO);
        c.laser_grid.normals.push(DVec3::Z);
        assert!(c.check().unwrap_err().contains("laser grid has 3 points"));
    }

    #[test]
    fn files_that_are_not_y_tal_captures_get_a_clear_message() {
        let dir = tempfile::tempdir().unwrap();
        let text = dir.path().join("notes.hdf5");
        std::fs::write(&text, "not hdf5").unwrap();
        let e = YtalCapture::read(&text).unwrap_err().to_string();
        assert!(e.contains("notes.hdf5") && e.contains("HDF5"), "{e}");
        let other = dir.path().join("znlos.hdf5");
        let mut b = FileBuilder::new();
        b.create_dataset("data").with_f32_data(&[0.0; 4]);
        std::fs::write(&other, b.finish().unwrap()).unwrap();
        let e = YtalCapture::read(&other).unwrap_err().to_string();
        assert!(e.contains("no dataset `H`") && e.contains("`data`"), "{e}");
    }
}

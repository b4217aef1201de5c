//! Decoding a capture: the datasets read through [`Reader`], the histogram flags taken
//! out of `scene_info`, and the checks that `H`, the grids and the origins fit
//! together. A panic inside the HDF5 layer becomes an error that names the file.
use std::path::Path;

use hdf5_pure::File;

use super::dataset::Reader;
use super::{FLAG_KEYS, Grid, GridFormat, HFormat, MAX_FILE_BYTES, YtalCapture, YtalError};

/// Splits the flag lists out of a `scene_info` text: the text without them, and the
/// (index, bit) pairs they name. A list is read in YAML's flow style, as Periscope
/// writes it (`periscope_overflow: [3, 17]`), or its block style, as y-tal writes it
/// back after reading the file (PyYAML's `yaml.dump`: the key alone, then one `- 3`
/// line an item). `Err` names a malformed list.
fn take_flags(info: &str) -> Result<(String, Vec<(usize, u8)>), String> {
    let mut rest = String::new();
    let mut marks = Vec::new();
    let index = |key: &str, item: &str| {
        item.parse::<usize>()
            .map_err(|_| format!("`scene_info` key `{key}` lists {item:?}, not a transient index"))
    };
    let mut lines = info.lines().peekable();
    while let Some(line) = lines.next() {
        match FLAG_KEYS.iter().find_map(|(key, bit)| {
            line.strip_prefix(key)
                .and_then(|l| l.strip_prefix(':'))
                .map(|l| (key, *bit, l))
        }) {
            Some((key, bit, list)) if list.trim().is_empty() => {
                // Block style: the items follow, each `- N`, at most indented.
                while let Some(item) = lines
                    .peek()
                    .and_then(|l| l.trim_start().strip_prefix('-'))
                    .map(str::trim)
                {
                    marks.push((index(key, item)?, bit));
                    lines.next();
                }
            }
            Some((key, bit, list)) => {
                let inner = list
                    .trim()
                    .strip_prefix('[')
                    .and_then(|l| l.strip_suffix(']'))
                    .ok_or_else(|| {
                        format!("`scene_info` key `{key}` should be a list like [3, 17], it is {list:?}")
                    })?;
                for item in inner.split(',').map(str::trim).filter(|s| !s.is_empty()) {
                    marks.push((index(key, item)?, bit));
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

/// A `scene_info` that says nothing (empty, or the empty mapping `{}` the writer puts
/// where there is none) reads as none.
fn says_something(info: String) -> Option<String> {
    let t = info.trim();
    (!t.is_empty() && t != "{}").then_some(info)
}

/// Runs a decode, turning a panic inside the HDF5 or MAT layer into an error that names the
/// file. The fuzzer found malformed chunk layouts that make hdf5-pure 0.47 overflow
/// an offset (`chunked_read.rs`, `copy_chunk_to_output`): a malformed file must be
/// an error for the user, never a crash of `recon` or of the daemon.
pub(crate) fn guarded<T>(path: &Path, decode: impl FnOnce() -> Result<T, YtalError>) -> Result<T, YtalError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(decode)).unwrap_or_else(|payload| {
        Err(YtalError::Hdf5 {
            path: path.to_path_buf(),
            message: format!(
                "is malformed: its decoder failed on it ({}); it is not a capture that can be read",
                panic_message(payload.as_ref())
            ),
        })
    })
}

/// The text a panic was raised with.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_owned())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

/// Peak memory per value of `H` while it is read and reconstructed, bytes: the values
/// as read (4), the HDF5 layer's decompressed chunks (4), and the transient set's counts
/// and weights (8).
const BYTES_PER_H_VALUE: u64 = 16;

/// y-tal's name for a frequency-domain `H_format` code (`tal.enums.HFormat` 10 to 13).
fn frequency_format(code: f64) -> Option<&'static str> {
    [
        (10.0, "F_Sx_Sy"),
        (11.0, "F_Lx_Ly_Sx_Sy"),
        (12.0, "F_Si"),
        (13.0, "F_Li_Si"),
    ]
    .into_iter()
    .find(|&(c, _)| c == code)
    .map(|(_, name)| name)
}

/// Bytes in a GiB, for messages.
const GIB: f64 = (1u64 << 30) as f64;

/// Whether reading and reconstructing a transient array of `shape` (dataset `name`)
/// fits what this process can still allocate. Each size check on a dataset holds on
/// its own; what the whole read takes must fit too, or the read would abort the
/// process instead of failing. The file, which the HDF5 layer holds whole while it
/// decodes, is already read by then, so what is left has counted it
/// ([`file_memory_check`] judged it before the read). `Err` says how much it needs and
/// what to do.
pub(crate) fn memory_check(shape: &[usize], name: &str) -> Result<(), String> {
    let values = shape.iter().map(|&d| d as u64).product::<u64>();
    let need = values.saturating_mul(BYTES_PER_H_VALUE);
    match crate::io::memory_available() {
        Some(available) if need > available => Err(format!(
            "`{name}` holds {values} values (shape {shape:?}): reading and reconstructing it takes about \
             {:.1} GiB, more than the {:.1} GiB this process can still use (free memory, its \
             address-space limit, and the memory limit of the container or service it runs in): \
             reconstruct it where more is free, or crop it (fewer bins or relay points) first",
            need as f64 / GIB,
            available as f64 / GIB
        )),
        _ => Ok(()),
    }
}

/// Whether an HDF5 file of `len` bytes, which the reader holds whole in memory while it
/// decodes, fits what this process can still allocate: checked before it is read, so
/// that a file larger than the memory left fails with this message instead of the
/// process being killed. `Err` says what to do.
pub(crate) fn file_memory_check(len: u64) -> Result<(), String> {
    match crate::io::memory_available() {
        Some(available) if len > available => Err(format!(
            "is {:.1} GiB, which is read whole into memory to be decoded, more than the {:.1} GiB this \
             process can still use (free memory, its address-space limit, and the memory limit of the \
             container or service it runs in): reconstruct it where more is free, or crop it first",
            len as f64 / GIB,
            available as f64 / GIB
        )),
        _ => Ok(()),
    }
}

/// The largest magnitude of an `H` value: sums of up to 10^8 such values stay finite in
/// single precision (f32::MAX is about 3.4e38).
const MAX_H_VALUE: f32 = 1e30;

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
        file_memory_check(file_len).map_err(|message| YtalError::Hdf5 {
            path: path.to_path_buf(),
            message,
        })?;
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

    pub(crate) fn decode(file: File, path: &Path, file_len: u64) -> Result<YtalCapture, YtalError> {
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
            r.format(match frequency_format(code) {
                Some(name) => format!(
                    "`H_format` is {code} ({name}), one of y-tal's frequency-domain layouts: `H` holds only \
                     the band of the transients' spectrum its phasor-field wavelengths use, from which the \
                     time-domain transients every Periscope method fits cannot be recovered. Reconstruct \
                     it with y-tal (`tal.reconstruct.pf_dev`), or render or export the capture in the time \
                     domain (`histogram_mode: time`, H_format 1 to 4)"
                ),
                None => format!("`H_format` is {code}; expected 1 to 4 (T_Sx_Sy … T_Li_Si)"),
            })
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
        if h_shape.len() == rank + 1 && h_shape[rank] == 4 && !h_shape.contains(&0) {
            // y-tal's polarised renders keep the Stokes parameters on a last axis.
            return Err(r.format(format!(
                "`H` has shape {h_shape:?}: `H_format` {} with a last axis of 4, a polarised render (its Stokes \
                 parameters); Periscope reconstructs intensity: keep the first (h5py: `f['H'] = f['H'][..., 0]` \
                 into a new file), as y-tal's reader says to",
                h_format.name()
            )));
        }
        if h_shape.len() != rank || h_shape.contains(&0) {
            return Err(r.format(format!(
                "`H` has shape {h_shape:?} but `H_format` {} needs {rank} non-empty dimensions",
                h_format.name()
            )));
        }
        memory_check(&h_shape, "H").map_err(|m| r.format(m))?;
        let h = ds.read_f32().map_err(|e| {
            let half = matches!(ds.dtype(), Ok(hdf5_pure::DType::Other(_)))
                && ds.element_size().is_ok_and(|n| n == 2);
            r.format(if half {
                "dataset `H` holds 16-bit floats (float16), which this reader does not decode: store it as \
                 float32 (h5py: `f['H'] = f['H'][()].astype('float32')` into a new file)"
                    .to_owned()
            } else {
                format!("dataset `H` is not numeric: {e}")
            })
        })?;
        if let Some(i) = h.iter().position(|v| !v.is_finite()) {
            return Err(r.format(format!("`H` value {i} is not finite")));
        }
        if let Some(i) = h.iter().position(|v| v.abs() > MAX_H_VALUE) {
            return Err(r.format(format!(
                "`H` value {i} is {:e}: sums over the capture would overflow single precision \
                 (values above {MAX_H_VALUE:e} are refused); divide `H` by a constant first, the \
                 reconstruction does not depend on its scale",
                h[i]
            )));
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
        // A `scene_info` that is there but cannot be read is said: the histogram flags
        // (overflowed transients, left out of the fit) are kept in it, and without
        // them every transient is taken as good.
        let scene_info = match r.file.dataset("scene_info") {
            Err(_) => None,
            Ok(d) => match r
                .checked_shape(&d, "scene_info", 1 << 16)
                .map_err(|e| e.to_string())
                .and_then(|_| d.read_string().map_err(|e| e.to_string()))
            {
                Ok(v) => v.into_iter().next().and_then(says_something),
                Err(e) => {
                    tracing::warn!(
                        capture = %r.path.display(),
                        "`scene_info` cannot be read as text ({e}): the capture's provenance and any \
                         histogram flags it holds are not used, so every transient is taken as good"
                    );
                    None
                }
            },
        };
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
            capture.scene_info = says_something(rest);
            capture.flags = Some(flags);
        }
        capture.check().map_err(|m| r.format(m))?;
        Ok(capture)
    }

    /// Checks that `H`, the grids and the origins fit together, and that every point,
    /// normal and origin is finite (a reader that derives them from a header value,
    /// as the LCT and f-k readers do from `width`, hands on what that value makes).
    pub(crate) fn check(&self) -> Result<(), String> {
        if self.h_shape.is_empty() {
            return Err("`H` has no shape: it needs a time axis and the relay's".into());
        }
        for (side, grid) in [("laser", &self.laser_grid), ("sensor", &self.sensor_grid)] {
            if let Some(i) = grid.points.iter().position(|p| !p.is_finite()) {
                return Err(format!(
                    "point {i} of the {side} grid is {}: every relay point must be finite",
                    grid.points[i]
                ));
            }
            if let Some(i) = grid.normals.iter().position(|n| !n.is_finite()) {
                return Err(format!(
                    "normal {i} of the {side} grid is {}: every normal must be finite",
                    grid.normals[i]
                ));
            }
        }
        for (name, origin) in [("laser_xyz", self.laser_xyz), ("sensor_xyz", self.sensor_xyz)] {
            if let Some(o) = origin
                && !o.is_finite()
            {
                return Err(format!("`{name}` is {o}: it must be a finite point"));
            }
        }
        let columns: usize = self.h_shape[1..]
            .iter()
            .try_fold(1usize, |a, &d| a.checked_mul(d))
            .ok_or("the shape of `H` overflows")?;
        // Grids stored as (X, Y, 3) must match `H`'s own dimensions, not only in count:
        // a transposed grid would put every transient at the wrong point.
        let dims: Vec<(&str, &Grid, &[usize])> = match self.h_format {
            // A laser grid with a point per sensor point pairs them by position: a
            // transposed one of the same count would pair each with another's laser.
            HFormat::TSxSy if self.laser_grid.points.len() > 1 => vec![
                ("sensor", &self.sensor_grid, &self.h_shape[1..3]),
                ("laser", &self.laser_grid, &self.h_shape[1..3]),
            ],
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
}

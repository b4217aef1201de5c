//! Every public NLOS capture format, read into one in-memory capture
//! ([`YtalCapture`]: transients, relay grids, bin width, time origin), so every method
//! reconstructs any of them. [`read_capture`] tells the format from the file's
//! contents, not its name:
//!
//! | format | container | told by | reader |
//! |---|---|---|---|
//! | y-tal (`tal.io.write_capture`, mitransient, Periscope's exports) | HDF5 | `H` | [`YtalCapture`] |
//! | Zaragoza ZNLOS (Galindo et al. 2019) | HDF5 | `data` | [`znlos`] |
//! | Stanford confocal LCT (O'Toole et al. 2018) | MAT v5 or v7.3 | `rect_data` and `width` | [`crate::io::lct`] |
//! | Stanford f-k (Lindell et al. 2019) | MAT v7.3 (or v5) | `meas`, with `tofgrid` in `tof.mat` beside it | [`fk`] |
//! | phasor field (Liu et al. 2019, Nature) | MAT v7.3 | a `dataset` struct | [`phasor`] |
//! | phasor-field diffraction (Liu et al. 2020) | MAT v7.3 (or v5) | `rect_data`, `ts`, `SPAD_index` | [`phasor`] |
//!
//! y-tal's frequency-domain `H_format`s (10 to 13) and its deprecated `data_t` layout
//! are refused by name, with what to do. The layouts, each claim cited from the
//! formats' reference code: docs/research/nlos-capture-formats.md; how each maps onto
//! a capture: docs/formats.md.
use std::io::Read as _;
use std::path::Path;

use hdf5_pure::File;

use super::ytal::{Grid, GridFormat, Reader, YtalCapture, YtalError, guarded};

pub mod fk;
pub(crate) mod mat;
pub mod phasor;
pub mod znlos;

use mat::Mat;

/// Largest capture file read, bytes (as for y-tal captures).
pub const MAX_FILE_BYTES: u64 = super::ytal::MAX_FILE_BYTES;

/// Speed of light, m/s (the formats that give bins in seconds).
pub(crate) const C: f64 = 299_792_458.0;

/// The largest half side, metres, a Stanford capture's `width` may give its scanned
/// square (the phasor layouts' `spacing` is bounded by 10 m the same way): a relay
/// wider than a building is a damaged header, and a huge one makes its grid's points
/// infinite (`2·width` overflows at 1e308).
pub(crate) const MAX_HALF_SIDE_M: f64 = 50.0;

/// What a file's first bytes say it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Container {
    /// MATLAB v5 (`save`, scipy's `savemat`).
    MatV5,
    /// MATLAB v5 written big-endian: refused by name.
    MatV5BigEndian,
    /// HDF5, with or without a userblock (MAT v7.3 is HDF5 after 512 bytes).
    Hdf5,
    /// Neither.
    Unknown,
}

fn container(head: &[u8]) -> Container {
    if head.len() >= 128 && head[126..128] == *b"IM" && head[124..126] == [0x00, 0x01] {
        return Container::MatV5;
    }
    // A MAT v5 file written on a big-endian machine ("MI", version 0x0100).
    if head.len() >= 128 && head[126..128] == *b"MI" && head[124..126] == [0x01, 0x00] {
        return Container::MatV5BigEndian;
    }
    const SIGNATURE: &[u8; 8] = b"\x89HDF\r\n\x1a\n";
    // The HDF5 superblock sits at 0, 512, 1024, ... (a userblock before it).
    let mut at = 0usize;
    while at + 8 <= head.len() {
        if head[at..at + 8] == *SIGNATURE {
            return Container::Hdf5;
        }
        at = if at == 0 { 512 } else { at * 2 };
    }
    Container::Unknown
}

/// Whether a file's first bytes (a few KiB) are those of a container some capture
/// format uses: MATLAB v5, or HDF5 (at 0 or after a userblock, as MAT v7.3). A cheap
/// test before a file is read whole (the daemon's import checks an upload with it).
pub fn is_capture_container(head: &[u8]) -> bool {
    container(head) != Container::Unknown
}

fn hdf5_error(path: &Path, message: impl Into<String>) -> YtalError {
    YtalError::Hdf5 {
        path: path.to_owned(),
        message: message.into(),
    }
}

/// Reads a capture in any format this module knows (table above), telling the format
/// from the contents. An f-k measurement finds its `tof.mat` in its own directory.
pub fn read_capture(path: &Path) -> Result<YtalCapture, YtalError> {
    let meta = std::fs::metadata(path).map_err(|e| hdf5_error(path, format!("cannot be read ({e})")))?;
    if !meta.is_file() {
        return Err(hdf5_error(path, "is not a file"));
    }
    if meta.len() > MAX_FILE_BYTES {
        return Err(hdf5_error(
            path,
            format!(
                "is {} bytes, more than the {MAX_FILE_BYTES} a capture file may have here",
                meta.len()
            ),
        ));
    }
    let mut head = Vec::with_capacity(4096);
    std::fs::File::open(path)
        .and_then(|f| f.take(4096).read_to_end(&mut head))
        .map_err(|e| hdf5_error(path, format!("cannot be read ({e})")))?;
    match container(&head) {
        Container::MatV5 => {
            let bytes = super::read_regular_capped(path, super::lct::MAX_FILE_BYTES)
                .map_err(|e| hdf5_error(path, e.to_string()))?;
            // A fault a hostile file finds in a decoder is the file's error, as for HDF5.
            guarded(path, || from_v5(&bytes, path, path.parent()))
        }
        Container::Hdf5 => {
            super::ytal::file_memory_check(meta.len()).map_err(|m| hdf5_error(path, m))?;
            guarded(path, || {
                let file = File::open(path)
                    .map_err(|e| hdf5_error(path, format!("cannot be read as HDF5 ({e})")))?;
                from_hdf5(file, path, meta.len(), path.parent())
            })
        }
        Container::Unknown => Err(not_a_capture(path)),
        Container::MatV5BigEndian => Err(big_endian(path)),
    }
}

/// Reads a capture held in memory (`name` is used in messages), with the same checks
/// as [`read_capture`]; files a format keeps beside the capture (f-k's `tof.mat`) are
/// not looked for.
pub fn capture_from_bytes(bytes: Vec<u8>, name: &Path) -> Result<YtalCapture, YtalError> {
    match container(&bytes[..bytes.len().min(4096)]) {
        Container::MatV5 => guarded(name, || from_v5(&bytes, name, None)),
        Container::Hdf5 => {
            let len = bytes.len() as u64;
            guarded(name, || {
                let file = File::from_bytes(bytes)
                    .map_err(|e| hdf5_error(name, format!("cannot be read as HDF5 ({e})")))?;
                from_hdf5(file, name, len, None)
            })
        }
        Container::Unknown => Err(not_a_capture(name)),
        Container::MatV5BigEndian => Err(big_endian(name)),
    }
}

fn big_endian(path: &Path) -> YtalError {
    hdf5_error(
        path,
        "is a MATLAB v5 file written big-endian, which Periscope does not read: save it again with \
         `save(..., '-v7.3')`, or with scipy's `savemat` (little-endian)",
    )
}

fn not_a_capture(path: &Path) -> YtalError {
    hdf5_error(
        path,
        "is neither HDF5 nor a MATLAB .mat file: give a capture (y-tal or ZNLOS .hdf5; Stanford LCT, \
         f-k or phasor-field .mat; docs/formats.md) or a run directory",
    )
}

/// A MAT v5 file: its compressed elements inflated with a bound, parsed, dispatched.
fn from_v5(bytes: &[u8], path: &Path, dir: Option<&Path>) -> Result<YtalCapture, YtalError> {
    from_mat(&parse_v5(bytes, path)?, dir)
}

/// Parses a MAT v5 file after inflating its compressed elements with a bound.
pub(crate) fn parse_v5<'a>(bytes: &[u8], path: &'a Path) -> Result<Mat<'a>, YtalError> {
    let format = |m: String| YtalError::Format {
        path: path.to_owned(),
        message: m,
    };
    let inflated = super::lct::inflate_elements(bytes, super::lct::MAX_INFLATED_BYTES).map_err(format)?;
    let arrays = inflated.arrays;
    let plain = inflated.bytes;
    // matfile is a parser of untrusted bytes this crate does not own: a panic inside it
    // is an unreadable file, not a crash.
    let mat = std::panic::catch_unwind(|| matfile::MatFile::parse(std::io::Cursor::new(plain)))
        .map_err(|_| format("not a MATLAB v5 file matfile can read (its parser gave up)".into()))?
        .map_err(|e| {
            format(format!(
                "not a MATLAB v5 file matfile can read ({e}); if it holds structs or cells, save it again \
                 with `save(..., '-v7.3')`, which Periscope reads"
            ))
        })?;
    Ok(Mat::V5 { mat, arrays, path })
}

/// Opens a MATLAB file held in memory (either container) and runs `f` on it.
pub(crate) fn with_mat<T>(
    bytes: Vec<u8>,
    path: &Path,
    f: impl FnOnce(&Mat<'_>) -> Result<T, YtalError>,
) -> Result<T, YtalError> {
    match container(&bytes[..bytes.len().min(4096)]) {
        Container::MatV5 => f(&parse_v5(&bytes, path)?),
        Container::Hdf5 => {
            let file_len = bytes.len() as u64;
            guarded(path, || {
                let file = File::from_bytes(bytes)
                    .map_err(|e| hdf5_error(path, format!("cannot be read as HDF5 ({e})")))?;
                f(&Mat::V73(Reader { file, path, file_len }))
            })
        }
        Container::Unknown => Err(hdf5_error(
            path,
            "is not a MATLAB .mat file (neither v5 nor v7.3)",
        )),
        Container::MatV5BigEndian => Err(big_endian(path)),
    }
}

/// An HDF5 file: y-tal, ZNLOS, or a MAT v7.3 file of one of the MATLAB formats.
fn from_hdf5(file: File, path: &Path, file_len: u64, dir: Option<&Path>) -> Result<YtalCapture, YtalError> {
    if file.dataset("H").is_ok() {
        return YtalCapture::decode(file, path, file_len);
    }
    // A root group that cannot be listed is a damaged file, not one of an unknown
    // layout (which is then named by the variables it has: none).
    if let Err(e) = file.root().datasets() {
        return Err(hdf5_error(
            path,
            format!(
                "is damaged or truncated: its root group cannot be read ({e}; the file is {file_len} bytes); \
                 copy it again from where it was made"
            ),
        ));
    }
    let r = Reader { file, path, file_len };
    if r.has("data") {
        return znlos::from_reader(&r);
    }
    if r.has("data_t") {
        return Err(r.format(
            "it has `data_t`: y-tal's deprecated HDF5_NLOS_DIRAC layout, which Periscope does not read; \
             convert it with y-tal (`tal.io.write_capture(out, tal.io.read_capture(file))`)"
                .into(),
        ));
    }
    from_mat(&Mat::V73(r), dir)
}

/// A MATLAB file (either container) of one of the MATLAB formats.
fn from_mat(mat: &Mat<'_>, dir: Option<&Path>) -> Result<YtalCapture, YtalError> {
    if mat.has("meas") {
        return fk::from_mat(mat, dir);
    }
    if mat.has("dataset") {
        return phasor::from_dataset(mat);
    }
    if mat.has("rect_data") {
        if mat.has("width") {
            return super::lct::from_mat(mat);
        }
        if mat.has("ts") {
            return phasor::from_rect_data(mat);
        }
        return Err(mat.error(
            "it has `rect_data` but neither `width` (a Stanford LCT capture's half side) nor `ts` (a \
             phasor-field capture's bin): its scan geometry is unknown",
        ));
    }
    Err(mat.error(format!(
        "no variable of a capture format Periscope reads (it has: {}). Periscope reads y-tal and ZNLOS \
         HDF5, and Stanford LCT (`rect_data`, `width`), f-k (`meas`), and phasor-field (`dataset`; \
         `rect_data`, `ts`) .mat files: docs/formats.md",
        mat.names().join(", ")
    )))
}

/// A grid of relay points with their normals, laid out `[a, b]` (`a` slowest).
pub(crate) fn grid(points: Vec<glam::DVec3>, normals: Vec<glam::DVec3>, shape: [usize; 2]) -> Grid {
    Grid {
        points,
        normals,
        format: GridFormat::XY3,
        shape: shape.to_vec(),
    }
}

/// A `scene_info` naming where a capture came from: `source: "…"`, the text a YAML
/// double-quoted scalar, so a path holding `: ` or ` #` reads back whole (y-tal's
/// PyYAML refused the first and cut the second short).
pub(crate) fn source_info(text: String) -> String {
    format!("source: {}", super::ytal::yaml_string(&text))
}

/// A confocal capture on a planar wall (normals +z, toward the hidden scene), its
/// transients `h` of shape `[bins, a, b]` in C order with `points` flattened the same
/// way (`b` fastest), bins of `delta_t` metres of hidden path from the wall: the
/// Stanford layouts, whose files are pre-rectified or rectified on reading.
pub(crate) fn confocal_wall(
    h: Vec<f32>,
    [bins, a, b]: [usize; 3],
    points: Vec<glam::DVec3>,
    delta_t: f64,
    scene_info: String,
) -> YtalCapture {
    let relay = grid(points, vec![glam::DVec3::Z; a * b], [a, b]);
    YtalCapture {
        h,
        h_shape: vec![bins, a, b],
        h_format: super::ytal::HFormat::TSxSy,
        sensor_grid: relay.clone(),
        laser_grid: relay,
        sensor_xyz: None,
        laser_xyz: None,
        delta_t,
        t_start: 0.0,
        t_accounts_first_and_last_bounces: false,
        scene_info: Some(scene_info),
        flags: None,
    }
}

/// A list of relay points with their normals.
pub(crate) fn list(points: Vec<glam::DVec3>, normals: Vec<glam::DVec3>) -> Grid {
    Grid {
        shape: vec![points.len()],
        points,
        normals,
        format: GridFormat::N3,
    }
}

/// Checks transients as read: finite and non-negative (counts or rendered radiance).
/// An HDF5 attribute's text, whatever string type holds it (fixed or variable length,
/// ASCII or UTF-8, sized to its content or padded, the first of an array, or bytes);
/// `None` for a number.
pub(crate) fn text_attr(v: &hdf5_pure::AttrValue) -> Option<String> {
    use hdf5_pure::AttrValue as A;
    let text = match v {
        A::String(s) | A::AsciiString(s) | A::VarLenString(s) => s.clone(),
        A::StringSized { value, .. } | A::AsciiStringSized { value, .. } => value.clone(),
        A::StringArray(v) | A::AsciiStringArray(v) | A::VarLenAsciiCharArray(v) => v.first()?.clone(),
        A::StringArraySized { values, .. } | A::AsciiStringArraySized { values, .. } => {
            values.first()?.clone()
        }
        A::U8Array(b) => String::from_utf8(b.clone()).ok()?,
        A::I8Array(b) => String::from_utf8(b.iter().map(|&c| c as u8).collect()).ok()?,
        _ => return None,
    };
    Some(text.trim_end_matches('\0').trim().to_owned())
}

/// An HDF5 attribute's number (the first of an array), whatever its numeric type;
/// `None` for text or an empty array.
pub(crate) fn number_attr(v: &hdf5_pure::AttrValue) -> Option<f64> {
    use hdf5_pure::AttrValue as A;
    Some(match v {
        A::F32(x) => f64::from(*x),
        A::F64(x) => *x,
        A::I8(x) => f64::from(*x),
        A::I16(x) => f64::from(*x),
        A::I32(x) => f64::from(*x),
        A::I64(x) => *x as f64,
        A::U8(x) => f64::from(*x),
        A::U16(x) => f64::from(*x),
        A::U32(x) => f64::from(*x),
        A::U64(x) => *x as f64,
        A::F32Array(a) => f64::from(*a.first()?),
        A::F64Array(a) => *a.first()?,
        A::I8Array(a) => f64::from(*a.first()?),
        A::I16Array(a) => f64::from(*a.first()?),
        A::I32Array(a) => f64::from(*a.first()?),
        A::I64Array(a) => *a.first()? as f64,
        A::U8Array(a) => f64::from(*a.first()?),
        A::U16Array(a) => f64::from(*a.first()?),
        A::U32Array(a) => f64::from(*a.first()?),
        A::U64Array(a) => *a.first()? as f64,
        _ => return None,
    })
}

/// Every value a count: finite, non-negative, and at most 10³⁰ (as a y-tal `H`'s: sums
/// of up to 10⁸ of them stay finite in single precision, where 3·10³⁸ made the
/// reconstruction overflow to NaN after its whole run).
pub(crate) fn check_counts(values: &[f32], name: &str) -> Result<(), String> {
    const MAX_COUNT: f32 = 1e30;
    match values
        .iter()
        .position(|v| !v.is_finite() || *v < 0.0 || *v > MAX_COUNT)
    {
        Some(i) => Err(format!(
            "`{name}` value {} at index {i} is not a count (finite, non-negative, at most 1e30)",
            values[i]
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests;

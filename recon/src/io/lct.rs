//! Stanford's confocal LCT captures (O'Toole, Lindell and Wetzstein 2018, "Confocal
//! non-line-of-sight imaging based on the light-cone transform"), read into a
//! [`YtalCapture`] so every method reconstructs them.
//!
//! The layout (`docs/research/nlos-capture-formats.md` §1, from the release's files
//! and `cnlos_reconstruction.m`): a MAT v5 file (compressed elements) with two
//! variables, `rect_data` of MATLAB dims (x, y, t), counts, and `width`, half the side
//! of the scanned square on the wall, metres. Nothing else is stored: the bin width is
//! the SPAD's native 4 ps (hard-coded in the reference code), the data are
//! pre-rectified (bin 0 is the wall: round-trip hidden path length 0), and the scan
//! points are `linspace(-width, width, N)` along x and y on the wall, the hidden scene
//! in front of it (+z here). The reference code zeroes the first 600 bins (the wall's
//! own return); this reader keeps them, as the file has them, and the reconstruction's
//! volume starts where the settings say.
//!
//! The file is read whole (at most [`MAX_FILE_BYTES`]); each compressed element is
//! inflated with a bound ([`MAX_INFLATED_BYTES`]), so a file that would expand without
//! end is refused, not followed.
use std::io::Read as _;
use std::path::Path;

use glam::DVec3;

use super::formats::mat::Mat;
use super::ytal::{YtalCapture, YtalError};

/// Largest `.mat` file read, bytes.
pub const MAX_FILE_BYTES: u64 = 4 << 30;

/// Largest size the file's compressed elements may inflate to, bytes in all.
pub const MAX_INFLATED_BYTES: u64 = 8 << 30;

/// The SPAD's native bin, seconds (the reference code's `bin_resolution`).
pub const BIN_S: f64 = 4e-12;

/// Speed of light, m/s.
const C: f64 = 299_792_458.0;

/// MAT v5 element types used here.
const MI_MATRIX: u32 = 14;
const MI_COMPRESSED: u32 = 15;

/// Whether `path` names a MATLAB file (`.mat`).
pub fn is_mat_path(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("mat"))
}

fn format_error(path: &Path, message: impl Into<String>) -> YtalError {
    YtalError::Format {
        path: path.to_owned(),
        message: message.into(),
    }
}

/// Reads a Stanford LCT capture (MAT v5, as the release's files are, or v7.3).
/// [`crate::io::formats::read_capture`] reads it too, telling the format from the
/// contents.
pub fn read_lct(path: &Path) -> Result<YtalCapture, YtalError> {
    let bytes = super::read_regular_capped(path, MAX_FILE_BYTES).map_err(|e| YtalError::Hdf5 {
        path: path.to_owned(),
        message: e.to_string(),
    })?;
    // Handed over, not copied: the file is held once.
    super::formats::with_mat(bytes, path, from_mat)
}

/// Decodes a Stanford LCT capture held in memory (`path` names it in errors).
pub fn lct_from_bytes(bytes: &[u8], path: &Path) -> Result<YtalCapture, YtalError> {
    super::formats::with_mat(bytes.to_vec(), path, from_mat)
}

/// The capture of an LCT file's variables.
pub(crate) fn from_mat(mat: &Mat<'_>) -> Result<YtalCapture, YtalError> {
    let path = mat.path();
    let rect = mat.var_f32("rect_data")?.ok_or_else(|| {
        format_error(
            path,
            format!(
                "no `rect_data`: not a Stanford LCT capture (variables: {}); `periscope recon` tells the \
                 other public formats apart by themselves (docs/formats.md)",
                mat.names().join(", ")
            ),
        )
    })?;
    let width = mat
        .scalar("width")?
        .ok_or_else(|| format_error(path, "no scalar `width` (half the scanned side, metres)"))?;
    if !(width.is_finite() && width > 0.0 && width <= super::formats::MAX_HALF_SIDE_M) {
        return Err(format_error(
            path,
            format!(
                "`width` is {width}: it must be a positive length in metres, at most {} (half the scanned side)",
                super::formats::MAX_HALF_SIDE_M
            ),
        ));
    }
    let &[nx, ny, nt] = rect.dims.as_slice() else {
        return Err(format_error(
            path,
            format!(
                "`rect_data` has dims {:?}; an LCT capture's are (x, y, t)",
                rect.dims
            ),
        ));
    };
    if nx < 2 || ny < 2 || nt < 2 {
        return Err(format_error(
            path,
            format!("`rect_data` of dims ({nx}, {ny}, {nt}) is too small"),
        ));
    }
    let data = rect.values;
    if nx.checked_mul(ny).and_then(|n| n.checked_mul(nt)) != Some(data.len()) {
        return Err(format_error(
            path,
            "`rect_data` holds fewer values than its dims say",
        ));
    }
    super::formats::check_counts(&data, "rect_data").map_err(|m| format_error(path, m))?;
    // MATLAB stores (x, y, t) column-major: x varies fastest. H is (t, x, y), C order.
    let mut h = vec![0f32; nx * ny * nt];
    for t in 0..nt {
        for y in 0..ny {
            for x in 0..nx {
                h[t * nx * ny + x * ny + y] = data[x + nx * (y + ny * t)];
            }
        }
    }
    let along = |n: usize, i: usize| -width + 2.0 * width * i as f64 / (n - 1) as f64;
    let mut points = Vec::with_capacity(nx * ny);
    for x in 0..nx {
        for y in 0..ny {
            points.push(DVec3::new(along(nx, x), along(ny, y), 0.0));
        }
    }
    let capture = super::formats::confocal_wall(
        h,
        [nt, nx, ny],
        points,
        C * BIN_S,
        crate::io::formats::source_info(format!(
            "Stanford confocal LCT capture ({}), {nx} x {ny} points over [-{width}, {width}] m, \
         {nt} bins of 4 ps from the wall",
            path.display()
        )),
    );
    capture.check().map_err(|m| format_error(path, m))?;
    Ok(capture)
}

/// A MAT v5 file with its compressed top-level elements inflated in place (at most
/// `limit` bytes in all, or what this process can hold, whichever is less), so the
/// parser never inflates without a bound, and an index of its top-level arrays. Each
/// top-level element must be (or inflate to) one MATLAB array whose elements nest at
/// most [`MAX_NESTING`] deep and hold no compressed element (MATLAB writes none
/// there; the parser would inflate it without a bound, recursing once a level).
pub fn inflate_elements(bytes: &[u8], limit: u64) -> Result<Inflated, String> {
    const HEADER: usize = 128;
    if bytes.len() < HEADER || bytes[126..128] != *b"IM" {
        return Err("not a little-endian MATLAB v5 file (MAT v7.3 files are HDF5, and read as such)".into());
    }
    // The parser copies the inflated bytes and converts the values again: three times
    // them must fit in what this process can still use.
    let (limit, held) = match crate::io::memory_available() {
        Some(available) if available / 3 < limit => (available / 3, true),
        _ => (limit, false),
    };
    let past = || {
        if held {
            format!(
                "its arrays take more than {:.1} GiB once inflated, more than a third of the memory this \
                 process can still use (the parser holds them about three times over): read it on a machine \
                 with more memory, or save a smaller capture",
                limit as f64 / (1u64 << 30) as f64
            )
        } else {
            format!("the compressed elements inflate past {limit} bytes, more than a capture may hold")
        }
    };
    let mut out = bytes[..HEADER].to_vec();
    let mut arrays = Vec::new();
    let mut at = HEADER;
    let mut plain_bytes = 0u64;
    while at + 8 <= bytes.len() {
        let start = at;
        let kind = u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"));
        let len = u32::from_le_bytes(bytes[at + 4..at + 8].try_into().expect("4 bytes")) as usize;
        let body = at + 8;
        let end = body
            .checked_add(len)
            .filter(|&e| e <= bytes.len())
            .ok_or_else(|| format!("an element at byte {at} runs past the end of the file"))?;
        let element = match kind {
            MI_COMPRESSED => {
                let left = limit.saturating_sub(plain_bytes);
                let mut plain = Vec::new();
                flate2::read::ZlibDecoder::new(&bytes[body..end])
                    .take(left + 1)
                    .read_to_end(&mut plain)
                    .map_err(|e| format!("a compressed element at byte {at} does not inflate: {e}"))?;
                if plain.len() as u64 > left {
                    return Err(past());
                }
                at = end;
                plain
            }
            MI_MATRIX => {
                let element = bytes[at..end].to_vec();
                at = end.next_multiple_of(8).min(bytes.len());
                element
            }
            other => {
                return Err(format!(
                    "a top-level element of type {other} at byte {at}: not a MATLAB array"
                ));
            }
        };
        plain_bytes += element.len() as u64;
        if plain_bytes > limit {
            return Err(past());
        }
        arrays.push(top_level_array(&element).map_err(|m| format!("the element at byte {start}: {m}"))?);
        out.extend_from_slice(&element);
        // An element written uncompressed is padded to 8 bytes.
        out.resize(out.len().next_multiple_of(8), 0);
    }
    Ok(Inflated { bytes: out, arrays })
}

/// A MAT v5 file's bytes with its compressed elements inflated, and its arrays.
pub struct Inflated {
    /// The file, every top-level element plain.
    pub bytes: Vec<u8>,
    /// Its top-level arrays, in file order.
    pub arrays: Vec<V5Array>,
}

/// A top-level MATLAB array of a MAT v5 file, as its header says.
#[derive(Clone, Debug, PartialEq)]
pub struct V5Array {
    /// Its name.
    pub name: String,
    /// MATLAB's class number (`mxDOUBLE_CLASS` 6, `mxSTRUCT_CLASS` 2, …).
    pub class: u8,
    /// Whether it is complex.
    pub complex: bool,
    /// Its dims, as MATLAB reports them.
    pub dims: Vec<usize>,
}

impl V5Array {
    /// Whether its class is a numeric one (double, single, the integers).
    pub fn numeric(&self) -> bool {
        (6..=15).contains(&self.class)
    }

    /// Its class as MATLAB names it.
    pub fn class_name(&self) -> &'static str {
        match self.class {
            1 => "cell",
            2 => "struct",
            3 => "object",
            4 => "char",
            5 => "sparse",
            6 => "double",
            7 => "single",
            8 => "int8",
            9 => "uint8",
            10 => "int16",
            11 => "uint16",
            12 => "int32",
            13 => "uint32",
            14 => "int64",
            15 => "uint64",
            _ => "unknown",
        }
    }
}

/// How deep MATLAB arrays may nest in a file read here (cells of structs of …).
pub const MAX_NESTING: usize = 64;

/// One tagged data element at `at` of `b`: its type, its data's range, and where the
/// next element starts. The small form (type and length packed in one word, at most
/// four bytes of data) is read too.
fn tag(b: &[u8], at: usize) -> Result<(u32, std::ops::Range<usize>, usize), String> {
    let word = |i: usize| {
        b.get(i..i + 4)
            .map(|w| u32::from_le_bytes(w.try_into().expect("4 bytes")))
            .ok_or_else(|| format!("an element at byte {at} of an array is cut short"))
    };
    let first = word(at)?;
    if first >> 16 != 0 {
        let len = (first >> 16) as usize;
        if len > 4 || at + 8 > b.len() {
            return Err(format!("a small element at byte {at} of an array is malformed"));
        }
        return Ok((first & 0xffff, at + 4..at + 4 + len, at + 8));
    }
    let len = word(at + 4)? as usize;
    let end = (at + 8)
        .checked_add(len)
        .filter(|&e| e <= b.len())
        .ok_or_else(|| format!("an element at byte {at} of an array runs past its end"))?;
    Ok((first, at + 8..end, end.next_multiple_of(8).min(b.len())))
}

/// The header of a top-level element (`miMATRIX` tag included), and a walk of every
/// element nested in it: no compressed element, nesting at most [`MAX_NESTING`] deep
/// (iterative: a file cannot exhaust the stack here).
fn top_level_array(element: &[u8]) -> Result<V5Array, String> {
    let (kind, body, _) = tag(element, 0)?;
    if kind != MI_MATRIX {
        return Err(format!(
            "a compressed element holds an element of type {kind}, not a MATLAB array (MATLAB compresses \
             only arrays, one an element)"
        ));
    }
    // Whatever follows the array would reach the parser as more top-level elements,
    // compressed ones included, which it inflates without a bound. MATLAB writes one
    // array a compressed element, padded at most to 8 bytes.
    let rest = &element[body.end..];
    if rest.len() >= 8 || rest.iter().any(|&b| b != 0) {
        return Err(format!(
            "a compressed element holds {} more bytes after its MATLAB array (MATLAB compresses one \
             array an element): the file is damaged or was not written by MATLAB",
            rest.len()
        ));
    }
    let b = &element[body];
    // Array flags, dims, name.
    let (_, flags, next) = tag(b, 0)?;
    let flags = b
        .get(flags.start..flags.start + 4)
        .map(|w| u32::from_le_bytes(w.try_into().expect("4 bytes")))
        .ok_or("its array flags are cut short")?;
    let (_, dims_at, next) = tag(b, next)?;
    let dims = b[dims_at]
        .chunks_exact(4)
        .map(|c| usize::try_from(i32::from_le_bytes(c.try_into().expect("4 bytes"))))
        .collect::<Result<Vec<usize>, _>>()
        .map_err(|_| "a negative dim".to_owned())?;
    let (_, name_at, next) = tag(b, next)?;
    let name = String::from_utf8_lossy(&b[name_at]).into_owned();
    let class = (flags & 0xff) as u8;
    let mut stack = vec![(b, 0usize)];
    while let Some((b, depth)) = stack.pop() {
        if depth > MAX_NESTING {
            return Err(format!("arrays nest more than {MAX_NESTING} deep"));
        }
        let mut at = 0;
        while at + 8 <= b.len() {
            let (kind, data, next) = tag(b, at)?;
            match kind {
                MI_COMPRESSED => {
                    return Err(
                        "a compressed element inside an array, which MATLAB never writes: the file is damaged \
                         or not MATLAB's"
                            .into(),
                    );
                }
                MI_MATRIX => stack.push((&b[data], depth + 1)),
                _ => {}
            }
            at = next;
        }
    }
    // A numeric array's values must be as many as its dims say: the parser checks with
    // a product that wraps in 32 bits, and its readers allocate from the dims.
    if (6..=15).contains(&class) && next + 8 <= b.len() {
        let (kind, real, _) = tag(b, next)?;
        let size = match kind {
            1 | 2 => 1,
            3 | 4 => 2,
            5..=7 => 4,
            9 | 12 | 13 => 8,
            other => {
                return Err(format!(
                    "`{name}`'s values are of element type {other}, not a number"
                ));
            }
        };
        let held = real.len() / size;
        if dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d)) != Some(held) {
            return Err(format!(
                "`{name}` has dims {dims:?} but holds {held} values: the file is damaged"
            ));
        }
    }
    Ok(V5Array {
        name,
        class,
        complex: flags & 0x0800 != 0,
        dims,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The fixture: scipy's `savemat` (as the Stanford release's files are written) of
    /// one point target at (0.1, -0.05, 0.3) m seen from an 8 × 8 grid over
    /// [-0.2, 0.2]² m, pixel (i, j) holding 100 + 10 i + j counts in the bin of its
    /// round trip (recon/tests/data/lct-point.py made it). A swapped axis, a mirrored
    /// grid or a shifted time origin puts a count where the geometry says nothing is.
    #[test]
    fn a_known_scene_lands_on_its_points_and_bins() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/lct-point.mat");
        let c = read_lct(&path).unwrap();
        assert_eq!(c.h_shape, vec![1024, 8, 8]);
        assert_eq!(c.len(), 64);
        let target = DVec3::new(0.1, -0.05, 0.3);
        for k in 0..64 {
            let p = c.pair(k);
            assert_eq!(p.xi, p.xd, "confocal");
            let (i, j) = (k / 8, k % 8);
            assert!((p.xd.x - (-0.2 + 0.4 * i as f64 / 7.0)).abs() < 1e-12);
            assert!((p.xd.y - (-0.2 + 0.4 * j as f64 / 7.0)).abs() < 1e-12);
            let bins: Vec<f32> = c.transient(k).collect();
            let (peak, &v) = bins.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap();
            assert_eq!(v, (100 + 10 * i + j) as f32, "pixel ({i}, {j})");
            let path_m = 2.0 * target.distance(p.xd);
            let want = (path_m / c.delta_t).floor() as usize;
            assert_eq!(peak, want, "pixel ({i}, {j}): round trip {path_m} m");
            assert_eq!(c.hidden_start(k), 0.0, "bin 0 is the wall");
        }
    }

    #[test]
    fn other_layouts_and_hostile_files_are_refused_with_a_reason() {
        let dir = tempfile::tempdir().unwrap();
        let junk = dir.path().join("junk.mat");
        std::fs::write(&junk, b"not a mat file").unwrap();
        let e = read_lct(&junk).unwrap_err().to_string();
        assert!(e.contains("is not a MATLAB .mat file"), "{e}");
        // A compressed element that would inflate past the bound is refused, not followed.
        let fixture =
            std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/lct-point.mat")).unwrap();
        let e = inflate_elements(&fixture, 1000).err().unwrap();
        assert!(e.contains("inflate past 1000 bytes"), "{e}");
        assert!(inflate_elements(&fixture, MAX_INFLATED_BYTES).is_ok());
        // An element claiming more bytes than the file has.
        let mut cut = fixture.clone();
        cut.truncate(200);
        assert!(
            inflate_elements(&cut, MAX_INFLATED_BYTES)
                .err()
                .unwrap()
                .contains("past the end")
        );
    }
}

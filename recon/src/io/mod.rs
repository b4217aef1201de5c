//! Files the reconstruction writes and reads: numpy `.npy` arrays (via `npyz`), PNG
//! images (via `png`) and y-tal HDF5 captures ([`ytal`], via `hdf5-pure`), so a program
//! that uses this crate as a library reads and writes the community's capture format
//! without the daemon.
//!
//! Images share one orientation with the arrays, documented in docs/recon.md: column
//! `ix` runs along +x left to right, and row 0 is the *largest* y, so y points up. That
//! is `np.flipud(array)` of the `[ny, nx]` array, what `plt.imshow(a, origin="lower")`
//! shows. Files are written to a temporary name and renamed, so a crash never leaves a
//! half-written output under the final name.
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};

use npyz::WriterBuilder;

use crate::volume::{DepthMap, Volume};

pub mod formats;
pub mod lct;
pub mod ytal;

/// Why a file could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum IoError {
    /// The operating system refused.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An `.npy` file that is not a float array of the expected kind.
    #[error("{path}: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> IoError + '_ {
    move |source| IoError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// A temporary file's path of its own beside `path`, `<name>.<pid>-<n>.tmp` (n counts
/// the calls in this process), so writers racing on one path, or on two paths with the
/// same stem, never share one. Every atomic write here and in the daemon takes it.
pub fn temporary_beside(path: &Path) -> PathBuf {
    static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let mut name = path.file_name().unwrap_or_default().to_owned();
    name.push(format!(".{}-{n}.tmp", std::process::id()));
    path.with_file_name(name)
}

/// Writes `bytes` to `path` atomically and durably: into a temporary file of its own
/// beside it ([`temporary_beside`]), synced, renamed over `path`, then the directory
/// synced so that the rename survives a crash. A failed write removes its temporary
/// file. [`ytal::YtalCapture::write`] and the daemon's `store::write_atomic` take it.
pub fn write_bytes_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    refuse_non_regular_target(path)?;
    let tmp = temporary_beside(path);
    let written = File::create(&tmp)
        .and_then(|mut f| f.write_all(bytes).and_then(|()| f.sync_all()))
        .and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp);
        return Err(e);
    }
    if let Some(dir) = path.parent()
        && let Ok(d) = File::open(dir)
    {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Writes through `write` into a temporary file of its own beside `path`
/// (`<name>.<pid>-<n>.tmp`, so writers racing on one path never share one), syncs, then
/// renames over `path`. A failed write removes its temporary file.
fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), IoError> {
    if let Some(why) = non_regular_target(path) {
        return Err(IoError::Format {
            path: path.to_path_buf(),
            message: why.into(),
        });
    }
    let tmp = temporary_beside(path);
    let written = (|| {
        let file = File::create(&tmp).map_err(io_err(&tmp))?;
        let mut out = BufWriter::new(file);
        write(&mut out).map_err(io_err(&tmp))?;
        let file = out.into_inner().map_err(|e| io_err(&tmp)(e.into_error()))?;
        file.sync_all().map_err(io_err(&tmp))?;
        std::fs::rename(&tmp, path).map_err(io_err(path))
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Writes a float32 array of `shape` (C order) as `.npy`.
pub fn write_npy(path: &Path, shape: &[usize], data: &[f32]) -> Result<(), IoError> {
    let want: usize = shape.iter().product();
    if want != data.len() {
        return Err(IoError::Format {
            path: path.to_path_buf(),
            message: format!("{} values do not fill shape {shape:?}", data.len()),
        });
    }
    let shape: Vec<u64> = shape.iter().map(|&n| n as u64).collect();
    write_atomically(path, |out| {
        let mut writer = npyz::WriteOptions::new()
            .default_dtype()
            .shape(&shape)
            .writer(out)
            .begin_nd()?;
        writer.extend(data.iter().copied())?;
        writer.finish()
    })
}

/// Reads a C-order float32 or float64 `.npy` array: its shape and values as f32.
pub fn read_npy(path: &Path) -> Result<(Vec<usize>, Vec<f32>), IoError> {
    let format = |message: String| IoError::Format {
        path: path.to_path_buf(),
        message,
    };
    let file = File::open(path).map_err(io_err(path))?;
    let npy =
        npyz::NpyFile::new(BufReader::new(file)).map_err(|e| format(format!("not an .npy file: {e}")))?;
    if npy.order() != npyz::Order::C && npy.shape().len() > 1 {
        return Err(format(
            "Fortran-order arrays are not supported; save with C order".into(),
        ));
    }
    let shape: Vec<usize> = npy.shape().iter().map(|&n| n as usize).collect();
    let dtype = npy.dtype().descr();
    let data = match dtype.as_str() {
        "'<f4'" => npy.into_vec::<f32>().map_err(io_err(path))?,
        "'<f8'" => npy
            .into_vec::<f64>()
            .map_err(io_err(path))?
            .into_iter()
            .map(|v| v as f32)
            .collect(),
        other => {
            return Err(format(format!(
                "dtype {other} is not little-endian float32 or float64"
            )));
        }
    };
    Ok((shape, data))
}

/// Writes a volume as `.npy` of shape `[nz, ny, nx]`.
pub fn write_volume(path: &Path, volume: &Volume) -> Result<(), IoError> {
    let [nx, ny, nz] = volume.grid.shape;
    write_npy(path, &[nz, ny, nx], &volume.data)
}

/// Viridis, sampled at nine evenly spaced points (linear interpolation in between).
const VIRIDIS: [[u8; 3]; 9] = [
    [68, 1, 84],
    [71, 44, 122],
    [59, 81, 139],
    [44, 113, 142],
    [33, 144, 141],
    [39, 173, 129],
    [92, 200, 99],
    [170, 220, 50],
    [253, 231, 37],
];

/// The colour of `t` in [0, 1] on the depth colour map.
pub fn colour(t: f64) -> [u8; 3] {
    let t = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) } * (VIRIDIS.len() - 1) as f64;
    let i = (t.floor() as usize).min(VIRIDIS.len() - 2);
    let f = t - i as f64;
    std::array::from_fn(|c| (VIRIDIS[i][c] as f64 * (1.0 - f) + VIRIDIS[i + 1][c] as f64 * f).round() as u8)
}

fn write_png(
    path: &Path,
    size: [usize; 2],
    colour_type: png::ColorType,
    pixels: &[u8],
) -> Result<(), IoError> {
    write_atomically(path, |out| {
        let mut encoder = png::Encoder::new(&mut *out, size[0] as u32, size[1] as u32);
        encoder.set_color(colour_type);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(pixels).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)?;
        out.flush()
    })
}

/// Depth PNG: near the relay is dark purple, far is yellow, masked pixels black; row 0
/// is the largest coordinate along the map's rows ([`DepthMap::distance_fraction`]).
pub fn write_depth_png(path: &Path, map: &DepthMap) -> Result<(), IoError> {
    let [nx, ny] = map.shape;
    let mut pixels = Vec::with_capacity(nx * ny * 3);
    for row in (0..ny).rev() {
        for ix in 0..nx {
            let d = map.depth[row * nx + ix];
            if d.is_finite() {
                pixels.extend(colour(map.distance_fraction(d as f64)));
            } else {
                pixels.extend([0, 0, 0]);
            }
        }
    }
    write_png(path, [nx, ny], png::ColorType::Rgb, &pixels)
}

/// Albedo PNG: the max projection, grey, scaled so the brightest pixel is white.
pub fn write_albedo_png(path: &Path, map: &DepthMap) -> Result<(), IoError> {
    let [nx, ny] = map.shape;
    let max = map.peak.iter().copied().fold(0.0f32, f32::max);
    let scale = if max > 0.0 { 255.0 / max } else { 0.0 };
    let mut pixels = Vec::with_capacity(nx * ny);
    for row in (0..ny).rev() {
        for ix in 0..nx {
            pixels.push((map.peak[row * nx + ix] * scale).round().clamp(0.0, 255.0) as u8);
        }
    }
    write_png(path, [nx, ny], png::ColorType::Grayscale, &pixels)
}

/// Refuses to replace `path` unless it is a regular file or does not exist: renaming
/// over a device node (`/dev/full`), a FIFO, a directory or a symbolic link would
/// replace that thing with a regular file (as root, a device node too).
pub fn refuse_non_regular_target(path: &Path) -> std::io::Result<()> {
    match non_regular_target(path) {
        Some(why) => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} {why}", path.display()),
        )),
        None => Ok(()),
    }
}

/// Why `path` may not be replaced (see [`refuse_non_regular_target`]), without the
/// path, for errors that name it themselves; `None` when it may.
pub(crate) fn non_regular_target(path: &Path) -> Option<&'static str> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if !m.file_type().is_file() => Some(
            "exists and is not a regular file (a device, FIFO, directory or link): it is left as it is; \
             write to another path",
        ),
        _ => None,
    }
}

/// Reads a whole regular file of at most `limit` bytes. Anything else is refused
/// before it is opened or read: a FIFO (which would block), a device such as
/// `/dev/zero` (which never ends), a directory, or a file over the limit; a file that
/// grows past the limit while it is read is refused too.
pub fn read_regular_capped(path: &Path, limit: u64) -> std::io::Result<Vec<u8>> {
    use std::io::Read;
    let not_regular = || {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!(
                "{} is not a regular file (a FIFO, device or directory): give a file",
                path.display()
            ),
        )
    };
    let too_large = |len: u64| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "{} is {len} bytes or more, more than the {limit} it may have here",
                path.display()
            ),
        )
    };
    let meta = std::fs::metadata(path)?;
    if !meta.is_file() {
        return Err(not_regular());
    }
    if meta.len() > limit {
        return Err(too_large(meta.len()));
    }
    let file = File::open(path)?;
    if !file.metadata()?.is_file() {
        return Err(not_regular());
    }
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    file.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// Memory this process can still take, bytes: the smaller of the system's available
/// memory (`MemAvailable`) and what its address-space limit leaves. `None` where that
/// cannot be read (not Linux).
pub fn memory_available() -> Option<u64> {
    let kib = |text: &str, key: &str| -> Option<u64> {
        text.lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .map(|k| k << 10)
    };
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let available = kib(&meminfo, "MemAvailable:")?;
    let limit = std::fs::read_to_string("/proc/self/limits").ok().and_then(|t| {
        t.lines()
            .find(|l| l.starts_with("Max address space"))
            .and_then(|l| l.split_whitespace().nth(3).and_then(|v| v.parse::<u64>().ok()))
    });
    let used = std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|t| kib(&t, "VmSize:"))
        .unwrap_or(0);
    Some(match limit {
        Some(l) => available.min(l.saturating_sub(used)),
        None => available,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        let data: Vec<f32> = (0..24).map(|i| i as f32 * 0.5).collect();
        write_npy(&path, &[2, 3, 4], &data).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(&bytes[..6], b"\x93NUMPY");
        let header = String::from_utf8_lossy(&bytes[10..80]);
        assert!(
            header.contains("'descr': '<f4'") && header.contains("(2, 3, 4"),
            "{header}"
        );
        assert_eq!(read_npy(&path).unwrap(), (vec![2, 3, 4], data));
        assert!(write_npy(&path, &[5], &[1.0]).is_err());
    }

    #[test]
    fn colour_map_ends() {
        assert_eq!(colour(0.0), VIRIDIS[0]);
        assert_eq!(colour(1.0), VIRIDIS[8]);
        assert_eq!(colour(f64::NAN), VIRIDIS[0]);
    }
}

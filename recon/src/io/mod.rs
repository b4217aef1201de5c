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
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    // The file is in place by now: a failure here is said as the directory's
    // ([`FolderNotSynced`]), so a message does not call a file that is there unwritten.
    sync_directory(dir).map_err(|source| {
        std::io::Error::new(
            source.kind(),
            FolderNotSynced {
                dir: dir.to_path_buf(),
                source,
            },
        )
    })
}

/// [`write_bytes_atomically`]'s error where the file was written and renamed into
/// place but its folder could not be synced: the file is there, its name may not
/// survive a power cut. [`FolderNotSynced::of`] finds it in an `io::Error`.
#[derive(Debug, thiserror::Error)]
#[error("written, but its folder {} could not be synced ({source}), so the new name may not survive a power cut", .dir.display())]
pub struct FolderNotSynced {
    /// The folder.
    pub dir: PathBuf,
    /// Why its sync failed.
    pub source: std::io::Error,
}

impl FolderNotSynced {
    /// The folder-sync failure `e` carries, if that is what it is.
    pub fn of(e: &std::io::Error) -> Option<&FolderNotSynced> {
        e.get_ref()
            .and_then(|inner| inner.downcast_ref::<FolderNotSynced>())
    }
}

/// Syncs directory `dir`, so that the names made, renamed or removed in it survive a
/// power cut. A file system that cannot sync a directory at all (`EINVAL`: some
/// network and FUSE ones) is taken as having nothing to sync, as PostgreSQL takes it;
/// any other failure (an `EIO` from a failing disk) is returned, since what was
/// written under those names may not survive a crash. Until 2026-12-07 every failure
/// was ignored.
pub fn sync_directory(dir: &Path) -> std::io::Result<()> {
    match File::open(dir)?.sync_all() {
        Err(e) if e.kind() == std::io::ErrorKind::InvalidInput => Ok(()),
        done => done,
    }
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
    // Looked at before it is opened: opening a FIFO waits for a writer.
    let meta = std::fs::metadata(path).map_err(io_err(path))?;
    if !meta.is_file() {
        return Err(format(
            "not a regular file (a FIFO, device or directory): give an .npy file".into(),
        ));
    }
    let mut reader = BufReader::new(File::open(path).map_err(io_err(path))?);
    // The header's shape is checked before the npy layer parses it: it multiplies the
    // dimensions unchecked (a panic in a debug build, an empty array in a release one).
    let (declared_shape, header_bytes) = npy_header_shape(&mut reader).unzip();
    if let Some(shape) = &declared_shape
        && shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d)).is_none()
    {
        return Err(format(format!("its shape {shape:?} overflows")));
    }
    let header_bytes = header_bytes.unwrap_or(0);
    let npy = npyz::NpyFile::new(reader).map_err(|e| format(format!("not an .npy file: {e}")))?;
    if npy.order() != npyz::Order::C && npy.shape().len() > 1 {
        return Err(format(
            "Fortran-order arrays are not supported; save with C order".into(),
        ));
    }
    // The header's shape against the file before anything is allocated for it (the
    // product wraps in the npy layer: a shape of (2^32, 2^32) read as empty).
    let declared = npy.shape().to_vec();
    let elements = declared
        .iter()
        .try_fold(1u64, |a, &d| a.checked_mul(d))
        .filter(|&n| usize::try_from(n).is_ok())
        .ok_or_else(|| format(format!("its shape {declared:?} overflows")))?;
    let dtype = npy.dtype().descr();
    let width = match dtype.as_str() {
        "'<f4'" => 4,
        "'<f8'" => 8,
        other => {
            return Err(format(format!(
                "dtype {other} is not little-endian float32 or float64"
            )));
        }
    };
    if elements.saturating_mul(width) > meta.len().saturating_sub(header_bytes) {
        return Err(format(format!(
            "its shape {declared:?} declares {} bytes of data but the file has {}: it is truncated or damaged",
            elements.saturating_mul(width),
            meta.len()
        )));
    }
    let shape: Vec<usize> = declared.iter().map(|&n| n as usize).collect();
    let data = if width == 4 {
        npy.into_vec::<f32>().map_err(io_err(path))?
    } else {
        npy.into_vec::<f64>()
            .map_err(io_err(path))?
            .into_iter()
            .map(|v| v as f32)
            .collect()
    };
    if data.len() as u64 != elements {
        return Err(format(format!(
            "its shape {declared:?} holds {elements} values but {} were read: it is truncated or damaged",
            data.len()
        )));
    }
    Ok((shape, data))
}

/// The `shape` an `.npy` header declares and the bytes before the data, read without
/// consuming `reader`'s data (it stays buffered); `None` where the header is not one
/// this can read, for the npy layer to name.
fn npy_header_shape(reader: &mut BufReader<File>) -> Option<(Vec<u64>, u64)> {
    use std::io::BufRead;
    let head = reader.fill_buf().ok()?;
    let (len, start): (usize, usize) = match head.get(6)? {
        1 => (u16::from_le_bytes([*head.get(8)?, *head.get(9)?]) as usize, 10),
        _ => (
            u32::from_le_bytes([*head.get(8)?, *head.get(9)?, *head.get(10)?, *head.get(11)?]) as usize,
            12,
        ),
    };
    let text = std::str::from_utf8(head.get(start..start.checked_add(len)?)?).ok()?;
    // As the npy layer reads it (a Python literal): the key in either quote, the
    // shape a tuple or a list.
    let key = text.find("'shape'").or_else(|| text.find("\"shape\""))?;
    let after = &text[key + "'shape'".len()..];
    let open = after.find(['(', '['])?;
    let close = if after.as_bytes()[open] == b'(' { ')' } else { ']' };
    let tuple = &after[open + 1..];
    let tuple = &tuple[..tuple.find(close)?];
    let shape = tuple
        .split(',')
        .map(str::trim)
        .filter(|d| !d.is_empty())
        .map(|d| d.trim_end_matches('L').parse::<u64>().ok())
        .collect::<Option<Vec<u64>>>()?;
    Some((shape, (start + len) as u64))
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
    // Reserved fallibly, and against what this process can still take: an
    // infallible reservation of a file the size of the limit (4 GiB by default for an
    // upload) aborts the process where memory is short, and no caller can catch that.
    let no_memory = |what: String| {
        std::io::Error::new(
            std::io::ErrorKind::OutOfMemory,
            format!(
                "{} is {} bytes; reading it {what}: read it where more memory is free (or raise the memory limit of the container or service it runs in)",
                path.display(),
                meta.len()
            ),
        )
    };
    if let Some(available) = memory_available()
        && meta.len() > available
    {
        return Err(no_memory(format!(
            "takes more than the {available} bytes this process can still use"
        )));
    }
    let mut bytes = Vec::new();
    bytes
        .try_reserve_exact(usize::try_from(meta.len()).unwrap_or(usize::MAX))
        .map_err(|e| no_memory(format!("could not be reserved ({e})")))?;
    file.take(limit + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > limit {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// Memory this process can still take, bytes: the smallest of the system's available
/// memory (`MemAvailable`), what its address-space limit leaves, and what the memory
/// limits of its control group and the groups above it leave (cgroup v2 `memory.max`
/// less the group's working set, `memory.current` without its inactive file cache,
/// as the kubelet counts it: a container's or a systemd unit's `MemoryMax`, where
/// `MemAvailable` reports the host's). `None` where that cannot be read (not Linux).
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
    let available = match limit {
        Some(l) => available.min(l.saturating_sub(used)),
        None => available,
    };
    Some(match cgroup_memory_left() {
        Some(left) => available.min(left),
        None => available,
    })
}

/// What the memory limits of this process's cgroup (v2) and every group above it
/// leave, bytes; `None` with no limit, or no cgroup v2 to read.
fn cgroup_memory_left() -> Option<u64> {
    let own = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    // The unified hierarchy's line: `0::/path`.
    let path = own.lines().find_map(|l| l.strip_prefix("0::"))?.trim();
    cgroup_left_under(Path::new("/sys/fs/cgroup"), path)
}

/// [`cgroup_memory_left`] for group `path` of the hierarchy mounted at `root`.
fn cgroup_left_under(root: &Path, path: &str) -> Option<u64> {
    let read = |dir: &Path, file: &str| std::fs::read_to_string(dir.join(file)).ok();
    let mut left: Option<u64> = None;
    let mut dir = root.join(path.trim_start_matches('/'));
    loop {
        if let Some(max) = read(&dir, "memory.max").and_then(|t| t.trim().parse::<u64>().ok()) {
            let current = read(&dir, "memory.current")
                .and_then(|t| t.trim().parse::<u64>().ok())
                .unwrap_or(0);
            // The page cache of files not recently used is reclaimed before the limit
            // bites: a daemon that has written gigabytes of histograms sits near its
            // limit in `memory.current` with most of it free to take.
            let reclaimable = read(&dir, "memory.stat")
                .and_then(|t| {
                    t.lines()
                        .find_map(|l| l.strip_prefix("inactive_file "))
                        .and_then(|v| v.trim().parse::<u64>().ok())
                })
                .unwrap_or(0);
            let here = max.saturating_sub(current.saturating_sub(reclaimable));
            left = Some(left.map_or(here, |l| l.min(here)));
        }
        if dir == root || !dir.pop() || !dir.starts_with(root) {
            break;
        }
    }
    left
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A folder-sync failure after the rename is told apart from a failed write: it
    /// says the file was written, and names the folder and the cause.
    #[test]
    fn a_folder_not_synced_is_told_from_a_file_not_written() {
        let e = std::io::Error::other(FolderNotSynced {
            dir: PathBuf::from("/data/runs"),
            source: std::io::Error::from_raw_os_error(5),
        });
        let found = FolderNotSynced::of(&e).expect("found in the io::Error");
        let text = found.to_string();
        assert!(
            text.starts_with("written, but its folder /data/runs") && text.contains("os error 5"),
            "{text}"
        );
        assert!(FolderNotSynced::of(&std::io::Error::from_raw_os_error(28)).is_none());
    }

    /// A container's or unit's memory limit caps what the memory checks believe is
    /// left, at whichever level of the hierarchy sets the tightest one. Until
    /// 2026-12-07 only the host's `MemAvailable` and the address-space limit counted,
    /// so under a 2 GiB `MemoryMax` a 3 GiB read passed every check.
    #[test]
    fn a_cgroup_limit_caps_the_memory_left() {
        let root = tempfile::tempdir().unwrap();
        let unit = root.path().join("system.slice/periscope.service");
        std::fs::create_dir_all(&unit).unwrap();
        let write = |dir: &Path, file: &str, text: &str| std::fs::write(dir.join(file), text).unwrap();
        // No limit anywhere ("max"), as on a host's root group.
        write(root.path(), "memory.max", "max\n");
        write(&unit, "memory.max", "max\n");
        assert_eq!(
            cgroup_left_under(root.path(), "/system.slice/periscope.service"),
            None
        );
        // The unit's own limit.
        write(&unit, "memory.max", "2147483648\n");
        write(&unit, "memory.current", "536870912\n");
        assert_eq!(
            cgroup_left_under(root.path(), "/system.slice/periscope.service"),
            Some(1_610_612_736)
        );
        // A tighter one on the slice above it.
        let slice = root.path().join("system.slice");
        write(&slice, "memory.max", "1073741824\n");
        write(&slice, "memory.current", "805306368\n");
        assert_eq!(
            cgroup_left_under(root.path(), "/system.slice/periscope.service"),
            Some(268_435_456)
        );
        // A group over its limit has nothing left, not a wrapped-around figure.
        write(&unit, "memory.current", "4294967296\n");
        assert_eq!(
            cgroup_left_under(root.path(), "/system.slice/periscope.service"),
            Some(0)
        );
        // Its inactive page cache is counted as free: 1.5 GiB of 1.75 GiB in use is
        // cache of files written and not read since.
        write(&unit, "memory.current", "1879048192\n");
        write(
            &unit,
            "memory.stat",
            "anon 268435456\nfile 1610612736\ninactive_file 1610612736\n",
        );
        write(&slice, "memory.max", "max\n");
        assert_eq!(
            cgroup_left_under(root.path(), "/system.slice/periscope.service"),
            Some(1_879_048_192)
        );
    }

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

    /// A header whose shape overflows, or declares more than the file holds, is
    /// refused before anything is allocated for it; a FIFO is refused, not waited on.
    /// Until 2026-12-07 a shape of (2^32, 2^32) read as an empty array (the npy layer's
    /// product wraps) and a truncated file's shape was returned with fewer values.
    #[test]
    fn npy_headers_that_lie_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        // Version 1.0: magic, version, header length (u16 LE), the header padded with
        // spaces and a newline to a multiple of 64 bytes, then 24 float32 values.
        let with_shape = |shape: &str| {
            let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
            while (10 + header.len() + 1) % 64 != 0 {
                header.push(' ');
            }
            header.push('\n');
            let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
            bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
            bytes.extend_from_slice(header.as_bytes());
            bytes.extend(std::iter::repeat_n(0.5f32.to_le_bytes(), 24).flatten());
            bytes
        };
        std::fs::write(&path, with_shape("(2, 3, 4)")).unwrap();
        assert_eq!(read_npy(&path).unwrap(), (vec![2, 3, 4], vec![0.5; 24]));
        // The npy layer reads the shape as a list too, and the keys in double quotes:
        // the check before it passed over both, and the layer's unchecked product
        // panicked in a debug build (until 2026-12-08).
        for shape in ["[4294967296, 4294967296]", "(4294967296, 4294967296)"] {
            let quoted: Vec<u8> = with_shape(shape)
                .into_iter()
                .map(|b| if b == b'\'' { b'"' } else { b })
                .collect();
            for b in [with_shape(shape), quoted] {
                std::fs::write(&path, b).unwrap();
                let e = read_npy(&path).unwrap_err().to_string();
                assert!(e.contains("overflows"), "{shape}: {e}");
            }
        }
        for (shape, says) in [
            ("(4294967296, 4294967296)", "overflows"),
            ("(2, 3, 40)", "truncated"),
            ("(2, 3, 5)", "truncated"),
        ] {
            std::fs::write(&path, with_shape(shape)).unwrap();
            let e = read_npy(&path).unwrap_err().to_string();
            assert!(e.contains(says) && e.contains("a.npy"), "{shape}: {e}");
        }
        #[cfg(unix)]
        {
            let fifo = dir.path().join("fifo.npy");
            let made = std::process::Command::new("mkfifo").arg(&fifo).status();
            if made.is_ok_and(|s| s.success()) {
                let e = read_npy(&fifo).unwrap_err().to_string();
                assert!(e.contains("not a regular file"), "{e}");
            }
        }
    }

    #[test]
    fn colour_map_ends() {
        assert_eq!(colour(0.0), VIRIDIS[0]);
        assert_eq!(colour(1.0), VIRIDIS[8]);
        assert_eq!(colour(f64::NAN), VIRIDIS[0]);
    }
}

//! `periscope recon` on y-tal captures made to hurt: a small file declaring a huge
//! `H` (an "HDF5 bomb"), a bin width that would need terabytes, a time origin of
//! −1e30 m, origins that are not finite, a transposed grid. Each must end in a clear
//! message naming the dataset, exit code 1, and never an abort, under a 4 GiB address
//! space limit (as on a lab PC that is also running the instrument).
use std::path::{Path, PathBuf};
use std::process::Command;

use glam::DVec3;
use periscope_recon::io::ytal::{Grid, GridFormat, HFormat, YtalCapture};

/// A planar `nx` × `ny` relay grid at `pitch` metres from `corner`, facing +z.
fn relay_grid(nx: usize, ny: usize, pitch: f64, corner: [f64; 2]) -> Grid {
    let points: Vec<DVec3> = (0..nx * ny)
        .map(|k| {
            DVec3::new(
                pitch * (k / ny) as f64 + corner[0],
                pitch * (k % ny) as f64 + corner[1],
                0.0,
            )
        })
        .collect();
    Grid {
        normals: vec![DVec3::Z; points.len()],
        points,
        format: GridFormat::XY3,
        shape: vec![nx, ny],
    }
}

/// A confocal 11 × 13 capture of 7 bins: small, with a shape whose bytes are unique in
/// the file, so tests can find and forge it.
fn capture() -> YtalCapture {
    let (nx, ny) = (11, 13);
    let grid = relay_grid(nx, ny, 0.05, [-0.25, -0.3]);
    YtalCapture {
        h: (0..7 * nx * ny).map(|v| (v % 5) as f32).collect(),
        h_shape: vec![7, nx, ny],
        h_format: HFormat::TSxSy,
        sensor_grid: grid.clone(),
        laser_grid: grid,
        sensor_xyz: None,
        laser_xyz: None,
        delta_t: 0.01,
        t_start: 1.0,
        t_accounts_first_and_last_bounces: false,
        scene_info: None,
        flags: None,
    }
}

/// Runs `periscope recon FILE` with the address space limited to 4 GiB; returns the
/// exit code (`None`: killed by a signal) and stderr.
fn recon_limited(file: &Path, out: &Path) -> (Option<i32>, String) {
    recon_within(4 << 20, file, out)
}

/// Runs `periscope recon FILE` with the address space limited to `kib` KiB.
fn recon_within(kib: u64, file: &Path, out: &Path) -> (Option<i32>, String) {
    let cmd = format!(
        "ulimit -v {kib}; exec '{}' recon '{}' --out '{}'",
        env!("CARGO_BIN_EXE_periscope"),
        file.display(),
        out.display()
    );
    let o = Command::new("sh").arg("-c").arg(cmd).output().unwrap();
    (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
}

/// Runs `periscope recon` within `kib` KiB of address space on the committed fuzz
/// seed `seed` (under `fuzz/corpus/`), copied into a fresh directory as `name`.
fn recon_of_seed(seed: &str, name: &str, kib: u64) -> (Option<i32>, String) {
    let seed = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/corpus")
        .join(seed);
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join(name);
    std::fs::copy(seed, &file).unwrap();
    recon_within(kib, &file, &dir.path().join("out"))
}

/// `c` as a file, unchecked: a hostile file is one the writer would refuse to make
/// (`YtalCapture::write` checks what it writes as the reader does), so its bytes are
/// written as they come.
fn write(dir: &Path, name: &str, c: &YtalCapture) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, c.to_bytes().unwrap()).unwrap();
    path
}

/// Replaces the first occurrence of `from` in the file by `to` (same length) and
/// re-seals the object header it lies in (HDF5 checksums its metadata with Jenkins'
/// lookup3), as a forger would.
fn forge(path: &Path, from: &[u8], to: &[u8]) {
    let mut bytes = std::fs::read(path).unwrap();
    let at = bytes
        .windows(from.len())
        .position(|w| w == from)
        .expect("the pattern is in the file");
    bytes[at..at + to.len()].copy_from_slice(to);
    let start = bytes[..at]
        .windows(4)
        .rposition(|w| w == b"OHDR")
        .expect("the pattern lies in a version-2 object header");
    let flags = bytes[start + 5];
    let mut p = start + 6;
    if flags & 0x20 != 0 {
        p += 16; // times
    }
    if flags & 0x10 != 0 {
        p += 4; // attribute phase change
    }
    let width = 1usize << (flags & 0x03);
    let mut size = 0usize;
    for k in 0..width {
        size |= usize::from(bytes[p + k]) << (8 * k);
    }
    let end = p + width + size;
    assert!(at < end, "the pattern is not in the header's first chunk");
    let sum = lookup3(&bytes[start..end]);
    bytes[end..end + 4].copy_from_slice(&sum.to_le_bytes());
    std::fs::write(path, bytes).unwrap();
}

/// Bob Jenkins' lookup3 `hashlittle` with seed 0, HDF5's metadata checksum.
fn lookup3(data: &[u8]) -> u32 {
    let mut a = 0xdead_beef_u32.wrapping_add(data.len() as u32);
    let (mut b, mut c) = (a, a);
    let word = |k: &[u8], i: usize| -> u32 {
        let mut w = [0u8; 4];
        for (j, x) in w.iter_mut().enumerate() {
            *x = k.get(i + j).copied().unwrap_or(0);
        }
        u32::from_le_bytes(w)
    };
    let mut k = data;
    while k.len() > 12 {
        a = a.wrapping_add(word(k, 0));
        b = b.wrapping_add(word(k, 4));
        c = c.wrapping_add(word(k, 8));
        a = a.wrapping_sub(c) ^ c.rotate_left(4);
        c = c.wrapping_add(b);
        b = b.wrapping_sub(a) ^ a.rotate_left(6);
        a = a.wrapping_add(c);
        c = c.wrapping_sub(b) ^ b.rotate_left(8);
        b = b.wrapping_add(a);
        a = a.wrapping_sub(c) ^ c.rotate_left(16);
        c = c.wrapping_add(b);
        b = b.wrapping_sub(a) ^ a.rotate_left(19);
        a = a.wrapping_add(c);
        c = c.wrapping_sub(b) ^ b.rotate_left(4);
        b = b.wrapping_add(a);
        k = &k[12..];
    }
    if k.is_empty() {
        return c;
    }
    a = a.wrapping_add(word(k, 0));
    b = b.wrapping_add(word(k, 4));
    c = c.wrapping_add(word(k, 8));
    c ^= b;
    c = c.wrapping_sub(b.rotate_left(14));
    a ^= c;
    a = a.wrapping_sub(c.rotate_left(11));
    b ^= a;
    b = b.wrapping_sub(a.rotate_left(25));
    c ^= b;
    c = c.wrapping_sub(b.rotate_left(16));
    a ^= c;
    a = a.wrapping_sub(c.rotate_left(4));
    b ^= a;
    b = b.wrapping_sub(a.rotate_left(14));
    c ^= b;
    c.wrapping_sub(b.rotate_left(24))
}

fn dims(d: [u64; 3]) -> Vec<u8> {
    d.iter().flat_map(|x| x.to_le_bytes()).collect()
}

#[test]
fn the_untouched_capture_reconstructs() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(dir.path(), "ok.hdf5", &capture());
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(0), "{stderr}");
}

#[test]
fn an_hdf5_bomb_is_refused_before_anything_is_allocated() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(dir.path(), "bomb.hdf5", &capture());
    let size = std::fs::metadata(&file).unwrap().len();
    // `H` now declares 7 × 2^20 × 2^20 values (28 TiB) in a file of a few KB.
    forge(&file, &dims([7, 11, 13]), &dims([7, 1 << 20, 1 << 20]));
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("dataset `H`") && stderr.contains("declares"),
        "{stderr}"
    );
    assert!(size < 64 << 10, "{size}");
    // Declared within the in-memory limit but far beyond what the file can hold.
    forge(&file, &dims([7, 1 << 20, 1 << 20]), &dims([7, 1 << 12, 1 << 12]));
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("dataset `H`") && stderr.contains("the file has"),
        "{stderr}"
    );
}

#[test]
fn a_contiguous_dataset_recorded_beyond_the_file_is_refused_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(dir.path(), "run.hdf5", &capture());
    // The relay points are stored contiguously: their layout message (version 3 or 4,
    // class 1) records an address and a byte count, 11 × 13 points × 3 × 4 bytes.
    // Forged to claim a TiB.
    let bytes = std::fs::read(&file).unwrap();
    let size = (11u64 * 13 * 3 * 4).to_le_bytes();
    let at = (0..bytes.len() - 18)
        .find(|&i| matches!(bytes[i], 3 | 4) && bytes[i + 1] == 1 && bytes[i + 10..i + 18] == size)
        .expect("a contiguous layout message of the relay points' size");
    let mut forged = bytes[at..at + 18].to_vec();
    forged[10..].copy_from_slice(&(1u64 << 40).to_le_bytes());
    forge(&file, &bytes[at..at + 18], &forged);
    let (code, stderr) = recon_within(1 << 20, &file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("run.hdf5") && stderr.contains("lies beyond the end of the file"),
        "{stderr}"
    );
}

#[test]
fn a_tiny_bin_width_is_refused_instead_of_allocating_terabytes() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = capture();
    c.delta_t = 1e-12;
    let file = write(dir.path(), "dt.hdf5", &c);
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("bins"), "{stderr}");
}

#[test]
fn absurd_time_origins_and_origins_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = capture();
    c.t_start = -1e30;
    let file = write(dir.path(), "t.hdf5", &c);
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("`t_start`"), "{stderr}");

    let mut c = capture();
    c.laser_xyz = Some(DVec3::new(f64::INFINITY, 0.0, 0.0));
    c.sensor_xyz = Some(DVec3::ZERO);
    c.t_accounts_first_and_last_bounces = true;
    let file = write(dir.path(), "xyz.hdf5", &c);
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("`laser_xyz`"), "{stderr}");
}

#[test]
fn a_transposed_grid_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = capture();
    c.sensor_grid.shape = vec![13, 11];
    let file = write(dir.path(), "tr.hdf5", &c);
    let (code, stderr) = recon_limited(&file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("`sensor_grid_xyz` is a [13, 11] grid"),
        "{stderr}"
    );
}

#[test]
fn a_file_that_crashes_the_hdf5_decoder_is_an_error_not_a_crash() {
    // Found by the `ytal_capture` fuzz target: a chunk layout that makes hdf5-pure
    // overflow an offset while placing a chunk. The chunk check refuses it first now;
    // the reader's panic guard stays behind it for what no check foresees.
    let (code, stderr) = recon_of_seed(
        "ytal_capture/seed-regression-hdf5-chunk-offset-overflow",
        "crash.hdf5",
        4 << 20,
    );
    assert_eq!(code, Some(1), "{stderr}");
    let last = stderr
        .lines()
        .rfind(|l| l.starts_with("error:"))
        .unwrap_or_default();
    assert!(
        last.contains("crash.hdf5")
            && (last.contains("malformed") || last.contains("lies outside the dataset")),
        "{stderr}"
    );
}

#[test]
fn a_chunk_recorded_beyond_the_file_is_refused_before_it_is_read() {
    // Found by the `ytal_capture` fuzz target: a 160 KB file whose chunk record (size
    // and address beyond the end of the file) made the HDF5 layer allocate 3.4 GB.
    // Refused under a 1 GiB address-space limit.
    let (code, stderr) = recon_of_seed(
        "ytal_capture/seed-regression-chunk-beyond-file",
        "chunk.hdf5",
        1 << 20,
    );
    assert_eq!(code, Some(1), "{stderr}");
    assert!(stderr.contains("dataset `H`: a chunk"), "{stderr}");
}

#[test]
fn a_chunk_index_the_hdf5_layer_cannot_list_is_refused_before_it_is_read() {
    // Found by the `capture_file` fuzz target: a 14 KB MAT v7.3 file whose `rect_data`
    // lists a chunk at the undefined address, which the HDF5 layer cannot place past
    // the file's 512-byte header; the chunk check used to pass over an index it could
    // not list, and the read then reserved 4 GiB (4.2 GB resident before the error).
    // Refused under a 1 GiB address-space limit.
    let (code, stderr) = recon_of_seed(
        "capture_file/seed-regression-mat73-chunk-index-unreadable",
        "forged.mat",
        1 << 20,
    );
    assert_eq!(code, Some(1), "{stderr}");
    assert!(
        stderr.contains("forged.mat") && stderr.contains("`rect_data`: its chunk index cannot be read"),
        "{stderr}"
    );
}

/// Finite but huge counts (3e38, near f32::MAX) overflowed the reconstruction's sums
/// and gave a volume that was all NaN, with exit 0. They are refused by name.
#[test]
fn counts_that_would_overflow_the_arithmetic_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = capture();
    c.h.iter_mut().for_each(|v| *v = 3e38);
    let file = write(dir.path(), "huge.hdf5", &c);
    let (code, err) = recon_limited(&file, &dir.path().join("out"));
    assert_ne!(code, Some(0), "{err}");
    assert!(code.is_some(), "killed by a signal: {err}");
    assert!(err.contains("huge.hdf5") && err.contains("overflow"), "{err}");
    assert!(!dir.path().join("out/volume.npy").exists());
}

/// Counts under the reader's limit (1e30) but past what the solvers' single precision
/// holds (1e21 here, with f-k, which squares them; FBP squared them too in its noise
/// floor until 2026-12-06, and now holds them) fail as not finite, and the message says
/// why and what to do (divide the counts), not only to report a bug, as it did until
/// 2026-12-06.
#[test]
fn counts_past_single_precision_are_told_to_be_divided() {
    let dir = tempfile::tempdir().unwrap();
    let mut c = capture();
    let peak = c.h.iter().copied().fold(0.0f32, f32::max);
    c.h.iter_mut().for_each(|v| *v = *v / peak * 1e21);
    let file = write(dir.path(), "large.hdf5", &c);
    let (code, err) = recon_with(&file, Some("method = \"fk\"\n"), &dir.path().join("out"));
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("not finite") && err.contains("divide the counts"),
        "{err}"
    );
    assert!(!dir.path().join("out/volume.npy").exists());
    // FBP holds them now: its noise floor squares in f64.
    let (code, err) = recon_with(&file, Some("method = \"fbp\"\n"), &dir.path().join("fbp"));
    assert_eq!(code, Some(0), "{err}");
    let (_, v) = periscope_recon::io::read_npy(&dir.path().join("fbp/volume.npy")).unwrap();
    assert!(v.iter().all(|x| x.is_finite()) && v.iter().any(|&x| x > 0.0));
}

/// A capture whose `H` fits every size check on its own, but whose reading and
/// reconstruction need more memory than the process may take (here an address-space
/// limit a small capture reconstructs within), ends in a clear message naming the file
/// instead of an abort in the allocator.
#[test]
fn a_capture_larger_than_the_memory_left_is_refused_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    // 8,192 bins × 64 × 64 points: 33.6 M values, about 512 MiB to reconstruct.
    let (bins, nx, ny) = (8192, 64, 64);
    let grid = relay_grid(nx, ny, 0.01, [-0.3, -0.3]);
    let big = YtalCapture {
        h: vec![1.0; bins * nx * ny],
        h_shape: vec![bins, nx, ny],
        sensor_grid: grid.clone(),
        laser_grid: grid,
        ..capture()
    };
    let file = write(dir.path(), "big.hdf5", &big);
    drop(big);
    let small = write(dir.path(), "small.hdf5", &capture());
    let limit = LIMIT_FOR_SMALL_RECON_KIB;
    let (code, err) = recon_within(limit, &small, &dir.path().join("small"));
    assert_eq!(
        code,
        Some(0),
        "the small capture must reconstruct within the limit: {err}"
    );
    let (code, err) = recon_within(limit, &file, &dir.path().join("big"));
    assert!(code.is_some_and(|c| c != 0), "exit {code:?}: {err}");
    assert!(
        err.contains("big.hdf5") && err.contains("GiB") && err.contains("memory"),
        "{err}"
    );
}

/// An HDF5 file larger than the memory left (a small capture padded to 1 GiB, sparse
/// on the disk) is refused before it is read, naming the file and what to do: the
/// HDF5 layer reads a file whole. Until 2026-12-07 the read was tried: under an
/// address-space limit it failed as "I/O error: out of memory", and where what is left
/// is a container's memory limit the kernel would kill the process instead.
#[test]
fn an_hdf5_file_larger_than_the_memory_left_is_refused_before_it_is_read() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(dir.path(), "padded.hdf5", &capture());
    std::fs::OpenOptions::new()
        .write(true)
        .open(&file)
        .unwrap()
        .set_len(1 << 30)
        .unwrap();
    let (code, err) = recon_within(LIMIT_FOR_SMALL_RECON_KIB, &file, &dir.path().join("out"));
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("padded.hdf5") && err.contains("read whole into memory"),
        "{err}"
    );
}

/// An address-space limit `periscope recon` on a small capture runs within (the
/// debug binary maps about 100 MiB before it reads anything), well short of what the
/// large capture above needs.
const LIMIT_FOR_SMALL_RECON_KIB: u64 = 400 << 10;

/// `periscope recon FILE --config CONFIG --out OUT` (when `config` is given, a
/// `[recon]` table's text); the exit code and stderr.
fn recon_with(file: &Path, config: Option<&str>, out: &Path) -> (Option<i32>, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_periscope"));
    cmd.arg("recon").arg(file);
    if let Some(text) = config {
        let path = file.with_extension("toml");
        std::fs::write(&path, text).unwrap();
        cmd.arg("--config").arg(path);
    }
    let o = cmd.arg("--out").arg(out).output().unwrap();
    (o.status.code(), String::from_utf8_lossy(&o.stderr).into_owned())
}

/// Messages that gave the wrong reason until 2026-12-06, each now naming the real one:
/// every transient flagged overflow (it said every transient was empty); a confocal
/// capture with one transient lit in the volume's window under LCT (it said the scan
/// had "1 points", as if the capture were not a grid); and an output file that is a
/// symbolic link (named three times in one message).
#[test]
fn what_is_wrong_with_a_capture_is_what_the_message_says() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");

    let mut c = capture();
    c.flags = Some(vec![periscope_recon::io::ytal::FLAG_OVERFLOW; 11 * 13]);
    let file = write(dir.path(), "overflowed.hdf5", &c);
    let (code, err) = recon_with(&file, None, &out);
    assert_eq!(code, Some(1), "{err}");
    assert!(
        err.contains("every stored histogram is flagged overflow"),
        "{err}"
    );

    // One transient holds counts, the rest are zero: LCT cannot find the grid from it,
    // and says why.
    let mut c = capture();
    c.h.iter_mut().for_each(|v| *v = 0.0);
    for t in 0..7 {
        c.h[t * 11 * 13] = 3.0;
    }
    let file = write(dir.path(), "one-lit.hdf5", &c);
    let (code, err) = recon_with(&file, Some("method = \"lct\"\n"), &out);
    assert_eq!(code, Some(2), "a method the capture cannot take: {err}");
    assert!(
        err.contains("1 point is fewer than three") && err.contains("only 1 of the capture's 143 transients"),
        "{err}"
    );

    // An output file that is a link: refused, the link left, the path named once.
    let file = write(dir.path(), "ok.hdf5", &capture());
    let linked = dir.path().join("linked");
    std::fs::create_dir(&linked).unwrap();
    let link = linked.join("volume.npy");
    std::os::unix::fs::symlink(dir.path().join("elsewhere.npy"), &link).unwrap();
    let (code, err) = recon_with(&file, None, &linked);
    assert_eq!(code, Some(1), "{err}");
    assert!(err.contains("not a regular file"), "{err}");
    assert_eq!(err.matches(&*link.to_string_lossy()).count(), 1, "{err}");
    assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
}

//! Shared helpers for Periscope's end-to-end tests: find the built `periscope` binary
//! and the repository's files, and run the binary with a bounded run time.
//!
//! The binary is the daemon's `main.rs` built in this package as `periscope-e2e`:
//! Cargo builds it before running this package's tests, for their profile and with
//! their features, so the tests never run a stale binary. Set `PERISCOPE_BIN` to test
//! another build.
#![warn(missing_docs)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use periscope_daemon::config::load_scene;
use periscope_recon::io::read_npy;
use periscope_sim::World;
use periscope_sim::truth::depth_truth;

mod plan;
mod skip;
pub use plan::SmallPlan;
pub use skip::skipped;

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ has a parent")
        .to_owned()
}

/// A path inside the repository.
pub fn repo_path(relative: &str) -> PathBuf {
    repo_root().join(relative)
}

/// The `periscope` binary under test: `periscope-e2e`, the daemon's `main.rs` built by
/// Cargo in this package before its tests run (so it is never stale), found beside the
/// test executables; `PERISCOPE_BIN` names another build to test.
pub fn periscope_bin() -> PathBuf {
    if let Some(path) = std::env::var_os("PERISCOPE_BIN") {
        return PathBuf::from(path);
    }
    let exe = std::env::current_exe().expect("the test knows its own path");
    // target/<profile>/deps/<test>-<hash> → target/<profile>/periscope-e2e
    let dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("test executables live in target/<profile>/deps");
    let bin = dir.join(format!("periscope-e2e{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.is_file(),
        "{} is missing: run the end-to-end tests through Cargo (cargo test -p periscope-tests), \
         which builds it first, or set PERISCOPE_BIN",
        bin.display()
    );
    bin
}

/// The shipped simulated instrument (`configs/instrument/sim.toml`) running in real
/// time (`time-scale = 1`), its scene path made absolute so the text can be written
/// anywhere: what the tests that drive a `periscope` child process start from.
pub fn real_time_sim_instrument() -> String {
    let text = std::fs::read_to_string(repo_path("configs/instrument/sim.toml")).expect("sim.toml");
    let scene = repo_path("configs/scenes/wall-letter.toml");
    text.replace(
        "\"../scenes/wall-letter.toml\"",
        &format!("{:?}", scene.to_str().expect("a UTF-8 path")),
    )
    .replace("[sim]\n", "[sim]\ntime-scale = 1.0\n")
}

/// What a finished `periscope` process left behind.
#[derive(Debug)]
pub struct Finished {
    /// Exit code (`None` when killed by a signal).
    pub code: Option<i32>,
    /// Standard output, lossily decoded.
    pub stdout: String,
    /// Standard error, lossily decoded.
    pub stderr: String,
}

/// Runs `periscope ARGS` in the repository root with no standard input, killing it if
/// it runs longer than `limit`.
pub fn periscope_with_limit(args: &[&str], limit: Duration) -> Finished {
    periscope_with_env(args, &[], limit)
}

/// [`periscope_with_limit`] with `env` added to its environment.
pub fn periscope_with_env(args: &[&str], env: &[(&str, &str)], limit: Duration) -> Finished {
    let mut child = Command::new(periscope_bin())
        .args(args)
        .current_dir(repo_root())
        .env("RUST_LOG", "warn")
        .envs(env.iter().copied())
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("periscope starts");
    let start = Instant::now();
    while child.try_wait().expect("wait on periscope").is_none() {
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("periscope {args:?} ran longer than {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let Output {
        status,
        stdout,
        stderr,
    } = child.wait_with_output().expect("collect periscope output");
    Finished {
        code: status.code(),
        stdout: String::from_utf8_lossy(&stdout).into_owned(),
        stderr: String::from_utf8_lossy(&stderr).into_owned(),
    }
}

/// Runs `periscope ARGS` with a 60 s limit.
pub fn periscope(args: &[&str]) -> Finished {
    periscope_with_limit(args, Duration::from_secs(60))
}

/// Every file under `configs/`, sorted, as paths relative to the repository root.
pub fn config_files() -> Vec<PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for entry in std::fs::read_dir(dir).expect("configs/ is readable") {
            let path = entry.expect("directory entry").path();
            if path.is_dir() {
                walk(&path, out);
            } else {
                out.push(path);
            }
        }
    }
    let root = repo_root();
    let mut files = Vec::new();
    walk(&root.join("configs"), &mut files);
    files.sort();
    files
        .into_iter()
        .map(|p| p.strip_prefix(&root).expect("under the root").to_owned())
        .collect()
}

/// How a reconstruction's depth map compares with the simulator's truth.
#[derive(Debug)]
pub struct Accuracy {
    /// Median |depth error| on pixels both call object, metres.
    pub median_error: f64,
    /// 90th percentile of the same.
    pub p90_error: f64,
    /// Silhouette intersection over union.
    pub iou: f64,
    /// Pixels where the truth has an object.
    pub object_pixels: usize,
}

impl Accuracy {
    /// The scene's bounds: median and 90th-percentile depth error (metres) below
    /// `median` and `p90`, silhouette IoU above `iou`.
    pub fn assert_within(&self, median: f64, p90: f64, iou: f64) {
        assert!(
            self.median_error < median,
            "median depth error {:.4} m ≥ {median} m: {self:?}",
            self.median_error
        );
        assert!(
            self.p90_error < p90,
            "90th-percentile depth error {:.4} m ≥ {p90} m: {self:?}",
            self.p90_error
        );
        assert!(self.iou > iou, "silhouette IoU {:.3} ≤ {iou}: {self:?}", self.iou);
    }
}

/// Scores `run/depth.npy` (`shape` = [nx, ny] pixels over `x` × `y`) against the
/// hidden objects of `scene` (a repository path), seen along +z.
pub fn accuracy(run: &Path, scene: &str, x: [f64; 2], y: [f64; 2], shape: [usize; 2]) -> Accuracy {
    let (dims, depth) = read_npy(&run.join("depth.npy")).expect("depth.npy");
    assert_eq!(dims, vec![shape[1], shape[0]], "depth.npy is [ny, nx]");
    let world = World::new(load_scene(&repo_path(scene)).unwrap(), 0.01, 1);
    let truth = depth_truth(&world, x, y, shape, 0.01);
    let (mut inter, mut union, mut errors) = (0usize, 0usize, Vec::new());
    for (d, t) in depth.iter().zip(&truth.depth) {
        let (has_d, has_t) = (d.is_finite(), t.is_finite());
        if has_d && has_t {
            inter += 1;
            errors.push((f64::from(*d) - t).abs());
        }
        if has_d || has_t {
            union += 1;
        }
    }
    errors.sort_by(f64::total_cmp);
    let pick = |q: f64| {
        errors
            .get(((errors.len() as f64 - 1.0) * q).round() as usize)
            .copied()
            .unwrap_or(f64::INFINITY)
    };
    Accuracy {
        median_error: pick(0.5),
        p90_error: pick(0.9),
        iou: inter as f64 / union.max(1) as f64,
        object_pixels: truth.depth.iter().filter(|t| t.is_finite()).count(),
    }
}

/// The lateral grid of a volume across the bars: x and y both run from `lo` in
/// columns `pitch` wide (the volume's `[nz, ny, nx]` shape gives their number).
#[derive(Clone, Copy, Debug)]
pub struct BarsGrid {
    /// The grid's first edge, metres, in x and in y.
    pub lo: f64,
    /// The columns' width, metres.
    pub pitch: f64,
}

impl BarsGrid {
    /// The simulator's bars plan (`configs/plans/wall-bars.toml`): 5 mm voxels from
    /// −0.2 m.
    pub const PLAN: Self = Self {
        lo: -0.2,
        pitch: 0.005,
    };

    fn centre(&self, i: usize) -> f64 {
        self.lo + (i as f64 + 0.5) * self.pitch
    }
}

/// Asserts the image across three 2 cm bars 2 cm apart at x = −0.04, 0, 0.04 m (the
/// simulator's `wall-bars` scene, and tests/data/ytal/render_bars.py's) in a run's
/// `volume.npy` on `grid`: a peak within 7.5 mm of each bar, and the profile at the
/// gaps' centres at most `max_dip` of the dimmest bar's (profile values linearly
/// interpolated between column centres, as the validation scorer's resolution test).
pub fn assert_bars_resolved(out: &Path, grid: BarsGrid, pitch: &str, max_dip: f64) {
    let profile = bar_profile(out, grid);
    let at = |x: f64| {
        let f = ((x - grid.lo) / grid.pitch - 0.5).clamp(0.0, (profile.len() - 1) as f64);
        let (i, t) = (f.floor() as usize, f - f.floor());
        profile[i] * (1.0 - t) + profile[(i + 1).min(profile.len() - 1)] * t
    };
    let bars = [-0.04, 0.0, 0.04].map(at);
    let gaps = [-0.02, 0.02].map(at);
    let dip = gaps.iter().fold(0.0f64, |m, g| m.max(*g)) / bars.iter().fold(f64::INFINITY, |m, b| m.min(*b));
    eprintln!("bars at {pitch}: bars {bars:.2?}, gaps {gaps:.2?}, dip {dip:.3}\n{profile:.2?}");
    assert!(
        dip <= max_dip,
        "the bars at {pitch} are not resolved: gaps {gaps:.2?} against bars {bars:.2?}"
    );
    for centre in [-0.04, 0.0, 0.04] {
        let near: Vec<usize> = (1..profile.len() - 1)
            .filter(|&i| (grid.centre(i) - centre).abs() <= 0.0125)
            .collect();
        let peak = *near
            .iter()
            .max_by(|&&a, &&b| profile[a].total_cmp(&profile[b]))
            .expect("the grid covers the bars");
        let x = grid.centre(peak);
        assert!(
            (x - centre).abs() <= 0.0075
                && profile[peak - 1] < profile[peak]
                && profile[peak + 1] < profile[peak],
            "at {pitch}, no peak at the bar at x = {centre} m (largest at {x:.4} m): {profile:.2?}"
        );
    }
}

/// A run's image across the bars: its volume's maximum along z, the mean over the rows
/// with |y| ≤ 0.1 m, scaled to a maximum of 1; one value per column of `grid`.
fn bar_profile(run: &Path, grid: BarsGrid) -> Vec<f64> {
    let (shape, volume) = read_npy(&run.join("volume.npy")).unwrap();
    assert_eq!(shape.len(), 3, "a volume");
    let (nz, ny, nx) = (shape[0], shape[1], shape[2]);
    let mut profile = vec![0.0f64; nx];
    let rows: Vec<usize> = (0..ny).filter(|&j| grid.centre(j).abs() <= 0.1).collect();
    for &j in &rows {
        for (i, p) in profile.iter_mut().enumerate() {
            let top = (0..nz)
                .map(|k| volume[(k * ny + j) * nx + i])
                .fold(0.0f32, f32::max);
            *p += f64::from(top) / rows.len() as f64;
        }
    }
    let max = profile.iter().fold(0.0f64, |m, v| m.max(*v));
    assert!(max > 0.0, "the volume is empty");
    profile.iter().map(|v| v / max).collect()
}

/// A volume's image as the validation scorer reads it: the maximum along depth of each
/// column (`volume.npy` is indexed z, y, x), divided by the volume's peak, and the depth
/// slice of each column's maximum (an empty column reads slice 0, as an argmax does).
pub struct Projection {
    /// Columns along x and y.
    pub nx: usize,
    /// Rows along y.
    pub ny: usize,
    /// Depth slices.
    pub nz: usize,
    /// Each column's maximum over the volume's peak, row by row (`iy * nx + ix`).
    pub mip: Vec<f64>,
    /// Each column's slice of its maximum, in the same order.
    pub slice: Vec<usize>,
}

impl Projection {
    /// The projection of `volume.npy` in `out`.
    pub fn of(out: &Path) -> Projection {
        let (dims, volume) = read_npy(&out.join("volume.npy")).expect("volume.npy");
        let (nz, ny, nx) = (dims[0], dims[1], dims[2]);
        let (mut mip, mut slice) = (vec![0.0f64; nx * ny], vec![0usize; nx * ny]);
        for iz in 0..nz {
            for c in 0..nx * ny {
                let v = f64::from(volume[iz * nx * ny + c]);
                if v > mip[c] {
                    mip[c] = v;
                    slice[c] = iz;
                }
            }
        }
        let peak = mip.iter().cloned().fold(0.0, f64::max);
        assert!(peak > 0.0, "an empty volume in {}", out.display());
        mip.iter_mut().for_each(|v| *v /= peak);
        Projection {
            nx,
            ny,
            nz,
            mip,
            slice,
        }
    }

    /// The silhouette: columns above Otsu's threshold of the projection.
    pub fn silhouette(&self) -> Vec<bool> {
        let threshold = otsu(&self.mip);
        self.mip.iter().map(|v| *v > threshold).collect()
    }
}

/// Otsu's threshold on values in [0, 1] (256 bins, the validation scorer's).
pub fn otsu(values: &[f64]) -> f64 {
    let mut hist = [0.0f64; 256];
    for v in values {
        hist[((v.clamp(0.0, 1.0) * 256.0) as usize).min(255)] += 1.0;
    }
    let total: f64 = hist.iter().sum();
    let (mut w0, mut mu, mut best) = (0.0, 0.0, (f64::NEG_INFINITY, 1.0));
    let mu_t: f64 = hist
        .iter()
        .enumerate()
        .map(|(k, h)| h / total * (k as f64 + 0.5) / 256.0)
        .sum();
    for (k, h) in hist.iter().enumerate().take(255) {
        w0 += h / total;
        mu += h / total * (k as f64 + 0.5) / 256.0;
        let between = (mu_t * w0 - mu).powi(2) / (w0 * (1.0 - w0));
        if between.is_finite() && between > best.0 {
            best = (between, (k + 1) as f64 / 256.0);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::SmallPlan;

    #[test]
    fn a_small_plan_key_is_replaced_in_its_own_table_or_added_to_it() {
        let t = SmallPlan::named("x")
            .set("los.grid", [4, 4])
            .set("pairs.grid", [3, 3])
            .set("recon.solver", "lct")
            .set("recon.gtr.epochs", 2)
            .toml();
        assert!(t.contains("\nname = \"x\"\n[los]\n"), "{t}");
        assert!(t.contains("\ngrid = [4, 4]\ndwell-ms = 1.0\n[relay]"), "{t}");
        assert!(t.contains("mode = \"confocal\"\ngrid = [3, 3]\n"), "{t}");
        assert!(
            t.contains("method = \"fbp\"\nsolver = \"lct\"\n[recon.volume]"),
            "{t}"
        );
        assert!(
            t.ends_with("shape = [32, 32, 16]\n[recon.gtr]\nepochs = 2\n"),
            "{t}"
        );
    }
}

//! How `periscope recon`'s time and memory grow with the work: capture size against
//! volume size, for `method = "gtr"` (3D-GTR, defaults) and `method = "fbp"`.
//!
//! `cargo bench -p periscope-daemon --bench scaling` (release). Setup (not timed): for
//! each capture size a y-tal HDF5 capture (`T_Si`, one transient per arbitrary pair:
//! illumination and detection points drawn independently and uniformly over a planar
//! 1 m relay, 512 bins of 5 mm of hidden path) rendered by the 3D-GTR forward model
//! from a fixed scene of 48 primitives (two patches 0.55 and 0.8 m from the relay),
//! scaled to a peak of about 100 counts. Timed: `periscope recon` on it, a child
//! process per run, with a volume of n × n × n voxels over 1 m × 1 m × 0.8 m (z from
//! 0.3 m); wall time from spawning to exit, and the child's peak resident memory as it
//! reports it. The median of `SCALING_RUNS` runs (default 3; 1 for a configuration
//! whose first run took over 60 s) is the figure.
//!
//! Knobs (environment): `SCALING_PAIRS` (default `1000,4000,16000,64000`),
//! `SCALING_VOLUMES` (edge n, default `64,128,256`), `SCALING_METHODS` (default
//! `gtr,fbp`), `SCALING_RUNS`, and `SCALING_MAX_S` (default 600): a configuration whose
//! time, extrapolated from the one before it with fewer pairs or voxels, would exceed
//! this is not run and says so. Results: a table on stdout and
//! `target/scaling.csv` (method, pairs, n, median seconds, peak MiB, runs), which
//! `tools/plot-scaling.py` draws (docs/recon.md, "How cost grows with the work").
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use glam::{DMat3, DQuat, DVec3};
use periscope_recon::gtr::{Kernel, RenderOptions, render_set};
use periscope_recon::io::ytal::{Grid, GridFormat, HFormat, YtalCapture};
use periscope_recon::{Pair, TimeAxis, TransientSet};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const BINS: usize = 512;
const BIN_M: f64 = 0.005;

fn list(name: &str, default: &str) -> Vec<String> {
    std::env::var(name)
        .unwrap_or_else(|_| default.into())
        .split(',')
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .collect()
}

fn number<T: std::str::FromStr>(name: &str, text: &str) -> T {
    text.parse()
        .unwrap_or_else(|_| panic!("{name}: `{text}` is not a number"))
}

/// The hidden scene: two patches of 24 primitives each.
fn scene() -> Vec<Kernel> {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let mut out = Vec::new();
    for (centre, half) in [
        (DVec3::new(-0.15, 0.05, 0.55), [0.12, 0.2]),
        (DVec3::new(0.2, -0.1, 0.8), [0.15, 0.1]),
    ] {
        for _ in 0..24 {
            let x = centre
                + DVec3::new(
                    rng.random_range(-half[0]..half[0]),
                    rng.random_range(-half[1]..half[1]),
                    rng.random_range(-0.01..0.01),
                );
            let q = DQuat::from_rotation_z(rng.random_range(0.0..std::f64::consts::PI));
            let s = DVec3::new(0.04, 0.04, 0.004);
            out.push(Kernel::new(x, DMat3::from_quat(q), s, 1.0));
        }
    }
    out
}

/// A y-tal capture of `pairs` arbitrary pairs of the scene, written to `path`.
fn write_capture(path: &Path, pairs: usize) {
    let mut rng = ChaCha8Rng::seed_from_u64(pairs as u64);
    let axis = TimeAxis {
        start: 0.0,
        width: BIN_M,
        bins: BINS,
    };
    let mut set = TransientSet::new(axis).unwrap();
    let zero = vec![0.0f32; BINS];
    let mut point = || DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
    for _ in 0..pairs {
        let (xi, xd) = (point(), point());
        set.push(
            Pair {
                xi,
                ni: DVec3::Z,
                xd,
                nd: DVec3::Z,
            },
            &zero,
        )
        .unwrap();
    }
    let rendered = render_set(&scene(), &set, &RenderOptions::default());
    let peak = rendered
        .iter()
        .copied()
        .fold(0.0f64, f64::max)
        .max(f64::MIN_POSITIVE);
    let scale = 100.0 / peak;
    // C order, time first: H[t, c].
    let mut h = vec![0.0f32; BINS * pairs];
    for (c, hist) in rendered.chunks(BINS).enumerate() {
        for (t, v) in hist.iter().enumerate() {
            h[t * pairs + c] = (v * scale) as f32;
        }
    }
    let grid = |points: Vec<DVec3>| Grid {
        normals: vec![DVec3::Z; points.len()],
        shape: vec![points.len()],
        points,
        format: GridFormat::N3,
    };
    let capture = YtalCapture {
        h,
        h_shape: vec![BINS, pairs],
        h_format: HFormat::TSi,
        laser_grid: grid(set.pairs().iter().map(|p| p.xi).collect()),
        sensor_grid: grid(set.pairs().iter().map(|p| p.xd).collect()),
        sensor_xyz: None,
        laser_xyz: None,
        delta_t: BIN_M,
        t_start: 0.0,
        t_accounts_first_and_last_bounces: false,
        scene_info: None,
        flags: None,
    };
    capture.write(path).unwrap();
}

/// One `periscope recon` run: wall seconds and the peak memory it reports, MiB.
fn run(capture: &Path, config: &Path, out: &Path) -> (f64, f64) {
    let _ = std::fs::remove_dir_all(out);
    let start = Instant::now();
    let output = Command::new(env!("CARGO_BIN_EXE_periscope"))
        .arg("recon")
        .arg(capture)
        .arg("--config")
        .arg(config)
        .arg("--out")
        .arg(out)
        .output()
        .expect("periscope recon runs");
    let seconds = start.elapsed().as_secs_f64();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "periscope recon failed on {}:\n{stdout}\n{}",
        capture.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let peak = stdout
        .lines()
        .find_map(|l| l.split("peak memory ").nth(1))
        .and_then(|t| t.trim_end_matches(" MiB").trim().parse::<f64>().ok())
        .unwrap_or(f64::NAN);
    (seconds, peak)
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    // `cargo bench` passes `--bench`; a filter argument is not supported here.
    let pairs: Vec<usize> = list("SCALING_PAIRS", "1000,4000,16000,64000")
        .iter()
        .map(|s| number("SCALING_PAIRS", s))
        .collect();
    let volumes: Vec<usize> = list("SCALING_VOLUMES", "64,128,256")
        .iter()
        .map(|s| number("SCALING_VOLUMES", s))
        .collect();
    let methods = list("SCALING_METHODS", "gtr,fbp");
    let runs: usize = number(
        "SCALING_RUNS",
        &std::env::var("SCALING_RUNS").unwrap_or_else(|_| "3".into()),
    );
    let max_s: f64 = number(
        "SCALING_MAX_S",
        &std::env::var("SCALING_MAX_S").unwrap_or_else(|_| "600".into()),
    );
    let dir = tempfile::tempdir().unwrap();
    println!("threads: {}", rayon::current_num_threads());
    let mut captures = BTreeMap::new();
    for &p in &pairs {
        let path = dir.path().join(format!("capture-{p}.hdf5"));
        let t = Instant::now();
        write_capture(&path, p);
        println!(
            "capture of {p} pairs: {:.0} MiB on disk, rendered and written in {:.1} s",
            std::fs::metadata(&path).unwrap().len() as f64 / (1u64 << 20) as f64,
            t.elapsed().as_secs_f64()
        );
        captures.insert(p, path);
    }
    let target = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target");
    let csv_path: PathBuf = std::env::var("CARGO_TARGET_DIR")
        .map_or(target, PathBuf::from)
        .join("scaling.csv");
    let mut csv = String::from("method,pairs,n,seconds,peak_mib,runs\n");
    println!("| method | pairs | volume | time (median) | peak memory | runs |");
    println!("| --- | --- | --- | --- | --- | --- |");
    // Seconds per unit of work of the last configuration run, per method, to skip
    // configurations that would take too long.
    let mut done: BTreeMap<(String, usize, usize), f64> = BTreeMap::new();
    for method in &methods {
        for &n in &volumes {
            for &p in &pairs {
                // Extrapolate from the largest run with fewer pairs or voxels: FBP's
                // work grows with pairs × voxels, 3D-GTR's mostly does not.
                let estimate = done
                    .iter()
                    .filter(|((m, q, k), _)| m == method && *q <= p && *k <= n)
                    .map(|((_, q, k), s)| {
                        let ratio = if method == "fbp" {
                            (p as f64 / *q as f64) * (n as f64 / *k as f64).powi(3)
                        } else {
                            1.0
                        };
                        s * ratio
                    })
                    .fold(0.0f64, f64::max);
                if estimate > max_s {
                    println!(
                        "| {method} | {p} | {n}³ | not run: about {estimate:.0} s by extrapolation, over SCALING_MAX_S = {max_s:.0} | | |"
                    );
                    continue;
                }
                let config = dir.path().join(format!("{method}-{n}.toml"));
                std::fs::write(
                    &config,
                    format!(
                        "method = \"{method}\"\n[volume]\nx = [-0.5, 0.5]\ny = [-0.5, 0.5]\nz = [0.3, 1.1]\nshape = [{n}, {n}, {n}]\n"
                    ),
                )
                .unwrap();
                let out = dir.path().join("out");
                let mut times = Vec::new();
                let mut peaks = Vec::new();
                for i in 0..runs.max(1) {
                    let (s, m) = run(&captures[&p], &config, &out);
                    times.push(s);
                    peaks.push(m);
                    if i == 0 && s > 60.0 {
                        break;
                    }
                }
                let (t, m, k) = (
                    median(&mut times),
                    peaks.iter().copied().fold(f64::NAN, f64::max),
                    times.len(),
                );
                done.insert((method.clone(), p, n), t);
                println!("| {method} | {p} | {n}³ | {t:.2} s | {m:.0} MiB | {k} |");
                csv.push_str(&format!("{method},{p},{n},{t:.3},{m:.1},{k}\n"));
            }
        }
    }
    std::fs::write(&csv_path, csv).unwrap();
    println!("written: {}", csv_path.display());
}

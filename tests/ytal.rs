//! y-tal HDF5 interop: captures written by y-tal itself (`tal.io.write_capture`, see
//! tests/data/ytal/generate.py) and several rendered by mitransient (render_torso.py,
//! render_bars.py) reconstruct with `periscope recon`, and a run's exported capture reads back.
//!
//! The fixtures hold a 0.2 m square patch 0.5 m in front of a planar relay, rendered
//! analytically. Tolerances: on pixels where both the reconstruction and the truth
//! have the patch, the median depth error is under 2 cm (measured 1.5–3 mm); the
//! silhouette overlaps the true square with IoU above 0.6 (measured 0.66–0.85).
use std::path::Path;
use std::time::Duration;

use periscope_recon::VolumeGrid;
use periscope_recon::io::read_npy;
use periscope_recon::io::ytal::{HFormat, YtalCapture};
use periscope_tests::{
    BarsGrid, Finished, Projection, assert_bars_resolved, periscope_with_limit, repo_path,
};

/// Median depth error over the patch and silhouette IoU of `out/depth.npy` on `grid`.
fn patch_accuracy(out: &Path, grid: &VolumeGrid) -> (f64, f64) {
    let patch = |x: f64, y: f64| (x - 0.05).abs() <= 0.1 && (y + 0.05).abs() <= 0.1;
    silhouette_accuracy(out, grid, patch, 0.5)
}

/// Median depth error against `depth` where `truth(x, y)` holds, and silhouette IoU, of
/// `out/depth.npy` on `grid` (pixels with a finite depth are the reconstruction's).
fn silhouette_accuracy(
    out: &Path,
    grid: &VolumeGrid,
    truth: impl Fn(f64, f64) -> bool,
    depth: f64,
) -> (f64, f64) {
    let (dims, depths) = read_npy(&out.join("depth.npy")).expect("depth.npy");
    let (ny, nx) = (dims[0], dims[1]);
    assert_eq!([nx, ny], [grid.shape[0], grid.shape[1]]);
    let v = grid.voxel();
    let (mut inter, mut union, mut errors) = (0usize, 0usize, Vec::new());
    for iy in 0..ny {
        for ix in 0..nx {
            let x = grid.x[0] + (ix as f64 + 0.5) * v.x;
            let y = grid.y[0] + (iy as f64 + 0.5) * v.y;
            let truth = truth(x, y);
            let d = depths[iy * nx + ix];
            if truth && d.is_finite() {
                inter += 1;
                errors.push((f64::from(d) - depth).abs());
            }
            if truth || d.is_finite() {
                union += 1;
            }
        }
    }
    assert!(!errors.is_empty(), "no depth on the target at all");
    errors.sort_by(f64::total_cmp);
    (errors[errors.len() / 2], inter as f64 / union as f64)
}

/// `periscope recon FILE [--config CONFIG] --out OUT`, however it ends.
fn try_recon(file: &str, config: Option<&str>, out: &Path) -> Finished {
    let out_s = out.to_str().unwrap();
    let mut args = vec!["recon", file, "--out", out_s];
    if let Some(c) = config {
        args.extend(["--config", c]);
    }
    periscope_with_limit(&args, Duration::from_secs(300))
}

/// [`try_recon`], which must succeed; its standard output.
fn recon(file: &str, config: Option<&str>, out: &Path) -> String {
    let done = try_recon(file, config, out);
    assert_eq!(
        done.code,
        Some(0),
        "periscope recon {file} failed:\n{}\n{}",
        done.stdout,
        done.stderr
    );
    done.stdout
}

/// `periscope recon FILE` with `method = "gtr"` and nothing else but `grid` set, as
/// the validation set is judged; returns the temporary directory (kept alive by the
/// caller) and the output folder in it.
fn gtr_with_defaults(file: &str, grid: &VolumeGrid) -> (tempfile::TempDir, std::path::PathBuf) {
    recon_on_grid(file, grid, "gtr", "")
}

/// `periscope recon FILE` with `method`, `grid` and the TOML text `extra`; returns the
/// temporary directory (kept alive by the caller) and the output folder in it.
fn recon_on_grid(
    file: &str,
    grid: &VolumeGrid,
    method: &str,
    extra: &str,
) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("recon.toml");
    std::fs::write(
        &config,
        format!(
            "method = \"{method}\"\n[volume]\nx = {:?}\ny = {:?}\nz = {:?}\nshape = {:?}\n{extra}",
            grid.x, grid.y, grid.z, grid.shape
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    recon(file, Some(config.to_str().unwrap()), &out);
    (dir, out)
}

fn check_fixture(name: &str, format: HFormat, config: Option<&str>) {
    let file = format!("tests/data/ytal/{name}.hdf5");
    let capture = YtalCapture::read(&repo_path(&file)).expect("y-tal's file reads");
    assert_eq!(capture.h_format, format);
    let dir = tempfile::tempdir().unwrap();
    let stdout = recon(&file, config, dir.path());
    assert!(stdout.contains(format.name()), "{stdout}");
    let grid = match config {
        Some(c) => {
            periscope_daemon::plan::load_recon(
                &periscope_daemon::config::TomlSource::load(&repo_path(c)).unwrap(),
                None,
            )
            .unwrap()
            .volume
        }
        None => capture.default_volume().unwrap(),
    };
    let (median, iou) = patch_accuracy(dir.path(), &grid);
    eprintln!("{name}: median depth error {median:.4} m, IoU {iou:.2}");
    assert!(median < 0.02, "{name}: median depth error {median:.3} m ≥ 2 cm");
    assert!(iou > 0.6, "{name}: silhouette IoU {iou:.2} ≤ 0.6");
}

#[test]
fn confocal_grid_capture_from_y_tal_reconstructs_with_defaults() {
    check_fixture("confocal_xy", HFormat::TSxSy, None);
}

#[test]
fn single_laser_point_list_with_both_legs_reconstructs() {
    check_fixture("single_laser_n3", HFormat::TSi, None);
}

#[test]
fn exhaustive_capture_reconstructs_with_a_recon_config() {
    check_fixture(
        "exhaustive_li_si",
        HFormat::TLiSi,
        Some("tests/data/ytal/fbp.toml"),
    );
}

/// `solver = "lct"` with `[gtr] virtual-scan = "splat"`: after the fit, LCT's volume
/// made without rendering the virtual scan finds y-tal's patch within the fixtures'
/// tolerances, and `volume.json`'s timings name the step that replaced the synthesis.
#[test]
fn gtr_then_lct_without_the_scan_finds_the_patch() {
    let file = "tests/data/ytal/confocal_xy.hdf5";
    let grid = YtalCapture::read(&repo_path(file))
        .expect("y-tal's file reads")
        .default_volume()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("recon.toml");
    std::fs::write(
        &config,
        format!(
            "method = \"gtr\"\nsolver = \"lct\"\n[volume]\nx = {:?}\ny = {:?}\nz = {:?}\nshape = {:?}\n\
             [gtr]\nvirtual-scan = \"splat\"\n",
            grid.x, grid.y, grid.z, grid.shape
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    recon(file, Some(config.to_str().unwrap()), &out);
    let (median, iou) = patch_accuracy(&out, &grid);
    eprintln!("gtr, splatted LCT: median depth error {median:.4} m, IoU {iou:.2}");
    assert!(median < 0.02, "median depth error {median:.4} m ≥ 0.02 m");
    assert!(iou > 0.6, "silhouette IoU {iou:.2} ≤ 0.6");
    let json = std::fs::read_to_string(out.join("volume.json")).unwrap();
    assert!(json.contains("\"splat and lct\""), "{json}");
    assert!(!json.contains("\"synthesis\""), "{json}");
}

/// A capture none of our code rendered: mitransient's path tracer, a two-torso relay
/// (tests/data/ytal/render_torso.py, `--scene centred`). The laser is fixed on one
/// back, 12 × 16 detection points lie on the other, and a T (0.28 × 0.40 m, strokes
/// 8 cm wide) hangs 0.6 m in front of the gap between them, seen obliquely from the
/// detection points. 3D-GTR with defaults and the validation set's grid recovers the T:
/// measured silhouette IoU 0.53, 0.72, 0.65 (seeds 0, 1, 2), median depth error 0.5 mm;
/// FBP alone gets 0.39. Seed 0 now scores 0.77 at 2.4 mm: the capture counts as coarse
/// (`CoarseFit`), so the fit takes batches of 8 and the surface prior. A mismatch between our renderer and an independent one (a
/// cosine, a leg's falloff, a normal, a time origin) would show here first.
#[test]
fn a_two_torso_capture_rendered_by_mitransient_reconstructs() {
    let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.195, 1.005], [32, 32, 81]).unwrap();
    let (_dir, out) = gtr_with_defaults("tests/data/ytal/torso_t.hdf5", &grid);
    let strokes = [[-0.20, 0.08, 0.10, 0.18], [-0.10, -0.02, -0.22, 0.10]];
    let t = |x: f64, y: f64| {
        strokes
            .iter()
            .any(|[x0, x1, y0, y1]| (*x0..*x1).contains(&x) && (*y0..*y1).contains(&y))
    };
    let (median, iou) = silhouette_accuracy(&out, &grid, t, 0.6);
    eprintln!("torso_t: median depth error {median:.4} m, IoU {iou:.2}");
    assert!(median < 0.01, "median depth error {median:.3} m ≥ 1 cm");
    assert!(iou > 0.45, "silhouette IoU {iou:.2} ≤ 0.45");
}

/// The mannequin of issue 54's two-torso regime, rendered by mitransient
/// (render_torso.py `--scene mannequin --mannequin=0,0.5,0 --grid 16x24 --points 256
/// --seed 4 --bins 256 --t-start 0.8 --spp 65536`): a 1 m child-sized mannequin 0.5 m
/// in front of two backs, the laser fixed on one, 256 detection points at random on
/// the other, 1.6 % of its light blocked. Scored as the validation set scores: Otsu's
/// threshold on the maximum projection, IoU with the true silhouette (228 pixels of
/// the 32 × 32 grid, `mannequin_mask.npy`, indexed x then y), and the depth at each
/// column's maximum against `mannequin_depth.npy`. Measured with defaults (seeds 0, 1,
/// 2), which on a capture this coarse ([`CoarseFit`]) take batches of 8 and the surface
/// prior ([`SurfacePrior`]): IoU 0.665, 0.672, 0.718. With the prior alone 0.59, 0.59,
/// 0.59; with neither (the defaults before 2026-12-04) 0.49, 0.53, 0.54, the torso's
/// light in a column of lumps at its centre, spread in depth. Before the fit and the
/// image were held to what the capture resolves (`resolvable_separation`: 64 mm here)
/// they scored 0.29, 0.25, 0.31: splits down to 11 mm drifted into lumps and the 78 mm
/// wave imaged them.
///
/// [`SurfacePrior`]: periscope_recon::gtr::SurfacePrior
/// [`CoarseFit`]: periscope_recon::gtr::CoarseFit
#[test]
fn a_mannequin_behind_two_backs_rendered_by_mitransient_is_found_whole() {
    let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.195, 1.205], [32, 32, 101]).unwrap();
    let (_dir, out) = gtr_with_defaults("tests/data/ytal/mannequin.hdf5", &grid);
    let score = silhouette_and_depths(&out, &grid, "mannequin");
    let median = score.errors[score.errors.len() / 2];
    eprintln!(
        "mannequin: IoU {:.3}, median depth error over the silhouette {median:.4} m",
        score.iou
    );
    assert!(
        score.iou > 0.6,
        "silhouette IoU {:.3} ≤ 0.6: the mannequin is not found whole",
        score.iou
    );
    assert!(median < 0.02, "median depth error {median:.3} m ≥ 2 cm");
    assert_eq!(
        fit_in_force(&out),
        (8, Some(0.018), true),
        "one laser spot and 256 detection points on two backs: a coarse capture"
    );
}

/// The validation set's scores of a volume against a rendered mannequin's truth.
struct Silhouette {
    /// Otsu's threshold on the maximum projection, IoU with the true silhouette.
    iou: f64,
    /// The depth error at each pixel of the true silhouette (the depth of the column's
    /// maximum), metres, in increasing order.
    errors: Vec<f64>,
}

/// [`Silhouette`] of `out/volume.npy` on `grid` against `tests/data/ytal/NAME_mask.npy`
/// and `NAME_depth.npy` (32 × 32, indexed x then y, as render_torso.py writes them).
fn silhouette_and_depths(out: &Path, grid: &VolumeGrid, name: &str) -> Silhouette {
    let image = Projection::of(out);
    let (nx, ny) = (image.nx, image.ny);
    let (_, mask) = read_npy(&repo_path(&format!("tests/data/ytal/{name}_mask.npy"))).unwrap();
    let (_, truth_depth) = read_npy(&repo_path(&format!("tests/data/ytal/{name}_depth.npy"))).unwrap();
    let dz = (grid.z[1] - grid.z[0]) / image.nz as f64;
    let found = image.silhouette();
    let (mut inter, mut union, mut errors) = (0usize, 0usize, Vec::new());
    for iy in 0..ny {
        for ix in 0..nx {
            let truth = mask[ix * ny + iy] > 0.5;
            let found = found[iy * nx + ix];
            inter += usize::from(truth && found);
            union += usize::from(truth || found);
            if truth {
                let depth = grid.z[0] + (image.slice[iy * nx + ix] as f64 + 0.5) * dz;
                errors.push((depth - f64::from(truth_depth[ix * ny + iy])).abs());
            }
        }
    }
    errors.sort_by(f64::total_cmp);
    Silhouette {
        iou: inter as f64 / union as f64,
        errors,
    }
}

/// Issue 54, part 2's two-torso fault: `fbp`'s depth behind two backs. A noisy
/// mannequin 0.35 m from the backs (render_torso.py, the fixture
/// `mannequin_near_noisy.hdf5`: 256 points, Poisson counts at a peak of 50 and 0.05 a
/// bin, as the validation set's noisy copies), on the validation grid, which reaches
/// 1.2 m. The falloff weight lifts the background's noise with the distance from the
/// relay, its amplitude as d_i·d_d: about twentyfold from 0.2 to 1.2 m in front of
/// the gap between the backs. Where the mannequin is dim (legs,
/// head) the column's maximum was that noise at the back of the volume: as
/// backprojected (`[fbp] noise-floor = false`, the code before) 16 of its 231 pixels
/// read more than 0.3 m off and the depth MAE is 83 mm (y-tal 0.20's `fbp` at its
/// baselines' 80 mm wave: 37 mm). With the background's noise floor taken off, none
/// does and the MAE is 33.9 mm, as on the noise-free render (34.6 mm).
#[test]
fn fbp_reads_a_noisy_mannequins_depth_and_not_the_noise_behind_it() {
    let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.195, 1.205], [32, 32, 101]).unwrap();
    let file = "tests/data/ytal/mannequin_near_noisy.hdf5";
    let read = |extra: &str| {
        let (_dir, out) = recon_on_grid(file, &grid, "fbp", extra);
        let score = silhouette_and_depths(&out, &grid, "mannequin_near");
        let mae = score.errors.iter().sum::<f64>() / score.errors.len() as f64;
        let lost = score.errors.iter().filter(|&&e| e > 0.3).count();
        (mae, lost, score.iou)
    };
    let (mae, lost, iou) = read("");
    let (raw_mae, raw_lost, _) = read("[fbp]\nnoise-floor = false\n");
    eprintln!(
        "noisy mannequin, fbp: depth MAE {mae:.4} m, {lost} pixels > 0.3 m off, IoU {iou:.3}; \
         as backprojected {raw_mae:.4} m, {raw_lost} pixels"
    );
    assert!(
        raw_lost >= 8,
        "the fixture no longer shows the fault: {raw_lost} pixels lost as backprojected"
    );
    assert!(
        lost <= 2 && mae < 0.045,
        "depth MAE {mae:.3} m with {lost} pixels more than 0.3 m off: the noise behind the mannequin wins"
    );
    assert!(iou > 0.3, "silhouette IoU {iou:.3}");
}

/// Bars finer than the relay pitch, rendered by mitransient (tests/data/ytal/
/// render_bars.py): three 2 cm bars 2 cm apart, 0.5 m from a planar relay scanned
/// confocally at a 4 cm pitch (12 × 12 points over 0.48 m), reconstructed with defaults
/// on the validation set's kind of grid (1 cm columns over 0.5 m, 1 cm slices from
/// 0.195 m), where the primitives start wider than the bars. Measured dip between
/// the bars (seeds 0, 1, 2): 0.52, 0.53, 0.58; with the step floor and densification
/// before 2026-11-26 (8 rounds over 4,096 steps) 0.82 at every seed, one blob.
#[test]
fn bars_finer_than_the_pitch_rendered_by_mitransient_are_resolved() {
    let grid = VolumeGrid::new([-0.25, 0.25], [-0.25, 0.25], [0.195, 1.005], [50, 50, 81]).unwrap();
    let (_dir, out) = gtr_with_defaults("tests/data/ytal/bars_coarse.hdf5", &grid);
    assert_bars_resolved(
        &out,
        BarsGrid {
            lo: -0.25,
            pitch: 0.01,
        },
        "a 4 cm pitch (mitransient)",
        0.7,
    );
    // A confocal grid over a plane is no coarse capture: its own fit, prior off; the
    // renderer's named falloff gives the gains, so none are estimated.
    assert_eq!(
        fit_in_force(&out),
        (4, None, false),
        "batch, surface spread, coarse"
    );
    assert_eq!(pair_gains(&out), "none");
}

/// The bars' capture as a measured file would be: its `scene_info` without the
/// renderer's name, so nothing says its laser falls off from a point, times a further
/// 3× ramp across the relay (an albedo or a laser power that drifts). With defaults
/// (`pair-gains = "auto"`) the fit estimates each illumination point's gain, says so
/// in `volume.json`, and still resolves the bars (measured dip 0.63; 0.70, 0.55, 0.57
/// at seeds 0–2 in a release build, against 0.57 at each with the file's falloff
/// known and no ramp).
#[test]
fn a_measured_captures_unknown_gains_are_estimated_and_the_bars_resolved() {
    let mut capture = YtalCapture::read(&repo_path("tests/data/ytal/bars_coarse.hdf5")).unwrap();
    let info = capture.scene_info.take().expect("the render's scene_info");
    assert!(info.contains("renderer:"), "{info}");
    capture.scene_info = Some(
        info.lines()
            .filter(|l| !l.starts_with("renderer:") && !l.starts_with("config:"))
            .collect::<Vec<_>>()
            .join("\n"),
    );
    let points = capture.sensor_grid.points.len();
    let (lo, hi) = capture.sensor_grid.points.iter().fold(
        (glam::DVec3::INFINITY, glam::DVec3::NEG_INFINITY),
        |(lo, hi), p| (lo.min(*p), hi.max(*p)),
    );
    let bins = capture.h.len() / points;
    for (k, p) in capture.sensor_grid.points.iter().enumerate() {
        let u = (*p - lo) / (hi - lo);
        let gain = (3f64.ln() * (0.6 * u.x + 0.4 * u.y)).exp() as f32;
        for b in 0..bins {
            capture.h[b * points + k] *= gain;
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bars_measured.hdf5");
    capture.write(&file).unwrap();
    let file = file.to_str().unwrap();
    let grid = VolumeGrid::new([-0.25, 0.25], [-0.25, 0.25], [0.195, 1.005], [50, 50, 81]).unwrap();
    let bars = BarsGrid {
        lo: -0.25,
        pitch: 0.01,
    };
    let (_dir, out) = gtr_with_defaults(file, &grid);
    assert_eq!(pair_gains(&out), "illumination");
    assert_bars_resolved(&out, bars, "a 4 cm pitch, gains unknown", 0.7);
}

/// The per-transient gains the fit estimated, as `volume.json` records them.
fn pair_gains(out: &Path) -> String {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("volume.json")).unwrap()).unwrap();
    json["fit"]["pair_gains"]
        .as_str()
        .expect("fit.pair_gains")
        .to_owned()
}

/// The fit's settings in force as `volume.json` records them: batch, surface spread,
/// and whether the capture counted as coarse.
fn fit_in_force(out: &Path) -> (u64, Option<f64>, bool) {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("volume.json")).unwrap()).unwrap();
    let fit = &json["fit"];
    (
        fit["batch"].as_u64().expect("fit.batch"),
        fit["surface_spread_m"].as_f64(),
        fit["coarse"].as_bool().expect("fit.coarse"),
    )
}

/// The brightest value over the patch against the 90th percentile over the bars, in
/// the maximum along z of `out/volume.npy` on `grid`: the far patch's brightness
/// relative to the near bars (render_bars.py's layout: 2 cm bars at x = −4, 0, 4 cm,
/// |y| ≤ 15 cm; a 10 cm patch centred on (0.2, 0.15)).
fn patch_over_bars(out: &Path, grid: &VolumeGrid) -> f64 {
    let (shape, v) = read_npy(&out.join("volume.npy")).expect("volume.npy");
    let (nz, ny, nx) = (shape[0], shape[1], shape[2]);
    let voxel = grid.voxel();
    let (mut bars, mut patch) = (Vec::new(), 0.0f64);
    for iy in 0..ny {
        for ix in 0..nx {
            let x = grid.x[0] + (ix as f64 + 0.5) * voxel.x;
            let y = grid.y[0] + (iy as f64 + 0.5) * voxel.y;
            let top = (0..nz)
                .map(|iz| f64::from(v[(iz * ny + iy) * nx + ix]))
                .fold(0.0, f64::max);
            let on_bar = y.abs() <= 0.15 && [-0.04, 0.0, 0.04].iter().any(|c| (x - c).abs() <= 0.01);
            if on_bar {
                bars.push(top);
            } else if (x - 0.2).abs() <= 0.05 && (y - 0.15).abs() <= 0.05 {
                patch = patch.max(top);
            }
        }
    }
    bars.sort_by(f64::total_cmp);
    patch / bars[bars.len() * 9 / 10]
}

/// A far, faint patch keeps its brightness when ambient light adds ten times the
/// signal's photons: mitransient's render of near bars and a 10 cm patch at 0.8 m
/// (render_bars.py `--patch`), noise-free and as Poisson counts at a peak of 50 with
/// that background (`--noise 50,10,1`). Its point-source laser's falloff is each
/// transient's gain in the fit's model, the counts kept as counted with one ambient
/// level: the patch over the bars comes out as in the noise-free capture (measured
/// 1.84 against 2.10). Dividing the falloff out of the counts instead, as before,
/// gave each transient its own background the fit did not know of, and the patch
/// fell to half (1.05; docs/recon.md, "Low light").
#[test]
fn a_far_patch_keeps_its_brightness_under_ten_times_its_light_in_ambient() {
    let grid = VolumeGrid::new([-0.32, 0.32], [-0.32, 0.32], [0.2, 1.0], [32, 32, 81]).unwrap();
    let (_clean_dir, clean) = gtr_with_defaults("tests/data/ytal/far_patch.hdf5", &grid);
    let (_noisy_dir, noisy) = gtr_with_defaults("tests/data/ytal/far_patch_ambient10.hdf5", &grid);
    let (c, n) = (patch_over_bars(&clean, &grid), patch_over_bars(&noisy, &grid));
    eprintln!("far patch over bars: {n:.3} under ambient light, {c:.3} without");
    assert!(
        (0.75..1.25).contains(&(n / c)),
        "the far patch over the bars is {n:.3} under ambient light against {c:.3} without"
    );
}

/// `method = "gtr"` on `capture`, with the volume at each of `gtr_depths` (z bounds),
/// exits with 2 and a message naming `cause` and FBP, writing no volume; `method =
/// "fbp"` on it (the volume at z 0.3–0.7 m) writes a finite, non-zero one.
fn refused_by_gtr_and_reconstructed_by_fbp(capture: &Path, gtr_depths: &[&str], cause: &str) {
    let dir = tempfile::tempdir().unwrap();
    let run = |name: &str, method: &str, z: &str| {
        let config = dir.path().join(format!("{name}.toml"));
        let text = format!(
            "method = \"{method}\"\n[volume]\nx = [-0.3, 0.3]\ny = [-0.3, 0.3]\nz = {z}\nshape = [12, 12, 10]\n"
        );
        std::fs::write(&config, text).unwrap();
        let out = dir.path().join(name);
        let done = try_recon(capture.to_str().unwrap(), Some(config.to_str().unwrap()), &out);
        (done, out)
    };
    for (i, z) in gtr_depths.iter().enumerate() {
        let (done, out) = run(&format!("gtr{i}"), "gtr", z);
        assert_eq!(done.code, Some(2), "z = {z}: {done:?}");
        assert!(
            done.stderr.contains(cause) && done.stderr.contains("fbp"),
            "z = {z}: {}",
            done.stderr
        );
        assert!(!out.join("volume.npy").exists());
    }
    let (done, out) = run("fbp", "fbp", "[0.3, 0.7]");
    assert_eq!(done.code, Some(0), "{done:?}");
    let (_, values) = read_npy(&out.join("volume.npy")).unwrap();
    assert!(values.iter().all(|v| v.is_finite()) && values.iter().any(|v| *v > 0.0));
}

/// A sign-inverted capture has a negative total, which no non-negative scene
/// explains: `method = "gtr"` refuses it as a settings error (exit code 2) naming the
/// cause instead of writing an empty volume, and FBP (magnitudes) still reconstructs
/// it.
#[test]
fn a_sign_inverted_capture_is_refused_by_gtr_and_reconstructed_by_fbp() {
    let dir = tempfile::tempdir().unwrap();
    let mut capture = YtalCapture::read(&repo_path("tests/data/ytal/confocal_xy.hdf5")).unwrap();
    for v in &mut capture.h {
        *v = -*v;
    }
    let inverted = dir.path().join("inverted.hdf5");
    capture.write(&inverted).unwrap();
    refused_by_gtr_and_reconstructed_by_fbp(&inverted, &["[0.3, 0.7]"], "negative");
}

/// A line scan (every relay point on one line) has no plane for 3D-GTR's virtual
/// scan: `method = "gtr"` refuses it as a settings error (exit code 2) that names the
/// cause and FBP, before the fit (with a volume behind the relay the refusal is still
/// the line's, not the fit's "no primitive ... is visible"), and FBP reconstructs it.
#[test]
fn a_line_scan_is_refused_by_gtr_before_the_fit_and_reconstructed_by_fbp() {
    let dir = tempfile::tempdir().unwrap();
    let mut capture = YtalCapture::read(&repo_path("tests/data/ytal/confocal_xy.hdf5")).unwrap();
    for grid in [&mut capture.sensor_grid, &mut capture.laser_grid] {
        for p in &mut grid.points {
            p.y = 0.0;
        }
    }
    let line = dir.path().join("line.hdf5");
    capture.write(&line).unwrap();
    refused_by_gtr_and_reconstructed_by_fbp(&line, &["[0.3, 0.7]", "[-0.7, -0.3]"], "collinear");
}

#[test]
fn a_file_that_is_not_a_capture_is_refused_with_its_name() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("broken.h5");
    std::fs::write(&bad, b"\x89HDF\r\n\x1a\ntruncated").unwrap();
    let done = periscope_with_limit(
        &[
            "recon",
            bad.to_str().unwrap(),
            "--out",
            dir.path().join("o").to_str().unwrap(),
        ],
        Duration::from_secs(60),
    );
    // Exit code 1 (a reported error), not a panic's 101 or a signal.
    assert_eq!(done.code, Some(1), "{done:?}");
    assert!(done.stderr.contains("broken.h5"), "{}", done.stderr);
    assert!(!dir.path().join("o").join("volume.npy").exists());
}

/// A Python that can `import tal` (y-tal): `PERISCOPE_YTAL_PYTHON`, else `python3`.
fn ytal_python() -> Option<String> {
    let python = std::env::var("PERISCOPE_YTAL_PYTHON").unwrap_or_else(|_| "python3".into());
    let ok = std::process::Command::new(&python)
        .args(["-c", "import tal"])
        .output()
        .is_ok_and(|o| o.status.success());
    ok.then_some(python)
}

/// Our export, read by y-tal's own reader (`tal.io.read_capture`, which refuses any
/// dataset it does not know), with the flags where our reader finds them.
#[test]
fn y_tal_reads_our_export() {
    let Some(python) = ytal_python() else {
        periscope_tests::skipped(format_args!(
            "y_tal_reads_our_export: y-tal is not installed (no `import tal` in \
             $PERISCOPE_YTAL_PYTHON or python3); .ci/run installs it"
        ));
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let done = periscope_with_limit(
        &[
            "run",
            "tests/data/plans/small-fbp.toml",
            "--out",
            run.to_str().unwrap(),
        ],
        Duration::from_secs(300),
    );
    assert_eq!(done.code, Some(0), "{done:?}");
    let ours = YtalCapture::read(&run.join("capture.hdf5")).unwrap();
    let script = "import sys, tal\n\
                  c = tal.io.read_capture(sys.argv[1])\n\
                  print(c.H.shape[0], c.H.shape[1], c.H_format, c.t_accounts_first_and_last_bounces)\n\
                  print(sorted(c.scene_info.keys()))\n";
    let out = std::process::Command::new(&python)
        .args(["-c", script, run.join("capture.hdf5").to_str().unwrap()])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "y-tal refused our export:\n{}{}",
        stdout,
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<&str> = stdout.lines().collect();
    assert_eq!(
        lines[0],
        format!("{} {} HFormat.T_Si True", ours.bins(), ours.len()),
        "{stdout}"
    );
    assert!(
        lines[1].contains("'periscope_overflow'") && lines[1].contains("'periscope_saturated'"),
        "{stdout}"
    );
    assert_eq!(ours.flags.as_ref().map(Vec::len), Some(ours.len()));
}

/// The falloff a point-source laser at `laser` gives illumination point `i` of `c`.
fn point_source_irradiance(c: &YtalCapture, laser: glam::DVec3, i: usize) -> f64 {
    let (x, n) = (c.laser_grid.points[i], c.laser_grid.normals[i]);
    let d = laser - x;
    d.dot(n) / d.length().powi(3)
}

#[test]
fn a_rendered_captures_point_source_laser_falloff_is_divided_out() {
    use periscope_daemon::capture::{Capture, CaptureError};
    use periscope_daemon::plan::LaserFalloff;

    // The confocal fixture, lit as a renderer's point-source laser would light it:
    // each transient times cos θ / d² from the laser origin, and `scene_info` naming
    // a renderer.
    let file = "tests/data/ytal/confocal_xy.hdf5";
    let plain = YtalCapture::read(&repo_path(file)).unwrap();
    let laser = plain.laser_xyz.expect("the fixture records its laser");
    let mut rendered = plain.clone();
    let n = rendered.len();
    for (k, v) in rendered.h.iter_mut().enumerate() {
        *v = (f64::from(*v) * point_source_irradiance(&plain, laser, k % n)) as f32;
    }
    rendered.scene_info = Some("renderer: a point-source test renderer\n".into());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rendered.hdf5");
    rendered.write(&path).unwrap();

    let volume = plain.default_volume().unwrap();
    let open = |p: &Path| Capture::open(p).unwrap();
    let original = open(&repo_path(file))
        .transients(&volume, LaserFalloff::Auto)
        .unwrap();
    assert!(
        original.falloff.is_none(),
        "a capture that names no renderer is taken as measured"
    );
    let compensated = open(&path).transients(&volume, LaserFalloff::Auto).unwrap();
    let applied = compensated
        .falloff
        .as_ref()
        .expect("auto compensates a rendered, scanned laser");
    assert_eq!(applied.laser, laser.as_vec3().as_dvec3());
    assert!(
        applied.why.contains("a point-source test renderer"),
        "{}",
        applied.why
    );
    let kept = open(&path).transients(&volume, LaserFalloff::None).unwrap();
    assert!(kept.falloff.is_none());

    // Pair by pair, the ratio to the original transients: one constant once the
    // falloff is divided out (the mean factor: the counts at gain 1, what the solvers
    // take), spread as the falloff otherwise.
    let ratios = |t: &periscope_daemon::capture::Transients| {
        let mut r = Vec::new();
        for i in 0..t.set.len() {
            let (a, b) = (t.set.measured(i), original.set.histogram(i));
            let peak = (0..b.len()).max_by(|&x, &y| b[x].total_cmp(&b[y])).unwrap();
            r.push(f64::from(a[peak]) / f64::from(b[peak]));
        }
        let (lo, hi) = r
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
        hi / lo
    };
    assert!(ratios(&compensated) < 1.0 + 1e-5, "{}", ratios(&compensated));
    assert!(
        ratios(&kept) > 1.2,
        "the test's falloff should vary: {}",
        ratios(&kept)
    );
    assert!(applied.range.1 / applied.range.0 > 1.2, "{:?}", applied.range);

    // Forced on a capture that records no laser origin: refused, naming file and key.
    let mut anonymous = rendered.clone();
    anonymous.laser_xyz = None;
    let bare = dir.path().join("no-laser.hdf5");
    anonymous.write(&bare).unwrap();
    let err = open(&bare)
        .transients(&volume, LaserFalloff::CosInverseSquare)
        .unwrap_err();
    assert!(matches!(err, CaptureError::LaserFalloff { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(
        msg.contains("no-laser.hdf5") && msg.contains("laser-falloff") && msg.contains("laser_xyz"),
        "{msg}"
    );
    // `auto` on it takes the counts as they are, with a warning, as for a geometry
    // that does not support the correction (until 2026-12-07 it was refused too).
    let auto = open(&bare).transients(&volume, LaserFalloff::Auto).unwrap();
    assert!(auto.falloff.is_none());

    // `periscope recon` says what it did.
    let config = dir.path().join("fbp.toml");
    std::fs::write(&config, "method = \"fbp\"\n").unwrap();
    let out = dir.path().join("out");
    let stdout = recon(path.to_str().unwrap(), Some(config.to_str().unwrap()), &out);
    assert!(stdout.contains("laser falloff accounted for"), "{stdout}");
}

/// A volume derived from a capture's relay is a volume a RECON.toml could give: a
/// relay of 800 m (positions in millimetres read as metres) is refused naming the
/// span and what to check, where its fit ran for minutes on a volume as wide; a relay
/// whose points all lie on one spot says that, and to give a `[volume]`, not that a
/// range nobody set "must be two finite numbers".
#[test]
fn a_default_volume_is_refused_over_a_relay_of_no_area_or_hundreds_of_metres() {
    let file = repo_path("tests/data/ytal/confocal_xy.hdf5");
    let mut wide = YtalCapture::read(&file).unwrap();
    for p in wide
        .sensor_grid
        .points
        .iter_mut()
        .chain(wide.laser_grid.points.iter_mut())
    {
        *p *= 1000.0;
    }
    let e = wide.default_volume().unwrap_err().to_string();
    assert!(
        e.contains("span") && e.contains("metres") && e.contains("[volume]"),
        "{e}"
    );
    // The same reason through a RECON.toml that leaves the volume to the capture
    // (until 2026-12-07: only "`volume` is required").
    let dir = tempfile::tempdir().unwrap();
    let (path, config) = (dir.path().join("mm.hdf5"), dir.path().join("fbp.toml"));
    wide.write(&path).unwrap();
    std::fs::write(&config, "method = \"fbp\"\n").unwrap();
    let done = try_recon(path.to_str().unwrap(), config.to_str(), &dir.path().join("out"));
    assert_eq!(done.code, Some(1), "{done:?}");
    assert!(
        done.stderr.contains("mm.hdf5") && done.stderr.contains("metres"),
        "{}",
        done.stderr
    );
    let mut spot = YtalCapture::read(&file).unwrap();
    let at = spot.sensor_grid.points[0];
    for p in spot
        .sensor_grid
        .points
        .iter_mut()
        .chain(spot.laser_grid.points.iter_mut())
    {
        *p = at;
    }
    let e = spot.default_volume().unwrap_err().to_string();
    assert!(e.contains("span no area") && e.contains("[volume]"), "{e}");
    assert!(YtalCapture::read(&file).unwrap().default_volume().is_ok());
}

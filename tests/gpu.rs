//! `[compute] device`: `periscope recon` with the 3D-GTR fit's steps, the synthesis and
//! the backprojection on a GPU gives the CPU's volume, records the adapter in
//! `volume.json`, and without any adapter refuses `"gpu"` with what to do while `"auto"`
//! runs on the CPU.
//!
//! Without a hardware GPU these run on Mesa's software Vulkan (lavapipe), which
//! `.ci/run` installs; where no adapter at all is found the comparison says so and
//! skips, unless `PERISCOPE_REQUIRE_GPU` is set (CI sets it).
use std::path::Path;
use std::time::Duration;

use periscope_recon::io::read_npy;
use periscope_tests::{Finished, Projection, periscope_with_env};

const CAPTURE: &str = "tests/data/ytal/confocal_xy.hdf5";
const GRID: &str = "[volume]\nx = [-0.3, 0.3]\ny = [-0.3, 0.3]\nz = [0.3, 0.7]\nshape = [24, 24, 32]\n";

/// `periscope recon CAPTURE` with `config` (and `env`) into `dir/NAME`.
fn recon(dir: &Path, name: &str, config: &str, env: &[(&str, &str)]) -> (Finished, std::path::PathBuf) {
    let toml = dir.join(format!("{name}.toml"));
    std::fs::write(&toml, format!("{config}\n{GRID}")).unwrap();
    let out = dir.join(name);
    let done = periscope_with_env(
        &[
            "recon",
            CAPTURE,
            "--config",
            toml.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        env,
        Duration::from_secs(300),
    );
    (done, out)
}

fn compute_of(out: &Path) -> serde_json::Value {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("volume.json")).unwrap()).unwrap();
    json["compute"].clone()
}

/// Relative L2 difference of two volumes.
fn difference(a: &Path, b: &Path) -> f64 {
    let (_, a) = read_npy(&a.join("volume.npy")).unwrap();
    let (_, b) = read_npy(&b.join("volume.npy")).unwrap();
    assert_eq!(a.len(), b.len());
    let (mut num, mut den) = (0.0f64, 0.0f64);
    for (x, y) in a.iter().zip(&b) {
        num += f64::from(x - y).powi(2);
        den += f64::from(*y).powi(2);
    }
    assert!(den > 0.0, "an empty volume");
    (num / den).sqrt()
}

/// How two volumes' images agree: the IoU of their silhouettes (Otsu's threshold on
/// the maximum projection, as the validation set scores) and the mean distance, in
/// depth slices, between the two maxima of the columns both silhouettes hold.
fn image_agreement(a: &Path, b: &Path) -> (f64, f64) {
    let (a, b) = (Projection::of(a), Projection::of(b));
    let (sa, sb) = (a.silhouette(), b.silhouette());
    let (mut inter, mut union, mut slices) = (0usize, 0usize, 0usize);
    for c in 0..sa.len() {
        inter += usize::from(sa[c] && sb[c]);
        union += usize::from(sa[c] || sb[c]);
        if sa[c] && sb[c] {
            slices += a.slice[c].abs_diff(b.slice[c]);
        }
    }
    assert!(inter > 0, "the silhouettes share no column");
    (inter as f64 / union as f64, slices as f64 / inter as f64)
}

/// The reconstruction on the GPU, or `None` where no adapter is found and the test
/// may skip (`PERISCOPE_REQUIRE_GPU` unset).
fn on_gpu(dir: &Path, name: &str, config: &str) -> Option<std::path::PathBuf> {
    let (done, gpu) = recon(
        dir,
        &format!("{name}-gpu"),
        &format!("{config}[compute]\ndevice = \"gpu\""),
        &[],
    );
    if done.code == Some(2) && done.stderr.contains("no GPU is usable") {
        assert!(
            std::env::var_os("PERISCOPE_REQUIRE_GPU").is_none(),
            "PERISCOPE_REQUIRE_GPU is set but: {}",
            done.stderr
        );
        periscope_tests::skipped(format_args!(
            "a_reconstruction_on_the_gpu_is_the_cpus: {}",
            done.stderr.trim()
        ));
        return None;
    }
    assert_eq!(
        done.code,
        Some(0),
        "{name} on the GPU:\n{}\n{}",
        done.stdout,
        done.stderr
    );
    let compute = compute_of(&gpu);
    assert_eq!(compute["device"], "gpu", "{compute}");
    assert!(
        compute["adapter"].as_str().is_some_and(|a| !a.is_empty()),
        "{compute}"
    );
    Some(gpu)
}

/// The same on the CPU.
fn on_cpu(dir: &Path, name: &str, config: &str) -> std::path::PathBuf {
    let (done, cpu) = recon(
        dir,
        &format!("{name}-cpu"),
        &format!("{config}[compute]\ndevice = \"cpu\""),
        &[],
    );
    assert_eq!(
        done.code,
        Some(0),
        "{name} on the CPU:\n{}\n{}",
        done.stdout,
        done.stderr
    );
    assert_eq!(compute_of(&cpu), serde_json::json!({"device": "cpu"}));
    cpu
}

/// 3D-GTR (its fit's steps, synthesis and FBP on the GPU) and FBP on the measured
/// pairs, each against the same on the CPU, and `volume.json` names the adapter:
///
/// - a fit of one epoch (400 primitives, 64 steps): the volumes agree to 2e-3 relative
///   L2 (measured on lavapipe: 1.1e-5);
/// - a fit of eight epochs (512 steps): its f32 steps go their own way, as any fit's
///   do over a few hundred steps (the split and prune rounds between epochs turn a
///   small difference into another cloud), so the images are compared: the
///   silhouettes' IoU above 0.9 and their depths within half a slice on average.
///   Measured on lavapipe: volumes 3.2e-4 apart, IoU 1.0, 0 slices; on an NVIDIA
///   H200 the volumes were 4.8e-2 apart (2026-12-04, when this test still asked for
///   2e-3 there), and the validation captures' default fits 1.9e-2 to 8.4e-2, with
///   silhouettes 0.94 to 1.0 alike and depths 0 to 0.21 slices apart (docs/gpu.md);
/// - FBP, the exact path on both (the CPU's default, `auto`, may take the hierarchy):
///   1e-3 relative L2 (measured on lavapipe: 1.5e-6).
///
/// The surface prior is off: its gradient takes the column means of each step on the
/// CPU and of each epoch's start on the GPU, whose steps run resident (docs/recon.md,
/// "A surface prior"), so with it the two fits differ by design (`recon/src/gpu/fit.rs`
/// checks the GPU's steps with it against the CPU's at the same terms). The fits are short: on lavapipe a
/// default fit's 8,192 steps take minutes (docs/gpu.md).
#[test]
fn a_reconstruction_on_the_gpu_is_the_cpus() {
    let dir = tempfile::tempdir().unwrap();
    let gtr = |epochs: u32| {
        format!("method = \"gtr\"\n[gtr]\nprimitives = 400\nepochs = {epochs}\nsurface-spread = 0\n")
    };
    for (name, config, bound) in [
        ("gtr-1", gtr(1), 2e-3),
        (
            "fbp",
            "method = \"fbp\"\n[fbp]\nbackprojection = \"exact\"\n".to_owned(),
            1e-3,
        ),
    ] {
        let Some(gpu) = on_gpu(dir.path(), name, &config) else {
            return;
        };
        let cpu = on_cpu(dir.path(), name, &config);
        let d = difference(&gpu, &cpu);
        eprintln!("{name}: GPU against CPU, relative L2 {d:.2e}");
        assert!(
            d < bound,
            "{name}: the GPU's volume differs from the CPU's by {d:e} (relative L2)"
        );
    }
    let Some(gpu) = on_gpu(dir.path(), "gtr-8", &gtr(8)) else {
        return;
    };
    let cpu = on_cpu(dir.path(), "gtr-8", &gtr(8));
    let (iou, slices) = image_agreement(&gpu, &cpu);
    eprintln!(
        "gtr-8: GPU against CPU, relative L2 {:.2e}, silhouettes' IoU {iou:.3}, depths {slices:.2} slices apart",
        difference(&gpu, &cpu)
    );
    assert!(
        iou > 0.9,
        "gtr-8: the GPU's silhouette is not the CPU's: IoU {iou:.3}"
    );
    assert!(
        slices < 0.5,
        "gtr-8: the GPU's depths are {slices:.2} slices from the CPU's on average"
    );
}

/// With no Vulkan driver to be found (the loader pointed at none), `"gpu"` fails
/// before any work with exit code 2 and a message naming the setting, and `"auto"`
/// reconstructs on the CPU and says so in `volume.json`.
#[test]
fn without_a_gpu_gpu_is_refused_and_auto_runs_on_the_cpu() {
    let dir = tempfile::tempdir().unwrap();
    let none = [
        ("VK_ICD_FILENAMES", "/nonexistent.json"),
        ("VK_DRIVER_FILES", "/nonexistent.json"),
    ];
    let (done, _) = recon(
        dir.path(),
        "gpu",
        "method = \"fbp\"\n[compute]\ndevice = \"gpu\"",
        &none,
    );
    assert_eq!(done.code, Some(2), "{}\n{}", done.stdout, done.stderr);
    assert!(
        done.stderr.contains("no GPU is usable") && done.stderr.contains("[compute] device"),
        "{}",
        done.stderr
    );
    let (done, out) = recon(dir.path(), "auto", "method = \"fbp\"", &none);
    assert_eq!(done.code, Some(0), "{}\n{}", done.stdout, done.stderr);
    assert_eq!(compute_of(&out), serde_json::json!({"device": "cpu"}));
}

/// A capture plan that asks for a GPU where none opens: `periscope check` says so on
/// the machine that would run it, and `periscope run` fails before its LOS scan (exit
/// 2, the setting named, the run left resumable) instead of measuring every pair and
/// failing at the reconstruction, as it did until 2026-12-06.
#[test]
fn a_plan_that_asks_for_a_gpu_where_none_opens_fails_before_it_measures() {
    let dir = tempfile::tempdir().unwrap();
    let none = [
        ("VK_ICD_FILENAMES", "/nonexistent.json"),
        ("VK_DRIVER_FILES", "/nonexistent.json"),
    ];
    let plan = dir.path().join("gpu.toml");
    std::fs::write(
        &plan,
        periscope_tests::SmallPlan::named("gpu")
            .set("recon.compute.device", "gpu")
            .toml(),
    )
    .unwrap();
    let plan = plan.to_str().unwrap();
    let checked = periscope_with_env(&["check", plan], &none, Duration::from_secs(120));
    assert_eq!(checked.code, Some(0), "{}\n{}", checked.stdout, checked.stderr);
    assert!(
        checked
            .stdout
            .contains("warning: recon.compute.device = \"gpu\": no GPU is usable")
            && checked.stdout.contains("fails before its LOS scan"),
        "{}",
        checked.stdout
    );
    let out = dir.path().join("run");
    let run = periscope_with_env(
        &["run", plan, "--out", out.to_str().unwrap()],
        &none,
        Duration::from_secs(120),
    );
    assert_eq!(run.code, Some(2), "{}\n{}", run.stdout, run.stderr);
    assert!(
        run.stderr.contains("no GPU is usable") && run.stderr.contains("[compute] device"),
        "{}",
        run.stderr
    );
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(info["state"], "failed", "{info}");
    assert!(!out.join("relay.ply").exists(), "the LOS scan ran");
    assert!(!out.join("pairs.json").exists(), "the pairs were planned");
}

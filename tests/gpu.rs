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
use periscope_tests::{Finished, periscope_with_env};

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

/// 3D-GTR (its fit's steps, synthesis and FBP on the GPU) and FBP on the measured
/// pairs, each against the same on the CPU: the volumes agree to 2e-3 relative L2 for
/// 3D-GTR (a fit of 512 steps whose gradients are f32 goes a slightly different way:
/// 4.8e-4 measured on lavapipe) and 1e-3 for FBP (1.5e-6), and `volume.json` names
/// the adapter. The fit is short (400 primitives, 8 epochs): on lavapipe a default
/// fit's 8,192 steps take minutes (docs/gpu.md).
#[test]
fn a_reconstruction_on_the_gpu_is_the_cpus() {
    let dir = tempfile::tempdir().unwrap();
    for (method, extra, bound) in [
        // The surface prior off: the CPU applies it as a gradient every step, the GPU,
        // whose steps run resident, as a pull once an epoch (docs/recon.md, "A surface
        // prior"), so with it the two fits differ by design.
        (
            "gtr",
            "[gtr]\nprimitives = 400\nepochs = 8\nsurface-spread = 0\n",
            2e-3,
        ),
        // The exact path on both: the CPU's default, `auto`, may take the hierarchy.
        ("fbp", "[fbp]\nbackprojection = \"exact\"\n", 1e-3),
    ] {
        let (done, gpu) = recon(
            dir.path(),
            &format!("{method}-gpu"),
            &format!("method = \"{method}\"\n{extra}[compute]\ndevice = \"gpu\""),
            &[],
        );
        if done.code == Some(2) && done.stderr.contains("no GPU is usable") {
            assert!(
                std::env::var_os("PERISCOPE_REQUIRE_GPU").is_none(),
                "PERISCOPE_REQUIRE_GPU is set but: {}",
                done.stderr
            );
            eprintln!(
                "SKIPPED a_reconstruction_on_the_gpu_is_the_cpus: {}",
                done.stderr.trim()
            );
            return;
        }
        assert_eq!(
            done.code,
            Some(0),
            "{method} on the GPU:\n{}\n{}",
            done.stdout,
            done.stderr
        );
        let compute = compute_of(&gpu);
        assert_eq!(compute["device"], "gpu", "{compute}");
        assert!(
            compute["adapter"].as_str().is_some_and(|a| !a.is_empty()),
            "{compute}"
        );
        let (done, cpu) = recon(
            dir.path(),
            &format!("{method}-cpu"),
            &format!("method = \"{method}\"\n{extra}[compute]\ndevice = \"cpu\""),
            &[],
        );
        assert_eq!(
            done.code,
            Some(0),
            "{method} on the CPU:\n{}\n{}",
            done.stdout,
            done.stderr
        );
        assert_eq!(compute_of(&cpu), serde_json::json!({"device": "cpu"}));
        let d = difference(&gpu, &cpu);
        eprintln!("{method}: GPU against CPU, relative L2 {d:.2e}");
        assert!(
            d < bound,
            "{method}: the GPU's volume differs from the CPU's by {d:e} (relative L2)"
        );
    }
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

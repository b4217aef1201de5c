//! Public capture formats through `periscope recon`, end to end: one file of a known
//! point scene per format (recon/tests/data/lct-point.py and public-formats.py, written
//! by the writers those formats come from: scipy's `savemat`, h5py, hdf5storage's MAT
//! v7.3) reconstructs with its point where it is.
use std::path::Path;

mod common;

/// Each fixture's point target; FBP and 3D-GTR must both put the volume's peak within
/// 1.5 voxels (the default volume's largest edge) or 1.5 cm, whichever is more.
#[test]
fn every_public_format_reconstructs_its_point_where_it_is() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recon/tests/data");
    for (file, target) in [
        ("lct-point.mat", [0.1, -0.05, 0.3]),
        ("fk-point/meas_10min.mat", [0.25, -0.1, 0.6]),
        ("znlos-point.hdf5", [0.1, -0.5, 0.05]),
        ("pf2019-point.mat", [-0.1, 0.05, 0.5]),
        ("pf2020-point.mat", [0.03, -0.02, 0.4]),
    ] {
        for method in ["fbp", "gtr"] {
            let err = peak_error(&root.join(file), method, target);
            assert!(
                err.0 < err.1,
                "{file} with {method}: the peak is {} m from the target",
                err.0
            );
            eprintln!(
                "formats: {file} with {method}: peak {:.1} mm from the target (voxel {:.1} mm)",
                err.0 * 1e3,
                err.1 / 1.5 * 1e3
            );
        }
    }
}

/// How far `periscope recon CAPTURE` with `method` puts the volume's peak from
/// `target`, and the distance allowed.
fn peak_error(fixture: &Path, method: &str, target: [f64; 3]) -> (f64, f64) {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("recon.toml");
    // What is checked is where each format puts the scene, not how sharp the fit gets:
    // 16 epochs (a fixture of 64 pairs would otherwise take the 8,192-step floor).
    std::fs::write(&config, format!("method = \"{method}\"\n[gtr]\nepochs = 16\n")).unwrap();
    let out = dir.path().join("out");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .arg("recon")
        .arg(fixture)
        .arg("--config")
        .arg(&config)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{} with {method}: {}",
        fixture.display(),
        String::from_utf8_lossy(&status.stderr)
    );
    common::peak_error(&out, target)
}

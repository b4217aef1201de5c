//! Public capture formats through `periscope recon`, end to end: one file of a known
//! point scene per format (recon/tests/data/lct-point.py and public-formats.py, written
//! by the writers those formats come from: scipy's `savemat`, h5py, hdf5storage's MAT
//! v7.3) reconstructs with its point where it is.
use std::path::Path;

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
    std::fs::write(&config, format!("method = \"{method}\"\n")).unwrap();
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
    let (shape, v) = periscope_recon::io::read_npy(&out.join("volume.npy")).unwrap();
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("volume.json")).unwrap()).unwrap();
    let (nz, ny, nx) = (shape[0], shape[1], shape[2]);
    let peak = v
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map(|(i, _)| i)
        .unwrap();
    let (iz, iy, ix) = (peak / (ny * nx), peak / nx % ny, peak % nx);
    let mut voxel = 0f64;
    let mut centre = |axis: &str, n: usize, i: usize| {
        let r = &meta[axis];
        let (lo, hi) = (r[0].as_f64().unwrap(), r[1].as_f64().unwrap());
        voxel = voxel.max((hi - lo) / n as f64);
        lo + (i as f64 + 0.5) * (hi - lo) / n as f64
    };
    let found = [centre("x", nx, ix), centre("y", ny, iy), centre("z", nz, iz)];
    let err = found
        .iter()
        .zip(target)
        .map(|(f, t)| (f - t).powi(2))
        .sum::<f64>()
        .sqrt();
    (err, (1.5 * voxel).max(0.015))
}

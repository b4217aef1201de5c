//! Public capture formats through `periscope recon`, end to end: one file of a known
//! point scene per format (recon/tests/data/lct-point.py and public-formats.py, written
//! by the writers those formats come from: scipy's `savemat`, h5py, hdf5storage's MAT
//! v7.3) reconstructs with its point where it is.
use std::path::Path;

mod common;

/// Each fixture's point target; FBP and 3D-GTR must both put the volume's peak within
/// 1.5 voxels (the default volume's largest edge) or 1.5 cm, whichever is more. The
/// depth map looks along the relay's normal: z for every format but ZNLOS, whose wall
/// lies in the x–z plane with its scene at −y, and there the target's pixel holds its
/// y within the same distance.
#[test]
fn every_public_format_reconstructs_its_point_where_it_is() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recon/tests/data");
    for (file, target, depth) in [
        ("lct-point.mat", [0.1, -0.05, 0.3], ["z", "+", "x", "y"]),
        ("fk-point/meas_10min.mat", [0.25, -0.1, 0.6], ["z", "+", "x", "y"]),
        ("znlos-point.hdf5", [0.1, -0.5, 0.05], ["y", "-", "x", "z"]),
        ("pf2019-point.mat", [-0.1, 0.05, 0.5], ["z", "+", "x", "y"]),
        ("pf2020-point.mat", [0.03, -0.02, 0.4], ["z", "+", "x", "y"]),
    ] {
        for method in ["fbp", "gtr"] {
            let dir = recon(&root.join(file), method);
            let out = dir.path().join("out");
            let err = common::peak_error(&out, target);
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
            check_depth_map(&out, &format!("{file} with {method}"), depth, target, err.1);
        }
    }
}

/// Checks that `out`'s `volume.json` names the depth map's `[axis, away, columns,
/// rows]` as `want` and that its `depth.npy` holds `target`'s depth at `target`'s
/// pixel, within `allowed` metres.
fn check_depth_map(out: &Path, what: &str, want: [&str; 4], target: [f64; 3], allowed: f64) {
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("volume.json")).unwrap()).unwrap();
    let d = &meta["depth"];
    let got = ["axis", "away", "columns", "rows"].map(|k| d[k].as_str().unwrap_or("?").to_owned());
    assert_eq!(got, want, "{what}: the depth map's axes in volume.json");
    let index = |name: &str| ["x", "y", "z"].iter().position(|a| *a == name).unwrap();
    let (axis, cols, rows) = (index(want[0]), index(want[2]), index(want[3]));
    let (shape, depth) = periscope_recon::io::read_npy(&out.join("depth.npy")).unwrap();
    let shape_zyx = &meta["shape_zyx"];
    let voxels = |a: usize| shape_zyx[2 - a].as_u64().unwrap() as usize;
    assert_eq!(
        shape,
        vec![voxels(rows), voxels(cols)],
        "{what}: depth.npy is [rows, columns]"
    );
    let pixel = |a: usize| {
        let r = &meta[["x", "y", "z"][a]];
        let (lo, hi) = (r[0].as_f64().unwrap(), r[1].as_f64().unwrap());
        (((target[a] - lo) / (hi - lo) * voxels(a) as f64).floor() as usize).min(voxels(a) - 1)
    };
    let found = depth[pixel(rows) * voxels(cols) + pixel(cols)] as f64;
    assert!(
        (found - target[axis]).abs() <= allowed,
        "{what}: depth {found} at the target's pixel against its {} = {}",
        want[0],
        target[axis]
    );
}

/// `periscope recon CAPTURE` with `method` into `out` in a new directory.
fn recon(fixture: &Path, method: &str) -> tempfile::TempDir {
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
    dir
}

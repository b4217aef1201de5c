//! Public capture formats through `periscope recon`, end to end: a Stanford LCT `.mat`
//! file of a known scene (recon/tests/data/lct-point.py, written by scipy's `savemat`
//! as the Stanford release's files are) reconstructs with its point where it is.
use std::path::Path;

/// One point target at (0.1, -0.05, 0.3) m; FBP and 3D-GTR must both put the
/// volume's peak within 1.5 cm of it (voxels are 6–9 mm).
#[test]
fn a_stanford_lct_capture_reconstructs_its_point_where_it_is() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let fixture = root.join("recon/tests/data/lct-point.mat");
    for method in ["fbp", "gtr"] {
        let dir = tempfile::tempdir().unwrap();
        let config = dir.path().join("recon.toml");
        std::fs::write(&config, format!("method = \"{method}\"\n")).unwrap();
        let out = dir.path().join("out");
        let status = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
            .arg("recon")
            .arg(&fixture)
            .arg("--config")
            .arg(&config)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(
            status.status.success(),
            "{method}: {}",
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
        let centre = |axis: &str, n: usize, i: usize| {
            let r = &meta[axis];
            let (lo, hi) = (r[0].as_f64().unwrap(), r[1].as_f64().unwrap());
            lo + (i as f64 + 0.5) * (hi - lo) / n as f64
        };
        let found = [centre("x", nx, ix), centre("y", ny, iy), centre("z", nz, iz)];
        let err = ((found[0] - 0.1).powi(2) + (found[1] + 0.05).powi(2) + (found[2] - 0.3).powi(2)).sqrt();
        assert!(
            err < 0.015,
            "{method}: peak at {found:?}, {err} m from the target"
        );
    }
}

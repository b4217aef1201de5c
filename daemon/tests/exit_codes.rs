//! Exit codes of the binary, which scripts and the CI rely on.
use std::path::Path;
use std::process::Command;

fn periscope(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(args)
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output()
        .expect("periscope runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn success_is_zero() {
    assert_eq!(periscope(&["--help"]).0, Some(0));
}

#[test]
fn config_errors_are_two() {
    let (code, stderr) = periscope(&["serve", "--instrument", "Cargo.toml"]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(stderr.contains("Cargo.toml"), "{stderr}");
}

/// A stored run whose plan no longer loads is a configuration error for every command
/// that reads it back, whichever reader finds it.
#[test]
fn a_stored_run_with_a_broken_plan_is_two() {
    use periscope_daemon::config::TomlSource;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("run");
    periscope_daemon::pipeline::prepare(
        &TomlSource::load(&root.join("configs/plans/demo.toml")).unwrap(),
        &TomlSource::load(&root.join("configs/instrument/sim.toml")).unwrap(),
        Some(&run),
        "test",
    )
    .unwrap();
    std::fs::write(run.join("plan.toml"), "name = 1\n").unwrap();
    let run = run.to_str().unwrap();
    let out = tmp.path().join("out");
    for args in [
        vec!["recon", run, "--out", out.to_str().unwrap()],
        vec!["export", run],
        vec!["resume", run],
    ] {
        let (code, stderr) = periscope(&args);
        assert_eq!(code, Some(2), "{args:?}: {stderr}");
        assert!(stderr.contains("plan.toml"), "{args:?}: {stderr}");
    }
    // A run directory as a reconstruction's output: its results and log would be
    // written over; refused before anything is read.
    let before = std::fs::read_dir(run).unwrap().count();
    let (code, stderr) = periscope(&["recon", run, "--out", run]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("is a run directory") && stderr.contains("--out"),
        "{stderr}"
    );
    assert_eq!(std::fs::read_dir(run).unwrap().count(), before);
    // A file as the output folder: named as such, exit 2, not "File exists (os error
    // 17)" after the capture was read (until 2026-12-06).
    let file = tmp.path().join("a-file");
    std::fs::write(&file, "kept").unwrap();
    let (code, stderr) = periscope(&[
        "recon",
        "tests/data/ytal/confocal_xy.hdf5",
        "--out",
        file.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("is not a folder") && stderr.contains("--out"),
        "{stderr}"
    );
    assert_eq!(std::fs::read(&file).unwrap(), b"kept");
    // A link to nothing as the output folder: named as such (until 2026-12-06 "File
    // exists (os error 17)"), the link left as it was.
    let link = tmp.path().join("dangling");
    std::os::unix::fs::symlink(tmp.path().join("nowhere"), &link).unwrap();
    let (code, stderr) = periscope(&[
        "recon",
        "tests/data/ytal/confocal_xy.hdf5",
        "--out",
        link.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("is a symbolic link to") && stderr.contains("which does not exist"),
        "{stderr}"
    );
    assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
}

/// A reconstruction the settings cannot do (here LCT, which needs confocal pairs, on a
/// capture with one fixed laser) is the user's to fix: exit 2, and the message says
/// what to use instead.
#[test]
fn a_solver_that_does_not_suit_the_capture_is_two() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("recon.toml");
    std::fs::write(
        &config,
        "method = \"lct\"\n[volume]\nx = [-0.5, 0.5]\ny = [-0.5, 0.5]\nz = [0.2, 1.0]\nshape = [8, 8, 8]\n",
    )
    .unwrap();
    let out = tmp.path().join("out");
    let (code, stderr) = periscope(&[
        "recon",
        "tests/data/ytal/single_laser_n3.hdf5",
        "--config",
        config.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("not confocal") && stderr.contains("use rsd or fbp"),
        "{stderr}"
    );
}

/// `periscope recon` of the y-tal fixture with the RECON.toml `config` under an
/// address-space limit of `kib` KiB: its exit code and stderr, and whether it wrote a
/// volume.
fn recon_within(kib: u64, config: &str) -> (Option<i32>, String, bool) {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("recon.toml");
    std::fs::write(&path, config).unwrap();
    let out = Command::new("sh")
        .arg("-c")
        .arg(format!("ulimit -v {kib} && exec \"$0\" \"$@\""))
        .arg(env!("CARGO_BIN_EXE_periscope"))
        .args(["recon", "tests/data/ytal/confocal_xy.hdf5", "--config"])
        .arg(&path)
        .arg("--out")
        .arg(tmp.path().join("out"))
        .current_dir(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))
        .output()
        .expect("periscope runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        tmp.path().join("out/volume.npy").exists(),
    )
}

/// A volume the process cannot hold is refused by `periscope recon` before it reads
/// the transients, naming the RECON.toml, the shape and both sizes, with exit 2. With
/// a 4 GiB address-space limit a 768³ FBP volume (about 8.4 GiB at FBP's 20 bytes a
/// voxel, measured) used to abort in the allocator ("memory allocation of … bytes
/// failed", signal 6) once the backprojection began.
#[test]
fn a_volume_larger_than_the_memory_left_is_refused_up_front() {
    let (code, stderr, wrote) = recon_within(
        4 << 20,
        "method = \"fbp\"\n[volume]\nx = [-0.5, 0.5]\ny = [-0.5, 0.5]\nz = [0.2, 1.0]\nshape = [768, 768, 768]\n",
    );
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("recon.toml")
            && stderr.contains("[768, 768, 768]")
            && stderr.contains("needs about 8.4 GiB")
            && stderr.contains("[volume] shape"),
        "{stderr}"
    );
    assert!(!wrote);
}

/// The same for 3D-GTR's virtual scan, which the volume's figure leaves out: a
/// 1024 × 1024 virtual grid (512 bins of `f64`, twice: 8 GiB) over a small volume,
/// under a 3 GiB address-space limit, is refused naming `virtual-grid`, with exit 2.
/// Until 2026-12-06 it aborted in the allocator (signal 6) when the scan was made.
#[test]
fn a_virtual_scan_larger_than_the_memory_left_is_refused_up_front() {
    let (code, stderr, wrote) = recon_within(
        3 << 20,
        "method = \"gtr\"\n[volume]\nx = [-0.4, 0.4]\ny = [-0.4, 0.4]\nz = [0.2, 0.9]\nshape = [16, 16, 16]\n\
         [gtr]\nprimitives = 1\nepochs = 1\nvirtual-grid = [1024, 1024]\n",
    );
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("recon.toml")
            && stderr.contains("virtual confocal scan")
            && stderr.contains("recon.gtr.virtual-grid"),
        "{stderr}"
    );
    assert!(!wrote);
}

/// `periscope calibrate --out` that cannot take the calibrated config is refused
/// before any scan, exit 2, naming `--out`: the instrument config it reads (until
/// 2026-12-06 replaced, its poses gone) and a path in a folder that does not exist
/// (until then found only after the scans, as "No such file or directory").
#[test]
fn a_calibration_output_that_cannot_take_the_config_is_refused_before_the_scans() {
    let tmp = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let text = std::fs::read_to_string(root.join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("\"../scenes/", &format!("\"{}/configs/scenes/", root.display()));
    let config = tmp.path().join("instrument.toml");
    std::fs::write(&config, &text).unwrap();
    let c = config.to_str().unwrap();
    let t = std::time::Instant::now();
    let (code, stderr) = periscope(&["calibrate", "--instrument", c, "--out", c]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("--out") && stderr.contains("is the instrument config the calibration reads"),
        "{stderr}"
    );
    assert_eq!(std::fs::read_to_string(&config).unwrap(), text);
    let missing = tmp.path().join("no-such-folder/calibrated.toml");
    let (code, stderr) = periscope(&["calibrate", "--instrument", c, "--out", missing.to_str().unwrap()]);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("--out") && stderr.contains("which is not a folder"),
        "{stderr}"
    );
    assert!(
        t.elapsed() < std::time::Duration::from_secs(10),
        "{:?}: scanned first?",
        t.elapsed()
    );
}

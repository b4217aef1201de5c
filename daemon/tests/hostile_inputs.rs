//! Inputs a user (or an attacker on the same host) can hand the daemon that used to
//! hang it, abort it or damage the system: a FIFO or `/dev/zero` where a file belongs,
//! a device node as an output, a 50 MB plan, a three-number grid, a lower-case bearer
//! scheme, and what a killed write leaves in a run directory. Each must end in a clear
//! message naming the file or key, promptly, with nothing replaced or lost.
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use periscope_daemon::config::{ConfigError, TomlSource};

/// Makes a FIFO at `path` (with `mkfifo`, which every Linux has).
fn fifo(path: &Path) {
    let ok = Command::new("mkfifo").arg(path).status().unwrap().success();
    assert!(ok, "mkfifo failed");
}

/// Runs `f` on another thread and fails the test if it takes longer than `limit` (a
/// read of a FIFO with no writer blocks forever).
fn within<T: Send + 'static>(limit: Duration, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(limit)
        .unwrap_or_else(|_| panic!("still blocked after {limit:?}"))
}

#[test]
fn an_output_path_that_is_not_a_regular_file_is_left_alone() {
    let dir = tempfile::tempdir().unwrap();
    let pipe = dir.path().join("out.hdf5");
    fifo(&pipe);
    let sub = dir.path().join("a-directory");
    std::fs::create_dir(&sub).unwrap();
    let link = dir.path().join("link.hdf5");
    std::os::unix::fs::symlink(dir.path().join("target"), &link).unwrap();
    for path in [&pipe, &sub, &link] {
        let e = periscope_recon::io::write_bytes_atomically(path, b"data").unwrap_err();
        assert!(e.to_string().contains("not a regular file"), "{e}");
        let kind = std::fs::symlink_metadata(path).unwrap().file_type();
        assert!(!kind.is_file(), "{} was replaced by a file", path.display());
    }
    // The daemon's own atomic writes go the same way.
    let e = periscope_daemon::store::write_atomic(&pipe, b"x").unwrap_err();
    assert!(e.to_string().contains("not a regular file"), "{e}");
    // A regular file is still replaced.
    let file = dir.path().join("plain");
    std::fs::write(&file, b"old").unwrap();
    periscope_recon::io::write_bytes_atomically(&file, b"new").unwrap();
    assert_eq!(std::fs::read(&file).unwrap(), b"new");
}

#[test]
fn a_fifo_or_an_endless_device_as_a_config_or_mesh_is_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let pipe = dir.path().join("plan.toml");
    fifo(&pipe);
    let p = pipe.clone();
    let e = within(Duration::from_secs(5), move || TomlSource::load(&p).unwrap_err());
    assert!(e.to_string().contains("plan.toml"), "{e}");
    assert!(e.to_string().contains("not a regular file"), "{e}");

    let mesh = dir.path().join("scene.obj");
    fifo(&mesh);
    let m = mesh.clone();
    let e = within(Duration::from_secs(5), move || {
        periscope_sim::Mesh::load(&m).unwrap_err()
    });
    assert!(e.to_string().contains("not a regular file"), "{e}");

    let zero = dir.path().join("zero.ply");
    std::os::unix::fs::symlink("/dev/zero", &zero).unwrap();
    let t = Instant::now();
    let e = periscope_sim::Mesh::load(&zero).unwrap_err();
    assert!(e.to_string().contains("not a regular file"), "{e}");
    assert!(t.elapsed() < Duration::from_secs(1), "read for {:?}", t.elapsed());
}

#[test]
fn a_plan_file_larger_than_any_plan_is_refused_before_it_is_parsed() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.toml");
    let array = "0,".repeat(25_000_000 / 2);
    std::fs::write(&path, format!("name = \"big\"\nnumbers = [{array}0]\n")).unwrap();
    let e = TomlSource::load(&path).unwrap_err();
    assert!(matches!(e, ConfigError::Read { .. }), "{e:?}");
    let text = e.to_string();
    assert!(text.contains("big.toml") && text.contains("4194304"), "{text}");
}

/// The shipped simulated instrument.
fn sim_instrument() -> periscope_daemon::config::InstrumentConfig {
    let src = TomlSource::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/instrument/sim.toml"))
        .unwrap();
    periscope_daemon::config::InstrumentConfig::from_source(&src).unwrap()
}

/// The tests' small FBP plan, as text.
fn small_fbp() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data/plans/small-fbp.toml"))
        .unwrap()
}

#[test]
fn a_grid_of_three_numbers_is_refused_with_its_key_and_line() {
    let instrument = sim_instrument();
    let plan = small_fbp().replace("grid = [8, 8]", "grid = [24, 24, 24]");
    let e = periscope_daemon::plan::Plan::from_source(&TomlSource::from_text("plan.toml", plan), &instrument)
        .unwrap_err()
        .to_string();
    assert!(e.contains("plan.toml:") && e.contains("pairs.grid"), "{e}");
    assert!(e.contains("exactly 2"), "{e}");
}

/// LCT and f-k take confocal pairs only: a plan that cannot give them (a detection
/// offset past the solver's tolerance, a layout of other pairs) is refused when it is
/// read, naming the key, not by the solver after the whole capture.
#[test]
fn a_confocal_solver_on_pairs_it_cannot_take_is_refused_with_the_plan() {
    let instrument = sim_instrument();
    let base = small_fbp();
    let read = |plan: String| {
        periscope_daemon::plan::Plan::from_source(&TomlSource::from_text("plan.toml", plan), &instrument)
            .map(drop)
            .map_err(|e| e.to_string())
    };
    for solver in ["lct", "fk"] {
        let plan = base.replace("method = \"fbp\"", &format!("method = \"{solver}\""));
        let e = read(plan.clone()).unwrap_err();
        assert!(e.contains("pairs.offset-mm") && e.contains("5.0 mm"), "{e}");
        // A run that stored such a plan before it was refused still opens: its
        // captured data stays readable (export, fbp), only a new run is refused.
        let stored = TomlSource::from_text("plan.toml", plan.clone());
        assert!(periscope_daemon::plan::Plan::stored(&stored, &instrument).is_ok());
        assert!(read(plan.replace("offset-mm = 5.0", "offset-mm = 1.5")).is_ok());
        assert!(
            read(plan.replace(
                "[recon.volume]",
                &format!("[recon.{solver}]\ngrid-tolerance = 6.0e-3\n[recon.volume]")
            ))
            .is_ok()
        );
        let fixed = plan
            .replace(
                "mode = \"confocal\"",
                "mode = \"fixed-laser\"\nlaser = [0.0, 0.0, 0.0]",
            )
            .replace("offset-mm = 5.0\n", "");
        let e = read(fixed).unwrap_err();
        assert!(e.contains("recon.method") && e.contains("fixed laser"), "{e}");
    }
    assert!(read(base.replace("method = \"fbp\"", "method = \"rsd\"")).is_ok());
}

/// A run's data left in a directory without its run.json (deleted, or a copy that left
/// it out) is refused as a new run's `--out` (a review, 2026-12-06): the new run
/// recovered that histogram log as its own, kept the old pairs under its own plan and
/// instrument, and overwrote the old plan's copy. An empty directory, or one holding
/// unrelated files, still takes a run.
#[test]
fn a_new_run_refuses_a_directory_holding_another_runs_data() {
    use periscope_daemon::pipeline;
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let plan = TomlSource::load(&root.join("configs/plans/demo.toml")).unwrap();
    let inst = TomlSource::load(&root.join("configs/instrument/sim.toml")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    for leftover in [
        "histograms.bin",
        "histograms.bin.damaged",
        "pairs.json",
        "relay.ply",
    ] {
        let out = tmp.path().join(format!("left-{leftover}"));
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join(leftover), b"the old run's bytes").unwrap();
        std::fs::write(out.join("plan.toml"), "name = \"the old plan\"\n").unwrap();
        let e = pipeline::prepare(&plan, &inst, Some(&out), "test").unwrap_err();
        let text = e.to_string();
        assert!(text.contains(leftover) && text.contains("no run.json"), "{text}");
        assert_eq!(std::fs::read(out.join(leftover)).unwrap(), b"the old run's bytes");
        assert_eq!(
            std::fs::read_to_string(out.join("plan.toml")).unwrap(),
            "name = \"the old plan\"\n",
            "the old plan's copy was overwritten"
        );
    }
    // A user's own files under names a run writes (a plan and an instrument config
    // kept together, with its token) are not replaced by the run's copies.
    let own = tmp.path().join("own-files");
    std::fs::create_dir(&own).unwrap();
    let config = "[api]\ntoken = \"0123456789abcdef0123\"\n";
    std::fs::write(own.join("instrument.toml"), config).unwrap();
    let e = pipeline::prepare(&plan, &inst, Some(&own), "test").unwrap_err();
    let text = e.to_string();
    assert!(
        text.contains("instrument.toml") && text.contains("no run.json"),
        "{text}"
    );
    assert_eq!(
        std::fs::read_to_string(own.join("instrument.toml")).unwrap(),
        config
    );
    let notes = tmp.path().join("with-notes");
    std::fs::create_dir(&notes).unwrap();
    std::fs::write(notes.join("notes.txt"), b"bench set-up").unwrap();
    pipeline::prepare(&plan, &inst, Some(&notes), "test").unwrap();
    pipeline::prepare(&plan, &inst, Some(&tmp.path().join("new/nested")), "test").unwrap();
}

/// A run directory's files are read as any config is: regular files only, within a
/// size. A FIFO or a link to `/dev/zero` put in place of `plan.toml`, `pairs.json`,
/// `relay.ply`, `run.json` or the histogram log hung `resume`, `recon` and `export`,
/// or filled memory (2.9 GB in 2 s), until 2026-12-06.
#[test]
fn a_fifo_or_an_endless_device_in_a_run_directory_is_refused_at_once() {
    use periscope_daemon::pipeline;
    use periscope_daemon::run_dir::RunDir;
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let plan = TomlSource::load(&root.join("configs/plans/demo.toml")).unwrap();
    let inst = TomlSource::load(&root.join("configs/instrument/sim.toml")).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    for (name, endless) in [
        ("plan.toml", false),
        ("instrument.toml", true),
        ("pairs.json", true),
        ("pairs.json", false),
        ("relay.ply", true),
        ("run.json", false),
        ("histograms.bin", false),
        ("histograms.bin", true),
    ] {
        let dir = tmp.path().join(format!("{name}-{endless}"));
        pipeline::prepare(&plan, &inst, Some(&dir), "test").unwrap();
        let path = dir.join(name);
        let _ = std::fs::remove_file(&path);
        if endless {
            std::os::unix::fs::symlink("/dev/zero", &path).unwrap();
        } else {
            fifo(&path);
        }
        let d = dir.clone();
        let t = Instant::now();
        let e = within(Duration::from_secs(5), move || {
            let run = RunDir::new(&d);
            match name {
                "pairs.json" => run.planned_pairs().map(|_| ()).map_err(|e| e.to_string()),
                "relay.ply" => periscope_daemon::run_dir::read_relay_ply(&d)
                    .map(|_| ())
                    .map_err(|e| e.to_string()),
                "histograms.bin" => periscope_daemon::store::read_log(&d)
                    .map(|_| ())
                    .map_err(|e| e.to_string()),
                _ => run.load().map(|_| ()).map_err(|e| e.to_string()),
            }
        })
        .unwrap_err();
        assert!(
            e.contains(name) && e.contains("not a regular file"),
            "{name} (endless {endless}): {e}"
        );
        assert!(t.elapsed() < Duration::from_secs(2), "{name}: {:?}", t.elapsed());
    }
}

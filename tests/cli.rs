//! The `periscope` command line as a user meets it: help texts, exit codes, and the
//! messages for mistakes a user can make.
use periscope_tests::periscope;

const SUBCOMMANDS: [&str; 6] = ["run", "check", "resume", "recon", "serve", "devices"];

#[test]
fn top_level_help_lists_every_subcommand() {
    let out = periscope(&["--help"]);
    assert_eq!(out.code, Some(0), "{out:?}");
    for sub in SUBCOMMANDS {
        assert!(
            out.stdout.contains(sub),
            "`{sub}` missing from --help:\n{}",
            out.stdout
        );
    }
}

#[test]
fn every_subcommand_explains_itself() {
    for sub in SUBCOMMANDS {
        let out = periscope(&[sub, "--help"]);
        assert_eq!(out.code, Some(0), "{sub}: {out:?}");
        assert!(out.stdout.contains("Usage: periscope"), "{sub}: {}", out.stdout);
        // The first line is the command's description, not an empty line.
        let first = out.stdout.lines().next().unwrap_or_default();
        assert!(
            first.split_whitespace().count() >= 4,
            "{sub} has no description: {first:?}"
        );
    }
}

#[test]
fn version_is_printed() {
    let out = periscope(&["--version"]);
    assert_eq!(out.code, Some(0));
    assert!(out.stdout.starts_with("periscope "), "{}", out.stdout);
}

#[test]
fn usage_mistakes_exit_with_2() {
    for args in [
        &["frobnicate"][..],
        &["run"],
        &["recon", "x"],
        &["serve", "--bind", "not-an-address"],
    ] {
        let out = periscope(args);
        assert_eq!(out.code, Some(2), "{args:?}: {out:?}");
        assert!(
            out.stderr.contains("Usage") || out.stderr.contains("error"),
            "{args:?}: {}",
            out.stderr
        );
    }
}

#[test]
fn a_missing_run_directory_is_named() {
    let out = periscope(&["resume", "runs/does-not-exist"]);
    assert_eq!(out.code, Some(1), "{out:?}");
    assert!(out.stderr.contains("runs/does-not-exist"), "{}", out.stderr);
}

/// `--log-file` appends to a log and never truncates: pointed at a run's histogram
/// log or at the plan being read, it emptied them (until 2026-12-06). Such targets,
/// and a FIFO (which blocked the command for good), are refused before anything runs.
#[test]
fn the_log_file_appends_and_never_replaces_data() {
    let dir = tempfile::tempdir().unwrap();
    let plan = dir.path().join("plan.toml");
    std::fs::write(&plan, include_str!("data/plans/small-fbp.toml")).unwrap();
    let p = |path: &std::path::Path| path.to_str().unwrap().to_owned();
    // A log is appended to.
    let log = dir.path().join("periscope.log");
    std::fs::write(&log, "an earlier line\n").unwrap();
    for _ in 0..2 {
        let out = periscope(&["--log-file", &p(&log), "check", &p(&plan)]);
        assert_eq!(out.code, Some(0), "{out:?}");
    }
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(text.starts_with("an earlier line\n"), "{text}");
    // The plan, a run's files, and a FIFO are refused, and left as they were.
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    std::fs::write(run.join("run.json"), "{}").unwrap();
    std::fs::write(run.join("histograms.bin"), b"counts").unwrap();
    let fifo = dir.path().join("fifo");
    assert!(
        std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    for (target, says) in [
        (plan.clone(), "named as data"),
        (run.join("histograms.bin"), "run directory"),
        (run.join("new.log"), "run directory"),
        (fifo, "not a regular file"),
    ] {
        // (A FIFO is never read here: reading one blocks.)
        let contents = |t: &std::path::Path| t.is_file().then(|| std::fs::read(t).unwrap());
        let before = contents(&target);
        let out = periscope_tests::periscope_with_limit(
            &["--log-file", &p(&target), "check", &p(&plan)],
            std::time::Duration::from_secs(60),
        );
        assert_eq!(out.code, Some(2), "{target:?}: {out:?}");
        assert!(
            out.stderr.contains("--log-file") && out.stderr.contains(says),
            "{target:?}: {}",
            out.stderr
        );
        assert_eq!(contents(&target), before, "{target:?}");
    }
}

#[test]
fn json_logs_are_json() {
    // A small run logs its stages at info level: every line on stderr must be one JSON
    // object with a level and a message, and there must be some.
    let dir = tempfile::tempdir().unwrap();
    let plan = dir.path().join("plan.toml");
    std::fs::write(&plan, include_str!("data/plans/small-fbp.toml")).unwrap();
    let out = std::process::Command::new(periscope_tests::periscope_bin())
        .current_dir(periscope_tests::repo_root())
        .env("RUST_LOG", "info")
        .args(["--log-format", "json", "run"])
        .arg(&plan)
        .arg("--out")
        .arg(dir.path().join("run"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{out:?}");
    let stderr = String::from_utf8_lossy(&out.stderr);
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert!(lines.len() >= 3, "too few log lines:\n{stderr}");
    for line in lines {
        let v: serde_json::Value = serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"));
        assert!(v["level"].is_string(), "{line}");
        assert!(v["fields"]["message"].is_string(), "{line}");
    }
    assert!(stderr.contains("stage started"), "{stderr}");
}

#[test]
fn devices_identifies_the_simulated_instrument_through_the_real_drivers() {
    let out = periscope(&["devices"]);
    assert_eq!(out.code, Some(0), "{out:?}");
    for want in [
        "laser arm  PGC-2",
        "spad arm   PGC-2",
        "histogrammer PTDC-SIM",
        "interlock closed",
    ] {
        assert!(out.stdout.contains(want), "missing `{want}` in:\n{}", out.stdout);
    }
}

#[test]
fn devices_names_the_missing_hardware() {
    let out = periscope(&["devices", "--instrument", "configs/instrument/lab.example.toml"]);
    assert_eq!(out.code, Some(1), "{out:?}");
    // Devices are opened laser controller first (the one an e-stop needs most): the
    // message names it, its port, and says what to check.
    assert!(
        out.stderr.contains("galvo pair `laser` on /dev/ttyUSB0"),
        "{}",
        out.stderr
    );
    assert!(out.stderr.contains("plugged in"), "{}", out.stderr);
}

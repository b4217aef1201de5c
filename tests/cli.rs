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

#[test]
fn json_logs_are_json() {
    let out = periscope(&["--log-format", "json", "devices"]);
    for line in out.stderr.lines().filter(|l| l.starts_with('{')) {
        assert!(line.ends_with('}') && line.contains("\"level\""), "{line}");
    }
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

//! Every file in `configs/` is loaded by a test, and the binary reports broken configs
//! with file, line and key.
use std::path::Path;

use periscope_daemon::config::{InstrumentConfig, load_scene};
use periscope_daemon::plan::Plan;
use periscope_tests::{config_files, periscope, repo_path};

#[test]
fn every_config_file_loads() {
    let files = config_files();
    assert!(!files.is_empty(), "configs/ is empty");
    for file in &files {
        let kind = file.iter().nth(1).and_then(|s| s.to_str()).unwrap_or_default();
        let full = repo_path(&file.to_string_lossy());
        match kind {
            "instrument" => {
                InstrumentConfig::load(&full).unwrap_or_else(|err| panic!("{err}"));
            }
            "scenes" => {
                let scene = load_scene(&full).unwrap_or_else(|err| panic!("{err}"));
                assert!(!scene.hidden.is_empty() && !scene.relay.mesh.triangles.is_empty());
            }
            "plans" => {
                let sim = InstrumentConfig::load(&repo_path("configs/instrument/sim.toml")).unwrap();
                let plan = Plan::load(&full, &sim).unwrap_or_else(|err| panic!("{err}"));
                assert!(plan.pairs.max_pairs() > 0);
            }
            _ => panic!(
                "{}: no loader is known for configs/{kind}/; add one to this test so the file is checked",
                file.display()
            ),
        }
    }
}

#[test]
fn shipped_instruments_are_accepted_by_the_binary() {
    // `devices` loads the instrument before anything else: an invalid config stops at
    // exit 2, a valid one gets further (the lab example then fails to find hardware).
    for file in [
        "configs/instrument/sim.toml",
        "configs/instrument/lab.example.toml",
    ] {
        let out = periscope(&["devices", "--instrument", file]);
        assert_ne!(out.code, Some(2), "{file}: {}", out.stderr);
    }
}

#[test]
fn a_broken_instrument_names_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/instrument/sim.toml"))
        .unwrap()
        .replace("bins = 1024", "bins = 0");
    let line = text.lines().position(|l| l.starts_with("bins")).unwrap() + 1;
    let bad = dir.path().join("broken.toml");
    std::fs::write(&bad, text).unwrap();
    let out = periscope(&["devices", "--instrument", bad.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    let expected = format!("broken.toml:{line}: key `tdc.bins`");
    assert!(
        out.stderr.contains(&expected),
        "expected `{expected}` in:\n{}",
        out.stderr
    );
}

/// What the counter would do differently from what the config says is refused by key:
/// a bin width it cannot bin at (12.5 ps, binned at 13 while the time axis read 12.5),
/// fewer than 16 bins, and a window past the laser's sync period (a counter times each
/// photon from the last sync: nothing is recorded past it, and longer returns fold into
/// the first bins). A plan's own window is held to the period too.
#[test]
fn an_instrument_whose_counter_cannot_do_what_it_says_is_refused_by_key() {
    let dir = tempfile::tempdir().unwrap();
    let sim = std::fs::read_to_string(repo_path("configs/instrument/sim.toml")).unwrap();
    for (from, to, key, says) in [
        (
            "bin-width-ps = 16.0",
            "bin-width-ps = 12.5",
            "tdc.bin-width-ps",
            "whole number",
        ),
        ("bins = 1024", "bins = 8", "tdc.bins", "between 16 and 65536"),
        (
            "offset-ns = 12.0 ",
            "offset-ns = 12.0005 ",
            "tdc.offset-ns",
            "whole number of picoseconds",
        ),
        (
            "rep-rate-mhz = 10.0",
            "rep-rate-mhz = 80.0",
            "tdc.offset-ns",
            "sync period of 12.50 ns",
        ),
    ] {
        assert!(sim.contains(from), "{from}");
        let bad = dir.path().join("counter.toml");
        std::fs::write(&bad, sim.replacen(from, to, 1)).unwrap();
        let out = periscope(&["devices", "--instrument", bad.to_str().unwrap()]);
        assert_eq!(out.code, Some(2), "{to}: {out:?}");
        assert!(
            out.stderr.contains(key) && out.stderr.contains(says),
            "{to}: {}",
            out.stderr
        );
    }
    let plan = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let long = dir.path().join("long.toml");
    std::fs::write(
        &long,
        plan.replacen(
            "[acquisition]\n",
            "[acquisition]\nbins = 65536\nbin-width-ps = 2000\n",
            1,
        ),
    )
    .unwrap();
    let out = periscope(&["check", long.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr.contains("acquisition.bins") && out.stderr.contains("sync period of 100.00 ns"),
        "{}",
        out.stderr
    );
}

#[test]
fn a_missing_instrument_file_is_named() {
    let out = periscope(&["devices", "--instrument", "configs/instrument/nope.toml"]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr.contains("nope.toml") && out.stderr.contains("check the path"),
        "{}",
        out.stderr
    );
    assert!(Path::new(&repo_path("configs/instrument/sim.toml")).is_file());
    // A file that is there but is not UTF-8 text is said to be that, not to be looked
    // for elsewhere (until 2026-12-06: "check the path").
    let dir = tempfile::tempdir().unwrap();
    let latin1 = dir.path().join("latin1.toml");
    std::fs::write(&latin1, b"name = \"caf\xe9\"\n").unwrap();
    let out = periscope(&["check", latin1.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr.contains("latin1.toml")
            && out.stderr.contains("not UTF-8")
            && !out.stderr.contains("check the path"),
        "{}",
        out.stderr
    );
}

#[test]
fn a_broken_scene_names_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/scenes/wall-letter.toml"))
        .unwrap()
        .replace("stroke = 0.07", "stroke = 0.3");
    let line = text.lines().position(|l| l.starts_with("stroke")).unwrap() + 1;
    let bad = dir.path().join("scene.toml");
    std::fs::write(&bad, text).unwrap();
    let err = load_scene(&bad).unwrap_err().to_string();
    let expected = format!("scene.toml:{line}: key `hidden[0].stroke`");
    assert!(err.contains(&expected), "expected `{expected}` in: {err}");
    assert!(err.contains("does not suit"), "{err}");
    // An array longer than its key takes is refused, not cut short.
    let text = std::fs::read_to_string(repo_path("configs/scenes/wall-letter.toml"))
        .unwrap()
        .replacen(
            "position = [0.0, 0.0, 0.6]",
            "position = [0.0, 0.0, 0.6, 99.0]",
            1,
        );
    std::fs::write(&bad, text).unwrap();
    let err = load_scene(&bad).unwrap_err().to_string();
    assert!(err.contains("position") && err.contains("exactly 3"), "{err}");
}

/// A relay whose albedo varies (`[relay.albedo-variation]`): the albedo stays within
/// the ramp and the cells' range and never above `albedo`, the ramp spans `smooth`
/// from corner to corner, a cell reads the same wherever it is asked, and the cells
/// spread over their range; out-of-range values and a variation on a hidden object
/// are refused with the file, line and key.
#[test]
fn a_patchy_relay_varies_as_its_scene_says_and_bad_values_name_their_key() {
    let path = repo_path("configs/scenes/patchy-wall-letter.toml");
    let scene = load_scene(&path).unwrap();
    let relay = &scene.relay;
    let at = |x: f64, y: f64| relay.albedo_at(glam::DVec3::new(x, y, 0.0));
    let (smooth, random) = (3.0, 0.3);
    let floor = relay.albedo / smooth * (1.0 - random) / (1.0 + random);
    // The same wall without the cells: the ramp alone.
    let text = std::fs::read_to_string(&path).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let smooth_only = dir.path().join("smooth.toml");
    std::fs::write(&smooth_only, text.replace("random = 0.3", "random = 0.0")).unwrap();
    let ramp = load_scene(&smooth_only).unwrap().relay;
    let corner = |x: f64, y: f64| ramp.albedo_at(glam::DVec3::new(x, y, 0.0));
    // A cell's own factor: the albedo over the ramp's.
    let cell = |x: f64, y: f64| at(x, y) / corner(x, y);
    for i in 0..80 {
        for j in 0..80 {
            let (x, y) = (-0.79 + 0.02 * i as f64, -0.79 + 0.02 * j as f64);
            let a = at(x, y);
            assert!(a > floor * 0.999 && a <= relay.albedo, "albedo {a} at ({x}, {y})");
            // The same 2 cm cell, asked at another point of it.
            let (here, there) = (cell(x, y), cell(x + 0.004, y - 0.004));
            assert!(
                (here - there).abs() < 1e-12,
                "one cell, one factor: {here} and {there}"
            );
        }
    }
    // The corners are the ramp's ends.
    let ratio = corner(0.8, 0.8) / corner(-0.8, -0.8);
    assert!((ratio - smooth).abs() < 1e-9, "corner to corner {ratio}");
    assert_eq!(corner(0.8, 0.8), ramp.albedo);
    // The cells' factors spread over their range: along a strip of 80 cells the
    // darkest and brightest differ by most of 1.3 / 0.7.
    let strip: Vec<f64> = (0..400).map(|i| cell(0.79, -0.79 + 0.004 * i as f64)).collect();
    let (lo, hi) = strip
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
    assert!(hi / lo > 1.6, "cells span {lo}..{hi}");

    for (from, to, key) in [
        ("random = 0.3", "random = 2.0", "relay.albedo-variation.random"),
        ("smooth = 3.0", "smooth = 0.5", "relay.albedo-variation.smooth"),
        ("cell-m = 0.02", "cell-m = 0.0", "relay.albedo-variation.cell-m"),
        (
            "direction = [0.6, 0.4]",
            "direction = [0.0, 0.0]",
            "relay.albedo-variation.direction",
        ),
    ] {
        let bad = text.replace(from, to);
        let line = bad.lines().position(|l| l.starts_with(to)).unwrap() + 1;
        let file = dir.path().join("scene.toml");
        std::fs::write(&file, bad).unwrap();
        let err = load_scene(&file).unwrap_err().to_string();
        let expected = format!("scene.toml:{line}: key `{key}`");
        assert!(err.contains(&expected), "expected `{expected}` in: {err}");
    }
    let hidden = format!("{text}\n[hidden.albedo-variation]\nrandom = 0.1\n");
    let file = dir.path().join("hidden.toml");
    std::fs::write(&file, hidden).unwrap();
    let err = load_scene(&file).unwrap_err().to_string();
    assert!(
        err.contains("hidden[0].albedo-variation") && err.contains("only the relay"),
        "{err}"
    );
}

#[test]
fn check_summarises_the_demo_and_moves_nothing() {
    let out = periscope(&["check", "configs/plans/demo.toml"]);
    assert_eq!(out.code, Some(0), "{out:?}");
    for want in [
        "plan `demo`",
        "confocal 24×24",
        "estimated duration",
        "within the galvo limits",
        "budget (per run",
        "captured histograms and transients",
    ] {
        assert!(out.stdout.contains(want), "missing `{want}`:\n{}", out.stdout);
    }
    assert!(!out.stdout.contains("OVER BUDGET"), "{}", out.stdout);
}

#[test]
fn check_refuses_a_plan_over_the_budget_naming_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let huge = text.replace("shape = [64, 64, 128]", "shape = [1024, 1024, 1024]");
    assert_ne!(huge, text);
    let plan = dir.path().join("huge.toml");
    std::fs::write(&plan, &huge).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]);
    // Exit 2, a configuration fault, as `periscope run` refuses the same plan (it
    // was 1 until 2026-12-06).
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(out.stdout.contains("OVER BUDGET"), "{}", out.stdout);
    assert!(
        out.stderr.contains("over budget") && out.stderr.contains("recon.volume.shape"),
        "{}",
        out.stderr
    );
    // `periscope run` refuses it before making a run directory, its message located
    // at the key that sizes the largest part (until 2026-12-08 every refusal was
    // located at `pairs`, whatever was over).
    let line = 1 + huge.lines().position(|l| l.starts_with("shape = [1024")).unwrap();
    let out_dir = dir.path().join("run");
    let out = periscope(&["run", plan.to_str().unwrap(), "--out", out_dir.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    let at = format!("huge.toml:{line}: key `recon.volume.shape`: over budget");
    assert!(out.stderr.contains(&at), "want `{at}`:\n{}", out.stderr);
    assert!(!out_dir.exists());
}

/// `periscope check` judges the TDC window against the total paths the run needs it to
/// record: the LOS scan's first bounces from the relay regions (the scan shares the
/// window) and the volume's paths through them. The demo's window records both; 360
/// bins record part of the volume's; 100 bins none of it; a 20 ns offset none of the
/// LOS returns. Each warns, naming the offset and bins that would record all, and with
/// them the check finds both recorded; one bin fewer than it names does not. None of it
/// is a limit problem: exit 0.
#[test]
fn check_judges_the_tdc_window_against_the_paths_the_run_needs() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let check = |acquisition: &str| {
        let plan = dir.path().join("window.toml");
        let edited = text.replace("[acquisition]\n", &format!("[acquisition]\n{acquisition}"));
        assert!(
            acquisition.is_empty() || edited != text,
            "no [acquisition] to edit"
        );
        std::fs::write(&plan, edited).unwrap();
        let out = periscope(&["check", plan.to_str().unwrap()]);
        assert_eq!(out.code, Some(0), "{out:?}");
        out.stdout
    };
    // The verdicts on the LOS returns and on the volume's paths.
    let verdicts = |out: &str| -> (String, String) {
        let line = out
            .lines()
            .find(|l| l.contains("TDC window:"))
            .unwrap_or_else(|| panic!("no window line:\n{out}"));
        let verdict = |after: &str| {
            let rest = &line[line.find(after).unwrap_or_else(|| panic!("{line}")) + after.len()..];
            let rest = &rest[rest.find(", ").unwrap() + 2..];
            rest.split([';', '(']).next().unwrap().trim().to_owned()
        };
        (
            verdict("LOS returns from"),
            verdict("the volume's paths through them:"),
        )
    };
    // The fixes a warning names, as [acquisition] lines.
    let fixes = |out: &str| -> String {
        let number = |key: &str| {
            out.find(key).map(|at| {
                out[at + key.len()..]
                    .chars()
                    .take_while(|c| c.is_ascii_digit() || *c == '.')
                    .collect::<String>()
                    .trim_end_matches('.')
                    .to_owned()
            })
        };
        let mut lines = String::new();
        if let Some(o) = number("acquisition.offset-ns at most ") {
            lines.push_str(&format!("offset-ns = {o}\n"));
        }
        if let Some(b) = number("acquisition.bins at least ") {
            lines.push_str(&format!("bins = {b}\n"));
        }
        assert!(!lines.is_empty(), "no fix named:\n{out}");
        lines
    };
    let all = ("all recorded".to_owned(), "all recorded".to_owned());
    let shipped = check("");
    assert_eq!(verdicts(&shipped), all, "{shipped}");
    assert!(!shipped.contains("warning"), "{shipped}");

    for (acquisition, los, volume, says) in [
        (
            "bins = 360\n",
            "all recorded",
            "part recorded",
            "far side may be seen by fewer pairs",
        ),
        (
            "bins = 100\n",
            "part recorded",
            "none recorded",
            "the run will fail before its first pair",
        ),
        (
            "offset-ns = 20.0\n",
            "none recorded",
            "part recorded",
            "the scan will find no relay",
        ),
        (
            "offset-ns = 0.0\n",
            "all recorded",
            "part recorded",
            "at this offset, or acquisition.offset-ns",
        ),
    ] {
        let out = check(acquisition);
        assert_eq!(
            verdicts(&out),
            (los.to_owned(), volume.to_owned()),
            "{acquisition}{out}"
        );
        assert!(
            out.contains("warning: acquisition:") && out.contains(says),
            "{acquisition}{out}"
        );
        // The fixes replace the case's own lines of the same keys.
        let merged = |fix: &str| -> String {
            let keys: Vec<&str> = fix.lines().filter_map(|l| l.split(" = ").next()).collect();
            acquisition
                .lines()
                .filter(|l| !keys.iter().any(|k| l.starts_with(&format!("{k} = "))))
                .map(|l| format!("{l}\n"))
                .chain(std::iter::once(fix.to_owned()))
                .collect()
        };
        let fixed = merged(&fixes(&out));
        let after = check(&fixed);
        assert_eq!(verdicts(&after), all, "{fixed}{after}");
        assert!(!after.contains("warning"), "{fixed}{after}");
        if let Some(b) = fixed.lines().find_map(|l| l.strip_prefix("bins = ")) {
            let fewer = fixed.replace(
                &format!("bins = {b}"),
                &format!("bins = {}", b.parse::<u32>().unwrap() - 1),
            );
            assert_ne!(verdicts(&check(&fewer)), all, "{fewer}");
        }
        // The later offset, where one is named, records all with fewer bins.
        if let Some(later) = later(&out).map(|l| merged(&l)) {
            let after = check(&later);
            assert_eq!(verdicts(&after), all, "{later}{after}");
            assert!(!after.contains("warning"), "{later}{after}");
        }
    }

    // A window that would need more bins than a histogram holds at its offset, but
    // not at a later one, is told the later one. 1 ps bins (0.3 mm of path) from
    // 0 ns, a volume reaching 8 m: about 69,000 bins from 0 m, 57,000 from the LOS
    // returns.
    let deep = text.replace("z = [0.3, 0.9]", "z = [0.3, 8.0]").replace(
        "[acquisition]\n",
        "[acquisition]\nbin-width-ps = 1\noffset-ns = 0.0\nbins = 65536\n",
    );
    assert_ne!(deep, text);
    let plan = dir.path().join("deep.toml");
    std::fs::write(&plan, &deep).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]).stdout;
    assert!(out.contains("warning: acquisition:"), "{out}");
    assert!(!out.contains("more than the 65536"), "{out}");
    let later = later(&out).unwrap_or_else(|| panic!("no later offset named:\n{out}"));
    let fixed = deep.replace("offset-ns = 0.0\nbins = 65536\n", &later);
    std::fs::write(&plan, &fixed).unwrap();
    let after = periscope(&["check", plan.to_str().unwrap()]).stdout;
    assert_eq!(verdicts(&after), all, "{fixed}{after}");

    // A volume whose paths (to 36.7 m) run past what the sync period holds (100 ns at
    // 10 MHz, 30 m): no window records them, and the bins that would (6,898 from
    // 12 ns, which `check` named until 2026-12-06) end past the period, which the plan
    // refuses. The warning names the least divider that holds them, with those bins,
    // and with both the check finds the paths recorded (until 2026-12-06 it said "a
    // larger tdc.sync-divider" without a number, whether any would do or not).
    let far = text.replace("z = [0.3, 0.9]", "z = [0.3, 16.0]");
    std::fs::write(&plan, &far).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]).stdout;
    assert!(
        out.contains("warning: acquisition:") && out.contains("past the 29.98 m a sync period holds"),
        "{out}"
    );
    let named = |key: &str| -> u32 {
        let at = out.rfind(key).unwrap_or_else(|| panic!("no {key}:\n{out}")) + key.len();
        out[at..]
            .chars()
            .take_while(char::is_ascii_digit)
            .collect::<String>()
            .parse()
            .unwrap()
    };
    let (divider, bins) = (named("tdc.sync-divider "), named("acquisition.bins at least "));
    assert_eq!(divider, 2, "{out}");
    let past = far.replace("[acquisition]\n", &format!("[acquisition]\nbins = {bins}\n"));
    std::fs::write(&plan, &past).unwrap();
    let refused = periscope(&["check", plan.to_str().unwrap()]);
    assert_eq!(refused.code, Some(2), "{refused:?}");
    assert!(refused.stderr.contains("sync period"), "{}", refused.stderr);
    let sim = std::fs::read_to_string(repo_path("configs/instrument/sim.toml")).unwrap();
    let scenes = repo_path("configs/scenes");
    let divided = sim
        .replace("sync-divider = 1\n", &format!("sync-divider = {divider}\n"))
        .replace("\"../scenes", &format!("\"{}", scenes.display()));
    assert_ne!(divided, sim);
    let instrument = dir.path().join("divided.toml");
    std::fs::write(&instrument, divided).unwrap();
    let out = periscope(&[
        "check",
        plan.to_str().unwrap(),
        "--instrument",
        instrument.to_str().unwrap(),
    ]);
    assert_eq!(out.code, Some(0), "{out:?}");
    assert_eq!(verdicts(&out.stdout).1, "all recorded", "{}", out.stdout);
}

/// The later offset a window warning names (`or acquisition.offset-ns X and bins at
/// least N`, or alone where the plan's offset would need too many bins), as
/// [acquisition] lines.
fn later(out: &str) -> Option<String> {
    out.match_indices("acquisition.offset-ns ").find_map(|(at, key)| {
        let rest = &out[at + key.len()..];
        let offset: String = rest
            .chars()
            .take_while(|c| c.is_ascii_digit() || *c == '.')
            .collect();
        let rest = rest[offset.len()..].strip_prefix(" and bins at least ")?;
        let bins: String = rest.chars().take_while(char::is_ascii_digit).collect();
        Some(format!("offset-ns = {offset}\nbins = {bins}\n"))
    })
}

/// The LOS scan moves the SPAD arm over its whole grid with the laser on: a scan past
/// the arm's limits is refused with the plan, naming both keys, not when the run reaches
/// that corner.
/// A fixed laser aimed away from the relay: `check` names a target past the laser
/// arm's limits, and a run whose target the arm reaches but no relay point lies near
/// fails at planning, naming `pairs.laser`, before anything is measured. Until
/// 2026-12-06 both passed: the relay point nearest, 70 m away, was lit.
#[test]
fn a_fixed_laser_aimed_away_from_the_relay_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/wall-letter-fixed-laser.toml")).unwrap();
    let far = text.replace("laser = [0.05, 0.05, 0.0]", "laser = [50.0, 50.0, 0.0]");
    assert_ne!(far, text);
    let plan = dir.path().join("far.toml");
    std::fs::write(&plan, far).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]);
    assert!(
        out.stdout.contains("pairs.laser") && out.stdout.contains("outside the laser arm's limits"),
        "{out:?}"
    );
    // In front of the wall, 30 cm off it: within the arm's reach, near no relay point.
    let off = text.replace("laser = [0.05, 0.05, 0.0]", "laser = [0.05, 0.05, 0.3]");
    let plan = dir.path().join("off.toml");
    std::fs::write(&plan, off).unwrap();
    let run = dir.path().join("run");
    let out = periscope(&["run", plan.to_str().unwrap(), "--out", run.to_str().unwrap()]);
    assert_ne!(out.code, Some(0), "{out:?}");
    assert!(
        out.stderr.contains("pairs.laser") && out.stderr.contains("from the nearest relay point"),
        "{}",
        out.stderr
    );
    assert!(
        !run.join("histograms.bin").exists()
            || std::fs::metadata(run.join("histograms.bin")).unwrap().len() == 0
    );
}

/// A direct LCT of confocal pairs on the S-shaped panel would measure every pair and
/// then fail (no plane fits the pairs within LCT's grid tolerance): the run fails once
/// the pairs are planned on the relay the LOS scan found, before the first is
/// measured, naming the method and the solver's reason, with exit code 2. Until
/// 2026-12-08 only the reconstruction found it, after the whole capture.
#[test]
fn a_direct_solver_that_cannot_take_the_planned_pairs_is_refused_before_the_capture() {
    let dir = tempfile::tempdir().unwrap();
    let plan = dir.path().join("lct.toml");
    let text = periscope_tests::SmallPlan::named("lct-on-s")
        .set("recon.method", "lct")
        .set("pairs.offset-mm", 0.0)
        .toml();
    std::fs::write(&plan, text).unwrap();
    let run = dir.path().join("run");
    let instrument = repo_path("configs/instrument/sim-s-wall-letter.toml");
    let out = periscope(&[
        "run",
        plan.to_str().unwrap(),
        "--instrument",
        instrument.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
    ]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr
            .contains("recon.method = \"lct\" cannot reconstruct the")
            && out
                .stderr
                .contains("pairs planned on the relay the LOS scan found")
            && out.stderr.contains("not planar"),
        "{}",
        out.stderr
    );
    assert!(
        !run.join("histograms.bin").exists()
            || std::fs::metadata(run.join("histograms.bin")).unwrap().len() == 0,
        "no pair was measured"
    );
    // The same plan on the flat wall runs.
    let flat = dir.path().join("flat");
    let out = periscope(&["run", plan.to_str().unwrap(), "--out", flat.to_str().unwrap()]);
    assert_eq!(out.code, Some(0), "{out:?}");
}

#[test]
fn check_refuses_an_los_scan_past_the_spad_arms_limits() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let wide = text.replace(
        "x = [-12.0, 12.0], y = [-12.0, 12.0]",
        "x = [-30.0, 12.0], y = [-12.0, 12.0]",
    );
    assert_ne!(wide, text);
    let plan = dir.path().join("wide.toml");
    std::fs::write(&plan, wide).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr.contains("los.angles-deg.x")
            && out.stderr.contains("[-20.00, 20.00]")
            && out.stderr.contains("galvo.spad.angle-limits-deg"),
        "{}",
        out.stderr
    );
}

#[test]
fn a_broken_plan_names_file_line_and_key() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    for (from, to, key) in [
        ("mode = \"confocal\"", "mode = \"spiral\"", "pairs.mode"),
        ("dwell-ms = 20.0", "dwell-ms = -1.0", "acquisition.dwell-ms"),
        (
            "shape = [64, 64, 128]",
            "shape = [64, 64, 1]",
            "recon.volume.shape",
        ),
        ("neighbours = 16", "neighbours = 2", "relay.neighbours"),
        // A hair-thin axis no solver can step through.
        ("z = [0.3, 0.9]", "z = [0.3, 0.3000001]", "recon.volume.z"),
        ("grid = [32, 32]", "grid = [3, 3]", "los.grid"),
        // A control character would break every YAML reader of the run's export.
        ("name = \"demo\"", "name = \"demo\\u0007bell\"", "name"),
        // A key the mode does not read does nothing: refused, naming it.
        (
            "grid = [24, 24]",
            "grid = [24, 24]\nlaser = [0.0, 0.0, 0.0]",
            "pairs.laser",
        ),
        ("grid = [24, 24]", "grid = [24, 24]\nseed = 5", "pairs.seed"),
        // Counters time in whole microseconds and place windows in whole picoseconds
        // (these were rounded and cut where the histogram said otherwise).
        ("dwell-ms = 20.0", "dwell-ms = 20.0005", "acquisition.dwell-ms"),
        (
            "dwell-ms = 20.0",
            "dwell-ms = 20.0\noffset-ns = 12.3456",
            "acquisition.offset-ns",
        ),
        // 3D-GTR fits a plane to the detection points: two never make one.
        ("grid = [24, 24]", "grid = [2, 1]", "pairs.mode"),
        // More pairs than a run's pairs.json may hold and be read back (4 Mi): until
        // 2026-12-07 the capture ran, and its data could not be resumed or exported.
        (
            "mode = \"confocal\"\ngrid = [24, 24]\noffset-mm = 5.0",
            "mode = \"scanned\"\nlaser-grid = [64, 64]\ngrid = [32, 32]",
            "pairs.grid",
        ),
    ] {
        let bad = dir.path().join("bad.toml");
        std::fs::write(&bad, text.replace(from, to)).unwrap();
        let out = periscope(&["check", bad.to_str().unwrap()]);
        assert_eq!(out.code, Some(2), "{key}: {out:?}");
        assert!(
            out.stderr.contains("bad.toml:") && out.stderr.contains(key),
            "{key}: {}",
            out.stderr
        );
    }
}

/// `periscope check` on an adaptive plan: the candidates, the budget and its batches,
/// and the range of durations when the stopping rule can end it early.
#[test]
fn check_describes_an_adaptive_capture_and_its_range_of_durations() {
    let out = periscope(&["check", "configs/plans/demo-adaptive.toml"]);
    assert_eq!(out.code, Some(0), "{out:?}");
    assert!(
        out.stdout.contains("adaptive, at most 288 of the confocal 24×24")
            && out
                .stdout
                .contains("72 spread over them first, then batches of 18"),
        "{}",
        out.stdout
    );
    let capture = |stdout: &str| -> String {
        let line = stdout.lines().find(|l| l.contains("estimated duration")).unwrap();
        line.split("capture ")
            .nth(1)
            .unwrap()
            .split(" s,")
            .next()
            .unwrap()
            .to_owned()
    };
    assert!(!capture(&out.stdout).contains(" to "), "{}", out.stdout);
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo-adaptive.toml")).unwrap();
    let stopping = text.replace("# stop-gain = 0.05", "stop-gain = 0.05");
    assert_ne!(stopping, text);
    let plan = dir.path().join("stopping.toml");
    std::fs::write(&plan, stopping).unwrap();
    let out = periscope(&["check", plan.to_str().unwrap()]);
    assert_eq!(out.code, Some(0), "{out:?}");
    let range = capture(&out.stdout);
    let (lo, hi) = range
        .split_once(" to ")
        .unwrap_or_else(|| panic!("no range: {}", out.stdout));
    assert!(lo.parse::<f64>().unwrap() < hi.parse::<f64>().unwrap(), "{range}");
    assert!(out.stdout.contains("ending early"), "{}", out.stdout);
}

#[test]
fn a_broken_adaptive_plan_names_the_key_and_what_to_do() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo-adaptive.toml")).unwrap();
    for (from, to, key, hint) in [
        ("candidates = \"confocal\"", "", "pairs.candidates", "is required"),
        (
            "candidates = \"confocal\"",
            "candidates = \"adaptive\"",
            "pairs.candidates",
            "planner",
        ),
        (
            "method = \"gtr\"",
            "method = \"fbp\"",
            "pairs.mode",
            "recon.method = \"gtr\"",
        ),
        (
            "pairs = 288",
            "pairs = 288\nstop-gain = 2.0",
            "recon.adaptive.stop-gain",
            "0 to 1",
        ),
        (
            "pairs = 288",
            "pairs = 10\nfirst = 20",
            "recon.adaptive.first",
            "budget",
        ),
        // An unknown planner is the `candidates` key's fault, not the mode's.
        (
            "candidates = \"confocal\"",
            "candidates = \"bogus\"",
            "pairs.candidates",
            "is not a mode",
        ),
        (
            "grid = [24, 24]",
            "grid = [24, 24]\ncount = 5",
            "pairs.count",
            "is not read by candidates `confocal`",
        ),
    ] {
        let bad = dir.path().join("bad.toml");
        let changed = text.replacen(from, to, 1);
        assert_ne!(changed, text, "{key}");
        std::fs::write(&bad, changed).unwrap();
        let out = periscope(&["check", bad.to_str().unwrap()]);
        assert_eq!(out.code, Some(2), "{key}: {out:?}");
        assert!(
            out.stderr.contains("bad.toml:") && out.stderr.contains(key) && out.stderr.contains(hint),
            "{key}: {}",
            out.stderr
        );
    }
    // `candidates` belongs to the adaptive mode only.
    let demo = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        demo.replacen("grid = [24, 24]", "grid = [24, 24]\ncandidates = \"confocal\"", 1),
    )
    .unwrap();
    let out = periscope(&["check", bad.to_str().unwrap()]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(
        out.stderr.contains("pairs.candidates") && out.stderr.contains("only for mode"),
        "{}",
        out.stderr
    );
}

/// `periscope check PLAN`'s line with the estimated duration.
fn estimated_duration(plan: &std::path::Path) -> String {
    let out = periscope(&["check", plan.to_str().unwrap()]);
    assert_eq!(out.code, Some(0), "{out:?}");
    out.stdout
        .lines()
        .find(|l| l.contains("estimated duration"))
        .expect("a duration line")
        .to_owned()
}

/// The seconds in `line` right after `after`.
fn seconds_after(line: &str, after: &str) -> f64 {
    line.split(after)
        .nth(1)
        .unwrap()
        .split(" s")
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// `periscope check` counts the fit's rounds of gain estimation where they will run: a
/// scanned laser without the relay scan's albedo (`pair-gains = "auto"`, the default),
/// or gains asked for; not where the scan gives them or the plan turns them off.
#[test]
fn check_counts_the_gain_rounds_where_the_fit_estimates_gains() {
    let dir = tempfile::tempdir().unwrap();
    // 4,096 pairs, so that the rounds' seconds show in whole seconds.
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml"))
        .unwrap()
        .replacen("grid = [24, 24]", "grid = [64, 64]", 1);
    let reconstruction = |name: &str, text: &str| -> f64 {
        let plan = dir.path().join(name);
        std::fs::write(&plan, text).unwrap();
        seconds_after(&estimated_duration(&plan), "reconstruction ")
    };
    let no_scan = text.replacen("[relay]\n", "[relay]\nalbedo-from-scan = false\n", 1);
    assert_ne!(no_scan, text);
    let scanned = reconstruction("demo.toml", &text);
    let estimated = reconstruction("no-scan.toml", &no_scan);
    let off = reconstruction(
        "off.toml",
        &no_scan.replacen("[recon.gtr]\n", "[recon.gtr]\npair-gains = \"none\"\n", 1),
    );
    let asked = reconstruction(
        "asked.toml",
        &text.replacen("[recon.gtr]\n", "[recon.gtr]\npair-gains = \"illumination\"\n", 1),
    );
    assert!(estimated > scanned, "{estimated} s against {scanned} s");
    assert_eq!(off, scanned);
    assert_eq!(asked, estimated);
}

/// `periscope check` counts the averaged epochs' smaller batches: a plan that leaves
/// `epochs` to the step floor (half the batch there by default) is told less time than
/// the same plan with `average-batch` at the batch, and the same as one that sets half.
#[test]
fn check_counts_the_averaged_epochs_smaller_batches() {
    let dir = tempfile::tempdir().unwrap();
    // 4,096 pairs, so that a sixth of the fit shows in whole seconds.
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml"))
        .unwrap()
        .replacen("grid = [24, 24]", "grid = [64, 64]", 1)
        .replacen("epochs = 16\n", "", 1);
    let reconstruction = |name: &str, text: &str| -> f64 {
        let plan = dir.path().join(name);
        std::fs::write(&plan, text).unwrap();
        seconds_after(&estimated_duration(&plan), "reconstruction ")
    };
    let with = |line: &str| text.replacen("[recon.gtr]\n", &format!("[recon.gtr]\n{line}\n"), 1);
    let default = reconstruction("default.toml", &text);
    let whole = reconstruction("whole.toml", &with("average-batch = 4"));
    let half = reconstruction("half.toml", &with("average-batch = 2"));
    assert!(default < whole, "{default} s against {whole} s");
    assert_eq!(default, half);
}

/// A plan that leaves `[gtr] batch` and `epochs` unset is told both reconstruction
/// times: the relay the scan finds decides whether the fit takes a coarse capture's
/// batches of 8, over the same steps.
#[test]
fn check_gives_a_coarse_captures_reconstruction_time_where_the_plan_leaves_the_batch_unset() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("configs/plans/demo.toml")).unwrap();
    let unset = text
        .replacen("batch = 4\n", "", 1)
        .replacen("epochs = 16\n", "", 1);
    assert_ne!(unset, text);
    let plan = dir.path().join("unset.toml");
    std::fs::write(&plan, unset).unwrap();
    let line = estimated_duration(&plan);
    assert!(line.contains("if the relay places points coarsely"), "{line}");
    let plain = seconds_after(&line, "reconstruction ");
    let coarse = seconds_after(&line, &format!("reconstruction {plain:.0} s ("));
    assert!(coarse > plain, "{line}");
    // The plan's own batch holds everywhere: one time.
    let out = periscope(&["check", "configs/plans/demo.toml"]);
    assert!(!out.stdout.contains("coarsely"), "{}", out.stdout);
}

/// A wavelength the plan sets whose envelope the solver would refuse (FBP's phasor
/// filter, RSD: at most 8 window lengths) is refused by `check` and submit, naming the
/// key, before anything is measured: until 2026-12-06 `periscope run` captured every
/// pair and then failed in the solver, naming a setting the plan did not hold by
/// that name. A simulator scene that cannot be built is refused by `check` too, as the
/// run would refuse it when it starts.
#[test]
fn check_refuses_what_the_run_would_refuse_after_the_capture() {
    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(repo_path("tests/data/plans/small-fbp.toml")).unwrap();
    for (table, value) in [
        ("[recon.fbp]", "wavelength = 30.0"),
        ("[recon.rsd]", "wavelength = 30.0"),
    ] {
        let plan = dir.path().join("long-wave.toml");
        let edited = text.replace(
            "method = \"fbp\"",
            if table == "[recon.rsd]" {
                "method = \"rsd\""
            } else {
                "method = \"fbp\""
            },
        );
        std::fs::write(&plan, format!("{edited}{table}\n{value}\n")).unwrap();
        let out = periscope(&["check", plan.to_str().unwrap()]);
        let key = format!("{}.wavelength", &table[1..table.len() - 1]);
        assert_eq!(out.code, Some(2), "{table}: {out:?}");
        assert!(
            out.stderr.contains(&key) && out.stderr.contains("envelope"),
            "{table}: {}",
            out.stderr
        );
        // A wavelength in range passes.
        std::fs::write(&plan, format!("{edited}{table}\nwavelength = 0.1\n")).unwrap();
        let out = periscope(&["check", plan.to_str().unwrap()]);
        assert_eq!(out.code, Some(0), "{table}: {out:?}");
    }
    // A scene whose letter is empty, through `check`.
    let scene = std::fs::read_to_string(repo_path("configs/scenes/wall-letter.toml")).unwrap();
    let broken = scene.replacen("text = \"", "text = \"\" # was \"", 1);
    assert_ne!(broken, scene, "no `text` in the demo scene");
    std::fs::write(dir.path().join("scene.toml"), broken).unwrap();
    let sim = std::fs::read_to_string(repo_path("configs/instrument/sim.toml")).unwrap();
    let instrument = dir.path().join("sim.toml");
    std::fs::write(
        &instrument,
        sim.replace("\"../scenes/wall-letter.toml\"", "\"scene.toml\""),
    )
    .unwrap();
    let out = periscope(&[
        "check",
        repo_path("configs/plans/demo.toml").to_str().unwrap(),
        "--instrument",
        instrument.to_str().unwrap(),
    ]);
    assert_eq!(out.code, Some(2), "{out:?}");
    assert!(out.stderr.contains("scene.toml"), "{}", out.stderr);
}

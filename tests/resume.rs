//! Crash safety: `kill -9` in the middle of a capture, a torn record at the end of the
//! histogram log, then `periscope resume`: every planned pair ends up stored exactly
//! once, the torn record is measured again, and the run completes with its outputs.
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_daemon::store::{HISTOGRAM_LOG, read_log};
use periscope_tests::{SmallPlan, periscope_bin, periscope_with_limit, repo_path, repo_root};

fn plan_toml() -> String {
    SmallPlan::named("resume-test")
        .set("los.grid", [16, 16])
        .set("relay.neighbours", 16)
        .set("pairs.grid", [12, 12])
        .set("acquisition.dwell-ms", 25.0)
        .set("recon.method", "gtr")
        .set("recon.gtr.primitives", 300)
        .set("recon.gtr.epochs", 2)
        .set("recon.gtr.virtual-grid", [32, 32])
        .toml()
}

/// The simulated instrument in real time (settling and dwell take their real
/// duration), so the capture lasts long enough to be killed in the middle.
fn realtime_instrument(dir: &Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(repo_path("configs/instrument/sim.toml")).unwrap();
    let scene = repo_path("configs/scenes/wall-letter.toml");
    let text = text.replace(
        "\"../scenes/wall-letter.toml\"",
        &format!("{:?}", scene.to_str().unwrap()),
    );
    assert!(text.trim_end().lines().any(|l| l.starts_with("[sim]")));
    let path = dir.join("instrument.toml");
    std::fs::write(&path, format!("{text}\ntime-scale = 1.0\n")).unwrap();
    path
}

#[test]
fn a_killed_capture_resumes_without_losing_or_repeating_a_pair() {
    let tmp = tempfile::tempdir().unwrap();
    let plan = tmp.path().join("plan.toml");
    std::fs::write(&plan, plan_toml()).unwrap();
    let instrument = realtime_instrument(tmp.path());
    let run = tmp.path().join("run");
    let mut child = Command::new(periscope_bin())
        .current_dir(repo_root())
        .args([
            "run",
            plan.to_str().unwrap(),
            "--instrument",
            instrument.to_str().unwrap(),
            "--out",
            run.to_str().unwrap(),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until some pairs are stored, then kill -9.
    let start = Instant::now();
    loop {
        let n = read_log(&run).map(|r| r.records.len()).unwrap_or(0);
        if n >= 20 {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "the capture never got going"
        );
        assert!(
            child.try_wait().unwrap().is_none(),
            "the run ended before it could be killed"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let before = read_log(&run).unwrap();
    let info = RunInfo::load(&run).unwrap();
    assert_eq!(info.state, RunState::Running, "a killed run still says running");
    let total = info.pairs_total;
    assert!(before.records.len() < total, "killed after the capture finished");
    // A torn write at the end: half a record.
    let log = run.join(HISTOGRAM_LOG);
    let mut bytes = std::fs::read(&log).unwrap();
    let torn = bytes[..bytes.len().min(1000)].to_vec();
    bytes.extend_from_slice(&torn[..torn.len() / 2]);
    std::fs::write(&log, &bytes).unwrap();
    eprintln!(
        "killed with {} of {total} pairs stored; appended a torn record ({} bytes read as damaged)",
        before.records.len(),
        read_log(&run).unwrap().discarded_bytes
    );

    let done = periscope_with_limit(&["resume", run.to_str().unwrap()], Duration::from_secs(300));
    assert_eq!(
        done.code,
        Some(0),
        "resume failed:\n{}\n{}",
        done.stdout,
        done.stderr
    );
    let after = read_log(&run).unwrap();
    eprintln!(
        "resumed: {} records in the log, {} of them captured by the resume\n{}",
        after.records.len(),
        after.records.len() - before.records.len(),
        done.stdout
            .lines()
            .filter(|l| !l.trim().is_empty())
            .take(12)
            .collect::<Vec<_>>()
            .join("\n")
    );
    assert_eq!(after.discarded_bytes, 0, "the torn tail was cut");
    let mut pairs: Vec<u32> = after.records.iter().map(|r| r.pair).collect();
    assert_eq!(pairs.len(), total, "every pair stored");
    pairs.sort_unstable();
    pairs.dedup();
    assert_eq!(pairs.len(), total, "no pair stored twice");
    assert_eq!(pairs, (0..total as u32).collect::<Vec<_>>());
    // The records stored before the kill are untouched.
    for (a, b) in before.records.iter().zip(&after.records) {
        assert_eq!(a, b);
    }
    assert_eq!(RunInfo::load(&run).unwrap().state, RunState::Completed);
    for f in ["volume.npy", "depth.png", "gaussians.ply"] {
        assert!(run.join(f).is_file(), "{f}");
    }
    // A completed run is not resumed again.
    let again = periscope_with_limit(&["resume", run.to_str().unwrap()], Duration::from_secs(30));
    assert_eq!(again.code, Some(1));
    assert!(again.stderr.contains("already complete"), "{}", again.stderr);
}

//! What the daemon's test files share: the simulated instrument with its runs in a
//! temporary directory, requests into the router without a socket, and the small
//! capture plan the end-to-end tests share too ([`SmallPlan`]). Each test file uses
//! part of it.
#![allow(dead_code)]

use std::path::Path;

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use periscope_daemon::config::TomlSource;
use tower::ServiceExt;

// One copy for both crates: the end-to-end crate exports it, these tests include it.
#[allow(unreachable_pub)]
#[path = "../../../tests/support/plan.rs"]
mod small_plan;
#[allow(unused_imports)] // like the rest of this module, not every test file uses it
pub(crate) use small_plan::SmallPlan;

#[allow(unreachable_pub)]
#[path = "../../../tests/support/skip.rs"]
mod skip;
#[allow(unused_imports)]
pub(crate) use skip::skipped;

/// A runtime of two workers whose blocking pool has one thread, for tests that take it
/// ([`take_the_blocking_pool`]), as requests timed out while their blocking work goes
/// on (an export, a stalled disk) can.
pub(crate) fn one_blocking_thread() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .max_blocking_threads(1)
        .enable_all()
        .build()
        .unwrap()
}

/// Takes the blocking pool's thread for `hold`; returns once it is taken.
pub(crate) fn take_the_blocking_pool(hold: std::time::Duration) -> tokio::task::JoinHandle<()> {
    let (taken_tx, taken) = std::sync::mpsc::channel();
    let hog = tokio::task::spawn_blocking(move || {
        taken_tx.send(()).unwrap();
        std::thread::sleep(hold);
    });
    taken.recv().unwrap();
    hog
}

/// Whether the caller, the test `name` of this test binary, is to run its body here:
/// true in a process of the binary running that test alone, which this starts (and
/// whose failure fails the caller) when called from the harness's own process, where
/// it returns false. A whole-process figure (memory, open files) then counts this test
/// alone, not the others the harness runs beside it on other threads.
pub(crate) fn in_own_process(name: &str) -> bool {
    const ALONE: &str = "PERISCOPE_TEST_ALONE";
    if std::env::var_os(ALONE).is_some_and(|n| n == name) {
        return true;
    }
    let out = std::process::Command::new(std::env::current_exe().expect("the test binary's path"))
        .args([name, "--exact", "--nocapture", "--test-threads=1"])
        .env(ALONE, name)
        .output()
        .expect("the test binary runs again");
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(
        out.status.success() && stdout.contains("1 passed"),
        "{name}, in a process of its own, failed ({}):\n{stdout}\n{stderr}",
        out.status
    );
    eprint!("{stderr}");
    false
}

/// Runs `body`, the test `name`, in a process of its own ([`in_own_process`]) on a
/// tokio runtime of `threads` workers (0: one current-thread runtime, as
/// `#[tokio::test]`). For a whole-process figure, and for a test that drops a daemon
/// or a catalogue and takes its `flock` again at once: a child process another test
/// starts shares the lock from its fork until it executes its program, and the second
/// take found it held.
pub(crate) fn alone(name: &str, threads: usize, body: impl std::future::Future<Output = ()>) {
    if in_own_process(name) {
        let mut rt = if threads == 0 {
            tokio::runtime::Builder::new_current_thread()
        } else {
            tokio::runtime::Builder::new_multi_thread()
        };
        if threads > 0 {
            rt.worker_threads(threads);
        }
        rt.enable_all().build().unwrap().block_on(body);
    }
}

/// The run at `dir` ended aborted by `by`, keeping the error (naming `error`) that
/// stopped it as the abort came, and `control` has taken its stop: a later abort is
/// the caller's to apply to the stored run.
pub(crate) fn assert_aborted_keeping_error(
    dir: &Path,
    control: &periscope_daemon::pipeline::Control,
    by: &str,
    error: &str,
) {
    use periscope_daemon::run_dir::{RunInfo, RunState};
    let info = RunInfo::load(dir).unwrap();
    assert_eq!(info.state, RunState::Aborted, "{:?}", info.error);
    let last = info.history.last().unwrap();
    assert_eq!((last.state, last.by.as_deref()), (RunState::Aborted, Some(by)));
    assert!(
        info.error.as_deref().is_some_and(|e| e.contains(error)),
        "{:?}",
        info.error
    );
    assert!(control.stop_taken() && !control.abort_by("carol"));
}

/// The shipped simulated instrument (`configs/instrument/sim.toml`) at `time_scale`,
/// with its runs in `runs`, `api_lines` added to its `[api]` table and `tail` after it.
pub(crate) fn sim_instrument(runs: &Path, time_scale: f64, api_lines: &str, tail: &str) -> TomlSource {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let path = root.join("configs/instrument/sim.toml");
    let mut text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[sim]\n", &format!("[sim]\ntime-scale = {time_scale}\n"));
    text.push_str(&format!(
        "\n[api]\nruns-dir = \"{}\"\n{api_lines}\n{tail}",
        runs.display()
    ));
    TomlSource::from_text(path, text)
}

/// A request with an optional bearer token, extra headers and a TOML body (if any).
pub(crate) fn request(
    method: Method,
    uri: &str,
    bearer: Option<&str>,
    headers: &[(&str, &str)],
    body: &str,
) -> Request<Body> {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(t) = bearer {
        req = req.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    if !body.is_empty() {
        req = req.header(header::CONTENT_TYPE, "application/toml");
    }
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    req.body(Body::from(body.to_owned())).unwrap()
}

/// Sends `req` through the router; the status and the body's bytes.
pub(crate) async fn send(router: &axum::Router, req: Request<Body>) -> (StatusCode, Vec<u8>) {
    let resp = router.clone().oneshot(req).await.unwrap();
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), 64 << 20).await.unwrap();
    (status, bytes.to_vec())
}

/// How far the peak of the `volume.npy` in `out` (a run's or `periscope recon`'s
/// outputs, with its `volume.json`) lies from `target`, metres, and the distance
/// allowed: 1.5 voxels (the largest edge) or 1.5 cm, whichever is more.
pub(crate) fn peak_error(out: &Path, target: [f64; 3]) -> (f64, f64) {
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

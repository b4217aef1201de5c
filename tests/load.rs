//! The daemon under load and hostile peers: `periscope serve` (the binary, in a child
//! process whose descriptor limit is set low) runs a real-time simulated capture while
//! the test floods it with unauthenticated reads, holds idle and trickling connections
//! past its descriptor limit, sends concurrent 1 MiB plan checks, and uploads capture
//! files to `POST /imports` back to back. The capture's pair
//! rate in each phase must stay within 10 % of the unloaded rate measured just before,
//! the laser's watchdog must never trip for want of progress, and the daemon's memory
//! must stay bounded.
//!
//! The load generators run in this process on the same two cores as the daemon; they
//! stand for clients on other hosts, whose work costs the instrument's PC nothing, so
//! their threads run at nice 10 ([`client_thread`]). What is measured is what the
//! daemon's handling of their requests costs the capture.
//!
//! A laser whose keepalive stops for want of progress trips its watchdog, which the
//! run notices as the laser going off under it: the run pauses. So the run still
//! capturing at the end, with no error recorded, is the proof the watchdog never
//! tripped. The pair rate is read from the run's histogram log on disk, not through the
//! API under load. Every loop is bounded in count and time; all traffic stays on
//! loopback.
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use periscope_daemon::run_dir::{RunInfo, RunState};
use periscope_tests::{SmallPlan, periscope_bin, repo_root};

const TOKEN: &str = "load-test-token-0123456789abcdef";

/// The child's soft limit on open files.
const NOFILE: usize = 256;

/// `[api] header-timeout-s` in the child.
const HEADER_TIMEOUT: Duration = Duration::from_secs(2);

/// How long each phase's pair rate is measured.
const WINDOW: Duration = Duration::from_secs(3);

/// The fraction of the unloaded pair rate each loaded phase must keep.
const KEEP: f64 = 0.9;

/// A capture of up to 48 × 48 pairs of 30 ms on a relay scanned finely enough to hold
/// them: most of a minute in real time, long enough for every phase.
fn plan_toml() -> String {
    SmallPlan::named("load")
        .set("los.grid", [64, 64])
        .set("pairs.grid", [48, 48])
        .set("acquisition.dwell-ms", 30.0)
        .toml()
}

struct Daemon {
    child: Child,
    addr: SocketAddr,
    runs: PathBuf,
    _dir: tempfile::TempDir,
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `periscope serve` on the simulated instrument at real time, with 100 finished runs
/// in its runs directory (what a lab's daemon lists).
fn daemon() -> Daemon {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs");
    for i in 0..100 {
        let run = runs.join(format!("20260101-0000{i:02}-old"));
        std::fs::create_dir_all(&run).unwrap();
        RunInfo {
            id: format!("20260101-0000{i:02}-old"),
            plan: "old".into(),
            state: RunState::Completed,
            stage: "done".into(),
            instrument_path: PathBuf::from("instrument.toml"),
            pairs_total: 64,
            pairs_done: 64,
            error: None,
            timings: vec![("capture".into(), 1.0)],
            created_unix_s: None,
            submitted_by: None,
            again_of: None,
            import: None,
            history: Vec::new(),
            adaptive_seconds: 0.0,
            adaptive_stopped: None,
            adaptive_batches: 0,
            acting: None,
        }
        .save(&run)
        .unwrap();
    }
    let text = periscope_tests::real_time_sim_instrument();
    let path = dir.path().join("instrument.toml");
    let api = format!(
        "\n[api]\nruns-dir = {:?}\ntoken = {TOKEN:?}\nheader-timeout-s = {}\n",
        runs.to_str().unwrap(),
        HEADER_TIMEOUT.as_secs_f64()
    );
    std::fs::write(&path, format!("{text}{api}")).unwrap();
    let script = format!(
        "ulimit -n {NOFILE} && exec {:?} serve --bind 127.0.0.1:0 --instrument {:?}",
        periscope_bin(),
        path
    );
    let mut child = Command::new("sh")
        .args(["-c", &script])
        .current_dir(repo_root())
        .env("RUST_LOG", "warn")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("sh starts periscope serve");
    // The daemon names its address on stderr; the rest of stderr is drained so the
    // child never blocks on a full pipe.
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = child.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            if let Some(rest) = line.split("http://").nth(1)
                && line.contains("dashboard on")
            {
                let addr = rest.split('/').next().unwrap_or("").to_owned();
                let _ = tx.send(addr);
            } else {
                eprintln!("daemon: {line}");
            }
        }
    });
    let addr = rx
        .recv_timeout(Duration::from_secs(60))
        .expect("periscope serve names its address")
        .parse()
        .unwrap();
    Daemon {
        child,
        addr,
        runs,
        _dir: dir,
    }
}

/// One HTTP/1.1 request on a fresh connection; the status (0 when the connection
/// failed or closed without an answer) and the body.
fn request(addr: SocketAddr, method: &str, path: &str, token: bool, body: &str) -> (u16, String) {
    let Ok(mut s) = TcpStream::connect_timeout(&addr, Duration::from_secs(5)) else {
        return (0, String::new());
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(60)));
    let auth = if token {
        format!("Authorization: Bearer {TOKEN}\r\n")
    } else {
        String::new()
    };
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n{auth}\
         Content-Type: application/toml\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    if s.write_all(head.as_bytes())
        .and_then(|()| s.write_all(body.as_bytes()))
        .is_err()
    {
        return (0, String::new());
    }
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    let text = String::from_utf8_lossy(&out).into_owned();
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b).to_owned();
    (status, body)
}

/// Uploads `bytes` of zeros as a capture file (`big.mat`) to `POST /imports`, calling
/// `tick` after each MiB sent; the answer's status.
fn upload(addr: SocketAddr, bytes: usize, tick: &dyn Fn()) -> u16 {
    let Ok(mut s) = TcpStream::connect_timeout(&addr, Duration::from_secs(5)) else {
        return 0;
    };
    let _ = s.set_read_timeout(Some(Duration::from_secs(60)));
    let boundary = "load-test-boundary";
    let head = format!(
        "--{boundary}\r\nContent-Disposition: form-data; name=\"capture\"; filename=\"big.mat\"\r\n\r\n"
    );
    let tail = format!("\r\n--{boundary}--\r\n");
    let request = format!(
        "POST /api/v1/imports HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\
         Authorization: Bearer {TOKEN}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\n\
         Content-Length: {}\r\n\r\n{head}",
        head.len() + bytes + tail.len()
    );
    if s.write_all(request.as_bytes()).is_err() {
        return 0;
    }
    let chunk = vec![0u8; 1 << 20];
    for _ in 0..bytes >> 20 {
        if s.write_all(&chunk).is_err() {
            return 0;
        }
        tick();
    }
    if s.write_all(tail.as_bytes()).is_err() {
        return 0;
    }
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out);
    String::from_utf8_lossy(&out)
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

/// Pairs stored so far by run `id`, from its histogram log.
fn pairs(runs: &Path, id: &str) -> usize {
    periscope_daemon::store::read_log(&runs.join(id)).map_or(0, |r| r.records.len())
}

/// Pairs per second over the next [`WINDOW`].
fn rate(runs: &Path, id: &str) -> f64 {
    let (t0, n0) = (Instant::now(), pairs(runs, id));
    std::thread::sleep(WINDOW);
    (pairs(runs, id) - n0) as f64 / t0.elapsed().as_secs_f64()
}

/// The child's resident memory, bytes.
fn rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb << 10)
}

/// A load-generating thread: at nice 10, as a client on another host would cost this
/// machine nothing (see the module docs).
fn client_thread<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> std::thread::JoinHandle<T> {
    std::thread::spawn(move || {
        let _ = periscope_daemon::priority::lower_current_thread(10);
        f()
    })
}

/// Runs `load` on `threads` threads until `stop` is set; returns the answers by status.
fn in_background(
    threads: usize,
    stop: &Arc<AtomicBool>,
    load: impl Fn() -> u16 + Send + Sync + 'static,
) -> Vec<std::thread::JoinHandle<Vec<u16>>> {
    let load = Arc::new(load);
    (0..threads)
        .map(|_| {
            let (stop, load) = (Arc::clone(stop), Arc::clone(&load));
            client_thread(move || {
                let mut got = Vec::new();
                // Bounded: at most 10,000 requests a thread, and the phase's deadline.
                while !stop.load(Ordering::Relaxed) && got.len() < 10_000 {
                    got.push(load());
                }
                got
            })
        })
        .collect()
}

fn finish(stop: &Arc<AtomicBool>, handles: Vec<std::thread::JoinHandle<Vec<u16>>>) -> Vec<u16> {
    stop.store(true, Ordering::Relaxed);
    handles.into_iter().flat_map(|h| h.join().unwrap()).collect()
}

fn count(answers: &[u16], status: u16) -> usize {
    answers.iter().filter(|&&s| s == status).count()
}

#[test]
fn a_capture_keeps_its_pace_under_read_floods_idle_connections_and_concurrent_checks() {
    if !cfg!(target_os = "linux") {
        periscope_tests::skipped(format_args!(
            "the load suite: it reads /proc and sets the child's limits with sh"
        ));
        return;
    }
    let d = daemon();
    let addr = d.addr;
    let (s, body) = request(addr, "POST", "/api/v1/runs", true, &plan_toml());
    assert_eq!(s, 201, "{body}");
    let id = serde_json::from_str::<serde_json::Value>(&body).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    // The capture under way.
    let start = Instant::now();
    while pairs(&d.runs, &id) < 20 {
        assert!(
            start.elapsed() < Duration::from_secs(120),
            "the capture never started"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let pid = d.child.id();
    let mut report = Vec::new();
    let runs = d.runs.clone();
    let run_id = id.clone();
    let check_rate = move |name: &str, loaded: f64, quiet: f64, report: &mut Vec<String>| {
        report.push(format!("{name}: {loaded:.1} pairs/s (unloaded {quiet:.1})"));
        let info = RunInfo::load(&runs.join(&run_id)).unwrap();
        assert!(
            info.state == RunState::Running && info.stage == "capture",
            "the capture was no longer running after {name} ({:?}, {}, {} of {} pairs): \
             the plan is too short for the suite\n{}",
            info.state,
            info.stage,
            info.pairs_done,
            info.pairs_total,
            report.join("\n")
        );
        assert!(
            loaded >= KEEP * quiet,
            "{name} slowed the capture: {loaded:.1} against {quiet:.1} pairs/s\n{}",
            report.join("\n")
        );
    };

    // 1. A flood of unauthenticated reads: 128 clients listing 101 runs as fast as
    //    they can.
    let quiet = rate(&d.runs, &id);
    let stop = Arc::new(AtomicBool::new(false));
    let flood = in_background(128, &stop, move || {
        request(addr, "GET", "/api/v1/runs", false, "").0
    });
    std::thread::sleep(Duration::from_millis(500));
    let loaded = rate(&d.runs, &id);
    let answers = finish(&stop, flood);
    report.push(format!(
        "read flood: {} requests, {} answered 200, {} others",
        answers.len(),
        count(&answers, 200),
        answers.len() - count(&answers, 200)
    ));
    check_rate("read flood", loaded, quiet, &mut report);
    assert!(count(&answers, 200) > 100, "{}", report.join("\n"));

    // 2. Idle connections past the descriptor limit, and clients trickling a header
    //    line at a time: the capture keeps its pace, the server closes them after the
    //    header timeout, and a new client is answered.
    let quiet = rate(&d.runs, &id);
    let t_idle = Instant::now();
    // Opened from another thread: past the server's cap they wait in the kernel's
    // backlog, and past that a connect waits for its timeout.
    let opener = client_thread(move || {
        let deadline = Instant::now() + Duration::from_secs(4);
        let mut held = Vec::new();
        while held.len() < 2 * NOFILE && Instant::now() < deadline {
            if let Ok(s) = TcpStream::connect_timeout(&addr, Duration::from_millis(100)) {
                held.push(s);
            }
        }
        held
    });
    let stop = Arc::new(AtomicBool::new(false));
    let trickled = Arc::new(AtomicUsize::new(0));
    let trickle = {
        let trickled = Arc::clone(&trickled);
        in_background(5, &stop, move || {
            let Ok(mut s) = TcpStream::connect(addr) else {
                return 0;
            };
            let _ = s.write_all(b"GET /api/v1/runs HTTP/1.1\r\nHost: 127.0.0.1\r\n");
            for i in 0..100 {
                std::thread::sleep(Duration::from_millis(500));
                if s.write_all(format!("X-Trickle-{i}: 1\r\n").as_bytes()).is_err() {
                    trickled.fetch_add(1, Ordering::Relaxed);
                    return 1;
                }
            }
            0
        })
    };
    std::thread::sleep(Duration::from_millis(500));
    let loaded = rate(&d.runs, &id);
    check_rate("idle and trickling connections", loaded, quiet, &mut report);
    // The server closes every idle connection: those it holds after the header
    // timeout, then those waiting in the backlog as their turn comes (the cap is
    // NOFILE less the reserve, so two rounds and a half).
    let mut idle = opener.join().unwrap();
    let opened = idle.len();
    let rounds = opened.div_ceil(NOFILE - 64) as u32 + 2;
    std::thread::sleep((t_idle + HEADER_TIMEOUT * rounds).saturating_duration_since(Instant::now()));
    let mut closed = 0;
    for s in &mut idle {
        let _ = s.set_read_timeout(Some(Duration::from_millis(20)));
        let mut b = [0u8; 1];
        match s.read(&mut b) {
            Ok(0) => closed += 1,
            Err(e)
                if e.kind() != std::io::ErrorKind::WouldBlock && e.kind() != std::io::ErrorKind::TimedOut =>
            {
                closed += 1
            }
            _ => {}
        }
    }
    drop(idle);
    let (health, _) = request(addr, "GET", "/api/v1/health", false, "");
    let waited = t_idle.elapsed();
    let trickle_answers = finish(&stop, trickle);
    report.push(format!(
        "idle: {opened} connections opened, {closed} closed by the server, health {health} after {:.1} s; \
         {} trickling clients cut off",
        waited.as_secs_f64(),
        trickled.load(Ordering::Relaxed).max(count(&trickle_answers, 1))
    ));
    assert_eq!(health, 200, "{}", report.join("\n"));
    assert_eq!(
        closed,
        opened,
        "idle connections left open\n{}",
        report.join("\n")
    );
    assert!(
        trickled.load(Ordering::Relaxed) >= 1,
        "a trickling client was never cut off\n{}",
        report.join("\n")
    );

    // 3. Concurrent checks of 1 MiB plans (no token needed on loopback): bounded
    //    memory, the capture's pace kept.
    let quiet = rate(&d.runs, &id);
    let rss_before = rss(pid);
    let big = format!(
        "{}\n[extra]\nnumbers = [{}0]\n",
        plan_toml(),
        "0,".repeat(500_000)
    );
    let big = Arc::new(big);
    let stop = Arc::new(AtomicBool::new(false));
    let peak = Arc::new(AtomicUsize::new(0));
    let checks = {
        let (big, peak) = (Arc::clone(&big), Arc::clone(&peak));
        in_background(32, &stop, move || {
            let s = request(addr, "POST", "/api/v1/check", false, &big).0;
            peak.fetch_max(rss(pid) as usize, Ordering::Relaxed);
            s
        })
    };
    std::thread::sleep(Duration::from_millis(500));
    let loaded = rate(&d.runs, &id);
    let answers = finish(&stop, checks);
    let rss_after = rss(pid);
    report.push(format!(
        "checks: {} answered ({} with 422), RSS {:.0} MiB before, {:.0} MiB peak, {:.0} MiB after",
        answers.len(),
        count(&answers, 422),
        rss_before as f64 / 1048576.0,
        peak.load(Ordering::Relaxed) as f64 / 1048576.0,
        rss_after as f64 / 1048576.0
    ));
    check_rate("concurrent checks", loaded, quiet, &mut report);
    assert!(
        (peak.load(Ordering::Relaxed) as u64) < rss_before + (512 << 20),
        "the checks held too much memory\n{}",
        report.join("\n")
    );

    // 4. Capture files uploaded to `POST /imports` back to back, 64 MiB each (zeros
    //    under a capture's name: each streams to disk whole, then is refused as no
    //    capture and deleted): the capture's pace kept, memory bounded by a chunk, not
    //    the file.
    let quiet = rate(&d.runs, &id);
    let rss_before = rss(pid);
    let stop = Arc::new(AtomicBool::new(false));
    let peak = Arc::new(AtomicUsize::new(0));
    let uploaded = Arc::new(AtomicUsize::new(0));
    let uploads = {
        let (peak, uploaded) = (Arc::clone(&peak), Arc::clone(&uploaded));
        in_background(1, &stop, move || {
            let s = upload(addr, 64 << 20, &|| {
                peak.fetch_max(rss(pid) as usize, Ordering::Relaxed);
            });
            if s == 422 {
                uploaded.fetch_add(64, Ordering::Relaxed);
            }
            s
        })
    };
    let t_up = Instant::now();
    std::thread::sleep(Duration::from_millis(500));
    let loaded = rate(&d.runs, &id);
    let answers = finish(&stop, uploads);
    let mib = uploaded.load(Ordering::Relaxed);
    report.push(format!(
        "imports: {} uploads ({} refused as no capture, as they should be), {mib} MiB in {:.1} s, \
         RSS {:.0} MiB before, {:.0} MiB peak",
        answers.len(),
        count(&answers, 422),
        t_up.elapsed().as_secs_f64(),
        rss_before as f64 / 1048576.0,
        peak.load(Ordering::Relaxed) as f64 / 1048576.0
    ));
    check_rate("capture uploads", loaded, quiet, &mut report);
    assert!(count(&answers, 422) >= 1, "{}", report.join("\n"));
    assert!(
        (peak.load(Ordering::Relaxed) as u64) < rss_before + (64 << 20),
        "the uploads held too much memory\n{}",
        report.join("\n")
    );
    let staging = d.runs.join(periscope_daemon::service::STAGING_DIR);
    assert_eq!(
        std::fs::read_dir(&staging).map_or(0, |d| d.count()),
        0,
        "refused uploads left files in {}",
        staging.display()
    );

    // Throughout: the run never paused (a tripped watchdog pauses it) and recorded no
    // error.
    let info = RunInfo::load(&d.runs.join(&id)).unwrap();
    report.push(format!(
        "run {id}: state {:?}, error {:?}",
        info.state, info.error
    ));
    eprintln!("{}", report.join("\n"));
    assert_eq!(info.state, RunState::Running, "{}", report.join("\n"));
    assert_eq!(info.error, None, "{}", report.join("\n"));
    let (s, body) = request(addr, "POST", &format!("/api/v1/runs/{id}/abort"), true, "");
    assert_eq!(s, 202, "{body}");
}

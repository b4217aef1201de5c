//! The dashboard: its files and endpoints through the router, and the page itself in
//! headless Chromium driven over WebDriver (chromedriver). The browser test starts the
//! API on loopback over the simulated instrument, submits the demo plan through the
//! page, watches the histogram, 3-D view and loss plot fill, pauses and resumes, waits
//! for the depth image and a volume slice, and presses the e-stop; the simulated laser
//! itself must be off. Screenshots go to `target/tmp/dashboard/`.
//!
//! Without `chromium` and `chromedriver` on the PATH (Debian: `apt-get install chromium
//! chromium-driver`; `.ci/run` installs them) the browser test says it skipped, unless
//! `PERISCOPE_REQUIRE_BROWSER` is set (CI), when it fails.
use std::net::SocketAddr;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use fantoccini::{Client, ClientBuilder, Locator};
use periscope_daemon::api::{ASSETS, AppState, app};
use periscope_daemon::service::Service;
use serde_json::Value;
use tower::ServiceExt;

mod common;

const TOKEN: &str = "dashboard-token-0123456789abcdef";
const DEMO: &str = include_str!("../../configs/plans/demo.toml");
const SMALL: &str = include_str!("../../tests/data/plans/small-fbp.toml");

fn service(runs: &Path, time_scale: f64) -> Arc<Service> {
    let src = common::sim_instrument(runs, time_scale, &format!("token = \"{TOKEN}\""), "");
    Service::open(src, Some(TOKEN.into())).unwrap()
}

async fn call(
    router: &axum::Router,
    method: Method,
    uri: &str,
    token: bool,
    body: &str,
) -> (StatusCode, Vec<u8>) {
    common::send(
        router,
        common::request(method, uri, token.then_some(TOKEN), &[], body),
    )
    .await
}

#[tokio::test]
async fn the_page_and_its_files_are_served_from_the_binary() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0)));
    let resp = router
        .clone()
        .oneshot(Request::get("/").body(Body::empty()).unwrap())
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let csp = resp.headers()[header::CONTENT_SECURITY_POLICY]
        .to_str()
        .unwrap()
        .to_owned();
    assert!(
        csp.contains("default-src 'self'") && csp.contains("frame-ancestors 'none'"),
        "{csp}"
    );
    let html = String::from_utf8(
        axum::body::to_bytes(resp.into_body(), 1 << 20)
            .await
            .unwrap()
            .to_vec(),
    )
    .unwrap();
    // Every file the page names is served, with its type; nothing comes from elsewhere.
    for (name, media, body) in ASSETS {
        let (s, bytes) = call(&router, Method::GET, &format!("/ui/{name}"), false, "").await;
        assert_eq!(s, StatusCode::OK, "{name}");
        assert_eq!(bytes, body.as_bytes(), "{name}");
        assert!(!media.is_empty());
    }
    // And every file the page or its scripts name (a worker the script starts).
    let scripts = ASSETS.iter().map(|(name, _, body)| (*name, *body));
    for (page, text) in [("index.html", html.as_str())].into_iter().chain(scripts) {
        for src in text.split(['"', '\'', '`']).filter(|s| s.starts_with("/ui/")) {
            let name = src.trim_start_matches("/ui/");
            assert!(
                ASSETS.iter().any(|(n, _, _)| *n == name),
                "{page} names {src}, which is not embedded"
            );
        }
    }
    assert!(
        !html.contains("http://") && !html.contains("https://"),
        "the page loads nothing from other sites"
    );
    let (s, body) = call(&router, Method::GET, "/ui/nope.js", false, "").await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::NOT_FOUND, Some("not-found"))
    );
}

#[tokio::test]
async fn check_reports_duration_budget_and_problems_without_queueing() {
    let dir = tempfile::tempdir().unwrap();
    // Real time, so the durations are the instrument's.
    let router = app(AppState::new(service(dir.path(), 1.0)));
    let (s, body) = call(&router, Method::POST, "/api/v1/check", false, DEMO).await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["plan"], "demo");
    assert_eq!(v["pairs"], 576);
    let d = &v["duration_s"];
    let sum =
        d["los"].as_f64().unwrap() + d["capture"].as_f64().unwrap() + d["reconstruction"].as_f64().unwrap();
    assert!((d["total"].as_f64().unwrap() - sum).abs() < 1e-9, "{d}");
    // 576 pairs × 20 ms of dwell at least.
    assert!(d["capture"].as_f64().unwrap() >= 576.0 * 0.020, "{d}");
    assert!(v["over_budget"].is_null(), "{v}");
    assert!(v["memory_bytes"].as_u64().unwrap() < v["memory_limit"].as_u64().unwrap());
    // The same report `periscope check` prints.
    assert!(
        v["report"].as_str().unwrap().contains("estimated duration"),
        "{v}"
    );
    assert_eq!(v["warnings"], serde_json::json!([]), "{v}");
    // A TDC window short of the volume is a warning, naming the bins that record it.
    let short = DEMO.replace("[acquisition]\n", "[acquisition]\nbins = 360\n");
    assert_ne!(short, DEMO);
    let (s, body) = call(&router, Method::POST, "/api/v1/check", false, &short).await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(s, StatusCode::OK, "{v}");
    let warnings = v["warnings"].as_array().unwrap();
    assert!(
        warnings.len() == 1
            && warnings[0]
                .as_str()
                .unwrap()
                .contains("acquisition.bins at least"),
        "{v}"
    );
    assert!(v["over_budget"].is_null(), "{v}");
    // Invalid plans name the key; over-budget plans are reported, not refused.
    let bad = DEMO.replace("grid = [24, 24]", "grid = [24, -1]");
    let (s, body) = call(&router, Method::POST, "/api/v1/check", false, &bad).await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("invalid-plan")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("grid"), "{v}");
    let huge = DEMO.replace("shape = [64, 64, 128]", "shape = [1024, 1024, 1024]");
    let (s, body) = call(&router, Method::POST, "/api/v1/check", false, &huge).await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(s, StatusCode::OK, "{v}");
    assert!(v["over_budget"].as_str().unwrap().contains("over budget"), "{v}");
    let runs = std::fs::read_dir(dir.path())
        .unwrap()
        .filter(|e| e.as_ref().unwrap().path().join("run.json").exists())
        .count();
    assert_eq!(runs, 0, "check made no run");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn geometry_lists_the_relay_pairs_and_volume_of_a_run() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, body) = call(&router, Method::POST, "/api/v1/runs", true, SMALL).await;
    assert_eq!(s, StatusCode::CREATED);
    let id = serde_json::from_slice::<Value>(&body).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    let t = Instant::now();
    loop {
        let st = svc.status(&id).unwrap();
        if st.state == periscope_daemon::run_dir::RunState::Completed {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "{st:?}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let (s, body) = call(
        &router,
        Method::GET,
        &format!("/api/v1/runs/{id}/geometry"),
        false,
        "",
    )
    .await;
    let g: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(s, StatusCode::OK, "{g}");
    let relay = g["relay"].as_array().unwrap();
    assert!(relay.len() > 32, "{}", relay.len());
    // The relay is the wall at z = 0 (sim.toml), within a millimetre.
    assert!(relay.iter().all(|p| p[2].as_f64().unwrap().abs() < 1e-3), "{g}");
    // Confocal pairs: as many distinct illumination and detection points as pairs.
    let pairs: Vec<Value> =
        serde_json::from_slice(&std::fs::read(dir.path().join(&id).join("pairs.json")).unwrap()).unwrap();
    assert!(pairs.len() > 16);
    assert_eq!(g["pairs"], pairs.len());
    assert_eq!(g["illumination"].as_array().unwrap().len(), pairs.len());
    assert_eq!(g["detection"].as_array().unwrap().len(), pairs.len());
    let first = &g["illumination"][0];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        let want = pairs[0]["xi"][k]
            .as_f64()
            .unwrap_or_else(|| pairs[0]["xi"][*axis].as_f64().unwrap());
        assert!(
            (first[k].as_f64().unwrap() - want).abs() <= 0.6e-4,
            "{first} vs {}",
            pairs[0]
        );
    }
    assert!(g["volume"]["z"][1].as_f64().unwrap() > 0.0, "{g}");
    let (s, _) = call(&router, Method::GET, "/api/v1/runs/nope/geometry", false, "").await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    svc.shutdown();
    worker.join().unwrap();
}

// ---------------------------------------------------------------- the browser test

/// chromedriver on a free loopback port, in a process group of its own: dropping it
/// (also when the test fails before closing its session) kills the group, Chromium and
/// its renderers included, so no browser outlives the test.
struct Chromedriver {
    child: Child,
    url: String,
    /// chromedriver's and Chromium's TMPDIR, removed after them: killed, Chromium
    /// leaves its `org.chromium.Chromium.*` directories (up to 8 MB each, a dozen a
    /// test run) where it made them, which was /tmp until 2026-12-08.
    tmp: tempfile::TempDir,
}

impl Drop for Chromedriver {
    fn drop(&mut self) {
        let group = format!("-{}", self.child.id());
        let _ = Command::new("kill")
            .args(["-KILL", "--", &group])
            .stderr(Stdio::null())
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
        // The browsers in its group die after it: its TMPDIR is removed once they are
        // gone (for up to 5 s), so none writes there after the removal.
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(5)
            && Command::new("kill")
                .args(["-0", "--", &group])
                .stderr(Stdio::null())
                .status()
                .is_ok_and(|s| s.success())
        {
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

fn on_path(name: &str) -> Option<PathBuf> {
    std::env::var_os("PATH")?
        .to_str()?
        .split(':')
        .map(|d| Path::new(d).join(name))
        .find(|p| p.is_file())
}

/// Chromium and chromedriver, or why the browser test cannot run.
fn browser() -> Result<(PathBuf, PathBuf), String> {
    let chromium = std::env::var_os("PERISCOPE_CHROMIUM")
        .map(PathBuf::from)
        .or_else(|| on_path("chromium"))
        .or_else(|| on_path("chromium-browser"))
        .or_else(|| on_path("google-chrome"));
    let driver = on_path("chromedriver");
    match (chromium, driver) {
        (Some(c), Some(d)) => Ok((c, d)),
        (c, d) => Err(format!(
            "missing {}{}{}",
            if c.is_none() { "chromium" } else { "" },
            if c.is_none() && d.is_none() { " and " } else { "" },
            if d.is_none() { "chromedriver" } else { "" }
        )),
    }
}

/// The API on a loopback socket: its address and the server's task.
async fn serve(svc: &Arc<Service>) -> (SocketAddr, tokio::task::JoinHandle<()>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let direct = listener.local_addr().unwrap();
    let router = app(AppState::new(Arc::clone(svc)));
    let server = tokio::spawn(async move {
        axum::serve(
            listener,
            router.into_make_service_with_connect_info::<SocketAddr>(),
        )
        .await
        .unwrap();
    });
    (direct, server)
}

/// The API on a loopback socket, and a proxy in front of it the test can cut: the
/// direct address, the proxy's, its cutter, and the server's task.
async fn serve_behind_proxy(
    svc: &Arc<Service>,
) -> (
    SocketAddr,
    SocketAddr,
    tokio::sync::watch::Sender<u64>,
    tokio::task::JoinHandle<()>,
) {
    let (direct, server) = serve(svc).await;
    let (addr, cut) = cuttable_proxy(direct).await;
    (direct, addr, cut, server)
}

/// Chromium and chromedriver, or `None` after saying the test `what` skipped (a
/// failure instead when `PERISCOPE_REQUIRE_BROWSER` is set, as in CI).
fn browser_or_skip(what: &str) -> Option<(PathBuf, PathBuf)> {
    match browser() {
        Ok(b) => Some(b),
        Err(why) => {
            assert!(
                std::env::var_os("PERISCOPE_REQUIRE_BROWSER").is_none(),
                "PERISCOPE_REQUIRE_BROWSER is set but {what} cannot run: {why}"
            );
            common::skipped(format_args!(
                "{what}: {why} (Debian: apt-get install chromium chromium-driver; .ci/run installs them)"
            ));
            None
        }
    }
}

async fn start_chromedriver(path: &Path) -> Chromedriver {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let tmp = tempfile::tempdir().unwrap();
    let child = Command::new(path)
        .arg(format!("--port={port}"))
        .env("TMPDIR", tmp.path())
        .process_group(0)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot start {}: {e}", path.display()));
    let driver = Chromedriver {
        child,
        url: format!("http://127.0.0.1:{port}"),
        tmp,
    };
    // Ready when its WebDriver status says so: a listening port alone is not enough
    // (on a clean-clone CI run the session request's connection was reset, most likely
    // by a chromedriver still starting under load), and the status also shows that the
    // port is chromedriver's.
    let t = Instant::now();
    let http = reqwest::Client::new();
    loop {
        let ready = match http.get(format!("{}/status", driver.url)).send().await {
            Ok(resp) => resp.bytes().await.is_ok_and(|b| {
                serde_json::from_slice::<Value>(&b).is_ok_and(|v| v["value"]["ready"] == Value::Bool(true))
            }),
            Err(_) => false,
        };
        if ready {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(20),
            "chromedriver on port {port} did not report itself ready within 20 s"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    driver
}

/// A loopback TCP proxy in front of the daemon whose connections the test can cut,
/// as a network drop or a restarted router would: existing connections close, new
/// ones go through.
async fn cuttable_proxy(target: SocketAddr) -> (SocketAddr, tokio::sync::watch::Sender<u64>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (cut, watch) = tokio::sync::watch::channel(0u64);
    tokio::spawn(async move {
        while let Ok((mut inbound, _)) = listener.accept().await {
            let mut watch = watch.clone();
            watch.mark_unchanged();
            tokio::spawn(async move {
                let Ok(mut outbound) = tokio::net::TcpStream::connect(target).await else {
                    return;
                };
                tokio::select! {
                    _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound) => {}
                    _ = watch.changed() => {}
                }
            });
        }
    });
    (addr, cut)
}

/// What [`switchable_proxy`] does with the page's connections.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Link {
    /// Forwards both ways.
    Pass,
    /// Forwards nothing more and closes nothing: the connections open now stay silent
    /// for good, new ones are accepted and held unanswered (closed when the mode
    /// changes). A daemon wedged behind its listener, or a network that lost the
    /// connections without a reset, looks like this to a browser.
    Stall,
    /// Closes the open connections and answers each new request `503`, as a daemon
    /// shedding load does.
    Busy,
}

/// A loopback proxy in front of the daemon that the test switches between [`Link`]s.
async fn switchable_proxy(target: SocketAddr) -> (SocketAddr, tokio::sync::watch::Sender<Link>) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let (link, watch) = tokio::sync::watch::channel(Link::Pass);
    tokio::spawn(async move {
        while let Ok((mut inbound, _)) = listener.accept().await {
            let mut watch = watch.clone();
            let mode = *watch.borrow_and_update();
            tokio::spawn(async move {
                match mode {
                    Link::Busy => {
                        // The request's head, then the refusal.
                        let mut head = Vec::new();
                        let mut buf = [0u8; 4096];
                        while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < 65536 {
                            match inbound.read(&mut buf).await {
                                Ok(0) | Err(_) => return,
                                Ok(n) => head.extend_from_slice(&buf[..n]),
                            }
                        }
                        let body = r#"{"error":"busy","message":"the daemon is busy: try again"}"#;
                        let answer = format!(
                            "HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n\
                             content-length: {}\r\nconnection: close\r\n\r\n{body}",
                            body.len()
                        );
                        let _ = inbound.write_all(answer.as_bytes()).await;
                        let _ = inbound.shutdown().await;
                    }
                    Link::Stall => {
                        let _ = watch.wait_for(|m| *m != Link::Stall).await;
                    }
                    Link::Pass => {
                        let Ok(mut outbound) = tokio::net::TcpStream::connect(target).await else {
                            return;
                        };
                        let changed = tokio::select! {
                            _ = tokio::io::copy_bidirectional(&mut inbound, &mut outbound) => None,
                            m = watch.wait_for(|m| *m != Link::Pass) => m.ok().map(|m| *m),
                        };
                        if changed == Some(Link::Stall) {
                            // Silent for good, both ends held open.
                            std::future::pending::<()>().await;
                        }
                    }
                }
            });
        }
    });
    (addr, link)
}

async fn probe(c: &Client) -> Value {
    c.execute("return window.periscope || null;", vec![])
        .await
        .unwrap()
}

/// Polls the page's probe until `pred` holds.
async fn wait_page(c: &Client, what: &str, limit: Duration, pred: impl Fn(&Value) -> bool) -> Value {
    let t = Instant::now();
    loop {
        let v = probe(c).await;
        if pred(&v) {
            return v;
        }
        assert!(t.elapsed() < limit, "the page never showed {what}: {v}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn click(c: &Client, css: &str) {
    // A table the page re-renders (the runs list, as a run changes state) can replace
    // the element between finding and clicking it: find it again, a few times.
    for attempt in 1.. {
        let e = c
            .find(Locator::Css(css))
            .await
            .unwrap_or_else(|e| panic!("{css}: {e}"));
        match e.click().await {
            Ok(_) => return,
            Err(e) if attempt < 5 && e.to_string().contains("stale element") => {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Err(e) => panic!("clicking {css}: {e}"),
        }
    }
}

async fn text(c: &Client, css: &str) -> String {
    c.find(Locator::Css(css)).await.unwrap().text().await.unwrap()
}

async fn wait_text(c: &Client, css: &str, limit: Duration, pred: impl Fn(&str) -> bool) -> String {
    let t = Instant::now();
    loop {
        let s = text(c, css).await;
        if pred(&s) {
            return s;
        }
        if t.elapsed() > limit {
            let banner = text(c, "#banner").await;
            let check = text(c, "#check-summary").await;
            panic!(
                "{css} never matched: {s:?} (banner {banner:?}, check {check:?}, probe {})",
                probe(c).await
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

async fn screenshot(c: &Client, dir: &Path, name: &str) {
    let png = c.screenshot().await.unwrap();
    assert!(png.starts_with(b"\x89PNG"), "{name} is not a PNG");
    std::fs::write(dir.join(name), png).unwrap();
}

/// Non-background pixels of a canvas (drawn content, not a blank element).
async fn inked(c: &Client, id: &str) -> u64 {
    let js = "const c = document.getElementById(arguments[0]); \
              if (!c || !c.width) return 0; \
              const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
              let n = 0; for (let i = 0; i < d.length; i += 4) \
                if (d[i + 3] > 0 && !(d[i] > 245 && d[i + 1] > 245 && d[i + 2] > 245)) n++; \
              return n;";
    c.execute(js, vec![Value::from(id)])
        .await
        .unwrap()
        .as_u64()
        .unwrap()
}

/// A headless Chromium session with a viewport of `w` × `h` CSS pixels; below 500 px
/// (under Chromium's smallest window) as a phone, through its mobile emulation.
async fn session(driver: &Chromedriver, chromium: &Path, w: u32, h: u32) -> Client {
    let mut options = serde_json::json!({
        "binary": chromium,
        "args": ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 format!("--window-size={},{}", w.max(500), h), "--hide-scrollbars",
                 "--disable-background-networking", "--disable-component-update", "--no-first-run"]
    });
    if w < 500 {
        options["mobileEmulation"] = serde_json::json!({
            "deviceMetrics": { "width": w, "height": h, "pixelRatio": 2, "touch": true }
        });
    }
    let caps: serde_json::Map<String, Value> = serde_json::from_value(serde_json::json!({
        "browserName": "chrome",
        "goog:chromeOptions": options
    }))
    .unwrap();
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&driver.url)
        .await
        .expect("chromedriver starts a Chromium session")
}

/// Where the browser tests' screenshots go (`target/tmp/dashboard/`), made if missing.
fn screenshots_dir() -> PathBuf {
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR")).join("dashboard");
    std::fs::create_dir_all(&shots).unwrap();
    shots
}

/// Types the token into the page's token form and sends it.
async fn type_token(c: &Client) {
    c.find(Locator::Css("#token"))
        .await
        .unwrap()
        .send_keys(TOKEN)
        .await
        .unwrap();
    click(c, "#token-form button").await;
}

/// [`type_token`], then waits for the page to say the token is set.
async fn enter_token(c: &Client, limit: Duration) {
    type_token(c).await;
    wait_text(c, "#token-state", limit, |s| s.contains("token set")).await;
}

/// Runs the script `js` (with `args`) until its value is neither null nor false, and
/// returns that value.
async fn wait_js(c: &Client, what: &str, limit: Duration, js: &str, args: Vec<Value>) -> Value {
    let t = Instant::now();
    loop {
        let v = c.execute(js, args.clone()).await.unwrap();
        if !v.is_null() && v != Value::Bool(false) {
            return v;
        }
        assert!(
            t.elapsed() < limit,
            "the page never showed {what} (probe {})",
            probe(c).await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_runs_the_demo_from_the_dashboard_in_chromium() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard browser test") else {
        return;
    };
    let shots = screenshots_dir();
    let dir = tempfile::tempdir().unwrap();
    // Half real time: the demo's 576 pairs × 20 ms take about 6 s, long enough to pause.
    let svc = service(dir.path(), 0.5);
    let worker = svc.start_worker();
    // The browser reaches the daemon through a proxy the test can cut.
    let (_, addr, cut, server) = serve_behind_proxy(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 2000).await;
    let limit = Duration::from_secs(120);

    // Page load: navigation to the first complete render (instrument and runs shown).
    let t = Instant::now();
    c.goto(&format!("http://{addr}/")).await.unwrap();
    let p = wait_page(&c, "ready", Duration::from_secs(20), |v| v["ready"] == true).await;
    let load_wall = t.elapsed();
    let load_ms = p["loadMs"].as_f64().unwrap();
    assert!(load_ms < 5000.0, "page load {load_ms} ms");
    wait_text(&c, "#inst-body", limit, |s| {
        s.contains("laser") && s.contains("off")
    })
    .await;
    assert!(text(&c, "#token-state").await.contains("enter the API token"));

    // The token, once for the tab.
    enter_token(&c, limit).await;

    // The demo plan: checked (budget and duration shown) before it can be submitted.
    click(&c, "#load-demo").await;
    let summary = wait_text(&c, "#check-summary", limit, |s| s.starts_with("valid")).await;
    assert!(
        summary.contains("576 pairs") && summary.contains("memory"),
        "{summary}"
    );
    let submit = c.find(Locator::Css("#submit")).await.unwrap();
    assert!(submit.is_enabled().await.unwrap());
    submit.click().await.unwrap();
    let id = wait_text(&c, "#run-id", limit, |s| s.ends_with("-demo")).await;

    // Live: histograms arrive and are drawn; the relay and pairs are in the 3-D view.
    wait_page(&c, "histograms", limit, |v| v["histograms"].as_u64() >= Some(5)).await;
    wait_text(&c, "#view-caption", limit, |s| s.contains("relay points")).await;
    // The instrument panel shows the arms and the signal rate from the run itself.
    let live = wait_text(&c, "#inst-body", limit, |s| s.contains("live signal")).await;
    assert!(
        live.contains("counts/s") && live.contains("SPAD arm at"),
        "{live}"
    );
    assert!(inked(&c, "view3d").await > 500);

    // Pause and resume from the page.
    click(&c, "#run-actions .act-pause").await;
    wait_text(&c, "#run-state", limit, |s| s == "paused").await;
    assert_eq!(
        svc.status(&id).unwrap().state,
        periscope_daemon::run_dir::RunState::Paused
    );
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    assert!(!rig.emission(), "the laser is on while the run is paused");
    let before = probe(&c).await["histograms"].as_u64().unwrap();
    click(&c, "#run-actions .act-resume").await;
    wait_page(&c, "histograms after resuming", limit, |v| {
        v["histograms"].as_u64() > Some(before + 5)
    })
    .await;

    // A dropped connection: the page reconnects its event stream by itself and catches
    // up (status, then the stream again); histograms keep coming.
    let p = probe(&c).await;
    let (streams, seen) = (
        p["streamsOpened"].as_u64().unwrap(),
        p["histograms"].as_u64().unwrap(),
    );
    cut.send_modify(|g| *g += 1);
    wait_page(&c, "a reconnected event stream", limit, |v| {
        v["streamsOpened"].as_u64() > Some(streams) && v["histograms"].as_u64() > Some(seen + 3)
    })
    .await;

    // The optimiser: loss points and Gaussians appear while the capture streams in.
    wait_page(&c, "the loss curve and Gaussians", limit, |v| {
        v["lossPoints"].as_u64() >= Some(3) && v["snapshots"].as_u64() >= Some(1)
    })
    .await;
    screenshot(&c, &shots, "live.png").await;
    eprintln!("dashboard: live view at {:.1} s", t.elapsed().as_secs_f64());

    // Results: depth and albedo with axes, volume projections and a slice; the volume
    // loads once its part of the page is shown.
    wait_page(&c, "the results", Duration::from_secs(300), |v| {
        v["resultsShown"] == true
    })
    .await;
    c.execute("document.getElementById('volume-part').scrollIntoView();", vec![])
        .await
        .unwrap();
    wait_page(&c, "the volume", limit, |v| v["sliceShown"] == true).await;
    // The completed fit's final loss is shown, and no capture ETA lingers.
    let loss = wait_text(&c, "#run-loss", limit, |s| !s.is_empty()).await;
    assert!(loss.starts_with("final loss"), "{loss}");
    assert_eq!(text(&c, "#run-eta").await, "");
    for canvas in [
        "depth-canvas",
        "albedo-canvas",
        "mip-x",
        "mip-y",
        "mip-z",
        "slice-canvas",
    ] {
        assert!(inked(&c, canvas).await > 2000, "{canvas} is blank");
    }
    let downloads = text(&c, "#downloads").await;
    for f in [
        "volume.npy",
        "depth.png",
        "gaussians.ply",
        "relay.ply",
        "capture.hdf5",
    ] {
        assert!(downloads.contains(f), "{downloads}");
    }
    c.execute(
        "const s = document.getElementById('results'); s.scrollIntoView();",
        vec![],
    )
    .await
    .unwrap();
    screenshot(&c, &shots, "results.png").await;
    eprintln!("dashboard: results at {:.1} s", t.elapsed().as_secs_f64());

    // Event-to-screen latency: from the daemon storing a histogram to the frame that
    // shows it.
    let mut lat: Vec<f64> = probe(&c).await["latencies"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_f64)
        .collect();
    let n = lat.len();
    assert!(n >= 20, "only {n} histograms were timed");
    let (median, p95) = (percentile(&mut lat, 0.5), percentile(&mut lat, 0.95));
    assert!(median < 500.0, "event-to-screen median {median} ms");

    // E-stop from the page: a second demo run, stopped mid-capture.
    c.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    click(&c, "#load-demo").await;
    wait_text(&c, "#check-summary", limit, |s| s.starts_with("valid")).await;
    click(&c, "#submit").await;
    let second = wait_text(&c, "#run-id", limit, |s| s.ends_with("-demo") && s != id).await;
    let seen = probe(&c).await["histograms"].as_u64().unwrap();
    wait_page(&c, "the second run's histograms", limit, |v| {
        v["histograms"].as_u64() > Some(seen + 3)
    })
    .await;
    assert!(rig.emission(), "the laser is on during the capture");
    let pressed = Instant::now();
    click(&c, "#estop").await;
    let note = wait_text(&c, "#estop-text", limit, |s| s.starts_with("E-STOP done")).await;
    let off = rig
        .off_since(pressed)
        .expect("the simulated laser is off after the e-stop");
    assert!(!rig.emission());
    assert!(note.contains("arms parked") && note.contains(&second), "{note}");
    wait_text(&c, "#run-state", limit, |s| s == "aborted").await;
    let off_ms = (off - pressed).as_secs_f64() * 1e3;

    eprintln!(
        "dashboard: page load {load_ms:.0} ms in the page ({:.0} ms from navigation), \
         event-to-screen latency median {median:.0} ms, 95th percentile {p95:.0} ms over {n} histograms, \
         laser off {off_ms:.0} ms after the e-stop click; screenshots in {}",
        load_wall.as_secs_f64() * 1e3,
        shots.display()
    );
    // The browser's temporary directories (`org.chromium.Chromium.*`, Chrome's
    // `com.google.Chrome.*`) are in the driver's, removed with it.
    let made = std::fs::read_dir(driver.tmp.path()).unwrap().count();
    assert!(made > 0, "the browser made nothing in its TMPDIR");
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// A public capture imported from the page: the file chosen in the import card, the
/// method from its menu (written into the settings), a refused file's reason in the
/// banner, and the import's results drawn like a run's, its downloads offered.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_operator_imports_a_public_capture_from_the_page() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard import test") else {
        return;
    };
    let shots = screenshots_dir();
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let (_, addr, _cut, server) = serve_behind_proxy(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 2000).await;
    let limit = Duration::from_secs(120);
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", Duration::from_secs(20), |v| v["ready"] == true).await;
    // Without a key the page says why it cannot import.
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recon/tests/data");
    let choose = |path: PathBuf| {
        let c = c.clone();
        async move {
            c.find(Locator::Css("#import-file"))
                .await
                .unwrap()
                .send_keys(path.canonicalize().unwrap().to_str().unwrap())
                .await
                .unwrap();
        }
    };
    choose(data.join("lct-point.mat")).await;
    let why = wait_text(&c, "#import-why", limit, |s| !s.is_empty()).await;
    assert!(why.contains("enter an operator key"), "{why}");
    enter_token(&c, limit).await;
    let enabled = || async {
        c.find(Locator::Css("#import-go"))
            .await
            .unwrap()
            .is_enabled()
            .await
            .unwrap()
    };
    let t = Instant::now();
    while !enabled().await {
        assert!(
            t.elapsed() < limit,
            "import never enabled: {}",
            text(&c, "#import-why").await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // The method menu writes the settings.
    c.execute(
        "const m = document.getElementById('import-method'); m.value = 'fbp'; \
         m.dispatchEvent(new Event('change'));",
        vec![],
    )
    .await
    .unwrap();
    let recon = c
        .execute("return document.getElementById('import-recon').value;", vec![])
        .await
        .unwrap();
    assert_eq!(recon, "method = \"fbp\"\n");
    click(&c, "#import-go").await;
    let banner = wait_text(&c, "#banner", limit, |s| s.contains("imported")).await;
    assert!(banner.contains("lct-point.mat"), "{banner}");
    let id = wait_text(&c, "#run-id", limit, |s| s.ends_with("-lct-point")).await;
    wait_text(&c, "#run-state", limit, |s| s == "completed").await;
    wait_page(&c, "the import's results", limit, |v| v["resultsShown"] == true).await;
    assert!(inked(&c, "depth-canvas").await > 200, "the depth image is blank");
    let downloads = wait_text(&c, "#downloads", limit, |s| s.contains("capture.hdf5")).await;
    for f in ["volume.npy", "depth.png", "recon.toml"] {
        assert!(downloads.contains(f), "{downloads}");
    }
    let row = text(&c, &format!("tr[data-run='{id}']")).await;
    assert!(row.contains("imported lct-point.mat"), "{row}");
    let run = svc.status(&id).unwrap();
    assert_eq!(run.imported.as_deref(), Some("lct-point.mat"));
    c.execute(
        "window.scrollTo(0, document.getElementById('import').offsetTop - 90);",
        vec![],
    )
    .await
    .unwrap();
    screenshot(&c, &shots, "import.png").await;
    // A file that is not a capture: refused, with the reason in the banner.
    choose(Path::new(env!("CARGO_MANIFEST_DIR")).join("Cargo.toml")).await;
    click(&c, "#import-go").await;
    let refused = wait_text(&c, "#banner", limit, |s| s.starts_with("import refused")).await;
    assert!(refused.contains("not a capture file name"), "{refused}");
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// The faults an operator found (issue: an e-stop that always works, a laser state
/// that cannot lie, views true to the run), each checked in Chromium: the e-stop from
/// a phone-sized tab that has no token; the safety bar live from the run's own
/// readings (laser ON during the capture) and UNKNOWN when the daemon is gone, with the
/// e-stop sending the operator to the hardware one; views keyed to the selected run
/// (downloads, banner, results); a plan error's line and reason shown; results loaded
/// lazily and the event log once; one column at 390 px with the E-STOP pinned.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_stays_true_to_the_instrument_and_to_the_run() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard truth test") else {
        return;
    };
    let shots = screenshots_dir();
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.5);
    let worker = svc.start_worker();
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    let (direct, addr, cut, server) = serve_behind_proxy(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let limit = Duration::from_secs(120);
    let http = reqwest::Client::new();

    // A completed small run, submitted by a script: an adaptive capture, whose choices
    // the page draws from its event log.
    let adaptive = SMALL
        .replace(
            "mode = \"confocal\"",
            "mode = \"adaptive\"\ncandidates = \"confocal\"",
        )
        .replace("method = \"fbp\"", "method = \"gtr\"")
        + "[recon.gtr]\nprimitives = 300\nepochs = 4\nvirtual-grid = [16, 16]\n\
           [recon.adaptive]\npairs = 40\nfirst = 16\nbatch = 8\nlive-steps = 32\n";
    assert!(adaptive.contains("candidates") && adaptive.contains("\"gtr\""));
    let small: Value = serde_json::from_slice(
        &http
            .post(format!("http://{direct}/api/v1/runs"))
            .bearer_auth(TOKEN)
            .header("content-type", "application/toml")
            .body(adaptive)
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap(),
    )
    .unwrap();
    let small = small["id"].as_str().unwrap().to_owned();
    let t = Instant::now();
    while svc.status(&small).unwrap().state != periscope_daemon::run_dir::RunState::Completed {
        assert!(t.elapsed() < limit, "the small run never completed");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    // A desktop tab without a token: the e-stop says it is armed; the safety bar is live.
    let c = session(&driver, &chromium, 1400, 1600).await;
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", Duration::from_secs(20), |v| v["ready"] == true).await;
    let armed = wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
    assert!(armed.contains("without a key"), "{armed}");
    wait_page(&c, "a known laser state", limit, |v| v["safety"] == "known").await;
    assert_eq!(probe(&c).await["safetyEmission"], false);

    // The plan editor: an error's line is marked and its reason shown without a click.
    c.execute(
        "const p = document.getElementById('plan'); \
         p.value = 'name = \"bad\"\\nseed = 7\\n[pairs]\\nmode = 3\\n'; \
         p.dispatchEvent(new Event('input'));",
        vec![],
    )
    .await
    .unwrap();
    let problem = wait_text(&c, "#check-problem", limit, |s| s.starts_with("line")).await;
    assert!(problem.contains("mode"), "{problem}");
    let p = probe(&c).await;
    assert!(p["errorLine"].as_u64().is_some_and(|l| l >= 3), "{p}");
    assert!(
        !c.find_all(Locator::Css("#plan-lines .err"))
            .await
            .unwrap()
            .is_empty()
    );
    assert!(
        !c.find(Locator::Css("#submit"))
            .await
            .unwrap()
            .is_enabled()
            .await
            .unwrap()
    );

    // A plan whose TDC window stops short of the volume: valid, and the check's warning
    // shown beside it, naming the bins that would record the rest.
    let short = DEMO.replace("[acquisition]\n", "[acquisition]\nbins = 360\n");
    c.execute(
        "const p = document.getElementById('plan'); p.value = arguments[0]; \
         p.dispatchEvent(new Event('input'));",
        vec![Value::String(short)],
    )
    .await
    .unwrap();
    let warned = wait_text(&c, "#check-warnings", limit, |s| s.contains("TDC window")).await;
    assert!(warned.contains("acquisition.bins at least"), "{warned}");

    // The completed run: depth at once, the volume only when shown, the log once.
    c.execute("window.periscope.fetched = {}; window.scrollTo(0, 0);", vec![])
        .await
        .unwrap();
    wait_text(&c, "#runs-body", limit, |s| s.contains(&small)).await;
    click(&c, &format!("tr[data-run=\"{small}\"] a")).await;
    wait_page(&c, "the small run's results", limit, |v| {
        v["resultsShown"] == true
    })
    .await;
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let fetched = probe(&c).await["fetched"].clone();
    assert!(
        fetched["volume.npy"].is_null(),
        "the volume was fetched off screen: {fetched}"
    );
    // The adaptive capture's choices, from its event log: 16 spread, then three
    // batches of 8 chosen by the fit, in the 3-D view and its caption.
    let p = probe(&c).await;
    assert_eq!(
        (p["chosen"].as_u64(), p["chosenBatches"].as_u64()),
        (Some(40), Some(4)),
        "{p}"
    );
    let caption = text(&c, "#chosen-caption").await;
    assert!(
        caption.contains("40 pairs chosen in 4 batches") && caption.contains("for coverage"),
        "{caption}"
    );
    assert_eq!(fetched["events.jsonl"], 1, "{fetched}");
    c.execute("document.getElementById('volume-part').scrollIntoView();", vec![])
        .await
        .unwrap();
    wait_page(&c, "the volume", limit, |v| v["sliceShown"] == true).await;
    let fetched = probe(&c).await["fetched"].clone();
    assert_eq!(
        (fetched["volume.npy"].as_u64(), fetched["events.jsonl"].as_u64()),
        (Some(1), Some(1)),
        "{fetched}"
    );
    let runs_of = |ids: Vec<Option<String>>| ids.into_iter().flatten().collect::<Vec<_>>();
    let mut buttons = Vec::new();
    for b in c.find_all(Locator::Css("#downloads button")).await.unwrap() {
        buttons.push(b.attr("data-run").await.unwrap());
    }
    let buttons = runs_of(buttons);
    assert!(
        !buttons.is_empty() && buttons.iter().all(|r| r == &small),
        "{buttons:?}"
    );

    // A phone-sized tab with no token: one column, the E-STOP pinned, and it works. It is
    // opened before the demo starts, so that the demo's capture (about 6 s) is still
    // running when the E-STOP is pressed there, however slowly the browser opens a tab.
    let phone = session(&driver, &chromium, 390, 844).await;
    phone.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&phone, "ready", Duration::from_secs(20), |v| v["ready"] == true).await;
    let layout = phone
        .execute(
            "const r = document.getElementById('estop').getBoundingClientRect(); \
             return { width: document.documentElement.scrollWidth, inner: window.innerWidth, \
                      right: r.right, bottom: r.bottom, height: window.innerHeight, \
                      position: getComputedStyle(document.querySelector('.estop-box')).position };",
            vec![],
        )
        .await
        .unwrap();
    let inner = layout["inner"].as_f64().unwrap();
    assert_eq!(inner, 390.0, "{layout}");
    assert!(
        layout["width"].as_f64().unwrap() <= inner + 0.5,
        "the page is wider than the phone: {layout}"
    );
    assert_eq!(layout["position"], "fixed", "{layout}");
    assert!(
        layout["right"].as_f64().unwrap() <= inner
            && layout["bottom"].as_f64().unwrap() <= layout["height"].as_f64().unwrap(),
        "the E-STOP is off screen: {layout}"
    );
    // The token, then the demo from the page: the "queued" banner belongs to that run.
    c.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    type_token(&c).await;
    click(&c, "#load-demo").await;
    wait_text(&c, "#check-summary", limit, |s| s.starts_with("valid")).await;
    let submit = c.find(Locator::Css("#submit")).await.unwrap();
    let t = Instant::now();
    while !submit.is_enabled().await.unwrap() {
        assert!(
            t.elapsed() < limit,
            "submit never enabled: {}",
            text(&c, "#submit-why").await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    submit.click().await.unwrap();
    let demo = wait_text(&c, "#run-id", limit, |s| s.ends_with("-demo")).await;
    wait_text(&c, "#banner", limit, |s| s.contains("queued")).await;
    // Switching runs: the banner goes, and nothing of the other run stays.
    click(&c, &format!("tr[data-run=\"{small}\"] a")).await;
    wait_text(&c, "#run-id", limit, |s| s == small).await;
    assert!(
        !c.find(Locator::Css("#banner"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    );
    click(&c, &format!("tr[data-run=\"{demo}\"] a")).await;
    wait_text(&c, "#run-id", limit, |s| s == demo).await;
    let mut buttons = Vec::new();
    for b in c.find_all(Locator::Css("#downloads button")).await.unwrap() {
        buttons.push(b.attr("data-run").await.unwrap());
    }
    assert!(
        runs_of(buttons).iter().all(|r| r == &demo),
        "the small run's downloads stayed"
    );
    assert!(
        !c.find(Locator::Css("#results-body"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    );

    // Live: the laser ON from the run's own readings, the pairs in the 3-D view during
    // the capture, the histogram's caption consistent with the progress.
    wait_page(&c, "the laser ON, live", limit, |v| {
        v["safety"] == "known" && v["safetyEmission"] == true
    })
    .await;
    let p = wait_page(&c, "the planned pairs in 3-D", limit, |v| {
        v["geometry"]["illumination"].as_u64().is_some_and(|n| n > 0)
    })
    .await;
    assert_eq!(
        svc.status(&demo).unwrap().state,
        periscope_daemon::run_dir::RunState::Running,
        "the pairs appeared only after the run: {p}"
    );
    let caption = wait_text(&c, "#hist-caption", limit, |s| s.contains("measured")).await;
    assert!(caption.contains("plan pair #"), "{caption}");
    screenshot(&c, &shots, "live-safety.png").await;

    // The phone-sized tab opened before the demo (below): the E-STOP pressed there.
    wait_page(&phone, "the live laser state", limit, |v| v["safety"] == "known").await;
    screenshot(&phone, &shots, "phone.png").await;
    wait_text(&phone, "#estop-state", limit, |s| s.starts_with("armed")).await;
    assert!(rig.emission(), "the laser is on during the capture");
    let pressed = Instant::now();
    click(&phone, "#estop").await;
    let note = wait_text(&phone, "#estop-text", limit, |s| s.starts_with("E-STOP done")).await;
    assert!(rig.off_since(pressed).is_some() && !rig.emission(), "{note}");
    assert!(note.contains(&demo), "{note}");
    phone.close().await.unwrap();

    // The aborted run keeps its partial data on the page.
    wait_text(&c, "#run-state", limit, |s| s == "aborted").await;
    let note = wait_text(&c, "#results-note", limit, |s| s.contains("kept")).await;
    assert!(note.contains("captured pairs"), "{note}");
    wait_text(&c, "#downloads", limit, |s| s.contains("capture.hdf5")).await;

    // The daemon gone: UNKNOWN, an alarm, and the e-stop sends the operator to the
    // hardware one.
    // (The server stops accepting and every open connection drops, as when the
    // process dies.)
    server.abort();
    svc.shutdown();
    cut.send_modify(|g| *g += 1);
    wait_page(&c, "UNKNOWN", Duration::from_secs(10), |v| {
        v["safety"] == "unknown"
    })
    .await;
    assert_eq!(text(&c, "#sb-state").await, "LASER STATE UNKNOWN");
    assert!(text(&c, "#series-alarm").await.starts_with("ALARM"));
    wait_text(&c, "#estop-state", limit, |s| s.contains("UNREACHABLE")).await;
    click(&c, "#estop").await;
    let note = wait_text(&c, "#estop-text", limit, |s| s.contains("HARDWARE")).await;
    assert!(note.contains("could not reach the daemon"), "{note}");
    c.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    screenshot(&c, &shots, "unknown.png").await;
    c.close().await.unwrap();
    drop(driver);
    worker.join().unwrap();
}

/// A daemon that stops answering without closing anything, then one shedding load: the
/// page says so on the E-STOP's label and the connection pill instead of showing what
/// it read last, the E-STOP cancels an upload that holds a connection and reports its
/// own failure where nothing else writes, and the safety stream, silent on a connection
/// that never closes, is opened again and live once the daemon answers.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_says_when_the_daemon_stops_answering() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard silence test") else {
        return;
    };
    let shots = screenshots_dir();
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let (direct, server) = serve(&svc).await;
    let (addr, link) = switchable_proxy(direct).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 1600).await;
    let limit = Duration::from_secs(60);
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", Duration::from_secs(20), |v| v["ready"] == true).await;
    enter_token(&c, limit).await;
    wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
    wait_page(&c, "a known laser state", limit, |v| v["safety"] == "known").await;
    wait_text(&c, "#conn", limit, |s| s == "connected").await;
    let capture = Path::new(env!("CARGO_MANIFEST_DIR")).join("../recon/tests/data/lct-point.mat");
    c.find(Locator::Css("#import-file"))
        .await
        .unwrap()
        .send_keys(capture.canonicalize().unwrap().to_str().unwrap())
        .await
        .unwrap();
    let t = Instant::now();
    while !c
        .find(Locator::Css("#import-go"))
        .await
        .unwrap()
        .is_enabled()
        .await
        .unwrap()
    {
        assert!(
            t.elapsed() < limit,
            "import never enabled: {}",
            text(&c, "#import-why").await
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }

    // Silence: an upload starts and waits; the E-STOP cancels it, and tells the operator
    // to use the hardware one when its own request goes unanswered.
    link.send_replace(Link::Stall);
    click(&c, "#import-go").await;
    wait_text(&c, "#import-status", limit, |s| s.starts_with("uploading")).await;
    click(&c, "#estop").await;
    let cancelled = wait_text(&c, "#import-status", limit, |s| s.contains("cancelled")).await;
    assert!(cancelled.contains("check the runs list"), "{cancelled}");
    let hint = wait_text(&c, "#estop-text", limit, |s| s.contains("no answer after")).await;
    assert!(hint.contains("HARDWARE"), "{hint}");
    // The polls give up: the label and the pill no longer say armed and connected.
    let label = wait_text(&c, "#estop-state", limit, |s| !s.starts_with("armed")).await;
    assert!(label.contains("NOT ANSWERING"), "{label}");
    let pill = wait_text(&c, "#conn", limit, |s| s != "connected").await;
    assert!(pill.contains("not answering"), "{pill}");
    let report = wait_text(&c, "#estop-text", limit, |s| s.contains("no answer within")).await;
    assert!(report.contains("HARDWARE"), "{report}");
    let p = wait_page(&c, "the silent safety stream given up", limit, |v| {
        v["safetySilences"].as_u64().is_some_and(|n| n >= 1)
    })
    .await;
    assert_eq!(p["safety"], "unknown", "{p}");
    c.execute("window.scrollTo(0, 0);", vec![]).await.unwrap();
    screenshot(&c, &shots, "not-answering.png").await;

    // The daemon answers again: all of it live, on new connections (the old ones stay
    // silent), and the E-STOP's failure still in view.
    link.send_replace(Link::Pass);
    wait_page(&c, "the laser state known again", limit, |v| {
        v["safety"] == "known"
    })
    .await;
    wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
    wait_text(&c, "#conn", limit, |s| s == "connected").await;
    assert!(text(&c, "#estop-text").await.contains("no answer within"));
    assert!(
        c.find(Locator::Css("#estop-report"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    );

    // Shedding load: a 503 is not a refused key.
    link.send_replace(Link::Busy);
    let busy = wait_text(&c, "#estop-state", limit, |s| !s.starts_with("armed")).await;
    assert!(busy.contains("unknown") && busy.contains("503"), "{busy}");
    assert!(!busy.contains("NOT armed"), "{busy}");
    link.send_replace(Link::Pass);
    wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
    click(&c, "#estop-dismiss").await;
    assert!(
        !c.find(Locator::Css("#estop-report"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    );
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// The E-STOP's report is on screen however far the page is scrolled: beside the
/// button, in the sticky header on a desktop and pinned with the button to the corner
/// of a phone's screen. Pressed at the bottom of the page, on a desktop-sized and on a
/// phone-sized tab, the report is inside the viewport and nothing covers it. Until
/// 683df1a the report sat below the header in the page's flow, outside the part that
/// stays on screen: at the bottom of the page it was scrolled off the top, and an
/// operator who pressed the E-STOP there saw no word of whether it worked.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_estop_report_is_on_screen_however_far_the_page_is_scrolled() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard E-STOP report test") else {
        return;
    };
    let shots = screenshots_dir();
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let (addr, server) = serve(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let limit = Duration::from_secs(20);
    // The bottom of the page, a screen or more below the header: a spacer at the end
    // makes the page two screens tall, should it be shorter.
    let to_bottom = "const d = document.documentElement; \
                     if (d.scrollHeight < 2 * innerHeight) { \
                       const s = document.createElement('div'); \
                       s.style.height = `${2 * innerHeight}px`; document.body.append(s); } \
                     window.scrollTo(0, d.scrollHeight); \
                     return { scrollY, inner: innerHeight };";
    // Where the report is, scrolled to the bottom again (its own height may have made
    // the page longer), and whether it is what is seen at its centre.
    let report_at = "window.scrollTo(0, document.documentElement.scrollHeight); \
                     const e = document.getElementById('estop-report'); \
                     const r = e.getBoundingClientRect(); \
                     const hit = document.elementFromPoint((r.left + r.right) / 2, (r.top + r.bottom) / 2); \
                     return { top: r.top, bottom: r.bottom, left: r.left, right: r.right, \
                              inner: innerHeight, width: innerWidth, scrollY, \
                              shown: !e.hidden && r.height > 0, onTop: !!hit && e.contains(hit) };";
    for (w, h, name) in [(1200, 600, "desktop"), (390, 844, "phone")] {
        let c = session(&driver, &chromium, w, h).await;
        c.goto(&format!("http://{addr}/")).await.unwrap();
        wait_page(&c, "ready", limit, |v| v["ready"] == true).await;
        wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
        let at = c.execute(to_bottom, vec![]).await.unwrap();
        assert!(
            at["scrollY"].as_f64().unwrap() >= at["inner"].as_f64().unwrap() / 2.0,
            "{name}: the page did not scroll far: {at}"
        );
        click(&c, "#estop").await;
        let note = wait_text(&c, "#estop-text", limit, |s| s.starts_with("E-STOP done")).await;
        let r = c.execute(report_at, vec![]).await.unwrap();
        let f = |k: &str| r[k].as_f64().unwrap();
        assert!(
            f("scrollY") >= f("inner") / 2.0,
            "{name}: the page is no longer scrolled down: {r}"
        );
        assert_eq!(r["shown"], true, "{name}: the report is hidden: {r} ({note})");
        assert!(
            f("top") >= -0.5
                && f("bottom") <= f("inner") + 0.5
                && f("left") >= -0.5
                && f("right") <= f("width") + 0.5,
            "{name}: the E-STOP's report is off screen at the bottom of the page: {r}"
        );
        assert_eq!(
            r["onTop"], true,
            "{name}: something covers the E-STOP's report: {r}"
        );
        screenshot(&c, &shots, &format!("estop-report-{name}.png")).await;
        c.close().await.unwrap();
    }
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// A 401 that comes late, to a request sent with a key the operator has since
/// replaced, leaves the new key alone. The page is given a wrong key, and the answers
/// to its requests made with that key (all but the E-STOP's check, whose 401 asks for
/// nothing) are held back in the page (its `fetch` wrapped) until the right key has
/// been entered while one of the polls whose 401 asks for the key again (the
/// instrument's, the queue's, the audit's) is waiting; then the 401s arrive, the page
/// reads them, and the right key is still the one in use: kept for the tab, the token
/// form saying so, the E-STOP's label naming it. Until 683df1a any 401 wiped whatever
/// key was in use when it came, so a slow answer to the old key's request threw away
/// the key just typed (from another machine, the E-STOP was then unarmed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_401_to_an_old_key_leaves_the_key_just_entered() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard late-401 test") else {
        return;
    };
    const WRONG: &str = "not-the-daemon-key-0123456789";
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let (addr, server) = serve(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 1200).await;
    let limit = Duration::from_secs(20);
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", limit, |v| v["ready"] == true).await;
    // Answers to requests sent with the wrong key are held until `release`, or until
    // the request is given up (a poll's 6 s limit), as a slow daemon's would be. `held`
    // counts those held now, `heldApi` those of them whose 401 asks for the key, `api`
    // has those answers' statuses once let through, and `read` counts their bodies read
    // by the page (a 401 is acted on once its body is read).
    c.execute(
        "const key = arguments[0]; const orig = window.fetch; \
         const w = window.lateKey = { held: 0, heldApi: 0, api: [], read: 0, release: false }; \
         const isApi = (p) => p === '/api/v1/instrument' || p === '/api/v1/queue' || p.startsWith('/api/v1/audit'); \
         window.fetch = async function (input, init) { \
           const auth = init && init.headers && init.headers.Authorization; \
           const path = typeof input === 'string' ? input : input.url; \
           if (auth !== `Bearer ${key}` || path.startsWith('/api/v1/whoami')) return orig.call(window, input, init); \
           const api = isApi(path); \
           const signal = init && init.signal; \
           w.held += 1; if (api) w.heldApi += 1; \
           try { \
             const r = await orig.call(window, input, init); \
             while (!w.release) { \
               if (signal && signal.aborted) throw signal.reason; \
               await new Promise((res) => setTimeout(res, 20)); \
             } \
             if (api) { \
               w.api.push(r.status); \
               const json = r.json.bind(r); \
               r.json = () => json().then((v) => { w.read += 1; return v; }); \
             } \
             return r; \
           } finally { w.held -= 1; if (api) w.heldApi -= 1; } \
         };",
        vec![Value::from(WRONG)],
    )
    .await
    .unwrap();
    // The wrong key; a poll goes out with it, and its answer is held.
    c.find(Locator::Css("#token"))
        .await
        .unwrap()
        .send_keys(WRONG)
        .await
        .unwrap();
    click(&c, "#token-form button").await;
    wait_js(
        &c,
        "a poll sent with the wrong key",
        limit,
        "return window.lateKey.heldApi > 0 || null;",
        vec![],
    )
    .await;
    // The right key, entered while that answer is still on its way.
    type_token(&c).await;
    // Read, and the held answers let go, in one step: a held poll gives up at its 6 s
    // limit, and a loaded machine must not run that out between the two.
    let now = c
        .execute(
            "const now = { heldApi: window.lateKey.heldApi, key: sessionStorage.getItem('periscope-token') }; \
             window.lateKey.release = true; return now;",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(now["key"], TOKEN, "the right key was not taken: {now}");
    assert!(
        now["heldApi"].as_u64().is_some_and(|n| n >= 1),
        "no answer to the wrong key was still held when the right one was entered: {now}"
    );
    // The late answers: 401s, read by the page.
    let w = wait_js(
        &c,
        "the held answers delivered and read",
        limit,
        "const w = window.lateKey; return w.held === 0 && w.read > 0 ? w : null;",
        vec![],
    )
    .await;
    let statuses = w["api"].as_array().unwrap();
    assert!(
        !statuses.is_empty() && statuses.iter().all(|s| s.as_u64() == Some(401)),
        "the wrong key's polls were not answered 401: {w}"
    );
    // Time for the page to act on them.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let key = c
        .execute("return sessionStorage.getItem('periscope-token');", vec![])
        .await
        .unwrap();
    assert_eq!(
        key,
        TOKEN,
        "a late 401 to the old key wiped the new one (token form: {:?})",
        text(&c, "#token-state").await
    );
    assert_eq!(text(&c, "#token-state").await, "token set for this tab");
    // The new key's own requests go on with it: the E-STOP's label names it.
    wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed: key")).await;
    assert_eq!(
        c.execute("return sessionStorage.getItem('periscope-token');", vec![])
            .await
            .unwrap(),
        TOKEN
    );
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// The runs table asks before it aborts, naming the run, and says when the daemon
/// refuses its search. Abort: the page's `confirm` stubbed to record its question;
/// answered no, the queued run stays queued; answered yes, it is aborted. The search:
/// one over the daemon's 128 bytes is refused (400 `bad-query`), and the page says so
/// beside the filter, in the daemon's words, until the filter is cleared. Until 683df1a
/// abort went ahead at once, unasked (the table is rebuilt as runs change state, and a
/// row can move under the pointer), and a refused search left the last list on screen
/// as if it answered the filter, with nothing said.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_runs_table_asks_before_an_abort_and_says_a_refused_search() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard runs-table test") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // No worker: the run stays queued for as long as the test needs.
    let svc = service(dir.path(), 0.0);
    let id = svc.submit(SMALL.to_owned()).unwrap().id;
    let (addr, server) = serve(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 1200).await;
    let limit = Duration::from_secs(20);
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", limit, |v| v["ready"] == true).await;
    enter_token(&c, limit).await;
    let abort = format!("tr[data-run=\"{id}\"] .act-abort");
    wait_js(
        &c,
        "the queued run's abort button",
        limit,
        "return document.querySelector(arguments[0]) !== null || null;",
        vec![Value::from(abort.as_str())],
    )
    .await;

    // Answered no: asked, naming the run, and nothing done.
    c.execute(
        "window.asked = []; window.confirm = (m) => { window.asked.push(m); return false; };",
        vec![],
    )
    .await
    .unwrap();
    click(&c, &abort).await;
    // Time for an abort the page would send unasked to reach the daemon.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let asked = c.execute("return window.asked;", vec![]).await.unwrap();
    let state = svc.status(&id).unwrap().state;
    assert_eq!(
        asked.as_array().map(Vec::len),
        Some(1),
        "abort asked {asked}; the run is {state:?}"
    );
    let question = asked[0].as_str().unwrap();
    assert!(
        question.starts_with("Abort") && question.contains(&id),
        "the question does not name the run {id}: {question}"
    );
    assert_eq!(
        state,
        periscope_daemon::run_dir::RunState::Queued,
        "aborted though the operator said no"
    );

    // Answered yes: aborted.
    c.execute(
        "window.confirm = (m) => { window.asked.push(m); return true; };",
        vec![],
    )
    .await
    .unwrap();
    click(&c, &abort).await;
    let t = Instant::now();
    while svc.status(&id).unwrap().state != periscope_daemon::run_dir::RunState::Aborted {
        assert!(
            t.elapsed() < limit,
            "the run was not aborted when the operator said yes: {:?}",
            svc.status(&id).unwrap().state
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let asked = c.execute("return window.asked;", vec![]).await.unwrap();
    assert_eq!(asked.as_array().map(Vec::len), Some(2), "{asked}");
    wait_text(&c, &format!("tr[data-run=\"{id}\"]"), limit, |s| {
        s.contains("aborted")
    })
    .await;

    // A search of 200 bytes, over the daemon's 128: refused, and said beside the filter.
    let filter = "const f = document.getElementById('runs-filter'); f.value = arguments[0]; \
                  f.dispatchEvent(new Event('input'));";
    c.execute(filter, vec![Value::from("x".repeat(200))])
        .await
        .unwrap();
    let problem = wait_js(
        &c,
        "the refused search said",
        limit,
        "const p = document.getElementById('runs-problem'); \
         return p && !p.hidden && p.textContent ? p.textContent : null;",
        vec![],
    )
    .await;
    let problem = problem.as_str().unwrap();
    assert!(
        problem.contains("200 bytes") && problem.contains("at most 128"),
        "{problem}"
    );
    assert!(
        c.find(Locator::Css("#runs-problem"))
            .await
            .unwrap()
            .is_displayed()
            .await
            .unwrap()
    );
    // The list shown is the last one read.
    assert!(text(&c, "#runs-body").await.contains(&id));
    // The filter cleared: answered, and nothing more to say.
    c.execute(filter, vec![Value::from("")]).await.unwrap();
    wait_js(
        &c,
        "the refusal gone once the filter is cleared",
        limit,
        "return document.getElementById('runs-problem').hidden || null;",
        vec![],
    )
    .await;
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
}

/// A plan check the E-STOP cancels is no verdict on the plan: the page says the plan was
/// not checked and why, shows no problem with it, and Check asks again. The daemon's
/// answer to the check is held back in the page (its `fetch` wrapped for
/// `/api/v1/check`), so the check is still waiting when the E-STOP takes the page's
/// connections. Until 683df1a the cancelled check read as the daemon's refusal: a valid
/// plan was marked invalid, with the cancellation as its problem.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_check_the_estop_cancels_does_not_call_the_plan_invalid() {
    let Some((chromium, chromedriver)) = browser_or_skip("the dashboard cancelled-check test") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let (addr, server) = serve(&svc).await;
    let driver = start_chromedriver(&chromedriver).await;
    let c = session(&driver, &chromium, 1400, 1200).await;
    let limit = Duration::from_secs(20);
    c.goto(&format!("http://{addr}/")).await.unwrap();
    wait_page(&c, "ready", limit, |v| v["ready"] == true).await;
    wait_text(&c, "#estop-state", limit, |s| s.starts_with("armed")).await;
    click(&c, "#load-demo").await;
    wait_text(&c, "#check-summary", limit, |s| s.starts_with("valid")).await;
    // Checks wait for an answer that does not come, until cancelled (as a fetch is).
    c.execute(
        "const orig = window.fetch; window.heldChecks = 0; window.holdChecks = true; \
         window.fetch = function (input, init) { \
           const path = typeof input === 'string' ? input : input.url; \
           if (!window.holdChecks || path !== '/api/v1/check') return orig.call(window, input, init); \
           window.heldChecks += 1; \
           const signal = init && init.signal; \
           return new Promise((resolve, reject) => { \
             if (signal) signal.addEventListener('abort', () => reject(signal.reason), { once: true }); \
           }); \
         };",
        vec![],
    )
    .await
    .unwrap();
    click(&c, "#check").await;
    wait_js(
        &c,
        "the check waiting",
        limit,
        "return window.heldChecks > 0 || null;",
        vec![],
    )
    .await;
    click(&c, "#estop").await;
    let summary = wait_text(&c, "#check-summary", limit, |s| !s.starts_with("valid")).await;
    assert!(
        summary.starts_with("not checked") && summary.contains("cancelled by the E-STOP"),
        "the cancelled check judged the plan: {summary}"
    );
    let problem = c
        .execute(
            "return document.getElementById('check-problem').textContent;",
            vec![],
        )
        .await
        .unwrap();
    assert_eq!(problem, "", "the cancelled check showed a problem");
    wait_text(&c, "#estop-text", limit, |s| s.starts_with("E-STOP done")).await;
    // Check asks again, and is answered.
    c.execute("window.holdChecks = false;", vec![]).await.unwrap();
    click(&c, "#check").await;
    wait_text(&c, "#check-summary", limit, |s| s.starts_with("valid")).await;
    c.close().await.unwrap();
    drop(driver);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// Compression and validators on the page, its files and the downloads (tower-http),
/// and a favicon.
#[tokio::test]
async fn static_files_and_downloads_are_compressed_and_validated() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0);
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let get = |uri: &str, headers: &[(&str, &str)]| {
        let mut req = Request::builder().uri(uri);
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        router.clone().oneshot(req.body(Body::empty()).unwrap())
    };
    let body = |r: axum::response::Response| async move {
        axum::body::to_bytes(r.into_body(), usize::MAX)
            .await
            .unwrap()
            .to_vec()
    };
    let asset = |name: &str| {
        periscope_daemon::api::ASSETS
            .iter()
            .find(|(n, _, _)| *n == name)
            .unwrap()
            .2
            .as_bytes()
            .to_vec()
    };
    for uri in ["/", "/ui/app.js", "/ui/style.css"] {
        let r = get(uri, &[("accept-encoding", "gzip, br")]).await.unwrap();
        assert_eq!(r.status(), StatusCode::OK, "{uri}");
        assert_eq!(r.headers()[header::CONTENT_ENCODING], "br", "{uri}");
        assert_eq!(r.headers()[header::VARY], "accept-encoding", "{uri}");
        let tag = r.headers()[header::ETAG].to_str().unwrap().to_owned();
        let r = get(uri, &[("accept-encoding", "gzip, br"), ("if-none-match", &tag)])
            .await
            .unwrap();
        assert_eq!(r.status(), StatusCode::NOT_MODIFIED, "{uri}");
        // Each encoding is a representation of its own, with its own validator.
        let r = get(uri, &[("if-none-match", &tag)]).await.unwrap();
        assert_eq!(r.status(), StatusCode::OK, "{uri}");
        assert!(r.headers().get(header::CONTENT_ENCODING).is_none(), "{uri}");
    }
    // Compressed once, each encoding decodes to the file; a refused coding (q=0) is
    // not sent.
    let r = get("/ui/app.js", &[("accept-encoding", "br;q=0, gzip;q=0.5")])
        .await
        .unwrap();
    assert_eq!(r.headers()[header::CONTENT_ENCODING], "gzip");
    let mut plain = Vec::new();
    std::io::Read::read_to_end(&mut flate2::read::GzDecoder::new(&body(r).await[..]), &mut plain).unwrap();
    assert_eq!(plain, asset("app.js"));
    let r = get("/ui/app.js", &[("accept-encoding", "br")]).await.unwrap();
    let packed = body(r).await;
    let mut plain = Vec::new();
    std::io::Read::read_to_end(&mut brotli::Decompressor::new(&packed[..], 4096), &mut plain).unwrap();
    assert_eq!(plain, asset("app.js"));
    assert!(
        packed.len() * 3 < plain.len(),
        "{} of {}",
        packed.len(),
        plain.len()
    );
    let r = get("/ui/app.js", &[("accept-encoding", "identity")])
        .await
        .unwrap();
    assert!(r.headers().get(header::CONTENT_ENCODING).is_none());
    assert_eq!(body(r).await, asset("app.js"));
    let r = get("/favicon.ico", &[]).await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.headers()[header::CONTENT_TYPE], "image/svg+xml");
    // A download: compressed when it is text, validated by Last-Modified.
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, SMALL).await;
    assert_eq!(s, StatusCode::CREATED);
    let id = serde_json::from_slice::<Value>(&v).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    let t = Instant::now();
    while svc.status(&id).unwrap().state != periscope_daemon::run_dir::RunState::Completed {
        assert!(t.elapsed() < Duration::from_secs(60));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let uri = format!("/api/v1/runs/{id}/files/events.jsonl");
    let r = get(&uri, &[("accept-encoding", "gzip")]).await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.headers()[header::CONTENT_ENCODING], "gzip");
    let modified = r.headers()[header::LAST_MODIFIED].to_str().unwrap().to_owned();
    let r = get(&uri, &[("if-modified-since", &modified)]).await.unwrap();
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    let r = get(
        &format!("/api/v1/runs/{id}/files/volume.npy"),
        &[("accept-encoding", "gzip")],
    )
    .await
    .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert!(
        r.headers().get(header::CONTENT_ENCODING).is_none(),
        "float volumes are sent as they are"
    );
    assert!(r.headers().get(header::LAST_MODIFIED).is_some());
    svc.shutdown();
    worker.join().unwrap();
}

//! The API against hostile and careless clients: secrets that must not leave the
//! process, browsers pointed at the daemon by other sites, plans too large for the
//! machine, floods of submissions, streams and downloads, and requests racing each
//! other. Each test reproduces a finding of the hardening review and checks the fix.
use std::future::IntoFuture;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use common::{SmallPlan, send};
use periscope_daemon::api::{AppState, app};
use periscope_daemon::config::{TomlSource, redact_secrets};
use periscope_daemon::service::Service;
use serde_json::Value;
use tower::ServiceExt;

mod common;

const TOKEN: &str = "hardening-token-0123456789abcdef";

/// A small confocal plan solved by FBP (about a second at time-scale 0).
const PLAN: &str = include_str!("../../tests/data/plans/small-fbp.toml");

/// The simulated instrument with runs in `runs`, the token in its `[api]` table (as a
/// lab that keeps it in the file would), and `api_extra` lines added to that table.
fn instrument(runs: &Path, time_scale: f64, api_extra: &str, tail: &str) -> TomlSource {
    common::sim_instrument(
        runs,
        time_scale,
        &format!("token = \"{TOKEN}\"\n{api_extra}"),
        tail,
    )
}

fn service(runs: &Path, time_scale: f64, api_extra: &str, tail: &str) -> Arc<Service> {
    Service::open(instrument(runs, time_scale, api_extra, tail), Some(TOKEN.into())).unwrap()
}

fn request(method: Method, uri: &str, token: bool, headers: &[(&str, &str)], body: &str) -> Request<Body> {
    common::request(method, uri, token.then_some(TOKEN), headers, body)
}

async fn call(
    router: &axum::Router,
    method: Method,
    uri: &str,
    token: bool,
    body: &str,
) -> (StatusCode, Value) {
    let (s, b) = send(router, request(method, uri, token, &[], body)).await;
    (s, serde_json::from_slice(&b).unwrap_or(Value::Null))
}

async fn json(resp: reqwest::Response) -> Value {
    serde_json::from_slice(&resp.bytes().await.unwrap()).unwrap()
}

fn run_dirs(runs: &Path) -> usize {
    std::fs::read_dir(runs)
        .unwrap()
        .filter(|e| e.as_ref().unwrap().path().join("run.json").is_file())
        .count()
}

#[test]
fn the_token_is_cut_from_config_text_in_every_layout() {
    let cases = [
        "[api]\ntoken = \"s3cr3t-s3cr3t-s3cr3t\"\nruns-dir = \"r\"\n",
        "[api]\n  'token'='s3cr3t-s3cr3t-s3cr3t' # ours\n",
        "api.token = \"s3cr3t-s3cr3t-s3cr3t\"\nname = \"x\"\n",
        "api = { token = \"s3cr3t-s3cr3t-s3cr3t\", open-reads = true }\n",
        "[api]\ntoken = \"\"\"\ns3cr3t-s3cr3t-s3cr3t\n\"\"\"\n",
        "[api\ntoken = \"s3cr3t-s3cr3t-s3cr3t\"\n",
        // A multi-line literal whose second line reads as a key of its own once the
        // first is cut: the line cut left `api.s3cr3t-s3cr3t-s3cr3t = 1` behind.
        "[api]\ntoken = '''\ns3cr3t-s3cr3t-s3cr3t=1#'''\nruns-dir = \"r\"\n",
        // And one whose pieces a line-ending backslash joins, so no line of its value
        // is a line of the text.
        "[api]\ntoken = \"\"\"\ns3cr3t-s3cr3t=1#\\\ns3cr3t-s3cr3u=2#\"\"\"\nruns-dir = \"r\"\n",
    ];
    for text in cases {
        let out = redact_secrets(text);
        assert!(!out.contains("s3cr3t"), "{text:?} → {out:?}");
    }
    // The rest of the file keeps its layout and meaning.
    let out = redact_secrets(cases[0]);
    assert!(
        out.contains("runs-dir = \"r\"") && out.contains("# token = <redacted"),
        "{out}"
    );
    let out = redact_secrets(cases[3]);
    let v: toml::Table = out.parse().unwrap();
    assert_eq!(v["api"]["open-reads"].as_bool(), Some(true), "{out}");
    // A `token` key in another table is not the API's and stays.
    let other = "[sim]\ntoken = 3\n";
    assert_eq!(redact_secrets(other), other);
}

#[tokio::test]
async fn stored_and_downloaded_configs_never_carry_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "", "");
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let stored = std::fs::read_to_string(dir.path().join(&id).join("instrument.toml")).unwrap();
    assert!(!stored.contains(TOKEN), "the run stores the token:\n{stored}");
    assert!(stored.contains("runs-dir"), "{stored}");
    // A run stored before secrets were cut out: the download cuts it.
    std::fs::write(
        dir.path().join(&id).join("instrument.toml"),
        format!("name = \"x\"\n[api]\ntoken = \"{TOKEN}\"\n"),
    )
    .unwrap();
    let (s, body) = send(
        &router,
        request(
            Method::GET,
            &format!("/api/v1/runs/{id}/files/instrument.toml"),
            false,
            &[],
            "",
        ),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let body = String::from_utf8(body).unwrap();
    assert!(!body.contains(TOKEN) && body.contains("name = \"x\""), "{body}");
    // Nor does the config's debug form (what a log line would print).
    let cfg = periscope_daemon::config::InstrumentConfig::from_source(&instrument(dir.path(), 0.0, "", ""))
        .unwrap();
    assert!(!format!("{cfg:?}").contains(TOKEN));
}

#[tokio::test]
async fn foreign_host_names_and_cross_site_origins_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "hosts = [\"lab-pc.example.org\"]", "");
    let router = app(AppState::new(svc));
    let health = |host: &'static str| request(Method::GET, "/api/v1/health", false, &[("host", host)], "");
    for host in [
        "127.0.0.1:8080",
        "localhost:8080",
        "localhost",
        "[::1]:8080",
        "192.168.1.20",
        "LAB-PC.example.org:8080",
    ] {
        let (s, _) = send(&router, health(host)).await;
        assert_eq!(s, StatusCode::OK, "Host: {host}");
    }
    // A DNS-rebinding page reaches the daemon under its own name.
    for host in [
        "attacker.example",
        "localhost.attacker.example:8080",
        "127.0.0.1:80x",
        "",
    ] {
        let (s, b) = send(&router, health(host)).await;
        assert_eq!(s, StatusCode::FORBIDDEN, "Host: {host}");
        let v: Value = serde_json::from_slice(&b).unwrap();
        assert_eq!(v["error"], "host-not-allowed", "{v}");
        assert!(v["message"].as_str().unwrap().contains("[api] hosts"), "{v}");
    }
    // Mutations from another site's page are refused even with the token (a browser
    // may hold it); the daemon's own origin and clients without Origin pass.
    let estop = |origin: Option<&'static str>| {
        let mut h = vec![("host", "127.0.0.1:8080")];
        if let Some(o) = origin {
            h.push(("origin", o));
        }
        request(Method::POST, "/api/v1/estop", true, &h, "")
    };
    for origin in ["http://attacker.example", "null", "http://127.0.0.1:9999"] {
        let (s, b) = send(&router, estop(Some(origin))).await;
        assert_eq!(s, StatusCode::FORBIDDEN, "Origin: {origin}");
        assert!(String::from_utf8_lossy(&b).contains("origin-not-allowed"));
    }
    // A change refused at the door is in the audit trail as what it asked for, as
    // every refused change is; a refused read is not.
    let (s, _) = send(
        &router,
        request(
            Method::POST,
            "/api/v1/runs",
            true,
            &[("host", "attacker.example")],
            PLAN,
        ),
    )
    .await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (_, audit) = call(
        &router,
        Method::GET,
        "/api/v1/audit?actor=unknown&limit=100",
        true,
        "",
    )
    .await;
    let entries = audit["entries"].as_array().unwrap();
    let count = |action: &str, says: &str| {
        entries
            .iter()
            .filter(|e| {
                e["action"] == action
                    && e["outcome"] == "refused"
                    && e["detail"].as_str().unwrap_or("").contains(says)
            })
            .count()
    };
    assert_eq!(count("estop", "a page from"), 3, "{audit}");
    assert_eq!(count("submit", "attacker.example"), 1, "{audit}");
    assert!(
        entries
            .iter()
            .all(|e| !e["detail"].as_str().unwrap_or("").contains("/health")),
        "{audit}"
    );
    for origin in [Some("http://127.0.0.1:8080"), None] {
        let (s, b) = send(&router, estop(origin)).await;
        assert_eq!(
            s,
            StatusCode::OK,
            "Origin: {origin:?}: {}",
            String::from_utf8_lossy(&b)
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn instrument_status_comes_from_the_worker_and_never_opens_a_device() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "status-interval-s = 0.3", "");
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend())
        .unwrap()
        .clone();
    let router = app(AppState::new(Arc::clone(&svc)));
    // No worker yet: no reading, and the GET opens nothing.
    let before = rig.galvo_connects();
    for _ in 0..5 {
        let (s, v) = call(&router, Method::GET, "/api/v1/instrument", false, "").await;
        assert_eq!(s, StatusCode::OK);
        assert_eq!(v["reading"], Value::Null, "{v}");
        assert_eq!(v["devices"], Value::Null, "{v}");
    }
    assert_eq!(
        rig.galvo_connects(),
        before,
        "GET /instrument opened a galvo controller"
    );
    // The worker reads the devices when it starts and every status interval.
    let worker = svc.start_worker();
    let t = Instant::now();
    let v = loop {
        let (_, v) = call(&router, Method::GET, "/api/v1/instrument", false, "").await;
        if v["devices"].is_object() {
            break v;
        }
        assert!(t.elapsed() < Duration::from_secs(10), "no reading: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(v["devices"]["laser"]["emission"], false, "{v}");
    let age = v["reading"]["age_s"].as_f64().unwrap();
    assert!((0.0..5.0).contains(&age), "{v}");
    assert!(v["reading"]["taken_unix_s"].as_f64().unwrap() > 1.7e9, "{v}");
    tokio::time::sleep(Duration::from_millis(800)).await;
    let (_, later) = call(&router, Method::GET, "/api/v1/instrument", false, "").await;
    assert!(
        later["reading"]["taken_unix_s"].as_f64() > v["reading"]["taken_unix_s"].as_f64(),
        "the idle worker did not read again: {later}"
    );
    svc.shutdown();
    worker.join().unwrap();
}

/// Submits `plan`, which must be refused as over budget; the refusal's message.
async fn over_budget(router: &axum::Router, plan: &str) -> String {
    let (s, v) = call(router, Method::POST, "/api/v1/runs", true, plan).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("over-budget")),
        "{v}"
    );
    v["message"].as_str().unwrap().to_owned()
}

#[tokio::test]
async fn plans_over_the_budget_get_422_naming_the_key_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, "", "")));
    let scanned = |grid: [usize; 2]| {
        SmallPlan::default()
            .set("pairs.mode", "scanned")
            .unset("pairs.offset-mm")
            .set("pairs.laser-grid", grid)
            .set("pairs.grid", grid)
    };
    // 512⁴ pairs is past what a run may hold at all (its pairs.json must be read back):
    // refused as an invalid plan, naming the grid, before any budget.
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/runs",
        true,
        &scanned([512, 512]).toml(),
    )
    .await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("invalid-plan")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("pairs.grid"), "{v}");
    // 32⁴, a million pairs, is a layout a run may hold, and over the memory budget.
    let scanned = scanned([32, 32]);
    let huge_volume = SmallPlan::default().set("recon.volume.shape", [1024, 1024, 1024]);
    for (plan, names) in [(scanned, "pairs"), (huge_volume, "recon.volume.shape")] {
        let m = over_budget(&router, &plan.toml()).await;
        assert!(
            m.contains(names) && m.contains("GiB") && m.contains("budget.memory-gib"),
            "{m}"
        );
    }
    assert_eq!(run_dirs(dir.path()), 0);
    // A lab with a bigger machine raises the budget in the instrument config.
    let dir2 = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(
        dir2.path(),
        0.0,
        "",
        "[budget]\nmemory-gib = 200\n",
    )));
    let big = SmallPlan::default()
        .set("recon.volume.shape", [512, 512, 512])
        .toml();
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, &big).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    // A time budget: an hour of instrument time, on the simulator in real time. The
    // shared plan fits; with a dwell of 2 min a pair it would take 2.1 h, and is refused.
    let dir3 = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(
        dir3.path(),
        1.0,
        "",
        "[budget]\nhours = 1\n",
    )));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let slow = SmallPlan::default().set("acquisition.dwell-ms", 120000.0).toml();
    let m = over_budget(&router, &slow).await;
    assert!(
        m.contains("budget.hours")
            && m.contains("acquisition.dwell-ms")
            && m.contains("more than the instrument's 1.0 h"),
        "{m}"
    );
    assert_eq!(run_dirs(dir3.path()), 1);
}

#[tokio::test]
async fn a_full_queue_answers_429_and_makes_no_run() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, "max-queue = 3", "")));
    for _ in 0..3 {
        let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
    }
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::TOO_MANY_REQUESTS, Some("queue-full")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("max-queue"), "{v}");
    assert_eq!(run_dirs(dir.path()), 3);
}

#[tokio::test]
async fn stream_and_download_caps_answer_503_until_a_slot_frees() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "max-streams = 1\nmax-downloads = 1", "");
    let router = app(AppState::new(Arc::clone(&svc)));
    let (_, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    let id = v["id"].as_str().unwrap().to_owned();
    // A queued run's stream stays open (no worker runs it): it holds the one slot.
    let events = format!("/api/v1/runs/{id}/events");
    let first = router
        .clone()
        .oneshot(request(Method::GET, &events, false, &[], ""))
        .await
        .unwrap();
    assert_eq!(first.status(), StatusCode::OK);
    let (s, v) = call(&router, Method::GET, &events, false, "").await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::SERVICE_UNAVAILABLE, Some("too-many-streams")),
        "{v}"
    );
    drop(first);
    let again = router
        .clone()
        .oneshot(request(Method::GET, &events, false, &[], ""))
        .await
        .unwrap();
    assert_eq!(again.status(), StatusCode::OK, "the slot was not given back");
    drop(again);
    // A download whose body is not yet read holds the one download slot.
    let plan = format!("/api/v1/runs/{id}/files/plan.toml");
    let held = router
        .clone()
        .oneshot(request(Method::GET, &plan, false, &[], ""))
        .await
        .unwrap();
    assert_eq!(held.status(), StatusCode::OK);
    assert!(held.headers().get(header::CONTENT_LENGTH).is_some());
    let (s, v) = call(&router, Method::GET, &plan, false, "").await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::SERVICE_UNAVAILABLE, Some("too-many-downloads")),
        "{v}"
    );
    let body = axum::body::to_bytes(held.into_body(), 1 << 20).await.unwrap();
    assert!(String::from_utf8_lossy(&body).contains("name = \"small-fbp\""));
    let (s, _) = send(&router, request(Method::GET, &plan, false, &[], "")).await;
    assert_eq!(s, StatusCode::OK, "the download slot was not given back");
}

/// One remote host holds at most half the download slots: a host that reads its
/// downloads slowly held all of them until 2026-12-08, and the operator's own
/// downloads got 503 until it let go.
#[tokio::test]
async fn one_remote_host_holds_at_most_half_the_download_slots() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "max-downloads = 4", "");
    let router = app(AppState::new(Arc::clone(&svc)));
    let (_, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    let id = v["id"].as_str().unwrap().to_owned();
    let plan = format!("/api/v1/runs/{id}/files/plan.toml");
    let from = |host: &str| {
        let mut req = request(Method::GET, &plan, true, &[], "");
        req.extensions_mut().insert(axum::extract::ConnectInfo(
            format!("{host}:50000").parse::<std::net::SocketAddr>().unwrap(),
        ));
        req
    };
    // Bodies not read: each holds its slot.
    let mut held = Vec::new();
    for _ in 0..2 {
        let resp = router.clone().oneshot(from("192.0.2.7")).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK);
        held.push(resp);
    }
    let (s, body) = send(&router, from("192.0.2.7")).await;
    let v: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::SERVICE_UNAVAILABLE, Some("too-many-downloads")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("this host"), "{v}");
    // Another host and loopback are served beside it.
    let (s, _) = send(&router, from("192.0.2.8")).await;
    assert_eq!(s, StatusCode::OK);
    let (s, _) = send(&router, from("127.0.0.1")).await;
    assert_eq!(s, StatusCode::OK);
    // Its slots come back as its bodies end.
    drop(held);
    let (s, _) = send(&router, from("192.0.2.7")).await;
    assert_eq!(s, StatusCode::OK, "the host's slots were not given back");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn aborting_a_queued_run_ends_its_event_stream() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "", "");
    let router = app(AppState::new(Arc::clone(&svc)));
    let (_, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
    let id = v["id"].as_str().unwrap().to_owned();
    let stream = router
        .clone()
        .oneshot(request(
            Method::GET,
            &format!("/api/v1/runs/{id}/events"),
            false,
            &[],
            "",
        ))
        .await
        .unwrap();
    let (s, _) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{id}/abort"),
        true,
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED);
    let body = tokio::time::timeout(
        Duration::from_secs(5),
        axum::body::to_bytes(stream.into_body(), 1 << 20),
    )
    .await
    .expect("the aborted run's event stream never ended")
    .unwrap();
    assert!(String::from_utf8_lossy(&body).starts_with("event: status"));
}

#[tokio::test]
async fn a_run_missing_from_queue_json_is_queued_again_on_restart() {
    let dir = tempfile::tempdir().unwrap();
    let id = {
        let router = app(AppState::new(service(dir.path(), 0.0, "", "")));
        let (_, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
        v["id"].as_str().unwrap().to_owned()
    };
    // The daemon died after making the run directory, before saving the queue.
    std::fs::write(dir.path().join("queue.json"), "[]").unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, "", "")));
    let (_, v) = call(&router, Method::GET, &format!("/api/v1/runs/{id}"), false, "").await;
    assert_eq!(
        (v["state"].as_str(), v["queue_position"].as_u64()),
        (Some("queued"), Some(0)),
        "{v}"
    );
    let queue = std::fs::read_to_string(dir.path().join("queue.json")).unwrap();
    assert!(queue.contains(&id), "{queue}");
}

/// Several clients submit, pause, resume, abort, e-stop and poll at once against a
/// running worker; afterwards every run is in a final or paused state that agrees with
/// queue.json, nothing is left running, and the laser is off.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn concurrent_clients_leave_consistent_states() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.2, "", "");
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let ids = Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let mut tasks = Vec::new();
    for client in 0..6u64 {
        let (router, ids) = (router.clone(), Arc::clone(&ids));
        tasks.push(tokio::spawn(async move {
            let mut statuses = Vec::new();
            for step in 0..12u64 {
                let pick = |ids: &Vec<String>| {
                    ids.get(((client * 7 + step * 3) as usize) % ids.len().max(1))
                        .cloned()
                };
                let (action, id) = {
                    let ids = ids.lock().unwrap();
                    ((client + step) % 6, pick(&ids))
                };
                let (s, v) = match (action, id) {
                    (0, _) | (_, None) => {
                        let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
                        if s == StatusCode::CREATED {
                            ids.lock().unwrap().push(v["id"].as_str().unwrap().to_owned());
                        }
                        (s, v)
                    }
                    (action @ 1..=3, Some(id)) => {
                        let verb = ["pause", "resume", "abort"][action as usize - 1];
                        call(
                            &router,
                            Method::POST,
                            &format!("/api/v1/runs/{id}/{verb}"),
                            true,
                            "",
                        )
                        .await
                    }
                    (4, _) if step % 4 == 0 => call(&router, Method::POST, "/api/v1/estop", true, "").await,
                    (_, Some(id)) => {
                        call(&router, Method::GET, &format!("/api/v1/runs/{id}"), false, "").await
                    }
                };
                // Every answer is a success or a clean refusal, never a 5xx.
                assert!(
                    s.is_success() || s == StatusCode::CONFLICT,
                    "client {client} step {step}: {s} {v}"
                );
                statuses.push(s);
                tokio::time::sleep(Duration::from_millis(15)).await;
            }
            statuses
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    // Settle: abort whatever still waits, then wait for the worker to go idle.
    let ids = ids.lock().unwrap().clone();
    assert!(ids.len() >= 3, "{ids:?}");
    for id in &ids {
        let _ = call(
            &router,
            Method::POST,
            &format!("/api/v1/runs/{id}/abort"),
            true,
            "",
        )
        .await;
    }
    let t = Instant::now();
    loop {
        let (_, list) = call(&router, Method::GET, "/api/v1/runs", false, "").await;
        let busy = list
            .as_array()
            .unwrap()
            .iter()
            .any(|r| r["state"] == "running" || r["state"] == "queued");
        // The worker records a run's end in run.json before it takes the run off the
        // queue (and rewrites queue.json) and lets go of the instrument: wait for both.
        let (_, inst) = call(&router, Method::GET, "/api/v1/instrument", false, "").await;
        if !busy && inst["busy"] == false {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "runs never settled: {list}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let queue: Vec<String> =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("queue.json")).unwrap()).unwrap();
    for id in &ids {
        let (_, v) = call(&router, Method::GET, &format!("/api/v1/runs/{id}"), false, "").await;
        let state = v["state"].as_str().unwrap();
        assert!(
            ["completed", "aborted", "paused", "failed"].contains(&state),
            "{id}: {v}"
        );
        // queue.json holds exactly the runs that can still run.
        assert_eq!(
            queue.contains(id),
            state == "paused",
            "{id} is {state}; queue {queue:?}"
        );
    }
    assert!(
        !periscope_daemon::devices::sim::rig_of(svc.backend())
            .unwrap()
            .emission(),
        "the laser is on after everything stopped"
    );
    svc.shutdown();
    worker.join().unwrap();
}

/// 10,000 submissions while a capture runs: 429 once the queue is full, the daemon's
/// memory flat, and the capture's pair rate within 10 % of an undisturbed one. In a
/// process of its own: the memory measured is the process's, and the tests the harness
/// runs beside it on other threads once added 105 MiB to it.
#[test]
fn a_submission_flood_gets_429_and_does_not_slow_the_capture() {
    common::alone(
        "a_submission_flood_gets_429_and_does_not_slow_the_capture",
        2,
        submission_flood(),
    );
}

async fn submission_flood() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 1.0, "max-queue = 20", "");
    let worker = svc.start_worker();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let base = format!("http://{}/api/v1", listener.local_addr().unwrap());
    let server = tokio::spawn(
        axum::serve(
            listener,
            app(AppState::new(Arc::clone(&svc)))
                .into_make_service_with_connect_info::<std::net::SocketAddr>(),
        )
        .into_future(),
    );
    let client = reqwest::Client::new();
    // Real time: a 28 × 28 grid keeps about 520 pairs on the relay, at about 45 pairs/s
    // (20 ms each plus the LOS-masked moves) about 12 s of capture per run, twice the
    // flood (6.2 s on a 2-core machine), so no flooded run starts (and leaves the queue)
    // while it lasts. A 20 × 20 grid kept 265 pairs, 6 s: as long as the flood.
    let capture_plan = SmallPlan::default()
        .set("los.grid", [24, 24])
        .set("pairs.grid", [28, 28])
        .toml();
    let submit = |plan: String| {
        let (client, base) = (client.clone(), base.clone());
        async move {
            client
                .post(format!("{base}/runs"))
                .bearer_auth(TOKEN)
                .header("content-type", "application/toml")
                .body(plan)
                .send()
                .await
                .unwrap()
        }
    };
    // The pair rate of a capture, from its progress while in the capture stage.
    let rate_of = |id: String| {
        let (client, base) = (client.clone(), base.clone());
        async move {
            let mut first: Option<(Instant, f64)> = None;
            let mut last = (Instant::now(), 0.0);
            loop {
                let v = json(client.get(format!("{base}/runs/{id}")).send().await.unwrap()).await;
                let done = v["pairs_done"].as_f64().unwrap_or(0.0);
                if v["stage"] == "capture" && done > 0.0 {
                    let now = (Instant::now(), done);
                    first.get_or_insert(now);
                    last = now;
                } else if first.is_some() || !["queued", "running"].contains(&v["state"].as_str().unwrap()) {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            let (t0, d0) = first.expect("the capture was seen");
            (last.1 - d0) / last.0.duration_since(t0).as_secs_f64()
        }
    };
    let rss = || -> u64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
        line.split_whitespace().nth(1).unwrap().parse::<u64>().unwrap() * 1024
    };

    let quiet: Value = json(submit(capture_plan.clone()).await).await;
    let quiet_rate = rate_of(quiet["id"].as_str().unwrap().to_owned()).await;

    let busy: Value = json(submit(capture_plan.clone()).await).await;
    let busy_url = format!("{base}/runs/{}", busy["id"].as_str().unwrap());
    // Wait for the capture stage before flooding.
    let t = Instant::now();
    loop {
        let v = json(client.get(&busy_url).send().await.unwrap()).await;
        if v["stage"] == "capture" && v["pairs_done"].as_u64() > Some(0) {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "{v}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let rss_before = rss();
    let done_before = json(client.get(&busy_url).send().await.unwrap()).await["pairs_done"]
        .as_f64()
        .unwrap();
    let t_flood = Instant::now();
    let mut flood = Vec::new();
    for _ in 0..8 {
        let (client, url) = (client.clone(), format!("{base}/runs"));
        flood.push(tokio::spawn(async move {
            let mut counts = [0usize; 2];
            for _ in 0..1250 {
                let s = client
                    .post(&url)
                    .bearer_auth(TOKEN)
                    .header("content-type", "application/toml")
                    .body(PLAN)
                    .send()
                    .await
                    .unwrap()
                    .status();
                match s.as_u16() {
                    201 => counts[0] += 1,
                    429 => counts[1] += 1,
                    other => panic!("flood request got {other}"),
                }
            }
            counts
        }));
    }
    let mut created = 0;
    let mut refused = 0;
    for f in flood {
        let [c, r] = f.await.unwrap();
        created += c;
        refused += r;
    }
    let after = json(client.get(&busy_url).send().await.unwrap()).await;
    let flood_s = t_flood.elapsed().as_secs_f64();
    let rss_after = rss();
    assert_eq!(
        after["stage"], "capture",
        "the capture ended during the flood: {after}"
    );
    let busy_rate = (after["pairs_done"].as_f64().unwrap() - done_before) / flood_s;
    eprintln!(
        "flood: 10,000 submissions in {flood_s:.1} s ({:.0}/s): {created} queued, {refused} refused; \
         RSS {:.1} → {:.1} MiB; pair rate {quiet_rate:.1}/s alone, {busy_rate:.1}/s under the flood",
        10_000.0 / flood_s,
        rss_before as f64 / 1048576.0,
        rss_after as f64 / 1048576.0
    );
    // The queue held the running capture, so 19 more fit.
    assert_eq!(created, 19);
    assert_eq!(refused, 10_000 - 19);
    assert_eq!(run_dirs(dir.path()), 2 + 19);
    assert!(
        rss_after < rss_before + (48 << 20),
        "memory grew by {} MiB under the flood",
        (rss_after - rss_before) >> 20
    );
    assert!(
        busy_rate > 0.9 * quiet_rate,
        "the flood slowed the capture: {busy_rate:.1} vs {quiet_rate:.1} pairs/s"
    );
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// Every route × token (none, wrong, right) × client (loopback, another machine) ×
/// `open-reads`: the token (an admin key) is accepted everywhere; a wrong one is
/// refused everywhere; without one, loopback may read and e-stop, other machines may
/// read only with `open-reads`, and nobody may change anything. (The full role matrix,
/// with keys of every role, expired and revoked, is `tests/run_service.rs`.)
#[tokio::test]
async fn every_route_enforces_the_token_rules_for_every_client() {
    use axum::extract::ConnectInfo;
    use periscope_daemon::access::Role;
    use periscope_daemon::api::access::required_role;
    use periscope_daemon::api::routes;
    for open_reads in [false, true] {
        let dir = tempfile::tempdir().unwrap();
        let extra = if open_reads { "open-reads = true" } else { "" };
        let svc = service(dir.path(), 0.0, extra, "");
        let router = app(AppState::new(Arc::clone(&svc)));
        let (s, v) = call(&router, Method::POST, "/api/v1/runs", true, PLAN).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        let id = v["id"].as_str().unwrap().to_owned();
        for (method, route) in routes() {
            let (method, route) = (method.as_str(), route.as_str());
            let need = required_role(&Method::from_bytes(method.as_bytes()).unwrap(), route).unwrap();
            let uri = route.replace("{id}", &id).replace("{name}", "plan.toml");
            for token in [None, Some("wrong-token-wrong-token-wrong"), Some(TOKEN)] {
                // Loopback as IPv4, as IPv6, and as an IPv4 client of a dual-stack
                // listener (`--bind [::]:…`) sees it: all three are this machine.
                for (peer, remote) in [
                    ("127.0.0.1:50000", false),
                    ("[::ffff:127.0.0.1]:50000", false),
                    ("[::1]:50000", false),
                    ("192.0.2.7:50000", true),
                ] {
                    let mut req = Request::builder().method(method).uri(&uri);
                    if let Some(t) = token {
                        req = req.header(header::AUTHORIZATION, format!("Bearer {t}"));
                    }
                    let body = if (uri.ends_with("/runs") && method == "POST") || uri.ends_with("/check") {
                        PLAN
                    } else {
                        ""
                    };
                    if !body.is_empty() {
                        req = req.header(header::CONTENT_TYPE, "application/toml");
                    }
                    let mut req = req.body(Body::from(body)).unwrap();
                    let peer: std::net::SocketAddr = peer.parse().unwrap();
                    req.extensions_mut().insert(ConnectInfo(peer));
                    let resp = router.clone().oneshot(req).await.unwrap();
                    let status = resp.status();
                    drop(resp);
                    let keyless =
                        (!remote && need <= Role::Observer) || (need == Role::Observer && open_reads);
                    // A wrong key is refused everywhere but at the e-stop from this
                    // machine, which needs none (docs/safety.md).
                    let authorised = match token {
                        None => keyless,
                        Some(t) => t == TOKEN || (route == "/api/v1/estop" && !remote),
                    };
                    let case =
                        format!("{method} {route}, token {token:?}, from {peer}, open-reads {open_reads}");
                    if authorised {
                        assert!(
                            status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN,
                            "{case}: {status}"
                        );
                    } else {
                        assert_eq!(status, StatusCode::UNAUTHORIZED, "{case}");
                    }
                }
            }
            let _ = svc.unlock_queue(None, true);
        }
        // The dashboard's files carry no instrument data: a browser anywhere loads them
        // without a token (it cannot send one for a page load), and the page asks.
        for uri in ["/", "/ui/app.js", "/ui/vendor/uPlot.iife.min.js"] {
            let mut req = Request::builder().uri(uri).body(Body::empty()).unwrap();
            req.extensions_mut().insert(ConnectInfo(
                "192.0.2.7:50000".parse::<std::net::SocketAddr>().unwrap(),
            ));
            let status = router.clone().oneshot(req).await.unwrap().status();
            assert_eq!(status, StatusCode::OK, "{uri}, remote, no token");
        }
        // The e-stop may have held the run; the queue cap is 100, so submissions passed.
        assert!(run_dirs(dir.path()) >= 2);
    }
}

/// `PERISCOPE_TOKEN` is the token `serve` uses, over `[api] token` in the config.
#[test]
fn the_environment_token_overrides_the_configured_one() {
    let dir = tempfile::tempdir().unwrap();
    let inst = instrument(dir.path(), 0.0, "", "");
    let path = dir.path().join("instrument.toml");
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes");
    let text = inst
        .text()
        .replace("\"../scenes/", &format!("\"{}/", scenes.display()));
    std::fs::write(&path, text).unwrap();
    let env_token = "from-the-environment-0123456789";
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(["serve", "--bind", "127.0.0.1:0", "--instrument"])
        .arg(&path)
        .env("PERISCOPE_TOKEN", env_token)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The bound address is printed on stderr.
    let mut stderr = std::io::BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    let addr = loop {
        line.clear();
        assert!(
            std::io::BufRead::read_line(&mut stderr, &mut line).unwrap() > 0,
            "serve exited"
        );
        if let Some(rest) = line.split("http://").nth(1) {
            break rest.split('/').next().unwrap().to_owned();
        }
    };
    let post = |token: &str| {
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        std::io::Write::write_all(
            &mut s,
            format!(
                                "POST /api/v1/runs/no-such-run/abort HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {token}\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
            )
            .as_bytes(),
        )
        .unwrap();
        let mut reply = String::new();
        std::io::Read::read_to_string(&mut s, &mut reply).unwrap();
        reply.lines().next().unwrap_or_default().to_owned()
    };
    let with_config = post(TOKEN);
    let with_env = post(env_token);
    let _ = child.kill();
    let _ = child.wait();
    assert!(with_config.contains(" 401 "), "{with_config}");
    // Past the key check: the run does not exist.
    assert!(with_env.contains(" 404 "), "{with_env}");
}

/// The `Authorization` scheme is case-insensitive (RFC 9110 §11.1): `bearer` and
/// `BEARER` with the right token are let through, the wrong token is not.
#[tokio::test]
async fn the_bearer_scheme_is_accepted_in_any_case() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, "", "")));
    for scheme in ["bearer", "BEARER", "Bearer"] {
        let auth = format!("{scheme} {TOKEN}");
        let (s, b) = send(
            &router,
            request(
                Method::POST,
                "/api/v1/runs",
                false,
                &[("authorization", &auth)],
                PLAN,
            ),
        )
        .await;
        assert_eq!(
            s,
            StatusCode::CREATED,
            "{scheme}: {}",
            String::from_utf8_lossy(&b)
        );
    }
    let (s, _) = send(
        &router,
        request(
            Method::POST,
            "/api/v1/runs",
            false,
            &[("authorization", "bearer wrong-token")],
            PLAN,
        ),
    )
    .await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
}

/// `app` served on a loopback port by the daemon's own connection handling: its address,
/// the notice that stops it, and the server's task.
async fn serve(
    app: axum::Router,
    limits: periscope_daemon::api::server::ConnectionLimits,
) -> (
    std::net::SocketAddr,
    Arc<tokio::sync::Notify>,
    tokio::task::JoinHandle<std::io::Result<()>>,
) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let stop = Arc::new(tokio::sync::Notify::new());
    let server = {
        let stop = Arc::clone(&stop);
        tokio::spawn(async move {
            periscope_daemon::api::server::serve_connections(listener, app, limits, async move {
                stop.notified().await
            })
            .await
        })
    };
    (addr, stop, server)
}

/// A client that stops reading a response is cut off once no byte has gone out for the
/// write timeout (`[api] request-timeout-s`, 1 s here): it gets part of a 64 MiB body,
/// then the end of the connection, not the whole body whenever it resumes reading.
/// Without it such a client held its socket, and a download or stream slot, forever.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_is_cut_off_after_the_write_timeout() {
    use periscope_daemon::api::server::ConnectionLimits;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    const BODY: usize = 64 << 20;
    let app = axum::Router::new().route("/big", axum::routing::get(|| async { vec![7u8; BODY] }));
    let limits = ConnectionLimits {
        header_timeout: Duration::from_secs(5),
        max_connections: 8,
        max_per_peer: 8,
        write_timeout: Duration::from_secs(1),
    };
    let (addr, stop, server) = serve(app, limits).await;
    let mut client = tokio::net::TcpStream::connect(addr).await.unwrap();
    client
        .write_all(b"GET /big HTTP/1.1\r\nhost: localhost\r\n\r\n")
        .await
        .unwrap();
    // Not reading: the server's writes wait on full socket buffers, then time out.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let mut got = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(20), client.read_to_end(&mut got)).await;
    let read = read.expect("the connection was never closed");
    assert!(
        read.is_err() || got.len() < BODY,
        "the whole body ({} bytes) arrived after 3 s of not reading",
        got.len()
    );
    stop.notify_one();
    server.await.unwrap().unwrap();
}

/// A request head longer than the read buffer (`server::MAX_BUF`, 64 KiB) is answered
/// 431 and the connection closed once the buffer is full, not held until the header
/// timeout while it grows (hyper's default buffer took about 400 KB a connection, with
/// no key needed to send headers). A head within it is served.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_head_past_the_read_buffer_is_refused_when_it_fills() {
    use periscope_daemon::api::server::{ConnectionLimits, MAX_BUF};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let app = axum::Router::new().route("/", axum::routing::get(|| async { "ok" }));
    let limits = ConnectionLimits {
        header_timeout: Duration::from_secs(30),
        max_connections: 8,
        max_per_peer: 8,
        write_timeout: Duration::from_secs(5),
    };
    let (addr, stop, server) = serve(app, limits).await;
    // Within the buffer: served.
    let mut client = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "GET / HTTP/1.1\r\nhost: localhost\r\nx-pad: {}\r\nconnection: close\r\n\r\n",
        "a".repeat(16 << 10)
    );
    client.write_all(head.as_bytes()).await.unwrap();
    let mut got = Vec::new();
    client.read_to_end(&mut got).await.unwrap();
    assert!(
        got.starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&got[..got.len().min(200)])
    );
    // One header growing past it, never ended: refused once it fills, well before the
    // 30 s header timeout.
    let mut client = tokio::net::TcpStream::connect(addr).await.unwrap();
    let t = std::time::Instant::now();
    client
        .write_all(b"GET / HTTP/1.1\r\nhost: localhost\r\nx-pad: ")
        .await
        .unwrap();
    let chunk = vec![b'a'; 8 << 10];
    for _ in 0..(2 * MAX_BUF / chunk.len()) {
        if client.write_all(&chunk).await.is_err() {
            break;
        }
    }
    let mut got = Vec::new();
    let read = tokio::time::timeout(Duration::from_secs(10), client.read_to_end(&mut got)).await;
    assert!(read.is_ok(), "the connection was held open");
    assert!(t.elapsed() < Duration::from_secs(10), "{:?}", t.elapsed());
    assert!(
        got.is_empty() || got.starts_with(b"HTTP/1.1 431"),
        "{}",
        String::from_utf8_lossy(&got[..got.len().min(200)])
    );
    stop.notify_one();
    server.await.unwrap().unwrap();
}

/// This machine's address on its route out (a UDP "connection" sends nothing), if it
/// has one that is not loopback: what a connection to it comes from.
fn non_loopback_address() -> Option<std::net::IpAddr> {
    let udp = std::net::UdpSocket::bind("0.0.0.0:0").ok()?;
    udp.connect("192.0.2.1:9").ok()?;
    let ip = udp.local_addr().ok()?.ip();
    (!ip.is_loopback() && !ip.is_unspecified()).then_some(ip)
}

/// Idle connections from one remote host (a review, 2026-12-06): at most `[api]
/// max-connections-per-peer` are held, the rest closed at once; and with every
/// connection slot taken, loopback (the instrument's own computer, whose e-stop needs
/// no key) still gets a connection from its reserve. Until then the server stopped
/// accepting at its cap, and a host reconnecting as each idle connection timed out kept
/// the e-stop and the health check from connecting for a minute.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_host_cannot_hold_every_connection_or_keep_loopback_out() {
    use periscope_daemon::api::server::ConnectionLimits;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let Some(remote) = non_loopback_address() else {
        common::skipped(format_args!(
            "one_host_cannot_hold_every_connection_or_keep_loopback_out: this machine has no address but loopback to connect from"
        ));
        return;
    };
    let held = |limits: ConnectionLimits| async move {
        let app = axum::Router::new().route("/api/v1/health", axum::routing::get(|| async { "ok" }));
        let listener = tokio::net::TcpListener::bind("0.0.0.0:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let stop = Arc::new(tokio::sync::Notify::new());
        let server = {
            let stop = Arc::clone(&stop);
            tokio::spawn(async move {
                periscope_daemon::api::server::serve_connections(listener, app, limits, async move {
                    stop.notified().await
                })
                .await
            })
        };
        // Twenty idle connections from the remote address, opened one after another.
        let mut idle = Vec::new();
        for _ in 0..20 {
            idle.push(tokio::net::TcpStream::connect((remote, port)).await.unwrap());
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
        let mut open = 0;
        for c in &mut idle {
            let mut b = [0u8; 1];
            // Still open: the read waits; closed: it ends at once.
            if tokio::time::timeout(Duration::from_millis(100), c.read(&mut b))
                .await
                .is_err()
            {
                open += 1;
            }
        }
        // The health check from loopback, within a second.
        let t = std::time::Instant::now();
        let answered = tokio::time::timeout(Duration::from_secs(2), async {
            let mut c = tokio::net::TcpStream::connect(("127.0.0.1", port)).await.unwrap();
            c.write_all(b"GET /api/v1/health HTTP/1.1\r\nhost: localhost\r\nconnection: close\r\n\r\n")
                .await
                .unwrap();
            let mut got = Vec::new();
            c.read_to_end(&mut got).await.unwrap();
            got
        })
        .await;
        stop.notify_one();
        drop(idle);
        let _ = server.await;
        (
            open,
            answered
                .ok()
                .filter(|g| g.starts_with(b"HTTP/1.1 200"))
                .map(|_| t.elapsed()),
        )
    };
    let limits = |per_peer| ConnectionLimits {
        header_timeout: Duration::from_secs(5),
        max_connections: 8,
        max_per_peer: per_peer,
        write_timeout: Duration::from_secs(5),
    };
    let (open, health) = held(limits(4)).await;
    assert_eq!(
        open, 4,
        "idle connections from one host held, with a cap of 4 a host"
    );
    assert!(health.is_some(), "loopback's health check was not answered");
    // The host's cap as high as the server's: it holds every general slot, and
    // loopback is served from its reserve.
    let (open, health) = held(limits(8)).await;
    assert_eq!(open, 8);
    assert!(
        health.is_some_and(|t| t < Duration::from_secs(1)),
        "with every general slot held, loopback waited {health:?}"
    );
}

/// A request body trickled in a byte at a time (a review, 2026-12-06) holds its
/// connection, not one of the API's turns: with one turn (`max-concurrent = 1`) and a
/// submission's body trickling, a read of the runs list is answered at once, and the
/// trickle ends 408 at the request timeout. Until then the body was read inside the
/// turn, and eight such clients held every turn for 30 s.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trickled_body_holds_no_turn_of_the_api() {
    use periscope_daemon::api::server::ConnectionLimits;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, "max-concurrent = 1\nrequest-timeout-s = 3", "");
    let app = periscope_daemon::api::app(periscope_daemon::api::AppState::new(Arc::clone(&svc)));
    let limits = ConnectionLimits {
        header_timeout: Duration::from_secs(10),
        max_connections: 32,
        max_per_peer: 32,
        write_timeout: Duration::from_secs(10),
    };
    let (addr, stop, server) = serve(app, limits).await;
    let mut trickle = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /api/v1/runs HTTP/1.1\r\nhost: localhost\r\nauthorization: Bearer {TOKEN}\r\n\
         content-type: application/toml\r\ncontent-length: 1000\r\n\r\nname = "
    );
    trickle.write_all(head.as_bytes()).await.unwrap();
    let dripping = tokio::spawn(async move {
        for _ in 0..40 {
            tokio::time::sleep(Duration::from_millis(100)).await;
            if trickle.write_all(b" ").await.is_err() {
                break;
            }
        }
        let mut got = Vec::new();
        let _ = tokio::time::timeout(Duration::from_secs(10), trickle.read_to_end(&mut got)).await;
        got
    });
    tokio::time::sleep(Duration::from_millis(300)).await;
    let t = std::time::Instant::now();
    let resp = reqwest::Client::new()
        .get(format!("http://{addr}/api/v1/runs"))
        .bearer_auth(TOKEN)
        .timeout(Duration::from_secs(10))
        .send()
        .await
        .unwrap();
    let waited = t.elapsed();
    assert_eq!(resp.status(), reqwest::StatusCode::OK);
    assert!(
        waited < Duration::from_secs(1),
        "the runs list waited {waited:?} behind a trickled body"
    );
    let got = dripping.await.unwrap();
    assert!(
        got.starts_with(b"HTTP/1.1 408"),
        "{}",
        String::from_utf8_lossy(&got[..got.len().min(300)])
    );
    assert_eq!(
        run_dirs(dir.path()),
        0,
        "a run was made from a body that never arrived"
    );
    stop.notify_one();
    server.await.unwrap().unwrap();
    svc.shutdown();
}

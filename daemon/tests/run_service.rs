//! The run service at Bluesky's level, through the router: the role matrix (every
//! route × every role × key valid, expired and revoked), the catalogue's queries, the
//! audit trail, the queue's operations (lock, reorder, move, batch, run again), and
//! `/metrics` read by an independent Prometheus text-format parser.
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::ConnectInfo;
use axum::http::{Method, Request, StatusCode, header};
use periscope_daemon::access::{KeyStore, Role};
use periscope_daemon::api::{AppState, app, routes};
use periscope_daemon::service::Service;
use serde_json::{Value, json};
use tower::ServiceExt;

mod common;

const TOKEN: &str = "test-token-0123456789abcdef";
const PLAN: &str = include_str!("../../tests/data/plans/small-fbp.toml");

fn service(runs: &Path) -> Arc<Service> {
    let src = common::sim_instrument(runs, 0.0, &format!("token = \"{TOKEN}\"\n"), "");
    Service::open(src, Some(TOKEN.to_owned())).unwrap()
}

/// A request with a bearer key, a body (TOML for plans, JSON otherwise), and a peer.
fn request(method: &Method, uri: &str, key: Option<&str>, body: &str, remote: bool) -> Request<Body> {
    let mut req = Request::builder().method(method.clone()).uri(uri);
    if let Some(k) = key {
        req = req.header(header::AUTHORIZATION, format!("Bearer {k}"));
    }
    if !body.is_empty() {
        let ct = if body.trim_start().starts_with('{') {
            "application/json"
        } else {
            "application/toml"
        };
        req = req.header(header::CONTENT_TYPE, ct);
    }
    let mut req = req.body(Body::from(body.to_owned())).unwrap();
    let peer: std::net::SocketAddr = if remote {
        "192.0.2.7:50000".parse().unwrap()
    } else {
        "127.0.0.1:50000".parse().unwrap()
    };
    req.extensions_mut().insert(ConnectInfo(peer));
    req
}

async fn call(
    router: &axum::Router,
    method: Method,
    uri: &str,
    key: Option<&str>,
    body: &str,
) -> (StatusCode, Value) {
    let resp = router
        .clone()
        .oneshot(request(&method, uri, key, body, false))
        .await
        .unwrap();
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), 64 << 20).await.unwrap();
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

/// A JSON request with a bearer key past the queue's maintenance lock (its key in
/// `X-Periscope-Lock-Key`).
async fn call_locked(
    router: &axum::Router,
    method: Method,
    uri: &str,
    key: &str,
    body: String,
) -> (StatusCode, Value) {
    let req = Request::builder()
        .method(method)
        .uri(uri)
        .header(header::AUTHORIZATION, format!("Bearer {key}"))
        .header(header::CONTENT_TYPE, "application/json")
        .header("x-periscope-lock-key", "spad-lock-key")
        .body(Body::from(body))
        .unwrap();
    let resp = router.clone().oneshot(req).await.unwrap();
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), 1 << 20).await.unwrap();
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

/// A body each route accepts, so an authorised request is judged on its key alone.
fn body_for(method: &str, route: &str) -> String {
    match (method, route) {
        ("POST", "/api/v1/runs") | ("POST", "/api/v1/check") => PLAN.into(),
        ("POST", "/api/v1/runs/batch") => json!({ "plans": [PLAN] }).to_string(),
        ("PATCH", "/api/v1/runs/{id}") => json!({ "add_tags": ["t"] }).to_string(),
        ("PUT", "/api/v1/queue") => json!({ "order": [] }).to_string(),
        ("POST", "/api/v1/queue/move") => json!({ "run": "x", "position": 0 }).to_string(),
        ("POST", "/api/v1/queue/lock") => json!({ "reason": "matrix", "key": "matrix-lock-key" }).to_string(),
        ("POST", "/api/v1/queue/unlock") => json!({ "key": "matrix-lock-key" }).to_string(),
        ("POST", "/api/v1/keys") => json!({ "name": "k-matrix", "role": "observer" }).to_string(),
        _ => String::new(),
    }
}

/// Every documented route × caller (no key on loopback and remote, the token, a key of
/// each role, expired and revoked keys, a wrong key): the request is refused (401 for
/// no, unknown, expired or revoked keys; 403 for a role too low) exactly when the role
/// matrix says so, and never otherwise.
#[tokio::test]
async fn every_route_follows_the_role_matrix_for_every_key() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let keys = KeyStore::open(dir.path(), None);
    let now = periscope_daemon::run_dir::unix_now();
    let mut callers: Vec<(String, Option<String>, Option<Role>, bool)> = Vec::new();
    for role in [Role::Estop, Role::Observer, Role::Operator, Role::Admin] {
        let (_, secret) = keys
            .create(&format!("k-{}", role.name()), role, Some(now + 3600.0), "test")
            .unwrap();
        callers.push((format!("{} key", role.name()), Some(secret), Some(role), false));
    }
    let (_, expired) = keys
        .create("k-expired", Role::Admin, Some(now + 1.0), "test")
        .unwrap();
    let (_, revoked) = keys.create("k-revoked", Role::Admin, None, "test").unwrap();
    keys.revoke("k-revoked").unwrap();
    callers.push(("revoked admin key".into(), Some(revoked), None, false));
    callers.push(("wrong key".into(), Some("psk_0000".into()), None, false));
    callers.push(("token".into(), Some(TOKEN.into()), Some(Role::Admin), false));
    callers.push(("no key, loopback".into(), None, None, false));
    callers.push(("no key, remote".into(), None, None, true));
    // Let the expiring key expire.
    std::thread::sleep(Duration::from_millis(1100));
    callers.push(("expired admin key".into(), Some(expired), None, false));
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let mut checked = 0;
    for (method, route) in routes() {
        let m = Method::from_bytes(method.as_bytes()).unwrap();
        let need = periscope_daemon::api::access::required_role(&m, &route).expect("an API route");
        let uri = route.replace("{id}", &id).replace(
            "{name}",
            if route.starts_with("/api/v1/keys") {
                "k-nobody"
            } else {
                "plan.toml"
            },
        );
        for (who, key, role, remote) in &callers {
            let body = body_for(&method, &route);
            let resp = router
                .clone()
                .oneshot(request(&m, &uri, key.as_deref(), &body, *remote))
                .await
                .unwrap();
            let status = resp.status();
            drop(resp);
            let keyless_ok = key.is_none() && !remote && need <= Role::Observer;
            // The e-stop from this machine goes ahead whatever key is sent.
            let loopback_estop = route == "/api/v1/estop" && !remote;
            let expected = match (key, role) {
                (Some(_), None) if loopback_estop => None,
                (Some(_), None) => Some(StatusCode::UNAUTHORIZED),
                (Some(_), Some(r)) if *r < need => Some(StatusCode::FORBIDDEN),
                (Some(_), Some(_)) => None,
                (None, _) if keyless_ok => None,
                (None, _) => Some(StatusCode::UNAUTHORIZED),
            };
            let case = format!("{method} {route} by {who}: {status}");
            match expected {
                Some(e) => assert_eq!(status, e, "{case}"),
                None => assert!(
                    status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN,
                    "{case}"
                ),
            }
            checked += 1;
        }
        // The matrix's lock leaves the queue locked for the next routes; unlock it.
        let _ = svc.unlock_queue(None, true);
    }
    assert!(checked > 200, "{checked}");
    // Reads refused for their role are not in the audit trail (a wall panel's e-stop key
    // polling the status must not fill it); changes refused for it are.
    let (_, audit) = call(
        &router,
        Method::GET,
        "/api/v1/audit?actor=k-estop&limit=1000",
        None,
        "",
    )
    .await;
    let entries = audit["entries"].as_array().unwrap();
    let changes = routes().iter().filter(|(m, _)| m != "GET").count();
    assert!(
        !entries.is_empty() && entries.len() <= changes,
        "{} entries for the e-stop key",
        entries.len()
    );
    // Refused authentications are in the audit trail, under the key's name where known.
    let (_, audit) = call(
        &router,
        Method::GET,
        "/api/v1/audit?actor=k-revoked&limit=5",
        None,
        "",
    )
    .await;
    assert!(audit["total"].as_u64().unwrap() > 0, "{audit}");
    assert_eq!(audit["entries"][0]["outcome"], "refused");
    svc.shutdown();
}

async fn wait_state(router: &axum::Router, id: &str, states: &[&str]) -> Value {
    let t = Instant::now();
    loop {
        let (_, v) = call(router, Method::GET, &format!("/api/v1/runs/{id}"), None, "").await;
        if states.contains(&v["state"].as_str().unwrap_or("")) {
            return v;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "{id} never became {states:?}: {v}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A lab day through the API: keys of two people, a batch, a locked queue that starts
/// nothing, reorder and move, a run again, tags and a note; the catalogue answers
/// each filter, and the audit trail names who did what.
///
/// In a process of its own ([`common::alone`]): the rebuild takes the catalogue's lock
/// the moment the daemon lets it go.
#[test]
fn the_catalogue_queue_and_audit_follow_a_lab_day() {
    common::alone("the_catalogue_queue_and_audit_follow_a_lab_day", 0, lab_day());
}

async fn lab_day() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let keys = KeyStore::open(dir.path(), None);
    let (_, alice) = keys.create("alice", Role::Operator, None, "test").unwrap();
    let (_, root) = keys.create("root", Role::Admin, None, "test").unwrap();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::GET, "/api/v1/whoami", Some(&alice), "").await;
    assert_eq!(
        (s, &v["name"], &v["role"]),
        (StatusCode::OK, &json!("alice"), &json!("operator"))
    );

    // A lock key that could not be sent back in its header (eight bytes, but four
    // characters, none of them ASCII) is refused.
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/queue/lock",
        Some(&root),
        &json!({"reason": "realigning", "key": "\u{e9}\u{e9}\u{e9}\u{e9}"}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(v["message"].as_str().unwrap().contains("visible ASCII"), "{v}");

    // The queue is locked before the worker starts: nothing may start.
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/queue/lock",
        Some(&root),
        &json!({"reason": "realigning the SPAD arm", "key": "spad-lock-key"}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let worker = svc.start_worker();
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(&alice), PLAN).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::LOCKED, Some("queue-locked")),
        "{v}"
    );
    assert!(
        v["message"].as_str().unwrap().contains("realigning the SPAD arm"),
        "{v}"
    );
    // A run that does not exist is not found, locked or not (it was 423).
    for action in ["resume", "again"] {
        let path = format!("/api/v1/runs/20200101-000000-none/{action}");
        let (s, v) = call(&router, Method::POST, &path, Some(&alice), "").await;
        assert_eq!(s, StatusCode::NOT_FOUND, "{action}: {v}");
    }
    // A batch with one invalid plan queues none.
    let bad_batch = json!({"plans": [PLAN, "name = 3"]}).to_string();
    let (s, v) = call_locked(&router, Method::POST, "/api/v1/runs/batch", &alice, bad_batch).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(v["message"].as_str().unwrap().contains("batch plan 2"), "{v}");
    // With the lock key, the batch of three is queued and stays queued.
    let batch = json!({"plans": [PLAN, PLAN, PLAN]}).to_string();
    let (s, runs) = call_locked(&router, Method::POST, "/api/v1/runs/batch", &alice, batch).await;
    assert_eq!(s, StatusCode::CREATED, "{runs}");
    let ids: Vec<String> = runs
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["id"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(ids.len(), 3);
    tokio::time::sleep(Duration::from_millis(500)).await;
    let (_, q) = call(&router, Method::GET, "/api/v1/queue", None, "").await;
    assert_eq!(q["running"], Value::Null, "a locked queue starts nothing: {q}");
    assert_eq!(q["lock"]["by"], "root");
    assert!(
        q["lock"].get("key_sha256").is_none(),
        "the lock key's digest is not shown"
    );
    // Reorder (the lock key again) and move: the last goes first, then the first last.
    let order = json!({"order": [ids[2], ids[0], ids[1]]}).to_string();
    let (s, v) = call_locked(&router, Method::PUT, "/api/v1/queue", &root, order).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    // The last moved to the end, where it is: the order stands, the move is audited.
    let to_end = json!({"run": ids[1], "position": 2}).to_string();
    let (s, v) = call_locked(&router, Method::POST, "/api/v1/queue/move", &root, to_end).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, v) = call(
        &router,
        Method::PUT,
        "/api/v1/queue",
        Some(&root),
        &json!({"order": [ids[0]]}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::LOCKED, "without the lock key: {v}");
    // Alice (an operator) may not reorder, whatever the lock.
    let (s, _) = call(
        &router,
        Method::PUT,
        "/api/v1/queue",
        Some(&alice),
        &json!({"order": []}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/queue/unlock",
        Some(&root),
        &json!({"key": "wrong-key!"}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::LOCKED, "{v}");
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/queue/unlock",
        Some(&root),
        &json!({"key": "spad-lock-key"}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    // Unlocked: they run in the new order.
    let last = wait_state(&router, &ids[1], &["completed"]).await;
    assert_eq!(last["state"], "completed");
    let by_start: Vec<f64> = ids
        .iter()
        .map(|id| {
            let rec = svc.catalogue().get(id).unwrap().unwrap().0;
            rec.history
                .iter()
                .find(|c| c.state == periscope_daemon::run_dir::RunState::Running)
                .map(|c| c.at_unix_s)
                .unwrap()
        })
        .collect();
    assert!(
        by_start[2] < by_start[0] && by_start[0] < by_start[1],
        "{by_start:?}"
    );

    // Run again, tag, annotate.
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{}/again", ids[0]),
        Some(&alice),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let again = v["id"].as_str().unwrap().to_owned();
    wait_state(&router, &again, &["completed"]).await;
    let (s, v) = call(
        &router,
        Method::PATCH,
        &format!("/api/v1/runs/{again}"),
        Some(&alice),
        &json!({"add_tags": ["repeat", "good"], "note": "same plan, new day"}).to_string(),
    )
    .await;
    assert_eq!(
        (s, &v["tags"]),
        (StatusCode::OK, &json!(["good", "repeat"])),
        "{v}"
    );
    let (s, v) = call(
        &router,
        Method::PATCH,
        &format!("/api/v1/runs/{again}"),
        Some(&alice),
        &json!({"add_tags": ["bad tag"]}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");

    // The catalogue: filters and paging.
    tokio::time::sleep(Duration::from_millis(300)).await; // the indexer's last touch
    let (s, page) = call(&router, Method::GET, "/api/v1/catalogue?tag=repeat", None, "").await;
    assert_eq!(s, StatusCode::OK, "{page}");
    assert_eq!(page["total"], 1);
    let rec = &page["runs"][0];
    assert_eq!(rec["id"], again.as_str());
    assert_eq!(rec["again_of"], ids[0].as_str());
    assert_eq!(rec["submitted_by"], "alice");
    assert_eq!(rec["note"], "same plan, new day");
    assert_eq!(rec["method"], "fbp");
    let states: Vec<&str> = rec["history"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["state"].as_str().unwrap())
        .collect();
    assert_eq!(states.first(), Some(&"queued"));
    assert_eq!(states.last(), Some(&"completed"));
    let (_, page) = call(
        &router,
        Method::GET,
        "/api/v1/catalogue?state=completed&sort=created&order=desc&limit=2",
        None,
        "",
    )
    .await;
    assert_eq!(page["total"], 4);
    assert_eq!(page["runs"].as_array().unwrap().len(), 2);
    assert_eq!(page["runs"][0]["id"], again.as_str());
    let resp = router
        .clone()
        .oneshot(request(
            &Method::GET,
            "/api/v1/runs?limit=1&q=same%20PLAN",
            None,
            "",
            false,
        ))
        .await
        .unwrap();
    assert_eq!(resp.headers()["x-total-count"], "1");
    let (s, v) = call(&router, Method::GET, "/api/v1/catalogue?state=lost", None, "").await;
    assert_eq!(s, StatusCode::BAD_REQUEST);
    assert!(v["message"].as_str().unwrap().contains("state `lost`"), "{v}");

    // The audit trail: who did what.
    let (_, audit) = call(&router, Method::GET, "/api/v1/audit?limit=100", None, "").await;
    let entries = audit["entries"].as_array().unwrap();
    let did = |actor: &str, action: &str, outcome: &str| {
        entries
            .iter()
            .any(|e| e["actor"] == actor && e["action"] == action && e["outcome"] == outcome)
    };
    assert!(did("root", "queue-lock", "ok"));
    assert!(did("alice", "submit", "refused"), "the locked submit");
    assert!(did("alice", "submit-batch", "ok"));
    assert!(did("alice", "submit-batch", "refused"));
    assert!(did("root", "queue-order", "ok"));
    assert!(
        entries
            .iter()
            .any(|e| e["action"] == "queue-move" && e["target"] == ids[1].as_str()),
        "a move names the run it moved: {audit}"
    );
    assert!(did("alice", "queue-order", "refused"), "the operator's reorder");
    assert!(did("root", "queue-unlock", "refused"));
    assert!(did("root", "queue-unlock", "ok"));
    assert!(did("alice", "again", "ok"));
    assert!(did("alice", "annotate", "ok"));
    // An e-stop from loopback without a key is recorded too.
    let (s, _) = call(&router, Method::POST, "/api/v1/estop", None, "").await;
    assert_eq!(s, StatusCode::OK);
    let (_, audit) = call(&router, Method::GET, "/api/v1/audit?action=estop", None, "").await;
    assert_eq!(audit["entries"][0]["actor"], "loopback");

    // The catalogue rebuilt from the directories holds the same rows.
    let before = svc.catalogue().query(&Default::default()).unwrap();
    // Not while the daemon runs (it would keep writing to the deleted file)...
    let refused = periscope_daemon::catalogue::Catalogue::rebuild(dir.path())
        .err()
        .expect("refused");
    assert!(
        refused.to_string().contains("stop it before a rebuild"),
        "{refused}"
    );
    svc.shutdown();
    worker.join().unwrap();
    drop(router);
    drop(svc);
    // ...after it: the same rows.
    let (cat, _) = periscope_daemon::catalogue::Catalogue::rebuild(dir.path()).unwrap();
    assert_eq!(cat.query(&Default::default()).unwrap(), before);
}

/// `/metrics` is the Prometheus text format (parsed by `prometheus-parse`, an
/// independent parser) with the instrument's, queue's, runs' and requests' metrics.
#[tokio::test]
async fn metrics_parse_as_prometheus_text() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED);
    let id = v["id"].as_str().unwrap().to_owned();
    wait_state(&router, &id, &["completed"]).await;
    let _ = call(&router, Method::GET, "/api/v1/runs/nope", None, "").await;
    // A wrong key is an authentication failure; a good key of too low a role (a wall
    // panel's e-stop key reading the status) is a role refusal, counted apart so that
    // it cannot fire the failed-authentication alert.
    let keys = KeyStore::open(dir.path(), None);
    let (_, panel) = keys.create("panel", Role::Estop, None, "test").unwrap();
    let (s, _) = call(&router, Method::GET, "/api/v1/runs", Some(&panel), "").await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (s, _) = call(&router, Method::GET, "/api/v1/runs", Some("psk_wrong"), "").await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    // The runs per state come from the catalogue, which its indexer updates moments
    // after run.json (a clean-clone CI run scraped it still "running").
    let t = Instant::now();
    let text = loop {
        let resp = router
            .clone()
            .oneshot(request(&Method::GET, "/metrics", None, "", false))
            .await
            .unwrap();
        assert_eq!(resp.status(), StatusCode::OK);
        assert!(
            resp.headers()[header::CONTENT_TYPE]
                .to_str()
                .unwrap()
                .starts_with("text/plain; version=0.0.4")
        );
        let bytes = axum::body::to_bytes(resp.into_body(), 1 << 20).await.unwrap();
        let text = String::from_utf8(bytes.to_vec()).unwrap();
        if text.contains("periscope_runs{state=\"completed\"} 1") || t.elapsed() > Duration::from_secs(10) {
            break text;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    let lines = text.lines().map(|l| Ok(l.to_owned()));
    let scrape = prometheus_parse::Scrape::parse(lines).expect("Prometheus text format");
    let value = |name: &str, label: Option<(&str, &str)>| -> Option<f64> {
        scrape
            .samples
            .iter()
            .find(|s| s.metric == name && label.is_none_or(|(k, v)| s.labels.get(k) == Some(v)))
            .map(|s| match s.value {
                prometheus_parse::Value::Gauge(v)
                | prometheus_parse::Value::Counter(v)
                | prometheus_parse::Value::Untyped(v) => v,
                prometheus_parse::Value::Histogram(ref b) => b.last().map_or(0.0, |b| b.count),
                prometheus_parse::Value::Summary(_) => 0.0,
            })
    };
    for name in [
        "periscope_laser_emission",
        "periscope_interlock_closed",
        "periscope_diffuser_in",
        "periscope_reading_age_seconds",
        "periscope_capture_pair_rate",
        "periscope_queue_length",
        "periscope_queue_locked",
        "periscope_instrument_busy",
        "periscope_status_interval_seconds",
    ] {
        assert!(value(name, None).is_some(), "{name} missing:\n{text}");
    }
    // Captures run for hours: the stage buckets reach a day (until 2026-12-07 they
    // stopped at 1638.4 s).
    assert!(
        text.contains("periscope_stage_duration_seconds_bucket{le=\"104857.6\",stage=\"capture\"}")
            || text.contains("periscope_stage_duration_seconds_bucket{stage=\"capture\",le=\"104857.6\"}"),
        "{text}"
    );
    assert_eq!(
        value("periscope_runs", Some(("state", "completed"))),
        Some(1.0),
        "{text}"
    );
    assert_eq!(
        value("periscope_runs_finished_total", Some(("state", "completed"))),
        Some(1.0),
        "{text}"
    );
    assert!(value("periscope_count_rate_hertz", Some(("channel", "detector"))).is_some());
    // Every pair the run stored, counted for rate(): the live events may come
    // coalesced, and the counter goes by how far the run's count moved.
    let (s, run) = call(
        &router,
        Method::GET,
        &format!("/api/v1/runs/{id}"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let stored = run["pairs_done"].as_f64().unwrap();
    assert!(stored > 0.0, "{run}");
    assert_eq!(
        value("periscope_capture_pairs_total", None),
        Some(stored),
        "{text}"
    );
    assert!(
        value("periscope_capture_photons_total", None).is_some_and(|c| c > 0.0),
        "{text}"
    );
    assert_eq!(value("periscope_auth_failures_total", None), Some(1.0), "{text}");
    assert_eq!(value("periscope_role_refusals_total", None), Some(1.0), "{text}");
    assert!(
        text.contains("periscope_stage_duration_seconds_bucket{") && text.contains("stage=\"capture\""),
        "{text}"
    );
    assert!(
        text.contains("periscope_recon_duration_seconds_count 1"),
        "{text}"
    );
    assert!(
        text.contains(
            "periscope_http_errors_total{method=\"GET\",route=\"/api/v1/runs/{id}\",status=\"404\"} 1"
        ),
        "{text}"
    );
    assert!(
        text.contains(
            "periscope_http_request_duration_seconds_count{method=\"POST\",route=\"/api/v1/runs\"} 1"
        )
    );
    // A client inventing methods adds no series.
    let _ = router
        .clone()
        .oneshot(request(
            &Method::from_bytes(b"FROB").unwrap(),
            "/api/v1/runs",
            None,
            "",
            false,
        ))
        .await
        .unwrap();
    let resp = router
        .clone()
        .oneshot(request(&Method::GET, "/metrics", None, "", false))
        .await
        .unwrap();
    let bytes = axum::body::to_bytes(resp.into_body(), 1 << 20).await.unwrap();
    let text = String::from_utf8(bytes.to_vec()).unwrap();
    assert!(
        !text.contains("FROB") && text.contains("method=\"other\""),
        "{text}"
    );
    // Remote scrapers need a key (observer or above).
    let resp = router
        .clone()
        .oneshot(request(&Method::GET, "/metrics", None, "", true))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::UNAUTHORIZED);
    svc.shutdown();
    worker.join().unwrap();
}

/// `periscope ARGS --instrument CONFIG`, CONFIG being `src` written into `dir` (its
/// scene path absolute): the exit code, stdout and stderr.
fn cli(
    dir: &Path,
    src: &periscope_daemon::config::TomlSource,
) -> impl Fn(&[&str]) -> (Option<i32>, String, String) + use<> {
    let config = dir.join("instrument.toml");
    let scenes = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/scenes");
    std::fs::write(
        &config,
        src.text()
            .replace("\"../scenes/", &format!("\"{}/", scenes.display())),
    )
    .unwrap();
    move |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
            .args(args)
            .arg("--instrument")
            .arg(&config)
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stdout).into_owned(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    }
}

/// The command line over the same runs directory as a daemon: a key made by
/// `periscope keys create` works at once, `periscope runs` finds the daemon's runs by
/// tag, `periscope keys revoke` stops the key at the next request, and
/// `periscope catalogue rebuild` and `periscope audit` report what the API did.
///
/// In a process of its own ([`common::alone`]): the rebuild takes the catalogue's lock
/// the moment the daemon lets it go.
#[test]
fn the_command_line_shares_keys_catalogue_and_audit_with_the_daemon() {
    common::alone(
        "the_command_line_shares_keys_catalogue_and_audit_with_the_daemon",
        0,
        command_line_beside_the_daemon(),
    );
}

async fn command_line_beside_the_daemon() {
    let dir = tempfile::tempdir().unwrap();
    let src = common::sim_instrument(dir.path(), 0.0, &format!("token = \"{TOKEN}\"\n"), "");
    let periscope = cli(dir.path(), &src);
    let svc = Service::open(src, Some(TOKEN.to_owned())).unwrap();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (code, secret, err) = periscope(&["keys", "create", "bob", "--role", "operator", "--expires", "30d"]);
    assert_eq!(code, Some(0), "{err}");
    let secret = secret.trim().to_owned();
    assert!(
        secret.starts_with("psk_") && err.contains("bob"),
        "{secret} / {err}"
    );
    // Where the key is kept, whole: a daemon started from another directory on a
    // relative runs-dir would not find it.
    let keys = dir.path().canonicalize().unwrap().join("keys.json");
    assert!(err.contains(&format!("kept in {}", keys.display())), "{err}");
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(&secret), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let (s, _) = call(
        &router,
        Method::PATCH,
        &format!("/api/v1/runs/{id}"),
        Some(&secret),
        &json!({"add_tags": ["cli-test"]}).to_string(),
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let (code, out, err) = periscope(&["runs", "--tag", "cli-test", "--json"]);
    assert_eq!(code, Some(0), "{err}");
    let page: Value = serde_json::from_str(&out).unwrap();
    assert_eq!(page["total"], 1);
    assert_eq!(page["runs"][0]["id"], id.as_str());
    assert_eq!(page["runs"][0]["submitted_by"], "bob");
    let (code, out, _) = periscope(&["runs", "--state", "queued"]);
    assert_eq!(code, Some(0));
    assert!(out.contains(&id) && out.contains("bob"), "{out}");
    let (code, _, err) = periscope(&["runs", "--state", "lost"]);
    assert_eq!(code, Some(2), "a bad filter is a usage error");
    assert!(err.contains("state `lost`"), "{err}");
    let (code, out, err) = periscope(&["keys", "list"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("bob") && out.contains("operator") && !out.contains(&secret),
        "{out}"
    );
    let (code, _, err) = periscope(&["keys", "revoke", "bob"]);
    assert_eq!(code, Some(0), "{err}");
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(&secret), PLAN).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED, "{v}");
    assert!(v["message"].as_str().unwrap().contains("revoked"), "{v}");
    let (code, _, err) = periscope(&["catalogue", "rebuild"]);
    assert_eq!(code, Some(1), "a rebuild under a running daemon is refused");
    assert!(err.contains("stop it before a rebuild"), "{err}");
    let (code, out, err) = periscope(&["catalogue", "sync"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("1 runs"), "{out}");
    svc.shutdown();
    drop(router);
    drop(svc);
    let (code, out, err) = periscope(&["catalogue", "rebuild"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("1 runs (1 read"), "{out}");
    let (code, out, err) = periscope(&["audit", "--actor", "bob"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("submit") && out.contains("annotate") && out.contains("refused"),
        "{out}"
    );
    let (code, out, _) = periscope(&["audit", "--action", "key-revoke"]);
    assert_eq!(code, Some(0));
    assert!(out.contains("cli") && out.contains("bob"), "{out}");
    let (code, out, _) = periscope(&["audit", "--target", "bob", "--until", "2999-01-01"]);
    assert_eq!(code, Some(0));
    assert!(out.contains("key-revoke") && !out.contains("submit"), "{out}");
    // A misspelt action: an empty page, and the actions the trail holds.
    let (code, out, err) = periscope(&["audit", "--action", "key-revok"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("0 of 0"), "{out}");
    assert!(
        err.contains("no entry has action `key-revok`") && err.contains("key-revoke, "),
        "{err}"
    );
    // A span that cannot hold anything is refused, by `runs` and `audit` alike.
    for cmd in ["runs", "audit"] {
        let (code, _, err) = periscope(&[cmd, "--since", "2026-12-02", "--until", "2026-12-01"]);
        assert_eq!(code, Some(2), "{cmd}: {err}");
        assert!(
            err.contains("--until 2026-12-01T00:00:00Z is not after since"),
            "{cmd}: {err}"
        );
    }
}

/// Whether the test must fail rather than skip when Prometheus is missing (`.ci/run`
/// installs Debian's `prometheus` and sets it).
fn prometheus_required() -> bool {
    std::env::var_os("PERISCOPE_REQUIRE_PROMETHEUS").is_some()
}

/// A real Prometheus (Debian's package) scrapes a real socket's `/metrics`: the target
/// is up and the daemon's series are queryable through Prometheus's own API; and
/// `promtool` accepts the shipped scrape config and alert rules (docs/).
#[tokio::test]
async fn a_real_prometheus_scrapes_the_daemon_and_accepts_the_shipped_config() {
    use std::future::IntoFuture;
    let on_path = |name: &str| {
        std::env::var_os("PATH").and_then(|p| {
            std::env::split_paths(&p)
                .map(|d| d.join(name))
                .find(|f| f.is_file())
        })
    };
    let (Some(prometheus), Some(promtool)) = (on_path("prometheus"), on_path("promtool")) else {
        assert!(
            !prometheus_required(),
            "PERISCOPE_REQUIRE_PROMETHEUS is set but prometheus or promtool is not on PATH (apt-get install prometheus)"
        );
        common::skipped(format_args!(
            "the Prometheus scrape: prometheus/promtool not on PATH; `.ci/run` installs Debian's prometheus for this test"
        ));
        return;
    };
    let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs");
    for (what, file) in [("config", "prometheus.yml"), ("rules", "prometheus-rules.yml")] {
        let out = std::process::Command::new(&promtool)
            .args(["check", what])
            .arg(docs.join(file))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "promtool check {what} {file}: {}",
            String::from_utf8_lossy(&out.stdout)
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let svc = service(&dir.path().join("runs"));
    // The worker reads the (simulated) devices while idle: the gauges Prometheus reads.
    let worker = svc.start_worker();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let target = listener.local_addr().unwrap();
    let server = tokio::spawn(
        axum::serve(
            listener,
            app(AppState::new(Arc::clone(&svc)))
                .into_make_service_with_connect_info::<std::net::SocketAddr>(),
        )
        .into_future(),
    );
    let web = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let config = dir.path().join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\nscrape_configs:\n  - job_name: periscope\n    static_configs:\n      - targets: ['{target}']\n"
        ),
    )
    .unwrap();
    struct Kill(std::process::Child);
    impl Drop for Kill {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let _prom = Kill(
        std::process::Command::new(&prometheus)
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("tsdb").display()
            ))
            .arg(format!("--web.listen-address={web}"))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    let client = reqwest::Client::new();
    let query = |q: &'static str| {
        let client = client.clone();
        async move {
            let encoded: String = q
                .bytes()
                .map(|b| match b {
                    b'a'..=b'z' | b'A'..=b'Z' | b'0'..=b'9' | b'_' => (b as char).to_string(),
                    _ => format!("%{b:02X}"),
                })
                .collect();
            let resp = client
                .get(format!("http://{web}/api/v1/query?query={encoded}"))
                .send()
                .await
                .ok()?;
            let v: Value = serde_json::from_slice(&resp.bytes().await.ok()?).ok()?;
            let r = v["data"]["result"].as_array()?.first()?.clone();
            r["value"][1].as_str()?.parse::<f64>().ok()
        }
    };
    let t = Instant::now();
    let up = loop {
        if let Some(v) = query("up{job=\"periscope\"}").await {
            break v;
        }
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "Prometheus never scraped the daemon"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    assert_eq!(up, 1.0, "the scrape failed (up = {up})");
    assert_eq!(query("periscope_queue_length").await, Some(0.0));
    // Once a scrape follows the worker's device reading, the simulator's closed
    // interlock shows through Prometheus.
    while query("periscope_reading_valid").await != Some(1.0) {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "no scrape saw a device reading"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    assert_eq!(query("periscope_interlock_closed").await, Some(1.0));
    assert_eq!(query("periscope_laser_emission").await, Some(0.0));
    // The stale-reading alert's comparison matches its two series, and a fresh reading
    // is inside it; nor does the failing-reading alert's condition hold.
    assert!(
        query("periscope_status_interval_seconds")
            .await
            .is_some_and(|s| s > 0.0)
    );
    assert!(
        query("periscope_reading_age_seconds < 3 * periscope_status_interval_seconds + 60")
            .await
            .is_some()
    );
    assert_eq!(query("periscope_reading_valid == 0").await, None);
    // The first scrape's own latency appears from the second scrape on: Prometheus
    // ingests the histograms too.
    while query("sum(periscope_http_request_duration_seconds_count{route=\"/metrics\"})")
        .await
        .is_none()
    {
        assert!(
            t.elapsed() < Duration::from_secs(60),
            "no scrape recorded the scrapes' latency"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// An event stream is authorised at its start and may run for hours: one opened with a
/// key ends within seconds of the key's revocation.
#[tokio::test]
async fn an_event_stream_ends_when_its_key_is_revoked() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let keys = KeyStore::open(dir.path(), None);
    let (_, secret) = keys.create("screen", Role::Observer, None, "test").unwrap();
    let router = app(AppState::new(Arc::clone(&svc)));
    // Events flow...
    let body = instrument_stream(&router, Some(&secret), true).await;
    keys.revoke("screen").unwrap();
    // ...and stop: the stream ends after the revocation.
    let t = Instant::now();
    assert!(
        ends_within(body, Duration::from_secs(10)).await,
        "the stream kept going after the key was revoked"
    );
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    svc.shutdown();
}

/// A key request the keys file cannot serve is the daemon's fault (500 `storage`, the
/// file named), not the caller's; a request for a key that is not there stays a 422.
#[tokio::test]
async fn a_keys_file_that_cannot_be_written_is_a_storage_error() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let router = app(AppState::new(Arc::clone(&svc)));
    let new_key = json!({ "name": "k-new", "role": "observer" }).to_string();
    let (s, v) = call(&router, Method::DELETE, "/api/v1/keys/k-nobody", Some(TOKEN), "").await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("invalid")),
        "{v}"
    );
    // The lock the store takes (its file made by the request above) cannot be opened
    // where a directory stands.
    let _ = std::fs::remove_file(dir.path().join("keys.lock"));
    std::fs::create_dir(dir.path().join("keys.lock")).unwrap();
    for (method, uri, body) in [
        (Method::POST, "/api/v1/keys", new_key.as_str()),
        (Method::DELETE, "/api/v1/keys/k-nobody", ""),
    ] {
        let (s, v) = call(&router, method.clone(), uri, Some(TOKEN), body).await;
        assert_eq!(s, StatusCode::INTERNAL_SERVER_ERROR, "{method} {uri}: {v}");
        assert_eq!(v["error"], "storage", "{v}");
        assert!(v["message"].as_str().unwrap().contains("keys.lock"), "{v}");
    }
    std::fs::remove_dir(dir.path().join("keys.lock")).unwrap();
    let (s, v) = call(&router, Method::POST, "/api/v1/keys", Some(TOKEN), &new_key).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    // The key made is its audit entry's target (it was null: the path names no key).
    let (_, audit) = call(&router, Method::GET, "/api/v1/audit?target=k-new", None, "").await;
    let actions: Vec<_> = audit["entries"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| (e["action"].as_str().unwrap(), e["outcome"].as_str().unwrap()))
        .collect();
    assert_eq!(actions, [("key-create", "ok")], "{audit}");
}

/// One writer a run, one daemon a runs directory. A run directory another process
/// holds (`periscope run` or `resume` under way; here a hold the test takes, which is
/// the same advisory lock) is left to it: the daemon's worker does not open it and
/// does not write its run.json, `periscope resume` refuses it, a daemon starting then
/// does not queue it, and a second daemon on the same runs directory is refused.
/// Before 2026-12-06 each of them went ahead: two processes appended to one
/// histogram log, and the second's recovery cut records the first had counted.
///
/// In a process of its own ([`common::alone`]): a daemon opened again at once found the
/// runs directory still held (`RunsDirInUse`, rarely).
#[test]
fn a_run_another_process_is_writing_is_left_to_it() {
    common::alone(
        "a_run_another_process_is_writing_is_left_to_it",
        2,
        another_process_writes_a_run(),
    );
}

async fn another_process_writes_a_run() {
    use periscope_daemon::run_dir::RunHold;
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let run = dir.path().join(&id);
    let hold = RunHold::take(&run).unwrap().expect("the run is held already");
    let before = std::fs::read(run.join("run.json")).unwrap();

    // A second daemon on this runs directory.
    let src = common::sim_instrument(dir.path(), 0.0, &format!("token = \"{TOKEN}\"\n"), "");
    let second = Service::open(src, Some(TOKEN.to_owned()))
        .err()
        .expect("a second daemon opened");
    assert!(
        second.to_string().contains("another Periscope daemon serves"),
        "{second}"
    );

    // `periscope resume` of the held run.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .arg("resume")
        .arg(&run)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("another Periscope process"), "{stderr}");

    // The daemon's worker: the run leaves its queue, its run.json untouched.
    let worker = svc.start_worker();
    let t = Instant::now();
    loop {
        let (_, q) = call(&router, Method::GET, "/api/v1/queue", None, "").await;
        if q["order"].as_array().is_some_and(Vec::is_empty) && q["running"].is_null() {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "still queued: {q}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(std::fs::read(run.join("run.json")).unwrap(), before);
    assert!(!run.join("histograms.bin").exists());
    svc.shutdown();
    worker.join().unwrap();
    drop((router, svc));

    // A daemon starting while the run is held does not queue it (it reads queued and
    // is in no queue.json: an orphan, which a daemon otherwise queues again) ...
    let svc = service(dir.path());
    assert!(svc.queue().order.is_empty(), "{:?}", svc.queue().order);
    svc.shutdown();
    drop(svc);
    // ... and once it is let go, does.
    drop(hold);
    let svc = service(dir.path());
    assert_eq!(svc.queue().order, vec![id.clone()]);
    assert_eq!(std::fs::read(run.join("run.json")).unwrap(), before);
    svc.shutdown();
}

/// The key and audit commands where their files are in a bad way (each before
/// 2026-12-06): a damaged keys.json is an error (exit 1) naming it and what to do,
/// not an empty table and exit 0; a key revoked while the catalogue cannot be opened
/// is recorded in the audit log (and the command succeeds), not lost with exit 1; an
/// audit entry quoting control characters prints them escaped, not to the terminal;
/// revoking a key that does not exist is a usage error (exit 2).
#[test]
fn key_and_audit_commands_say_what_is_wrong_with_their_files() {
    use periscope_daemon::catalogue::{AUDIT_FILE, AuditEntry, append_audit};
    let dir = tempfile::tempdir().unwrap();
    let src = common::sim_instrument(dir.path(), 0.0, "", "");
    let periscope = cli(dir.path(), &src);
    let (code, _, err) = periscope(&["keys", "create", "carol", "--role", "observer"]);
    assert_eq!(code, Some(0), "{err}");
    let (code, _, err) = periscope(&["keys", "revoke", "nobody"]);
    assert_eq!(code, Some(2), "{err}");

    // The catalogue cannot be opened: the revocation is made and recorded in the log.
    let catalogue = dir.path().join("catalogue.sqlite");
    let _ = std::fs::remove_file(&catalogue);
    for wal in ["catalogue.sqlite-wal", "catalogue.sqlite-shm"] {
        let _ = std::fs::remove_file(dir.path().join(wal));
    }
    std::fs::create_dir(&catalogue).unwrap();
    let (code, out, err) = periscope(&["keys", "revoke", "carol"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(
        out.contains("revoked") && err.contains("catalogue sync"),
        "{out} / {err}"
    );
    let log = std::fs::read_to_string(dir.path().join(AUDIT_FILE)).unwrap();
    assert!(
        log.lines()
            .any(|l| l.contains("key-revoke") && l.contains("carol")),
        "{log}"
    );
    std::fs::remove_dir(&catalogue).unwrap();

    // Control characters a client sent, printed escaped.
    append_audit(
        dir.path(),
        &AuditEntry::new("mallory", "operator", "submit", Some("x"), "refused")
            .detail("key \u{1b}]0;pwned\u{7}\u{1b}[31m\nforged line".to_owned()),
    )
    .unwrap();
    let (code, out, err) = periscope(&["audit", "--actor", "mallory"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(!out.contains('\u{1b}') && !out.contains('\u{7}'), "{out:?}");
    assert!(
        out.contains("\\u{1b}]0;pwned") && !out.contains("\nforged"),
        "{out}"
    );
    // The catalogue, open again, took the revocation from the log.
    let (code, out, err) = periscope(&["audit", "--action", "key-revoke"]);
    assert_eq!(code, Some(0), "{err}");
    assert!(out.contains("carol"), "{out}");
    // `--limit 0` is refused, as `runs --limit 0` is (it was read as 1).
    let (code, _, err) = periscope(&["audit", "--limit", "0"]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--limit 0"), "{err}");

    // A damaged keys file.
    std::fs::write(dir.path().join("keys.json"), "[{\"name\": ").unwrap();
    let (code, out, err) = periscope(&["keys", "list"]);
    assert_eq!(code, Some(1), "{out} / {err}");
    assert!(err.contains("keys.json") && err.contains("restore it"), "{err}");

    // A FIFO in its place: refused at once, not read forever (it hung `keys list`).
    std::fs::remove_file(dir.path().join("keys.json")).unwrap();
    let made = std::process::Command::new("mkfifo")
        .arg(dir.path().join("keys.json"))
        .status()
        .unwrap();
    assert!(made.success());
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .args(["keys", "list", "--instrument"])
        .arg(dir.path().join("instrument.toml"))
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t.elapsed() > Duration::from_secs(20) {
            child.kill().unwrap();
            panic!("`periscope keys list` still reading a FIFO keys.json after 20 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("keys.json") && err.contains("not a regular file"),
        "{err}"
    );
    std::fs::remove_file(dir.path().join("keys.json")).unwrap();

    // An expiry past what a keys file can hold was `inf`, stored as null: never.
    let (code, _, err) = periscope(&[
        "keys",
        "create",
        "dave",
        "--role",
        "observer",
        "--expires",
        "1e308d",
    ]);
    assert_eq!(code, Some(2), "{err}");
    assert!(err.contains("--expires") && err.contains("9999-12-31"), "{err}");
    let (_, out, _) = periscope(&["keys", "list"]);
    assert!(!out.contains("dave"), "{out}");

    // A runs directory that is not there (a mistyped `runs-dir`): every command that
    // reads it says so, exit 2, and none makes it.
    let other = tempfile::tempdir().unwrap();
    let missing = other.path().join("no-such-runs");
    let src = common::sim_instrument(&missing, 0.0, "", "");
    let periscope = cli(other.path(), &src);
    for args in [
        &["runs"][..],
        &["runs", "tag", "some-run", "x"],
        &["audit"],
        &["keys", "list"],
        &["keys", "revoke", "carol"],
        &["catalogue", "sync"],
        &["catalogue", "rebuild"],
    ] {
        let (code, out, err) = periscope(args);
        assert_eq!(code, Some(2), "{args:?}: {out} / {err}");
        assert!(
            err.contains("does not exist") && err.contains("runs-dir") && err.contains("no-such-runs"),
            "{args:?}: {err}"
        );
        assert!(!missing.exists(), "{args:?} made the runs directory");
    }
}

/// The daemon takes the catalogue's lock before it opens the catalogue (a review,
/// 2026-12-06): a `periscope catalogue rebuild` under way (the lock held exclusively,
/// the old file removed and a new one being written) finishes first, so the daemon
/// never keeps a connection to the file the rebuild replaced.
#[test]
fn the_daemon_opens_the_catalogue_only_once_it_holds_the_lock() {
    use periscope_daemon::catalogue::{CATALOGUE_FILE, LOCK_FILE};
    let dir = tempfile::tempdir().unwrap();
    let lock = std::fs::File::create(dir.path().join(LOCK_FILE)).unwrap();
    lock.lock().unwrap();
    let src = common::sim_instrument(dir.path(), 0.0, "", "");
    let (tx, rx) = std::sync::mpsc::channel();
    let opening = std::thread::spawn(move || {
        let svc = Service::open(src, None);
        let _ = tx.send(());
        svc
    });
    // Held off while the rebuild holds the lock, and the catalogue left untouched.
    assert!(
        rx.recv_timeout(Duration::from_millis(500)).is_err(),
        "the daemon started while a rebuild held the catalogue"
    );
    assert!(
        !dir.path().join(CATALOGUE_FILE).exists(),
        "the daemon opened the catalogue before it held the lock"
    );
    drop(lock);
    let svc = opening.join().unwrap().unwrap();
    assert!(dir.path().join(CATALOGUE_FILE).is_file());
    svc.shutdown();
}

/// The instrument's event stream ends with the service's shutdown, as a run's does
/// (until 2026-12-06 it went on, and every shutdown with a dashboard open waited out
/// the server's grace).
#[tokio::test]
async fn the_instrument_stream_ends_when_the_daemon_shuts_down() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let router = app(AppState::new(Arc::clone(&svc)));
    let body = instrument_stream(&router, None, false).await;
    svc.shutdown();
    assert!(
        ends_within(body, Duration::from_secs(5)).await,
        "the stream kept going after the shutdown"
    );
}

/// `GET /api/v1/instrument/events` (with `key`, from another host if `remote`), its
/// first event read: a safety reading.
async fn instrument_stream(
    router: &axum::Router,
    key: Option<&str>,
    remote: bool,
) -> axum::body::BodyDataStream {
    use tokio_stream::StreamExt as _;
    let resp = router
        .clone()
        .oneshot(request(
            &Method::GET,
            "/api/v1/instrument/events",
            key,
            "",
            remote,
        ))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let mut body = resp.into_body().into_data_stream();
    let first = tokio::time::timeout(Duration::from_secs(5), body.next())
        .await
        .unwrap();
    assert!(first.is_some_and(|c| c.is_ok_and(|b| b.starts_with(b"event: safety"))));
    body
}

/// Whether `body` ends within `limit`.
async fn ends_within(mut body: axum::body::BodyDataStream, limit: Duration) -> bool {
    use tokio_stream::StreamExt as _;
    tokio::time::timeout(limit, async { while body.next().await.is_some() {} })
        .await
        .is_ok()
}

/// One remote host holds at most `api::STREAMS_PER_PEER` event streams (a review,
/// 2026-12-06: one host could open all of `[api] max-streams` and read them a byte at a
/// time); loopback's are not counted, and a closed stream frees its host's slot.
#[tokio::test]
async fn one_host_holds_at_most_its_share_of_event_streams() {
    use periscope_daemon::api::STREAMS_PER_PEER;
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
    let router = app(AppState::new(Arc::clone(&svc)));
    let open = |remote: bool| {
        let router = router.clone();
        async move {
            router
                .oneshot(request(
                    &Method::GET,
                    "/api/v1/instrument/events",
                    Some(TOKEN),
                    "",
                    remote,
                ))
                .await
                .unwrap()
        }
    };
    let mut held = Vec::new();
    for _ in 0..STREAMS_PER_PEER {
        let r = open(true).await;
        assert_eq!(r.status(), StatusCode::OK);
        held.push(r);
    }
    let refused = open(true).await;
    assert_eq!(refused.status(), StatusCode::SERVICE_UNAVAILABLE);
    let body = axum::body::to_bytes(refused.into_body(), 1 << 20).await.unwrap();
    assert!(
        String::from_utf8_lossy(&body).contains("one host may hold"),
        "{body:?}"
    );
    // Loopback is not counted against it.
    assert_eq!(open(false).await.status(), StatusCode::OK);
    // A stream closed frees its host's slot.
    drop(held.pop());
    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    assert_eq!(open(true).await.status(), StatusCode::OK);
    drop(held);
    svc.shutdown();
}

/// A daemon that cannot listen (the port is taken) takes up no queued run: its worker
/// started before the bind until 2026-12-08, so the run was opened, its devices with
/// it, and left interrupted when the process exited on the error.
#[tokio::test]
async fn a_daemon_that_cannot_listen_takes_up_no_queued_run() {
    let runs = tempfile::tempdir().unwrap();
    let svc = service(runs.path());
    let queued = svc.submit(PLAN.to_owned()).unwrap();
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap();
    let e = periscope_daemon::api::serve(addr, Arc::clone(&svc))
        .await
        .unwrap_err();
    assert!(matches!(e, periscope_daemon::api::ServeError::Bind { .. }), "{e}");
    // A simulated run at time scale 0 would be well under way by now.
    tokio::time::sleep(std::time::Duration::from_secs(1)).await;
    let status = svc.status(&queued.id).unwrap();
    assert_eq!(
        status.state,
        periscope_daemon::run_dir::RunState::Queued,
        "{status:?}"
    );
    assert_eq!(status.pairs_done, 0);
}

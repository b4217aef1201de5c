//! The HTTP API: router tests without a socket (`tower::ServiceExt::oneshot`), against a
//! service whose instrument is the simulator and whose runs live in a temporary
//! directory. Bad input must get the right 4xx and change nothing.
use std::future::IntoFuture;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::http::{Method, StatusCode};
use periscope_daemon::api::{AppState, app, openapi, routes};
use periscope_daemon::config::TomlSource;
use periscope_daemon::service::Service;
use serde_json::Value;

mod common;
use common::SmallPlan;

const TOKEN: &str = "test-token-0123456789abcdef";

/// A small plan: 8×8 LOS, 8×8 confocal pairs, FBP (no 3D-GTR fit), so a run takes
/// about a second at time-scale 0.
pub const PLAN: &str = include_str!("../../tests/data/plans/small-fbp.toml");

/// The simulated instrument with its runs in `runs` and the given time scale.
fn instrument(runs: &Path, time_scale: f64, token: Option<&str>) -> TomlSource {
    let token = token.map(|t| format!("token = \"{t}\"\n")).unwrap_or_default();
    common::sim_instrument(runs, time_scale, &format!("body-limit-kib = 64\n{token}"), "")
}

fn service(runs: &Path, time_scale: f64, token: Option<&str>) -> Arc<Service> {
    let src = instrument(runs, time_scale, token);
    Service::open(src, token.map(str::to_owned)).unwrap()
}

async fn call(
    router: &axum::Router,
    method: Method,
    uri: &str,
    token: Option<&str>,
    body: &str,
) -> (StatusCode, Value) {
    let (status, bytes) = call_raw(router, method, uri, token, body).await;
    let json = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    (status, json)
}

async fn call_raw(
    router: &axum::Router,
    method: Method,
    uri: &str,
    token: Option<&str>,
    body: &str,
) -> (StatusCode, Vec<u8>) {
    common::send(router, common::request(method, uri, token, &[], body)).await
}

fn listing(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

async fn wait_for(
    router: &axum::Router,
    id: &str,
    what: &str,
    limit: Duration,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    let t = Instant::now();
    loop {
        let (s, v) = call(router, Method::GET, &format!("/api/v1/runs/{id}"), None, "").await;
        assert_eq!(s, StatusCode::OK, "{v}");
        if pred(&v) {
            return v;
        }
        assert!(t.elapsed() < limit, "run {id} never became {what}: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test]
async fn health_and_openapi_match_the_routes() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, Some(TOKEN))));
    let (s, v) = call(&router, Method::GET, "/api/v1/health", None, "").await;
    assert_eq!((s, v["status"].as_str()), (StatusCode::OK, Some("ok")));

    let (s, doc) = call(&router, Method::GET, "/api/v1/openapi.json", None, "").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(doc, openapi());
    // The contract docs/api.md describes: the generated document lists these
    // operations and no others.
    let mut documented = routes();
    documented.sort();
    let mut contract: Vec<(String, String)> = [
        ("GET", "/api/v1/health"),
        ("GET", "/api/v1/openapi.json"),
        ("GET", "/api/v1/instrument"),
        ("POST", "/api/v1/check"),
        ("POST", "/api/v1/runs"),
        ("POST", "/api/v1/imports"),
        ("GET", "/api/v1/runs"),
        ("GET", "/api/v1/runs/{id}"),
        ("POST", "/api/v1/runs/{id}/pause"),
        ("POST", "/api/v1/runs/{id}/resume"),
        ("POST", "/api/v1/runs/{id}/abort"),
        ("POST", "/api/v1/estop"),
        ("GET", "/api/v1/runs/{id}/events"),
        ("GET", "/api/v1/instrument/events"),
        ("GET", "/api/v1/runs/{id}/files/{name}"),
        ("GET", "/api/v1/runs/{id}/geometry"),
        ("PATCH", "/api/v1/runs/{id}"),
        ("POST", "/api/v1/runs/batch"),
        ("POST", "/api/v1/runs/{id}/again"),
        ("GET", "/api/v1/catalogue"),
        ("GET", "/api/v1/queue"),
        ("PUT", "/api/v1/queue"),
        ("POST", "/api/v1/queue/move"),
        ("POST", "/api/v1/queue/lock"),
        ("POST", "/api/v1/queue/unlock"),
        ("GET", "/api/v1/whoami"),
        ("GET", "/api/v1/keys"),
        ("POST", "/api/v1/keys"),
        ("DELETE", "/api/v1/keys/{name}"),
        ("GET", "/api/v1/audit"),
        ("GET", "/metrics"),
    ]
    .iter()
    .map(|(m, p)| (m.to_string(), p.to_string()))
    .collect();
    contract.sort();
    assert_eq!(
        documented, contract,
        "the OpenAPI document lists the API's operations"
    );
    // Against the router: every documented operation is served by a handler (not the
    // unknown-route fallback), and every other method on a documented path is a JSON
    // 405.
    let mut paths: Vec<&String> = documented.iter().map(|(_, p)| p).collect();
    paths.sort();
    paths.dedup();
    for p in paths {
        let uri = p.replace("{id}", "no-such-run").replace("{name}", "depth.png");
        for m in ["GET", "POST", "PUT", "PATCH", "DELETE"] {
            let method = Method::from_bytes(m.as_bytes()).unwrap();
            if m == "GET" && uri == "/api/v1/instrument/events" {
                // An endless stream: its head is the answer.
                use tower::ServiceExt as _;
                let req = common::request(method, &uri, Some(TOKEN), &[], "");
                let resp = router.clone().oneshot(req).await.unwrap();
                assert_eq!(resp.status(), StatusCode::OK);
                assert_eq!(resp.headers()["content-type"], "text/event-stream");
                continue;
            }
            let (s, v) = call(&router, method.clone(), &uri, Some(TOKEN), "").await;
            if documented.contains(&(m.to_owned(), p.to_owned())) {
                assert_ne!(v["error"], "not-found", "{m} {uri}: {v}");
                assert_ne!(v["error"], "method-not-allowed", "{m} {uri}: {v}");
                // What it answered (an empty body, an unknown run) is documented, and
                // so are the answers of the layers every route passes: a wrong key,
                // a Host the daemon does not answer to.
                let op = &doc["paths"][p.as_str()][m.to_ascii_lowercase()];
                let documents = |s: StatusCode| op["responses"].get(s.as_str()).is_some();
                assert!(documents(s), "{m} {p} answered {s}, undocumented: {v}");
                // (An e-stop from this machine is not refused for its key: docs/safety.md.)
                let (s, v) = call(&router, method.clone(), &uri, Some("psk_not-a-key"), "").await;
                assert!(
                    (s == StatusCode::UNAUTHORIZED || p == "/api/v1/estop")
                        && documents(StatusCode::UNAUTHORIZED),
                    "{m} {p} with a wrong key: {s} {v}"
                );
                use tower::ServiceExt as _;
                let req = common::request(method, &uri, Some(TOKEN), &[("host", "evil.example")], "");
                let resp = router.clone().oneshot(req).await.unwrap();
                assert!(
                    resp.status() == StatusCode::FORBIDDEN && documents(resp.status()),
                    "{m} {p} from another host name: {}",
                    resp.status()
                );
                assert!(documents(StatusCode::REQUEST_TIMEOUT), "{m} {p}");
                if op.get("requestBody").is_some() {
                    for s in [
                        StatusCode::BAD_REQUEST,
                        StatusCode::PAYLOAD_TOO_LARGE,
                        StatusCode::UNSUPPORTED_MEDIA_TYPE,
                    ] {
                        assert!(documents(s), "{m} {p} takes a body: {s} is not documented");
                    }
                }
            } else {
                assert_eq!(
                    (s, v["error"].as_str()),
                    (StatusCode::METHOD_NOT_ALLOWED, Some("method-not-allowed")),
                    "{m} {uri} is not documented, so not served"
                );
            }
        }
    }
    // Each operation's responses name the schemas the handlers return, and every
    // referenced schema is in the document.
    let text = doc.to_string();
    for schema in doc["components"]["schemas"].as_object().unwrap().keys() {
        assert!(
            text.contains(&format!("#/components/schemas/{schema}")),
            "{schema} is never used"
        );
    }
    for r in text.split("\"#/components/schemas/").skip(1) {
        let name = &r[..r.find('"').unwrap()];
        assert!(
            doc["components"]["schemas"][name].is_object(),
            "{name} is referenced but not defined"
        );
    }
    assert_eq!(
        doc["paths"]["/api/v1/runs/{id}"]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
            ["$ref"],
        "#/components/schemas/RunStatus"
    );
    assert_eq!(
        doc["components"]["schemas"]["RunState"]["enum"],
        serde_json::json!(["queued", "running", "paused", "completed", "aborted", "failed"])
    );
    // Keyless from this machine (an empty requirement beside the bearer one), as the
    // reads and the plan check are; every other change needs a key.
    assert_eq!(
        doc["paths"]["/api/v1/estop"]["post"]["security"],
        serde_json::json!([{}, { "bearer": [] }])
    );
    assert_eq!(
        doc["paths"]["/api/v1/runs"]["get"]["security"],
        serde_json::json!([{}, { "bearer": [] }])
    );
    assert_eq!(
        doc["paths"]["/api/v1/runs/{id}/abort"]["post"]["security"],
        serde_json::json!([{ "bearer": [] }])
    );
    let download = &doc["paths"]["/api/v1/runs/{id}/files/{name}"]["get"];
    assert_eq!(
        download["responses"]["200"]["content"]["application/octet-stream"]["schema"],
        serde_json::json!({ "type": "string", "format": "binary" })
    );
    let name = &download["parameters"][1];
    assert_eq!(name["name"], "name");
    assert!(
        name["schema"]["enum"]
            .as_array()
            .unwrap()
            .contains(&"capture.hdf5".into())
    );
    let (s, v) = call(&router, Method::DELETE, "/api/v1/runs", Some(TOKEN), "").await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::METHOD_NOT_ALLOWED, Some("method-not-allowed"))
    );
    let (s, v) = call(&router, Method::GET, "/api/v2/runs", None, "").await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::NOT_FOUND, Some("not-found"))
    );
}

#[tokio::test]
async fn bad_requests_get_4xx_and_change_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, Some(TOKEN))));
    let before = listing(dir.path());

    // Malformed TOML: 422 naming the line, like `periscope check`.
    let (s, v) = call(
        &router,
        Method::POST,
        "/api/v1/runs",
        Some(TOKEN),
        "name = \"x\"\n[los\n",
    )
    .await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("invalid-plan")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("request body:2"), "{v}");
    // A value out of range names its key.
    let bad = SmallPlan::default().set("acquisition.dwell-ms", -1.0).toml();
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), &bad).await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY, "{v}");
    assert!(
        v["message"].as_str().unwrap().contains("acquisition.dwell-ms"),
        "{v}"
    );
    // Missing and wrong tokens.
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", None, PLAN).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::UNAUTHORIZED, Some("unauthorized")),
        "{v}"
    );
    let (s, _) = call(
        &router,
        Method::POST,
        "/api/v1/runs",
        Some("wrong-token-wrong-token"),
        PLAN,
    )
    .await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    // The e-stop needs no key from this machine (docs/safety.md): it answers.
    let (s, _) = call(&router, Method::POST, "/api/v1/estop", None, "").await;
    assert_eq!(s, StatusCode::OK);
    // Oversized body (the limit is 64 KiB here).
    let huge = format!("{PLAN}\n# {}\n", "x".repeat(80 * 1024));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), &huge).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::PAYLOAD_TOO_LARGE, Some("body-too-large")),
        "{v}"
    );
    // Empty body.
    let (s, _) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), "").await;
    assert_eq!(s, StatusCode::UNPROCESSABLE_ENTITY);
    // Unknown run, unknown file, path tricks.
    for uri in [
        "/api/v1/runs/nope",
        "/api/v1/runs/nope/files/depth.png",
        "/api/v1/runs/..%2F..%2Fetc/files/run.json",
    ] {
        let (s, v) = call(&router, Method::GET, uri, None, "").await;
        assert_eq!(s, StatusCode::NOT_FOUND, "{uri}: {v}");
        assert!(v["message"].is_string(), "{uri}: {v}");
    }
    // Malformed query strings and paths: a JSON error naming the field, never axum's
    // plain text (which the dashboard cannot read) or a 500.
    let long_q = format!("/api/v1/runs?q={}", "_".repeat(25_001));
    // A search past 128 bytes (matched against seven columns of every run, under the
    // catalogue's lock; 1,024 were taken until 2026-12-06).
    let search = format!("/api/v1/runs?q={}", "a".repeat(129));
    for (uri, code, names) in [
        (long_q.as_str(), "bad-query", "q: 25001 bytes"),
        (search.as_str(), "bad-query", "q: 129 bytes"),
        ("/api/v1/runs?limit=abc", "bad-query", "limit"),
        (
            "/api/v1/catalogue?offset=18446744073709551615",
            "bad-query",
            "offset",
        ),
        ("/api/v1/audit?offset=18446744073709551615", "bad-query", "offset"),
        ("/api/v1/audit?limit=-1", "bad-query", "limit"),
        ("/api/v1/audit?limit=0", "bad-query", "limit"),
        ("/api/v1/audit?limit=5000", "bad-query", "limit"),
        // A span that holds nothing (until is exclusive): 200 with an empty page before.
        (
            "/api/v1/runs?since=2026-12-02&until=2026-12-01",
            "bad-query",
            "until: 2026-12-01T00:00:00Z is not after since",
        ),
        (
            "/api/v1/audit?since=2026-12-01&until=2026-12-01",
            "bad-query",
            "until: 2026-12-01T00:00:00Z is not after since",
        ),
        // A misspelt filter: every run was answered before, as if it had matched.
        ("/api/v1/runs?stat=paused", "bad-query", "unknown field `stat`"),
        ("/api/v1/audit?acton=abort", "bad-query", "unknown field `acton`"),
        ("/api/v1/runs/%FF", "bad-path", "UTF-8"),
        ("/api/v1/runs/%FF/files/run.json", "bad-path", "UTF-8"),
    ] {
        let (s, v) = call(&router, Method::GET, uri, Some(TOKEN), "").await;
        assert_eq!(
            (s, v["error"].as_str()),
            (StatusCode::BAD_REQUEST, Some(code)),
            "{uri}: {v}"
        );
        assert!(v["message"].as_str().unwrap().contains(names), "{uri}: {v}");
    }
    // JSON bodies of the wrong shape (a wrong type, a field missing or unknown) do not
    // parse as the request either: 400 `bad-body` naming the field, as malformed JSON
    // is (until 2026-12-06, axum's 422 with the code `bad-body`).
    for (method, uri, body, names) in [
        (
            Method::POST,
            "/api/v1/queue/move",
            r#"{"run":"x","position":-1}"#,
            "position",
        ),
        (Method::POST, "/api/v1/queue/move", r#"{"position":0}"#, "run"),
        (Method::PATCH, "/api/v1/runs/nope", r#"{"note":5}"#, "note"),
        (Method::POST, "/api/v1/keys", r#"{"name":"k","role":3}"#, "role"),
        (
            Method::POST,
            "/api/v1/keys",
            r#"{"name":"k","role":"admin","expiry":"1h"}"#,
            "expiry",
        ),
    ] {
        let req = axum::http::Request::builder()
            .method(method.clone())
            .uri(uri)
            .header("authorization", format!("Bearer {TOKEN}"))
            .header("content-type", "application/json")
            .body(axum::body::Body::from(body))
            .unwrap();
        let (s, bytes) = common::send(&router, req).await;
        let v: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(
            (s, v["error"].as_str()),
            (StatusCode::BAD_REQUEST, Some("bad-body")),
            "{method} {uri} {body}: {v}"
        );
        assert!(
            v["message"].as_str().unwrap().contains(names),
            "{method} {uri} {body}: {v}"
        );
    }
    // Media types are case-insensitive: `Application/TOML` is a plan, `image/png` not.
    for (ct, want) in [
        ("Application/TOML", StatusCode::OK),
        ("TEXT/plain; charset=utf-8", StatusCode::OK),
        ("image/png", StatusCode::UNSUPPORTED_MEDIA_TYPE),
    ] {
        let req = axum::http::Request::builder()
            .method(Method::POST)
            .uri("/api/v1/check")
            .header("authorization", format!("Bearer {TOKEN}"))
            .header("content-type", ct)
            .body(axum::body::Body::from(SmallPlan::default().toml()))
            .unwrap();
        let (s, bytes) = common::send(&router, req).await;
        assert_eq!(s, want, "{ct}: {}", String::from_utf8_lossy(&bytes));
    }
    for action in ["pause", "resume", "abort"] {
        let (s, v) = call(
            &router,
            Method::POST,
            &format!("/api/v1/runs/nope/{action}"),
            Some(TOKEN),
            "",
        )
        .await;
        assert_eq!(
            (s, v["error"].as_str()),
            (StatusCode::NOT_FOUND, Some("unknown-run")),
            "{v}"
        );
    }
    // Nothing was created but the audit trail's record of the refusals.
    let after: Vec<String> = listing(dir.path())
        .into_iter()
        .filter(|f| f != "audit.jsonl")
        .collect();
    assert_eq!(after, before, "nothing was created");
    let audit = std::fs::read_to_string(dir.path().join("audit.jsonl")).unwrap();
    assert!(audit.contains("\"outcome\":\"refused\""), "{audit}");

    // A queued run (no worker here): pausing it is a conflict, and changes nothing.
    let (s, run) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{run}");
    let id = run["id"].as_str().unwrap().to_owned();
    let run_json = std::fs::read(dir.path().join(&id).join("run.json")).unwrap();
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{id}/pause"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::CONFLICT, Some("conflict")),
        "{v}"
    );
    assert!(v["message"].as_str().unwrap().contains("queued"), "{v}");
    let (s, _) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{id}/resume"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::CONFLICT);
    assert_eq!(
        std::fs::read(dir.path().join(&id).join("run.json")).unwrap(),
        run_json
    );
    let (s, v) = call(
        &router,
        Method::GET,
        &format!("/api/v1/runs/{id}/files/secret.txt"),
        None,
        "",
    )
    .await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::NOT_FOUND, Some("unknown-file"))
    );
    let (s, v) = call(
        &router,
        Method::GET,
        &format!("/api/v1/runs/{id}/files/depth.png"),
        None,
        "",
    )
    .await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::NOT_FOUND, Some("file-not-ready"))
    );
}

#[tokio::test]
async fn without_a_token_configured_mutations_are_forbidden() {
    let dir = tempfile::tempdir().unwrap();
    let router = app(AppState::new(service(dir.path(), 0.0, None)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::FORBIDDEN, Some("no-token-configured"))
    );
    let (s, _) = call(&router, Method::GET, "/api/v1/runs", None, "").await;
    assert_eq!(s, StatusCode::OK, "reads stay open on loopback");
}

#[tokio::test]
async fn the_queue_persists_across_a_restart_and_an_interrupted_run_is_held() {
    let dir = tempfile::tempdir().unwrap();
    let ids: Vec<String> = {
        let router = app(AppState::new(service(dir.path(), 0.0, Some(TOKEN))));
        let mut ids = Vec::new();
        for k in 0..3 {
            let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
            assert_eq!(s, StatusCode::CREATED, "{v}");
            assert_eq!(v["queue_position"], k, "{v}");
            ids.push(v["id"].as_str().unwrap().to_owned());
        }
        ids
    };
    // The first run was running when the daemon died.
    let run_json = dir.path().join(&ids[0]).join("run.json");
    let text = std::fs::read_to_string(&run_json)
        .unwrap()
        .replace("\"queued\"", "\"running\"");
    std::fs::write(&run_json, text).unwrap();

    let router = app(AppState::new(service(dir.path(), 0.0, Some(TOKEN))));
    let (_, list) = call(&router, Method::GET, "/api/v1/runs", None, "").await;
    let states: Vec<(&str, &str)> = list
        .as_array()
        .unwrap()
        .iter()
        .map(|r| (r["id"].as_str().unwrap(), r["state"].as_str().unwrap()))
        .collect();
    assert_eq!(
        states,
        vec![(&*ids[0], "paused"), (&*ids[1], "queued"), (&*ids[2], "queued")],
        "{list}"
    );
    assert!(
        list[0]["error"].as_str().unwrap().contains("interrupted"),
        "{list}"
    );
    assert_eq!(list[1]["queue_position"], 0);
    assert_eq!(list[2]["queue_position"], 1);
    // Aborting a queued run takes it out of the queue at once.
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{}/abort", ids[2]),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(
        (s, v["state"].as_str()),
        (StatusCode::ACCEPTED, Some("aborted")),
        "{v}"
    );
    let queue = std::fs::read_to_string(dir.path().join("queue.json")).unwrap();
    assert!(
        queue.contains(&ids[0]) && queue.contains(&ids[1]) && !queue.contains(&ids[2]),
        "{queue}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_completes_and_its_results_download() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, Some(TOKEN));
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let done = wait_for(&router, &id, "completed", Duration::from_secs(120), |v| {
        v["state"] == "completed" || v["state"] == "failed"
    })
    .await;
    assert_eq!(done["state"], "completed", "{done}");
    assert_eq!(done["progress"], 1.0);
    assert!(done["pairs_done"].as_u64().unwrap() > 20, "{done}");
    for (name, magic) in [
        ("depth.png", &b"\x89PNG"[..]),
        ("albedo.png", b"\x89PNG"),
        ("volume.npy", b"\x93NUMPY"),
        ("relay.ply", b"ply"),
        ("capture.hdf5", b"\x89HDF"),
    ] {
        let (s, bytes) = call_raw(
            &router,
            Method::GET,
            &format!("/api/v1/runs/{id}/files/{name}"),
            None,
            "",
        )
        .await;
        assert_eq!(s, StatusCode::OK, "{name}");
        assert!(bytes.starts_with(magic), "{name}");
        assert!(
            done["files"].as_array().unwrap().iter().any(|f| f == name),
            "{done}"
        );
    }
    // A range of a file is served as it is; one past its end is the API's JSON error,
    // with the length it asks within (until 2026-12-07 an empty body typed as the file).
    let (volume_len, range) = {
        let (_, whole) = call_raw(
            &router,
            Method::GET,
            &format!("/api/v1/runs/{id}/files/volume.npy"),
            None,
            "",
        )
        .await;
        (whole.len(), whole[10..21].to_vec())
    };
    let uri = format!("/api/v1/runs/{id}/files/volume.npy");
    let (s, bytes) = common::send(
        &router,
        common::request(Method::GET, &uri, None, &[("range", "bytes=10-20")], ""),
    )
    .await;
    assert_eq!((s, bytes), (StatusCode::PARTIAL_CONTENT, range));
    use tower::ServiceExt as _;
    let resp = router
        .clone()
        .oneshot(common::request(
            Method::GET,
            &uri,
            None,
            &[("range", &format!("bytes={volume_len}-"))],
            "",
        ))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::RANGE_NOT_SATISFIABLE);
    assert_eq!(
        resp.headers()[axum::http::header::CONTENT_RANGE],
        format!("bytes */{volume_len}").as_str()
    );
    assert_eq!(
        resp.headers()[axum::http::header::CONTENT_TYPE],
        "application/json"
    );
    let v: Value =
        serde_json::from_slice(&axum::body::to_bytes(resp.into_body(), 1 << 20).await.unwrap()).unwrap();
    assert_eq!(v["error"], "range-not-satisfiable", "{v}");
    assert!(
        v["message"].as_str().unwrap().contains(&volume_len.to_string()),
        "{v}"
    );
    // tower-http answers a range it cannot parse as one it cannot satisfy: the same error.
    let (s, bytes) = common::send(
        &router,
        common::request(Method::GET, &uri, None, &[("range", "bytes=10-20t")], ""),
    )
    .await;
    let v: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::RANGE_NOT_SATISFIABLE, Some("range-not-satisfiable"))
    );
    assert!(v["message"].as_str().unwrap().contains("`bytes=10-20t`"), "{v}");
    // A file changed since the client's If-Unmodified-Since: 412, the API's JSON (until
    // 2026-12-07's first fix of the above, a 500 `storage`).
    let (s, bytes) = common::send(
        &router,
        common::request(
            Method::GET,
            &uri,
            None,
            &[("if-unmodified-since", "Thu, 01 Jan 1970 00:00:00 GMT")],
            "",
        ),
    )
    .await;
    let v: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(
        (s, v["error"].as_str()),
        (StatusCode::PRECONDITION_FAILED, Some("precondition-failed"))
    );
    // A finished run's event stream is its status, then the end.
    let (s, bytes) = call_raw(
        &router,
        Method::GET,
        &format!("/api/v1/runs/{id}/events"),
        None,
        "",
    )
    .await;
    assert_eq!(s, StatusCode::OK);
    let text = String::from_utf8(bytes).unwrap();
    assert!(text.starts_with("event: status\ndata: {"), "{text}");
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{id}/abort"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::CONFLICT, "{v}");
    svc.shutdown();
    worker.join().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pause_resume_abort_and_estop_keep_the_data() {
    let dir = tempfile::tempdir().unwrap();
    // Real-time simulation: 64 pairs × 20 ms dwell ≈ 1.5 s of capture.
    let svc = service(dir.path(), 1.0, Some(TOKEN));
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let submit = || async {
        let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        v["id"].as_str().unwrap().to_owned()
    };
    let capturing = |v: &Value| v["stage"] == "capture" && v["pairs_done"].as_u64().unwrap_or(0) >= 5;
    let limit = Duration::from_secs(60);

    // Pause lands between pairs; resume continues to the end.
    let a = submit().await;
    wait_for(&router, &a, "capturing", limit, capturing).await;
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{a}/pause"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let paused = wait_for(&router, &a, "paused", limit, |v| v["state"] == "paused").await;
    let (done, total) = (
        paused["pairs_done"].as_u64().unwrap(),
        paused["pairs_total"].as_u64().unwrap(),
    );
    assert!(done >= 5 && done < total, "{paused}");
    // The part of the capture before the pause is timed (20 ms a pair at real time)...
    let timing = |v: &Value, stage: &str| {
        v["timings"]
            .as_array()
            .and_then(|t| t.iter().find(|e| e[0] == stage))
            .and_then(|e| e[1].as_f64())
    };
    let part = timing(&paused, "capture").expect("the capture's part before the pause is timed");
    // The state history names who paused it (the token is the admin key `token`).
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join(&a).join("run.json")).unwrap())
            .unwrap();
    let last = info["history"].as_array().unwrap().last().unwrap().clone();
    assert_eq!(
        (last["state"].as_str(), last["by"].as_str()),
        (Some("paused"), Some("token")),
        "{info}"
    );
    assert!(part >= done as f64 * 0.02 * 0.8, "{part} s for {done} pairs");
    let log = std::fs::metadata(dir.path().join(&a).join("histograms.bin"))
        .unwrap()
        .len();
    assert!(log > 0);
    let (s, v) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{a}/resume"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED, "{v}");
    let fin = wait_for(&router, &a, "completed", limit, |v| v["state"] == "completed").await;
    assert_eq!(fin["pairs_done"], fin["pairs_total"], "{fin}");
    // The pairs counter counts each pair once over both sessions (until 2026-12-07 the
    // resume counted the first session's again), as the pair rate and ETA do.
    let (_, text) = call_raw(&router, Method::GET, "/metrics", None, "").await;
    let text = String::from_utf8(text).unwrap();
    let pairs_counted = text
        .lines()
        .find_map(|l| {
            l.strip_prefix("periscope_capture_pairs_total ")?
                .trim()
                .parse::<f64>()
                .ok()
        })
        .unwrap_or_else(|| panic!("no pairs counter in {text}"));
    assert_eq!(pairs_counted, total as f64, "{text}");
    // ...and the capture's time is the sum of its parts, not its last part.
    let whole = timing(&fin, "capture").unwrap();
    assert!(
        whole >= part + (total - done) as f64 * 0.02 * 0.8,
        "capture {whole} s: before the pause {part} s, then {} pairs",
        total - done
    );

    // Abort keeps what was captured.
    let b = submit().await;
    wait_for(&router, &b, "capturing", limit, capturing).await;
    let (s, _) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{b}/abort"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED);
    let ab = wait_for(&router, &b, "aborted", limit, |v| v["state"] == "aborted").await;
    let kept = periscope_daemon::store::read_log(&dir.path().join(&b))
        .unwrap()
        .records
        .len();
    assert!(kept >= 5, "{kept} records kept: {ab}");

    // E-stop: the running run aborts, the queued one is held, the laser is off.
    let c = submit().await;
    let d = submit().await;
    wait_for(&router, &c, "capturing", limit, capturing).await;
    let t = Instant::now();
    let (s, v) = call(&router, Method::POST, "/api/v1/estop", Some(TOKEN), "").await;
    assert_eq!((s, v["aborted"].as_str()), (StatusCode::OK, Some(&*c)), "{v}");
    assert!(
        t.elapsed() < Duration::from_secs(2),
        "e-stop took {:?}",
        t.elapsed()
    );
    // The simulated laser itself, not the daemon's belief: off within 50 ms, by the
    // direct path, and both arms parked.
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    let off = rig.off_since(t).expect("the laser is on after the e-stop");
    assert!(off - t < Duration::from_millis(50), "{:?}", off - t);
    assert!(v["laser"].as_str().unwrap().contains("out-of-band"), "{v}");
    assert!(v["laser_off_s"].as_f64().unwrap() < 0.05, "{v}");
    assert_eq!(v["parked"], true, "{v}");
    assert_eq!(v["held"][0].as_str(), Some(&*d), "{v}");
    let (_, vc) = call(&router, Method::GET, &format!("/api/v1/runs/{c}"), None, "").await;
    assert_eq!(vc["state"], "aborted", "{vc}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (_, vd) = call(&router, Method::GET, &format!("/api/v1/runs/{d}"), None, "").await;
    assert_eq!(vd["state"], "paused", "{vd}");
    // The worker reads the devices again after an e-stop; GET serves that reading.
    let t = Instant::now();
    let inst = loop {
        let (s, inst) = call(&router, Method::GET, "/api/v1/instrument", None, "").await;
        assert_eq!(s, StatusCode::OK);
        if inst["reading"]["age_s"]
            .as_f64()
            .is_some_and(|a| a < t.elapsed().as_secs_f64())
        {
            break inst;
        }
        assert!(
            t.elapsed() < Duration::from_secs(10),
            "no reading after the e-stop: {inst}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(inst["busy"], false, "{inst}");
    assert_eq!(inst["devices"]["laser"]["emission"], false, "{inst}");
    let (s, _) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{d}/abort"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED);
    svc.shutdown();
    worker.join().unwrap();
}

/// What one event-stream client saw.
#[derive(Debug, Default)]
struct Seen {
    names: Vec<String>,
}

async fn sse_client(client: reqwest::Client, url: String) -> Seen {
    let mut resp = client.get(&url).send().await.expect("event stream opens");
    assert_eq!(resp.status(), 200);
    let mut seen = Seen::default();
    let mut buf = String::new();
    while let Some(chunk) = resp.chunk().await.expect("event stream reads") {
        buf.push_str(&String::from_utf8_lossy(&chunk));
        while let Some(end) = buf.find("\n\n") {
            let block: String = buf.drain(..end + 2).collect();
            if let Some(name) = block.lines().find_map(|l| l.strip_prefix("event: ")) {
                seen.names.push(name.to_owned());
            }
        }
    }
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_event_streams_and_a_status_poller_follow_a_real_capture() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 1.0, Some(TOKEN));
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
    let resp = client
        .post(format!("{base}/runs"))
        .bearer_auth(TOKEN)
        .header("content-type", "application/toml")
        .body(PLAN)
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), 201);
    let id = serde_json::from_slice::<Value>(&resp.bytes().await.unwrap()).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_owned();
    let clients: Vec<_> = (0..50)
        .map(|_| tokio::spawn(sse_client(client.clone(), format!("{base}/runs/{id}/events"))))
        .collect();
    let poller = {
        let (client, url) = (client.clone(), format!("{base}/runs/{id}"));
        tokio::spawn(async move {
            let mut latencies = Vec::new();
            loop {
                let t = Instant::now();
                let resp = client.get(&url).send().await.unwrap();
                assert_eq!(resp.status(), 200);
                let v: Value = serde_json::from_slice(&resp.bytes().await.unwrap()).unwrap();
                latencies.push(t.elapsed());
                if v["state"] != "queued" && v["state"] != "running" {
                    return (v, latencies);
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
    };
    let (last, mut latencies) = tokio::time::timeout(Duration::from_secs(120), poller)
        .await
        .expect("the run finishes within 2 minutes")
        .unwrap();
    assert_eq!(last["state"], "completed", "{last}");
    for c in clients {
        let seen = tokio::time::timeout(Duration::from_secs(30), c)
            .await
            .expect("each stream ends when the run does")
            .unwrap();
        assert_eq!(seen.names.first().map(String::as_str), Some("status"), "{seen:?}");
        for name in [
            "stage-started",
            "planned",
            "pair",
            "stage-finished",
            "output",
            "completed",
        ] {
            assert!(seen.names.iter().any(|n| n == name), "no {name} event: {seen:?}");
        }
        assert!(!seen.names.iter().any(|n| n == "lagged"), "{seen:?}");
    }
    latencies.sort();
    eprintln!(
        "status polls: {}, median {:?}, max {:?}",
        latencies.len(),
        latencies[latencies.len() / 2],
        latencies.last().unwrap()
    );
    assert!(latencies.len() > 10);
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
}

/// A service on the simulator in real time, its worker and router, and one run of
/// [`PLAN`] submitted and capturing (at least 5 pairs stored): the run's id and status.
async fn a_capturing_run(
    runs: &Path,
) -> (
    Arc<Service>,
    std::thread::JoinHandle<()>,
    axum::Router,
    String,
    Value,
) {
    let svc = service(runs, 1.0, Some(TOKEN));
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", Some(TOKEN), PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let status = wait_for(&router, &id, "capturing", Duration::from_secs(60), |v| {
        v["stage"] == "capture" && v["pairs_done"].as_u64().unwrap_or(0) >= 5
    })
    .await;
    (svc, worker, router, id, status)
}

/// The e-stop never waits behind the blocking pool: here the pool's one thread is
/// taken for 3 s (as by requests whose timeout fired while their blocking work, an
/// export or a stalled disk, went on), and a keyed e-stop must still reach the laser
/// within 50 ms and answer within a second. Until 2026-12-06 its key check, its work
/// and its audit entry all queued on that pool.
#[test]
fn an_estop_does_not_wait_for_a_full_blocking_pool() {
    let rt = common::one_blocking_thread();
    rt.block_on(async {
        let dir = tempfile::tempdir().unwrap();
        let (svc, _worker, router, id, _) = a_capturing_run(dir.path()).await;
        let hog = common::take_the_blocking_pool(Duration::from_secs(3));
        let t = Instant::now();
        let (s, v) = call(&router, Method::POST, "/api/v1/estop", Some(TOKEN), "").await;
        let answered = t.elapsed();
        assert_eq!((s, v["aborted"].as_str()), (StatusCode::OK, Some(&*id)), "{v}");
        let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
        let off = rig.off_since(t).expect("the laser is on after the e-stop");
        assert!(
            off - t < Duration::from_millis(50),
            "laser off after {:?}",
            off - t
        );
        assert!(
            answered < Duration::from_secs(1),
            "the e-stop answered after {answered:?}, behind the blocking pool"
        );
        hog.await.unwrap();
    });
}

/// Holds the runs directory's catalogue in a write transaction for `hold`, as another
/// process (`periscope catalogue sync`) would; returns once it is held.
fn hold_the_catalogue(runs: &Path, hold: Duration) -> std::thread::JoinHandle<()> {
    let catalogue = runs.join(periscope_daemon::catalogue::CATALOGUE_FILE);
    let (held_tx, held) = std::sync::mpsc::channel();
    let holder = std::thread::spawn(move || {
        let conn = rusqlite::Connection::open(catalogue).unwrap();
        conn.execute_batch("BEGIN IMMEDIATE").unwrap();
        held_tx.send(()).unwrap();
        std::thread::sleep(hold);
        conn.execute_batch("ROLLBACK").unwrap();
    });
    held.recv().unwrap();
    holder
}

/// A loopback e-stop sent with a key the daemon refuses (a wall panel's expired key)
/// goes ahead, and the laser goes off before the refusal is recorded: the audit trail
/// waits for the catalogue's lock, held here for 2 s as `periscope catalogue sync`
/// would hold it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loopback_estop_with_a_refused_key_does_not_wait_for_the_audit_trail() {
    let dir = tempfile::tempdir().unwrap();
    let (svc, _worker, router, id, _) = a_capturing_run(dir.path()).await;
    let holder = hold_the_catalogue(dir.path(), Duration::from_secs(2));
    let t = Instant::now();
    let (s, v) = call(&router, Method::POST, "/api/v1/estop", Some("psk_expired"), "").await;
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    let off = rig.off_since(t).expect("the laser is on after the e-stop");
    assert!(
        off - t < Duration::from_millis(50),
        "laser off after {:?}, behind the audit trail",
        off - t
    );
    assert_eq!((s, v["aborted"].as_str()), (StatusCode::OK, Some(&*id)), "{v}");
    holder.join().unwrap();
    // The refusal is recorded all the same.
    let (_, audit) = call(
        &router,
        Method::GET,
        "/api/v1/audit?action=authenticate",
        Some(TOKEN),
        "",
    )
    .await;
    assert!(
        audit["entries"].as_array().unwrap().iter().any(|e| e["detail"]
            .as_str()
            .is_some_and(|d| d.contains("went ahead as loopback"))),
        "{audit}"
    );
}

/// E-stops pressed while another process holds the catalogue (as `periscope catalogue
/// sync` does) keep their audit entries waiting; sixteen of them, the most the e-stop's
/// threads run at once, must not keep a seventeenth from switching the laser off and
/// reporting it. Until 2026-12-06 the entries held the action's own slots, and each
/// answer waited for its entry: the seventeenth waited for the catalogue.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn estops_whose_audit_entries_wait_leave_the_next_estop_its_threads() {
    let dir = tempfile::tempdir().unwrap();
    let (svc, _worker, router, _id, _) = a_capturing_run(dir.path()).await;
    let holder = hold_the_catalogue(dir.path(), Duration::from_secs(6));
    let pressed: Vec<_> = (0..16)
        .map(|_| {
            let router = router.clone();
            tokio::spawn(async move { call(&router, Method::POST, "/api/v1/estop", Some(TOKEN), "").await })
        })
        .collect();
    // Their audit entries now wait for the catalogue.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let t = Instant::now();
    let (s, v) = call(&router, Method::POST, "/api/v1/estop", Some(TOKEN), "").await;
    let answered = t.elapsed();
    assert_eq!(s, StatusCode::OK, "{v}");
    assert!(
        answered < Duration::from_secs(3),
        "the seventeenth e-stop answered after {answered:?}, behind the audit trail"
    );
    for p in pressed {
        let (s, v) = p.await.unwrap();
        assert_eq!(s, StatusCode::OK, "{v}");
    }
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    assert!(!rig.emission(), "the laser is on after the e-stops");
    holder.join().unwrap();
    // Every e-stop is recorded once the catalogue lets go.
    let t = Instant::now();
    loop {
        let (_, audit) = call(
            &router,
            Method::GET,
            "/api/v1/audit?action=estop&limit=100",
            Some(TOKEN),
            "",
        )
        .await;
        let n = audit["entries"].as_array().map_or(0, Vec::len);
        if n >= 17 {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "{n} e-stops recorded: {audit}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// During a capture `/metrics` gives the laser as the run reads it (at every pair), not
/// the worker's reading from before the run, in which the laser was off: an alert on
/// emission with the interlock open must be able to fire while a run measures.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_give_the_runs_own_laser_reading_during_a_capture() {
    let dir = tempfile::tempdir().unwrap();
    let (svc, _worker, router, id, _) = a_capturing_run(dir.path()).await;
    let (s, text) = call_raw(&router, Method::GET, "/metrics", None, "").await;
    assert_eq!(s, StatusCode::OK);
    let text = String::from_utf8(text).unwrap();
    let gauge = |name: &str| {
        text.lines()
            .find_map(|l| {
                l.strip_prefix(name)?
                    .strip_prefix(' ')?
                    .trim()
                    .parse::<f64>()
                    .ok()
            })
            .unwrap_or_else(|| panic!("no {name} in {text}"))
    };
    assert_eq!(gauge("periscope_instrument_busy"), 1.0);
    assert_eq!(
        gauge("periscope_laser_emission"),
        1.0,
        "the laser is on in the capture"
    );
    assert_eq!(gauge("periscope_interlock_closed"), 1.0);
    assert_eq!(gauge("periscope_reading_valid"), 1.0);
    assert!(gauge("periscope_reading_age_seconds") < 3.0);
    let (s, _) = call(
        &router,
        Method::POST,
        &format!("/api/v1/runs/{id}/abort"),
        Some(TOKEN),
        "",
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED);
    drop(svc);
}

/// A running capture's export is made again at most every 10 s, however often it is
/// downloaded: a client looping on `capture.hdf5` cannot keep a core and the disk
/// re-exporting while the instrument measures. Two downloads half a second apart,
/// with pairs stored in between, get the same file; the run's own capture replaces it
/// when the run completes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_captures_export_is_not_remade_on_every_download() {
    let dir = tempfile::tempdir().unwrap();
    let (_svc, _worker, router, id, status) = a_capturing_run(dir.path()).await;
    let first_done = status["pairs_done"].as_u64().unwrap();
    let limit = Duration::from_secs(60);
    let url = format!("/api/v1/runs/{id}/files/capture.hdf5");
    let (s, first) = call_raw(&router, Method::GET, &url, Some(TOKEN), "").await;
    assert_eq!(s, StatusCode::OK);
    let later = wait_for(&router, &id, "further on", limit, |v| {
        v["pairs_done"].as_u64().unwrap_or(0) >= first_done + 5 || v["state"] != "running"
    })
    .await;
    assert_eq!(
        later["state"], "running",
        "the capture ended too soon to test: {later}"
    );
    let (s, second) = call_raw(&router, Method::GET, &url, Some(TOKEN), "").await;
    assert_eq!(s, StatusCode::OK);
    assert!(
        first == second,
        "the export was made again {} pairs later",
        later["pairs_done"]
    );
    // Once the run has written the whole capture, the export of it unfinished is
    // removed: until 2026-12-08 it stayed beside it, as large, for good.
    let cache = dir
        .path()
        .join(&id)
        .join(periscope_daemon::run_dir::file::EXPORT_CACHE);
    assert!(cache.is_file());
    let done = wait_for(&router, &id, "completed", limit, |v| v["state"] != "running").await;
    assert_eq!(done["state"], "completed", "{done}");
    let stamp = cache.with_file_name(".capture-export.hdf5.stamp");
    assert!(
        !cache.exists() && !stamp.exists(),
        "the unfinished capture's export is left"
    );
    let (s, whole) = call_raw(&router, Method::GET, &url, Some(TOKEN), "").await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(
        whole,
        std::fs::read(dir.path().join(&id).join("capture.hdf5")).unwrap()
    );
}

/// A gtr plan that streams a fit snapshot of 600 primitives after each of its 300
/// epochs: far more than a display budget of 256 KiB holds.
fn snapshot_plan() -> String {
    SmallPlan::named("snapshots")
        .set("recon.method", "gtr")
        .set("recon.volume.shape", [16, 16, 16])
        .set("recon.gtr.primitives", 600)
        .set("recon.gtr.epochs", 300)
        .set("recon.gtr.virtual-grid", [16, 16])
        .toml()
}

/// An event-stream client that never reads: the display-only events it holds (each
/// epoch's snapshot of the fit, thousands of Gaussians) stop at the streams' budget,
/// and the events a display cannot do without (stages, epochs, the end) still reach
/// it. Until 2026-12-06 only the ring's 1,024 events bounded them, whatever their
/// size: 300 epochs' snapshots of 600 Gaussians held 15 MB here (0.33 MB now), over 100 MB at the
/// default 2,000 and a longer fit.
#[test]
fn a_stream_client_that_never_reads_holds_no_more_than_the_display_budget() {
    use periscope_daemon::run_dir::RunState;
    const BUDGET: usize = 256 << 10;
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, Some(TOKEN));
    svc.set_stream_display_budget(BUDGET);
    let worker = svc.start_worker();
    let id = svc.submit(snapshot_plan()).unwrap().id;
    let mut rx = svc.subscribe(&id).unwrap().expect("a queued run has a channel");
    let (mut most, t) = (0, Instant::now());
    loop {
        most = most.max(svc.stream_bytes());
        let state = svc.status(&id).unwrap().state;
        if !matches!(state, RunState::Queued | RunState::Running) {
            assert_eq!(state, RunState::Completed);
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "the run never finished");
        std::thread::sleep(Duration::from_millis(2));
    }
    let (mut snapshots, mut largest, mut essential, mut names) = (0, 0, 0, Vec::new());
    // The run's last events reach the channel after its state says completed.
    let read = Instant::now();
    loop {
        use tokio::sync::broadcast::error::TryRecvError;
        let ev = match rx.try_recv() {
            Ok(ev) => ev,
            Err(TryRecvError::Lagged(n)) => {
                names.push(format!("lagged {n}"));
                continue;
            }
            Err(TryRecvError::Empty)
                if !names.iter().any(|n| n == "completed") && read.elapsed() < Duration::from_secs(10) =>
            {
                std::thread::sleep(Duration::from_millis(5));
                continue;
            }
            Err(_) => break,
        };
        if &*ev.name == "snapshot" {
            snapshots += 1;
            largest = largest.max(ev.json.len());
        } else if !["histogram", "safety"].contains(&&*ev.name) {
            essential += ev.json.len();
        }
        names.push(ev.name.to_string());
    }
    eprintln!("most held {most} B; {snapshots} snapshots of up to {largest} B; {essential} B of the rest");
    assert!(snapshots >= 2, "{names:?}");
    // Unbounded, 300 snapshots would have held many times the budget.
    assert!(300 * largest > 8 * BUDGET, "{largest}");
    assert!(most <= BUDGET + largest + essential, "{most}");
    for name in ["stage-started", "epoch", "output", "completed"] {
        assert!(names.iter().any(|n| n == name), "no {name}: {names:?}");
    }
    drop(rx);
    assert_eq!(
        svc.stream_bytes(),
        0,
        "every event's bytes are let go with the last reader"
    );
    svc.shutdown();
    worker.join().unwrap();
}

/// The same over HTTP with a key, as every remote dashboard reads: the check that ends
/// a keyed stream when its key lapses ran as a task that took the stream's events
/// ahead of the client, 16 more a stream outside the display budget, until
/// 2026-12-08. A client that reads nothing until the run ends now gets no more
/// snapshots than the budget keeps.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_keyed_stream_that_is_not_read_gets_no_more_than_the_display_budget() {
    use periscope_daemon::run_dir::RunState;
    const BUDGET: usize = 256 << 10;
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, Some(TOKEN));
    svc.set_stream_display_budget(BUDGET);
    let id = svc.submit(snapshot_plan()).unwrap().id;
    let router = app(AppState::new(Arc::clone(&svc)));
    let events = format!("/api/v1/runs/{id}/events");
    let resp = tower::ServiceExt::oneshot(
        router.clone(),
        common::request(Method::GET, &events, Some(TOKEN), &[], ""),
    )
    .await
    .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let worker = svc.start_worker();
    use tokio_stream::StreamExt as _;
    let mut body = resp.into_body().into_data_stream();
    let mut text = String::new();
    let stopped;
    loop {
        // Read as events come until the fit's first snapshot, then no more until the
        // run has ended.
        if let Some(at) = text.find("event: snapshot") {
            stopped = at;
            break;
        }
        let chunk = tokio::time::timeout(Duration::from_secs(120), body.next())
            .await
            .expect("no snapshot came")
            .expect("the stream ended before a snapshot")
            .unwrap();
        text.push_str(&String::from_utf8_lossy(&chunk));
    }
    let t = Instant::now();
    loop {
        let state = svc.status(&id).unwrap().state;
        if !matches!(state, RunState::Queued | RunState::Running) {
            assert_eq!(state, RunState::Completed);
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "the run never finished");
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let rest = tokio::time::timeout(Duration::from_secs(30), async {
        let mut rest = Vec::new();
        while let Some(chunk) = body.next().await {
            rest.extend_from_slice(&chunk.unwrap());
        }
        rest
    })
    .await
    .expect("the stream ends with the run");
    text.push_str(&String::from_utf8_lossy(&rest));
    // The snapshots the client was sent from the one it stopped reading at.
    let (mut snapshots, mut bytes, mut largest) = (0, 0, 0);
    for event in text[stopped..].split("\n\n") {
        if event.lines().any(|l| l == "event: snapshot") {
            let data: usize = event
                .lines()
                .filter_map(|l| l.strip_prefix("data:"))
                .map(str::len)
                .sum();
            snapshots += 1;
            bytes += data;
            largest = largest.max(data);
        }
    }
    eprintln!("{snapshots} snapshots, {bytes} B, the largest {largest} B");
    assert!(
        text.contains("event: completed"),
        "{}",
        &text[text.len().saturating_sub(400)..]
    );
    assert!(
        snapshots >= 1 && 20 * largest > BUDGET,
        "{snapshots} of up to {largest} B"
    );
    // The budget's worth, the one it stopped at and at most one more in flight.
    assert!(bytes <= BUDGET + 2 * largest, "{bytes} B of snapshots");
    svc.shutdown();
    tokio::task::spawn_blocking(move || worker.join().unwrap())
        .await
        .unwrap();
}

/// After a run the instrument is shown as read after it, never as the reading taken
/// before it: until the worker reads the devices again the state is unknown. Until
/// 2026-12-06 the pre-run reading was served, with its true age, which the staleness
/// rule could still take for current (a laser the run could not switch off showed as
/// off for up to the rest of the 21 s).
#[test]
fn after_a_run_the_instrument_is_never_shown_as_read_before_it() {
    use periscope_daemon::run_dir::RunState;
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 0.0, Some(TOKEN));
    let worker = svc.start_worker();
    // The idle reading taken before the run.
    let t = Instant::now();
    while svc.instrument_status().reading.is_none() {
        assert!(t.elapsed() < Duration::from_secs(10), "never read");
        std::thread::sleep(Duration::from_millis(2));
    }
    let before = svc.instrument_status().reading.unwrap().taken_unix_s;
    let id = svc.submit(SmallPlan::named("reading").toml()).unwrap().id;
    while svc.status(&id).unwrap().state != RunState::Running {
        assert!(t.elapsed() < Duration::from_secs(30), "never ran");
        std::thread::sleep(Duration::from_millis(1));
    }
    // Checked as often as the lock allows from the run's end until the worker has
    // read the devices again and a while after.
    let mut after_end = 0;
    while after_end < 300 {
        let done = svc.status(&id).unwrap().state == RunState::Completed;
        let status = svc.instrument_status();
        let safety = svc.safety();
        // Once the worker has let the run go (its state is saved a moment before).
        if done && status.run.is_none() {
            after_end += 1;
            let taken = status.reading.as_ref().map(|r| r.taken_unix_s);
            assert!(
                taken.is_none_or(|t| t > before),
                "the pre-run reading served after the run"
            );
            if safety.source == "idle" && safety.age_s.is_some() {
                // From the same reading or a newer one, a moment later.
                let now = svc.instrument_status().reading.map(|r| r.taken_unix_s);
                assert!(now.is_some_and(|t| t > before), "{now:?}");
            }
        }
        assert!(t.elapsed() < Duration::from_secs(60), "the run never finished");
        std::thread::sleep(Duration::from_micros(200));
    }
    assert!(after_end > 0);
    svc.shutdown();
    worker.join().unwrap();
}

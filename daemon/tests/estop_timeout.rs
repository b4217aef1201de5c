//! The e-stop is answered whatever `[api] request-timeout-s` says: with a 1 s request
//! timeout and a disk that stalls the run's way out for 1.5 s, the e-stop's answer (the
//! laser off, the run aborted and parked) still comes, where the timeout layer cut it
//! off with a 408 after the laser had gone off, telling the operator it failed.
//!
//! A test binary of its own: the disk stall (`store::SLOW_SYNC_MS`, feature
//! `test-hooks`) is process-wide and would slow every other API test.
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::http::{Method, StatusCode};
use periscope_daemon::api::{AppState, app};
use periscope_daemon::service::Service;
use serde_json::Value;

mod common;

const TOKEN: &str = "test-token-0123456789abcdef";
const PLAN: &str = include_str!("../../tests/data/plans/small-fbp.toml");

/// The simulated instrument at `time_scale` with a request timeout of 1 s.
fn service(runs: &std::path::Path, time_scale: f64) -> Arc<Service> {
    let src = common::sim_instrument(
        runs,
        time_scale,
        &format!("token = \"{TOKEN}\"\nrequest-timeout-s = 1.0\n"),
        "",
    );
    Service::open(src, Some(TOKEN.to_owned())).unwrap()
}

async fn call(router: &axum::Router, method: Method, uri: &str, body: &str) -> (StatusCode, Value) {
    let (status, bytes) = common::send(router, common::request(method, uri, Some(TOKEN), &[], body)).await;
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_estop_outlasting_the_request_timeout_is_still_answered() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), 1.0);
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let (s, v) = call(&router, Method::POST, "/api/v1/runs", PLAN).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let t = Instant::now();
    loop {
        let (_, v) = call(&router, Method::GET, &format!("/api/v1/runs/{id}"), "").await;
        if v["stage"] == "capture" && v["pairs_done"].as_u64().unwrap_or(0) >= 3 {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(60), "never capturing: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    periscope_daemon::store::SLOW_SYNC_MS.store(1500, Ordering::SeqCst);
    let pressed = Instant::now();
    let (s, v) = call(&router, Method::POST, "/api/v1/estop", "").await;
    let answered = pressed.elapsed();
    periscope_daemon::store::SLOW_SYNC_MS.store(0, Ordering::SeqCst);
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    let off = rig.off_since(pressed).expect("the laser is on after the e-stop");
    assert!(
        off - pressed < Duration::from_millis(50),
        "laser off after {:?}",
        off - pressed
    );
    assert_eq!(s, StatusCode::OK, "answered after {answered:?}: {v}");
    assert_eq!(v["aborted"].as_str(), Some(&*id), "{v}");
    assert!(
        answered > Duration::from_secs(1),
        "the run's way out did not outlast the timeout: {answered:?}"
    );

    svc.shutdown();
    worker.join().unwrap();
}

/// Any other request past the timeout is answered as every error is: JSON
/// `request-timeout` naming the key (a bare 408 with no body until 2026-12-06). A run's
/// status waits here for the blocking pool's one thread, taken for 3 s.
#[test]
fn a_request_past_the_timeout_is_a_json_error() {
    let rt = common::one_blocking_thread();
    rt.block_on(async {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path(), 0.0);
        let router = app(AppState::new(Arc::clone(&svc)));
        let hog = common::take_the_blocking_pool(Duration::from_secs(3));
        let t = Instant::now();
        // Without a key: a loopback read, which asks the key store nothing (a key's
        // check has a timeout of its own: the next test).
        let (s, bytes) = common::send(
            &router,
            common::request(Method::GET, "/api/v1/runs/nothing-here", None, &[], ""),
        )
        .await;
        let v: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(s, StatusCode::REQUEST_TIMEOUT, "after {:?}: {v}", t.elapsed());
        assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
        assert_eq!(v["error"], "request-timeout", "{v}");
        assert!(
            v["message"].as_str().unwrap().contains("request-timeout-s"),
            "{v}"
        );
        hog.await.unwrap();
        svc.shutdown();
    });
}

/// The key check runs before the timeout layer, on the blocking pool (a key in
/// `keys.json` may need the file read again). With the pool's one thread taken for
/// 3 s, a request with such a key is answered with JSON `request-timeout` within the
/// 1 s timeout: until 2026-12-06 it waited the whole 3 s, however short the timeout.
/// One with the daemon's token, which reads no file, is answered at once.
#[test]
fn a_key_check_waiting_for_a_busy_pool_is_cut_off_at_the_timeout() {
    let rt = common::one_blocking_thread();
    rt.block_on(async {
        let dir = tempfile::tempdir().unwrap();
        let svc = service(dir.path(), 0.0);
        let (_, key) = svc
            .keys()
            .create("panel", periscope_daemon::access::Role::Observer, None, "test")
            .unwrap();
        let router = app(AppState::new(Arc::clone(&svc)));
        let whoami = |secret: &str| common::request(Method::GET, "/api/v1/whoami", Some(secret), &[], "");
        // The key works while the pool is free.
        let (s, bytes) = common::send(&router, whoami(&key)).await;
        assert_eq!(s, StatusCode::OK, "{}", String::from_utf8_lossy(&bytes));

        let hog = common::take_the_blocking_pool(Duration::from_secs(3));
        let t = Instant::now();
        let (s, bytes) = common::send(&router, whoami(TOKEN)).await;
        let v: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(s, StatusCode::OK, "after {:?}: {v}", t.elapsed());
        assert_eq!(v["name"], "token", "{v}");
        assert!(t.elapsed() < Duration::from_millis(500), "{:?}", t.elapsed());

        let t = Instant::now();
        let (s, bytes) = common::send(&router, whoami(&key)).await;
        let v: Value = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
        assert_eq!(s, StatusCode::REQUEST_TIMEOUT, "after {:?}: {v}", t.elapsed());
        assert!(
            t.elapsed() >= Duration::from_millis(900) && t.elapsed() < Duration::from_secs(2),
            "{:?}",
            t.elapsed()
        );
        assert_eq!(v["error"], "request-timeout", "{v}");
        assert!(v["message"].as_str().unwrap().contains("key check"), "{v}");
        hog.await.unwrap();
        // The pool free again, the key works.
        let (s, _) = common::send(&router, whoami(&key)).await;
        assert_eq!(s, StatusCode::OK);
        svc.shutdown();
    });
}

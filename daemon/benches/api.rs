//! The HTTP API under load: a capture's pairs per second with and without 50
//! event-stream clients attached, and the status endpoint's latency meanwhile.
//!
//! `cargo bench -p periscope-daemon --bench api` (release). A round runs one plan (a
//! 48×48 confocal grid on the simulator at time-scale 0, so the capture is as fast as
//! the drivers and the physics go, FBP reconstruction) on a fresh service behind a real
//! socket, with no client or with 50 SSE clients and a status poller.
//!
//! Timed (criterion, group `api`, one iteration a round, 10 samples): the capture
//! stage's own time from the run's `run.json`, summed over the rounds (`iter_custom`),
//! so criterion's median is seconds per capture of 2,304 pairs and its throughput line
//! is pairs per second: the figures to quote. Not timed: starting the service, the LOS
//! scan, relay estimation and reconstruction, attaching the clients. Printed once after
//! the group: the rate over all rounds with and without clients, and the status
//! endpoint's latency during the loaded captures (median, p90, max).
use std::future::IntoFuture;
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use criterion::{Criterion, SamplingMode, Throughput, criterion_group, criterion_main};
use periscope_daemon::api::{AppState, app};
use periscope_daemon::config::TomlSource;
use periscope_daemon::service::Service;
use serde_json::Value;

// The plan the tests share (the end-to-end crate's `SmallPlan`).
#[allow(dead_code, unreachable_pub)]
#[path = "../../tests/support/plan.rs"]
mod small_plan;
use small_plan::SmallPlan;

const TOKEN: &str = "bench-token-0123456789abcdef";
const CLIENTS: usize = 50;
/// The plan's pairs: a 48 × 48 confocal grid.
const PAIRS: u64 = 48 * 48;

/// The shared small plan on a 16 × 16 LOS grid and 48 × 48 pairs, FBP on a coarse volume.
fn plan() -> String {
    SmallPlan::named("api-bench")
        .set("los.grid", [16, 16])
        .set("pairs.grid", [48, 48])
        .set("recon.volume.shape", [16, 16, 8])
        .toml()
}

fn service(runs: &Path) -> Arc<Service> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/instrument/sim.toml");
    let mut text = std::fs::read_to_string(&path).unwrap();
    text.push_str(&format!("\n[api]\nruns-dir = \"{}\"\n", runs.display()));
    Service::open(TomlSource::from_text(path, text), Some(TOKEN.into())).unwrap()
}

struct Round {
    /// Pairs measured, and the capture stage's own time from `run.json`.
    pairs: f64,
    capture: Duration,
    latencies: Vec<Duration>,
}

async fn round(clients: usize) -> Round {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path());
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
    let http = reqwest::Client::new();
    let v: Value = serde_json::from_slice(
        &http
            .post(format!("{base}/runs"))
            .bearer_auth(TOKEN)
            .header("content-type", "application/toml")
            .body(plan())
            .send()
            .await
            .unwrap()
            .bytes()
            .await
            .unwrap(),
    )
    .unwrap();
    let id = v["id"].as_str().unwrap().to_owned();
    // Attach the clients while the run is queued, then let the worker start it.
    let mut streams = Vec::new();
    for _ in 0..clients {
        let mut resp = http.get(format!("{base}/runs/{id}/events")).send().await.unwrap();
        let first = resp.chunk().await.unwrap();
        assert!(first.is_some());
        streams.push(tokio::spawn(async move {
            let mut bytes = 0usize;
            while let Ok(Some(c)) = resp.chunk().await {
                bytes += c.len();
            }
            bytes
        }));
    }
    let worker = svc.start_worker();
    let mut latencies = Vec::new();
    loop {
        let t = Instant::now();
        let v: Value = serde_json::from_slice(
            &http
                .get(format!("{base}/runs/{id}"))
                .send()
                .await
                .unwrap()
                .bytes()
                .await
                .unwrap(),
        )
        .unwrap();
        if clients > 0 && v["stage"] == "capture" {
            latencies.push(t.elapsed());
        }
        if v["state"] == "completed" || v["state"] == "failed" {
            assert_eq!(v["state"], "completed", "{v}");
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    for s in streams {
        s.await.unwrap();
    }
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join(&id).join("run.json")).unwrap())
            .unwrap();
    let capture_s = info["timings"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t[0] == "capture")
        .and_then(|t| t[1].as_f64())
        .unwrap();
    let pairs = info["pairs_done"].as_f64().unwrap();
    server.abort();
    svc.shutdown();
    worker.join().unwrap();
    assert_eq!(pairs, PAIRS as f64, "the capture measured every pair of the plan");
    Round {
        pairs,
        capture: Duration::from_secs_f64(capture_s),
        latencies,
    }
}

fn api(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let mut group = c.benchmark_group("api");
    // About 1 s of capture a round here: one round to warm up, two a sample.
    group
        .sample_size(10)
        .sampling_mode(SamplingMode::Flat)
        .warm_up_time(Duration::from_millis(1))
        .measurement_time(Duration::from_secs(15))
        .throughput(Throughput::Elements(PAIRS));
    // Pairs and capture seconds over every round (warm-up included), for the comparison
    // printed after the group; the loaded rounds' status latencies.
    let mut totals = [(0.0, 0.0); 2];
    let mut latencies = Vec::new();
    for (i, clients) in [0, CLIENTS].into_iter().enumerate() {
        let name = format!("capture, {clients} event streams");
        group.bench_function(name, |b| {
            b.iter_custom(|iters| {
                let mut capture = Duration::ZERO;
                for _ in 0..iters {
                    let r = rt.block_on(round(clients));
                    capture += r.capture;
                    totals[i].0 += r.pairs;
                    totals[i].1 += r.capture.as_secs_f64();
                    latencies.extend(r.latencies);
                }
                capture
            })
        });
    }
    group.finish();

    // Criterion's medians above are the figures to quote; these are over every round.
    let [(qp, qs), (lp, ls)] = totals;
    if qs > 0.0 && ls > 0.0 {
        let (q, l) = (qp / qs, lp / ls);
        println!(
            "capture over all rounds: {q:.0} pairs/s alone, {l:.0} pairs/s with {CLIENTS} event streams ({:+.1} %)",
            100.0 * (l / q - 1.0)
        );
    }
    latencies.sort();
    if !latencies.is_empty() {
        println!(
            "GET /runs/{{id}} during the loaded captures: {} polls, median {:.2} ms, p90 {:.2} ms, max {:.2} ms",
            latencies.len(),
            latencies[latencies.len() / 2].as_secs_f64() * 1e3,
            latencies[latencies.len() * 9 / 10].as_secs_f64() * 1e3,
            latencies.last().unwrap().as_secs_f64() * 1e3
        );
    }
}

criterion_group!(benches, api);
criterion_main!(benches);

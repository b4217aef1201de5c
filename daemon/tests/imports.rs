//! Imports (`POST /api/v1/imports`): a public capture file uploaded as a form becomes a
//! run that reconstructs it after the runs before it, with a run's results; a bad
//! upload is refused with its reason and leaves nothing behind; an e-stop stops an
//! import like any run. Through the router without a socket, over the simulator.
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::http::{Method, Request, StatusCode, header};
use periscope_daemon::api::{AppState, app};
use periscope_daemon::service::Service;
use serde_json::Value;

mod common;

const TOKEN: &str = "test-token-0123456789abcdef";

fn service(runs: &Path, api_lines: &str) -> Arc<Service> {
    let src = common::sim_instrument(runs, 0.0, &format!("token = \"{TOKEN}\"\n{api_lines}"), "");
    Service::open(src, Some(TOKEN.to_owned())).unwrap()
}

fn fixture(name: &str) -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../recon/tests/data")
        .join(name)
}

/// A form field: a file (field, file name, bytes) or text (field, value).
enum Part<'a> {
    File(&'a str, &'a str, Vec<u8>),
    Text(&'a str, &'a str),
}

const BOUNDARY: &str = "periscope-test-boundary-7f3a";

/// A multipart/form-data body as a browser's FormData sends it.
fn form(parts: &[Part<'_>]) -> Vec<u8> {
    let mut body = Vec::new();
    for p in parts {
        body.extend_from_slice(format!("--{BOUNDARY}\r\n").as_bytes());
        match p {
            Part::File(field, name, bytes) => {
                body.extend_from_slice(
                    format!(
                        "Content-Disposition: form-data; name=\"{field}\"; filename=\"{name}\"\r\n\
                         Content-Type: application/octet-stream\r\n\r\n"
                    )
                    .as_bytes(),
                );
                body.extend_from_slice(bytes);
            }
            Part::Text(field, value) => {
                body.extend_from_slice(
                    format!("Content-Disposition: form-data; name=\"{field}\"\r\n\r\n{value}").as_bytes(),
                );
            }
        }
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
    body
}

fn upload(token: Option<&str>, body: Body) -> Request<Body> {
    let mut req = Request::builder()
        .method(Method::POST)
        .uri("/api/v1/imports")
        .header(
            header::CONTENT_TYPE,
            format!("multipart/form-data; boundary={BOUNDARY}"),
        );
    if let Some(t) = token {
        req = req.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    req.body(body).unwrap()
}

async fn import(router: &axum::Router, parts: &[Part<'_>]) -> (StatusCode, Value) {
    let (s, bytes) = common::send(router, upload(Some(TOKEN), Body::from(form(parts)))).await;
    (s, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

async fn get(router: &axum::Router, uri: &str) -> (StatusCode, Vec<u8>) {
    common::send(router, common::request(Method::GET, uri, None, &[], "")).await
}

async fn wait_until(
    router: &axum::Router,
    id: &str,
    limit: Duration,
    pred: impl Fn(&Value) -> bool,
) -> Value {
    let t = Instant::now();
    loop {
        let (s, bytes) = get(router, &format!("/api/v1/runs/{id}")).await;
        assert_eq!(s, StatusCode::OK);
        let v: Value = serde_json::from_slice(&bytes).unwrap();
        if pred(&v) {
            return v;
        }
        assert!(t.elapsed() < limit, "run {id}: {v}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// The runs in the runs directory, and what is left of uploads in flight.
fn runs_and_staging(runs: &Path) -> (Vec<String>, usize) {
    let ids = std::fs::read_dir(runs)
        .unwrap()
        .filter_map(Result::ok)
        .filter(|e| e.path().join("run.json").is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    let staging = std::fs::read_dir(runs.join(periscope_daemon::service::STAGING_DIR))
        .map(|d| d.count())
        .unwrap_or(0);
    (ids, staging)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn imported_captures_of_every_kind_become_runs_with_their_results() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), "");
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let read = |name: &str| std::fs::read(fixture(name)).unwrap();
    // Stanford LCT (MAT v5) with settings; f-k (MAT v7.3) with the `tof.mat` its
    // reader looks for beside it; ZNLOS (HDF5) with the defaults (3D-GTR).
    let cases: Vec<(Vec<Part<'_>>, [f64; 3], &str)> = vec![
        (
            vec![
                Part::File("capture", "lct-point.mat", read("lct-point.mat")),
                Part::Text("recon", "method = \"fbp\"\n"),
                Part::Text("name", "stanford lct"),
            ],
            [0.1, -0.05, 0.3],
            "fbp",
        ),
        (
            vec![
                Part::File("capture", "meas_10min.mat", read("fk-point/meas_10min.mat")),
                Part::File("sidecar", "tof.mat", read("fk-point/tof.mat")),
                Part::Text("recon", "method = \"fbp\"\n"),
            ],
            [0.25, -0.1, 0.6],
            "fbp",
        ),
        (
            vec![Part::File(
                "capture",
                "znlos-point.hdf5",
                read("znlos-point.hdf5"),
            )],
            [0.1, -0.5, 0.05],
            "gtr",
        ),
    ];
    let mut ids = Vec::new();
    for (parts, _, _) in &cases {
        let (s, v) = import(&router, parts).await;
        assert_eq!(s, StatusCode::CREATED, "{v}");
        assert_eq!(v["state"], "queued", "{v}");
        ids.push(v["id"].as_str().unwrap().to_owned());
    }
    assert!(ids[0].ends_with("-stanford_lct"), "{ids:?}");
    for (id, (_, target, method)) in ids.iter().zip(&cases) {
        let done = wait_until(&router, id, Duration::from_secs(300), |v| {
            matches!(v["state"].as_str(), Some("completed" | "failed"))
        })
        .await;
        assert_eq!(done["state"], "completed", "{done}");
        assert!(done["pairs_done"].as_u64().unwrap() > 0, "{done}");
        let stages: Vec<&str> = done["timings"]
            .as_array()
            .unwrap()
            .iter()
            .map(|t| t[0].as_str().unwrap())
            .collect();
        assert_eq!(stages, ["reading", "reconstruction", "outputs"], "{done}");
        let run = dir.path().join(id);
        let volume: Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("volume.json")).unwrap()).unwrap();
        assert_eq!(volume["method"], *method, "{volume}");
        let (err, allowed) = common::peak_error(&run, *target);
        assert!(err < allowed, "{id}: the peak is {err} m from the target");
        eprintln!(
            "imports: {id} ({method}): peak {:.1} mm from the target",
            err * 1e3
        );
        // The capture, whatever it came as, downloads as y-tal HDF5 with every
        // transient of the file.
        let (s, bytes) = get(&router, &format!("/api/v1/runs/{id}/files/capture.hdf5")).await;
        assert_eq!(s, StatusCode::OK);
        assert!(bytes.starts_with(b"\x89HDF"));
        let back = periscope_recon::io::ytal::YtalCapture::read(&run.join("capture.hdf5")).unwrap();
        assert_eq!(back.len() as u64, done["pairs_done"].as_u64().unwrap());
        for name in ["depth.png", "albedo.png", "volume.npy"] {
            assert!(
                done["files"].as_array().unwrap().iter().any(|f| f == name),
                "{done}"
            );
        }
        // The 3-D view's geometry comes from the file.
        let (s, bytes) = get(&router, &format!("/api/v1/runs/{id}/geometry")).await;
        assert_eq!(s, StatusCode::OK);
        let g: Value = serde_json::from_slice(&bytes).unwrap();
        assert!(!g["relay"].as_array().unwrap().is_empty(), "{g}");
        assert_eq!(g["pairs"], done["pairs_done"], "{g}");
    }
    // The settings it came with download; a run without them has none.
    let (s, bytes) = get(&router, &format!("/api/v1/runs/{}/files/recon.toml", ids[0])).await;
    assert_eq!(
        (s, bytes.as_slice()),
        (StatusCode::OK, &b"method = \"fbp\"\n"[..])
    );
    let (s, _) = get(&router, &format!("/api/v1/runs/{}/files/recon.toml", ids[2])).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    // The catalogue finds a run by the file it imported, and says so.
    let (s, bytes) = get(&router, "/api/v1/runs?q=meas_10min").await;
    assert_eq!(s, StatusCode::OK);
    let found: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(found.as_array().unwrap().len(), 1, "{found}");
    assert_eq!(found[0]["imported"], "meas_10min.mat", "{found}");
    // An import has no plan to run again: refused with what to do.
    let (s, bytes) = common::send(
        &router,
        common::request(
            Method::POST,
            &format!("/api/v1/runs/{}/again", ids[1]),
            Some(TOKEN),
            &[],
            "",
        ),
    )
    .await;
    assert_eq!(s, StatusCode::CONFLICT);
    assert!(String::from_utf8_lossy(&bytes).contains("import the file again"));
    // The audit trail names who imported what.
    let (_, bytes) = get(&router, "/api/v1/audit?action=import").await;
    let audit: Value = serde_json::from_slice(&bytes).unwrap();
    let entries = audit["entries"].as_array().unwrap();
    assert_eq!(entries.len(), 3, "{audit}");
    assert!(
        entries.iter().any(|e| e["detail"]
            .as_str()
            .is_some_and(|d| d.contains("meas_10min.mat") && d.contains("tof.mat"))),
        "{audit}"
    );
    // `periscope recon` takes the import's run directory as it takes any run's.
    let out = dir.path().join("again-offline");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .arg("recon")
        .arg(dir.path().join(&ids[1]))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "{}",
        String::from_utf8_lossy(&status.stderr)
    );
    assert!(out.join("volume.npy").is_file());
    // Resume and export, which need a capture run's plan and log, say what to do.
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
        .arg("export")
        .arg(dir.path().join(&ids[1]))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&status.stderr);
    assert!(!status.status.success(), "{stderr}");
    assert!(
        stderr.contains("is an imported capture") && stderr.contains("periscope recon"),
        "{stderr}"
    );
    // A run.json edited to name a path out of `import/` (here the run directory
    // itself, which made `periscope recon` open it again some 400 levels deep until
    // 2026-12-07) is refused, naming the file and the field.
    let copy = dir.path().join("edited");
    std::fs::create_dir_all(copy.join("import")).unwrap();
    let text = std::fs::read_to_string(dir.path().join(&ids[1]).join("run.json")).unwrap();
    let mut info: Value = serde_json::from_str(&text).unwrap();
    for bad in ["..", "/etc/passwd", "sub/capture.mat"] {
        info["import"]["capture"] = Value::from(bad);
        std::fs::write(copy.join("run.json"), info.to_string()).unwrap();
        let status = std::process::Command::new(env!("CARGO_BIN_EXE_periscope"))
            .arg("recon")
            .arg(&copy)
            .arg("--out")
            .arg(dir.path().join("edited-out"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&status.stderr);
        assert!(!status.status.success(), "{bad}: {stderr}");
        assert!(
            stderr.contains("not a plain file name") && stderr.contains("run.json"),
            "{bad}: {stderr}"
        );
    }
    svc.shutdown();
    worker.join().unwrap();
}

#[tokio::test]
async fn bad_imports_are_refused_with_their_reason_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), "import-limit-mib = 0.25\n");
    let router = app(AppState::new(Arc::clone(&svc)));
    let lct = std::fs::read(fixture("lct-point.mat")).unwrap();
    let sidecars: Vec<String> = (0..17).map(|i| format!("s{i}.mat")).collect();
    let cases: Vec<(&str, Request<Body>, StatusCode, &str)> = vec![
        (
            "no key",
            upload(
                None,
                Body::from(form(&[Part::File("capture", "a.mat", lct.clone())])),
            ),
            StatusCode::UNAUTHORIZED,
            "unauthorized",
        ),
        (
            "not a form",
            common::request(Method::POST, "/api/v1/imports", Some(TOKEN), &[], "method = 1"),
            StatusCode::BAD_REQUEST,
            "multipart/form-data",
        ),
        (
            // The parser holds a part's headers (and the preamble) in memory until
            // they end: 2 MiB of them is refused, not buffered on to the upload limit.
            "a preamble of 2 MiB",
            upload(
                Some(TOKEN),
                Body::from(
                    [
                        vec![b'x'; 2 << 20],
                        b"\r\n".to_vec(),
                        form(&[Part::File("capture", "a.mat", lct.clone())]),
                    ]
                    .concat(),
                ),
            ),
            StatusCode::BAD_REQUEST,
            "before the next part's headers ended",
        ),
        (
            "a part header of 2 MiB",
            upload(
                Some(TOKEN),
                Body::from(
                    form(&[Part::File("capture", "a.mat", lct.clone())])
                        .splitn(2, |&b| b == b'\n')
                        .enumerate()
                        .flat_map(|(i, piece)| {
                            let mut v = piece.to_vec();
                            if i == 0 {
                                v.extend_from_slice(format!("\nX-Pad: {}\r", "p".repeat(2 << 20)).as_bytes());
                                v.push(b'\n');
                            }
                            v
                        })
                        .collect::<Vec<u8>>(),
                ),
            ),
            StatusCode::BAD_REQUEST,
            "before the next part's headers ended",
        ),
        (
            "an unknown field",
            upload(Some(TOKEN), Body::from(form(&[Part::Text("plan", "x")]))),
            StatusCode::BAD_REQUEST,
            "unknown form field `plan`",
        ),
        (
            "a capture without a file name",
            upload(Some(TOKEN), Body::from(form(&[Part::Text("capture", "x")]))),
            StatusCode::BAD_REQUEST,
            "must be a file",
        ),
        (
            "no capture",
            upload(Some(TOKEN), Body::from(form(&[Part::Text("name", "x")]))),
            StatusCode::UNPROCESSABLE_ENTITY,
            "no `capture` part",
        ),
        (
            "not a capture's name",
            upload(
                Some(TOKEN),
                Body::from(form(&[Part::File("capture", "scene.png", lct.clone())])),
            ),
            StatusCode::UNPROCESSABLE_ENTITY,
            "not a capture file name",
        ),
        (
            "text called .hdf5",
            upload(
                Some(TOKEN),
                Body::from(form(&[Part::File(
                    "capture",
                    "scene.hdf5",
                    b"x,y,z\n1,2,3\n".to_vec(),
                )])),
            ),
            StatusCode::UNPROCESSABLE_ENTITY,
            "neither HDF5 nor a MATLAB file",
        ),
        (
            "bad settings",
            upload(
                Some(TOKEN),
                Body::from(form(&[
                    Part::File("capture", "a.mat", lct.clone()),
                    Part::Text("recon", "method = \"fbq\"\n"),
                ])),
            ),
            StatusCode::UNPROCESSABLE_ENTITY,
            "method",
        ),
        (
            // A volume the daemon could not hold: refused by the instrument's memory
            // budget as a plan is, before the capture is read.
            "a volume past the memory budget",
            upload(
                Some(TOKEN),
                Body::from(form(&[
                    Part::File("capture", "a.mat", lct.clone()),
                    Part::Text(
                        "recon",
                        "method = \"fbp\"\n[volume]\nx = [-1.0, 1.0]\ny = [-1.0, 1.0]\nz = [0.1, 2.0]\nshape = [1024, 1024, 1024]\n",
                    ),
                ])),
            ),
            StatusCode::UNPROCESSABLE_ENTITY,
            "budget.memory-gib",
        ),
        (
            "a path for a name",
            upload(
                Some(TOKEN),
                Body::from(form(&[Part::File("capture", "../../.hidden", lct.clone())])),
            ),
            StatusCode::BAD_REQUEST,
            "plain file name",
        ),
        (
            "the same file twice",
            upload(
                Some(TOKEN),
                Body::from(form(&[
                    Part::File("capture", "a.mat", lct.clone()),
                    Part::File("sidecar", "a.mat", lct.clone()),
                ])),
            ),
            StatusCode::BAD_REQUEST,
            "sent twice",
        ),
        (
            "the settings twice",
            upload(
                Some(TOKEN),
                Body::from(form(&[
                    Part::File("capture", "a.mat", lct.clone()),
                    Part::Text("recon", "method = \"fbp\"\n"),
                    Part::Text("recon", "method = \"fbp\"\n"),
                ])),
            ),
            StatusCode::BAD_REQUEST,
            "`recon` is sent twice",
        ),
        (
            "too many sidecars",
            upload(
                Some(TOKEN),
                Body::from(form(
                    &sidecars
                        .iter()
                        .map(|n| Part::File("sidecar", n, Vec::new()))
                        .collect::<Vec<_>>(),
                )),
            ),
            StatusCode::BAD_REQUEST,
            "more than 16 `sidecar` files",
        ),
        (
            "over the limit",
            upload(
                Some(TOKEN),
                Body::from(form(&[Part::File("capture", "big.mat", vec![0u8; 300 << 10])])),
            ),
            StatusCode::PAYLOAD_TOO_LARGE,
            // A limit under a MiB said as it is, not as 0 MiB.
            "over 256 KiB, the most this daemon takes ([api] import-limit-mib)",
        ),
    ];
    for (what, req, status, says) in cases {
        let (s, bytes) = common::send(&router, req).await;
        let text = String::from_utf8_lossy(&bytes);
        assert_eq!(s, status, "{what}: {text}");
        assert!(text.contains(says), "{what}: {text}");
        // Nothing of a refused upload stays (its staging is removed off the runtime).
        tokio::time::sleep(Duration::from_millis(50)).await;
        assert_eq!(runs_and_staging(dir.path()), (Vec::new(), 0), "{what}");
    }
    // An upload that stops sending is dropped after `import-stall-s`, not held. A
    // daemon of its own: one daemon a runs directory, so the first goes first.
    svc.shutdown();
    drop((router, svc));
    let svc = service(dir.path(), "import-stall-s = 0.3\n");
    let router = app(AppState::new(Arc::clone(&svc)));
    let mut head = form(&[Part::File("capture", "a.mat", lct.clone())]);
    head.truncate(head.len() / 2);
    let stream = tokio_stream::StreamExt::chain(
        tokio_stream::iter([Ok::<_, std::io::Error>(head)]),
        tokio_stream::pending(),
    );
    let t = Instant::now();
    let (s, bytes) = common::send(&router, upload(Some(TOKEN), Body::from_stream(stream))).await;
    assert_eq!(
        s,
        StatusCode::REQUEST_TIMEOUT,
        "{}",
        String::from_utf8_lossy(&bytes)
    );
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(runs_and_staging(dir.path()), (Vec::new(), 0));
    // Nor is one that trickles, a few bytes just inside each stall window: after two
    // windows its average rate is judged (until 2026-12-06 it held the one import slot
    // for as long as it kept trickling; here it would have for 40 s).
    // The part's headers at once, then the file's bytes a few at a time, each
    // arriving well inside the 0.3 s stall window.
    let whole = form(&[Part::File("capture", "a.mat", lct.clone())]);
    let (first, rest) = whole.split_at(whole.len() / 4);
    let pieces: Vec<Vec<u8>> = std::iter::once(first.to_vec())
        .chain(rest.chunks(rest.len().div_ceil(2000)).map(<[u8]>::to_vec))
        .collect();
    let stream = tokio_stream::StreamExt::throttle(
        tokio_stream::iter(pieces.into_iter().map(Ok::<_, std::io::Error>)),
        Duration::from_millis(20),
    );
    let t = Instant::now();
    let (s, bytes) = common::send(&router, upload(Some(TOKEN), Body::from_stream(stream))).await;
    let text = String::from_utf8_lossy(&bytes);
    assert_eq!(s, StatusCode::REQUEST_TIMEOUT, "{text}");
    assert!(
        text.contains("upload-too-slow") && text.contains("KiB/s"),
        "{text}"
    );
    assert!(t.elapsed() < Duration::from_secs(5), "{:?}", t.elapsed());
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert_eq!(runs_and_staging(dir.path()), (Vec::new(), 0));
    // A file whose container is right but whose contents are not a capture is queued,
    // and its run fails with the reader's reason, the upload kept as it came.
    let worker = svc.start_worker();
    let mut cut = std::fs::read(fixture("znlos-point.hdf5")).unwrap();
    cut.truncate(4096);
    let (s, v) = import(&router, &[Part::File("capture", "cut.hdf5", cut.clone())]).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    let failed = wait_until(&router, &id, Duration::from_secs(60), |v| v["state"] == "failed").await;
    let error = failed["error"].as_str().unwrap();
    assert!(
        error.starts_with("imported capture: ") && error.contains("cut.hdf5"),
        "{failed}"
    );
    assert_eq!(
        std::fs::read(dir.path().join(&id).join("import/cut.hdf5")).unwrap(),
        cut
    );
    svc.shutdown();
    worker.join().unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_estop_stops_an_import_and_the_laser_stays_off() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), "status-interval-s = 0.2\n");
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    // A long fit, so the e-stop lands inside it.
    let lct = std::fs::read(fixture("lct-point.mat")).unwrap();
    let (s, v) = import(
        &router,
        &[
            Part::File("capture", "lct-point.mat", lct),
            Part::Text("recon", "method = \"gtr\"\n[gtr]\nepochs = 10000\n"),
        ],
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let id = v["id"].as_str().unwrap().to_owned();
    wait_until(&router, &id, Duration::from_secs(60), |v| {
        v["stage"] == "reconstruction"
    })
    .await;
    // No run holds the devices during an import: the worker still reads them, and
    // the safety state is the idle reading's, fresh.
    tokio::time::sleep(Duration::from_millis(600)).await;
    let (_, bytes) = get(&router, "/api/v1/instrument").await;
    let inst: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(inst["busy"], false, "{inst}");
    assert!(inst["reading"]["age_s"].as_f64().unwrap() < 0.5, "{inst}");
    assert_eq!(svc.safety().source, "idle");
    assert_eq!(svc.safety().emission, Some(false));
    // The import slow to stop (it hangs at its next checkpoint), as one reading a large
    // file is: the e-stop must not wait for it to reach the laser.
    assert!(svc.inject_hang(
        periscope_daemon::events::Stage::Reconstruction,
        Duration::from_secs(3)
    ));
    let t = Instant::now();
    let (s, bytes) = common::send(
        &router,
        common::request(Method::POST, "/api/v1/estop", Some(TOKEN), &[], ""),
    )
    .await;
    let report: Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(
        (s, report["aborted"].as_str()),
        (StatusCode::OK, Some(&*id)),
        "{report}"
    );
    assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    let rig = periscope_daemon::devices::sim::rig_of(svc.backend()).unwrap();
    assert!(
        rig.off_since(t).is_some(),
        "the laser is on after the e-stop: {report}"
    );
    // At once, through the laser controller, as with no run: an import holds no
    // device (its e-stop reached the laser only after waiting up to 2 s for the
    // import to stop, until 2026-12-06).
    assert!(
        report["laser"]
            .as_str()
            .unwrap()
            .contains("opened for the e-stop"),
        "{report}"
    );
    assert!(report["laser_off_s"].as_f64().unwrap() < 0.5, "{report}");
    let v = wait_until(&router, &id, Duration::from_secs(10), |v| v["state"] == "aborted").await;
    assert_eq!(v["error"], Value::Null, "{v}");
    svc.shutdown();
    worker.join().unwrap();
}

/// An import that follows another run reads the instruments at once: the run left no
/// reading (what it left the laser in is unknown until read), and until 2026-12-06 the
/// import's first reading came a whole `status-interval-s` later, so the safety bar
/// read LASER STATE UNKNOWN through an import shorter than that.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_import_after_a_run_reads_the_instrument_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), "status-interval-s = 60\n");
    let worker = svc.start_worker();
    let router = app(AppState::new(Arc::clone(&svc)));
    let lct = std::fs::read(fixture("lct-point.mat")).unwrap();
    let (s, v) = import(
        &router,
        &[
            Part::File("capture", "lct-point.mat", lct.clone()),
            Part::Text("recon", "method = \"fbp\"\n"),
        ],
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let first = v["id"].as_str().unwrap().to_owned();
    let (s, v) = import(
        &router,
        &[
            Part::File("capture", "lct-point.mat", lct),
            Part::Text("recon", "method = \"gtr\"\n[gtr]\nepochs = 10000\n"),
        ],
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let second = v["id"].as_str().unwrap().to_owned();
    wait_until(&router, &first, Duration::from_secs(60), |v| {
        v["state"] == "completed"
    })
    .await;
    wait_until(&router, &second, Duration::from_secs(60), |v| {
        v["stage"] == "reconstruction"
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let (_, bytes) = get(&router, "/api/v1/instrument").await;
    let inst: Value = serde_json::from_slice(&bytes).unwrap();
    assert!(inst["reading"]["age_s"].as_f64().is_some(), "{inst}");
    assert_eq!(svc.safety().emission, Some(false));
    let (s, _) = common::send(
        &router,
        common::request(
            Method::POST,
            &format!("/api/v1/runs/{second}/abort"),
            Some(TOKEN),
            &[],
            "",
        ),
    )
    .await;
    assert_eq!(s, StatusCode::ACCEPTED);
    wait_until(&router, &second, Duration::from_secs(30), |v| {
        v["state"] == "aborted"
    })
    .await;
    svc.shutdown();
    worker.join().unwrap();
}

/// An import that fails as it is asked to abort ends aborted, its error kept, as a
/// capture run does (`safety.rs`): until 2026-12-08 it ended failed and resumable, and
/// the abort, answered as under way, was lost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_import_that_fails_as_it_is_asked_to_abort_ends_aborted() {
    use periscope_daemon::events::{EventSink, Stage};
    use periscope_daemon::pipeline::{Control, PipelineError, execute_import};
    let dir = tempfile::tempdir().unwrap();
    let svc = service(dir.path(), "");
    let router = app(AppState::new(Arc::clone(&svc)));
    let lct = std::fs::read(fixture("lct-point.mat")).unwrap();
    let (s, v) = import(&router, &[Part::File("capture", "lct-point.mat", lct)]).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let run = svc.runs_dir().join(v["id"].as_str().unwrap());
    // No worker: the import runs here, and its first checkpoint panics before it
    // reads the abort, as a failure that comes first does.
    let control = Control::new();
    control.inject_panic(Stage::Reading);
    assert!(control.abort_by("bob"));
    let events = EventSink::open(&run).unwrap();
    let (d, c) = (run.clone(), control.clone());
    let r = tokio::task::spawn_blocking(move || execute_import(&d, c, events))
        .await
        .unwrap();
    assert!(matches!(r, Err(PipelineError::Aborted(_))), "{r:?}");
    common::assert_aborted_keeping_error(&run, &control, "bob", "injected panic");
}

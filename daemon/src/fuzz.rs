//! Entry points for fuzzing every reader of untrusted bytes (`fuzz/`, run by
//! `cargo fuzz`; see docs/fuzzing.md). Each takes arbitrary bytes and checks the
//! reader's contract: an answer or a named error, never a panic, an abort or an
//! allocation beyond the reader's limits. `daemon/tests/fuzz_seeds.rs` replays the
//! committed seeds and every past crash through the same functions on `cargo test`.
use std::io;
use std::time::Duration;

use periscope_drivers::galvo::protocol::{
    Reply, Request, decode_line, encode_line, parse_angles, parse_limits,
};
use periscope_drivers::galvo::{Connector, Link, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::protocol::{
    FrameHeader, WireConfig, WireInfo, WireStatus, decode_frame, decode_header, encode_frame,
};
use periscope_drivers::tdc::{TransportError, UsbTdc, UsbTransport};
use periscope_drivers::{AngleLimits, GalvoPair, Histogrammer, Laser, OpticalAngles, TdcConfig};
use periscope_sim::Mesh;

use crate::budget::{Budget, Limits};
use crate::config::{InstrumentConfig, TomlSource};
use crate::plan::{Plan, load_recon};
use periscope_recon::io::ytal::YtalCapture;

/// A fuzz target: takes any bytes, panics only on a broken contract.
pub type Target = fn(&[u8]);

/// The targets, by name (the names of `fuzz/fuzz_targets/*.rs` and of the corpus
/// folders).
pub const TARGETS: &[(&str, Target)] = &[
    ("ytal_capture", ytal_capture),
    ("histogram_log", histogram_log),
    ("relay_ply", relay_ply),
    ("tdc_frame", tdc_frame),
    ("tdc_receive", tdc_receive),
    ("galvo_line", galvo_line),
    ("galvo_receive", galvo_receive),
    ("plan_toml", plan_toml),
    ("config_toml", config_toml),
    ("mesh", mesh),
    ("capture_file", capture_file),
    ("http_request", http_request),
];

/// Capture files of every public format (files downloaded from papers): told apart by
/// their contents, MAT v5 (bounded inflation, matfile's parse) or HDF5 (MAT v7.3,
/// ZNLOS, y-tal), and the capture each format's reader builds.
pub fn capture_file(data: &[u8]) {
    // Like the y-tal reader: panics inside matfile or hdf5-pure are turned into errors
    // by the readers; the fuzzer's hook lets them through to them.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let fuzzer_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_parser = info
                .location()
                .is_some_and(|l| l.file().contains("matfile") || l.file().contains("hdf5-pure"));
            if !in_parser {
                fuzzer_hook(info);
            }
        }));
    });
    let Ok(c) =
        periscope_recon::io::formats::capture_from_bytes(data.to_vec(), std::path::Path::new("fuzz.mat"))
    else {
        return;
    };
    assert_eq!(c.h.len(), c.h_shape.iter().product::<usize>());
    // Finite and within single precision's sums; not necessarily non-negative: y-tal
    // keeps a background-subtracted `H` as it is (the other formats' counts are
    // checked as counts by their readers).
    assert!(c.h.iter().all(|v| v.is_finite() && v.abs() <= 1e30));
    if let Ok(volume) = c.default_volume() {
        let _ = c.transients(&volume);
    }
}

/// y-tal HDF5 captures (files downloaded from papers): decoding, the default volume
/// and the rebinned transients.
pub fn ytal_capture(data: &[u8]) {
    // The reader turns a panic inside hdf5-pure into an error (see `guarded` in
    // `periscope_recon::io::ytal`); libFuzzer's hook would abort at the panic, before
    // the reader can catch it, so panics located in hdf5-pure are let through to the
    // reader here. Any other panic still aborts.
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let fuzzer_hook = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_hdf5 = info.location().is_some_and(|l| l.file().contains("hdf5-pure"));
            if !in_hdf5 {
                fuzzer_hook(info);
            }
        }));
    });
    let Ok(c) = YtalCapture::from_bytes(data.to_vec(), std::path::Path::new("fuzz.hdf5")) else {
        return;
    };
    assert!(c.bins() > 0 && c.h.len() == c.bins() * c.len());
    if let Ok(volume) = c.default_volume()
        && let Ok(mut set) = c.transients(&volume)
    {
        assert!(set.len() <= c.len());
        // `scene_info` is read for a renderer's name without panicking, and the laser
        // falloff divided out leaves finite counts, or is refused leaving them as
        // they were.
        let _ = c.rendered_by();
        if let Some(laser) = c.laser_xyz {
            let before = set.clone();
            match set.compensate_laser_falloff(laser) {
                Ok((lo, hi)) => {
                    assert!(lo > 0.0 && hi >= lo && hi.is_finite());
                    assert!((0..set.len()).all(|i| set.histogram(i).iter().all(|v| v.is_finite())));
                }
                Err(_) => assert!((0..set.len()).all(|i| set.histogram(i) == before.histogram(i))),
            }
        }
    }
}

/// The histogram log (`histograms.bin`), read back on resume and export: the kept
/// and the discarded bytes add up to the input, the damaged ranges are ordered,
/// disjoint and cover exactly the discarded bytes, and every record kept (whole or a
/// partial sum) has sane settings and a pair of its own.
pub fn histogram_log(data: &[u8]) {
    let got = crate::store::parse_log(data);
    assert_eq!(got.valid_bytes + got.discarded_bytes, data.len() as u64);
    let mut end = 0;
    for r in &got.damaged {
        assert!(r.start >= end && r.end > r.start && r.end <= data.len() as u64);
        end = r.end;
    }
    let damaged: u64 = got.damaged.iter().map(|r| r.end - r.start).sum();
    assert_eq!(damaged, got.discarded_bytes);
    let mut pairs = std::collections::HashSet::new();
    for r in &got.records {
        assert!(!r.counts.is_empty() && r.counts.len() <= 1 << 20 && r.bin_width_ps > 0);
        assert!(!r.partial);
        assert!(pairs.insert(r.pair), "pair {} kept twice", r.pair);
    }
    // A partial sum only for a pair with no whole record, and one a pair.
    for r in &got.partial {
        assert!(!r.counts.is_empty() && r.counts.len() <= 1 << 20 && r.bin_width_ps > 0);
        assert!(r.partial);
        assert!(pairs.insert(r.pair), "pair {} kept twice", r.pair);
    }
}

/// `relay.ply`, read back on resume: only the relay layout with finite points and unit
/// normals is accepted.
pub fn relay_ply(data: &[u8]) {
    if let Ok(points) = crate::pipeline::parse_relay_ply(data) {
        for p in points {
            assert!(p.x.is_finite() && p.intensity.is_finite());
            assert!((p.n.length() - 1.0).abs() < 1e-3);
        }
    }
}

/// The TDC's wire formats: a frame that decodes is exactly what the encoder writes for
/// it; control replies decode or are refused.
pub fn tdc_frame(data: &[u8]) {
    let _ = decode_header(data);
    if let Ok((header, counts, len)) = decode_frame(data) {
        assert!(len <= data.len());
        assert_eq!(counts.len(), header.config.bins as usize);
        assert_eq!(encode_frame(&header, &counts), data[..len]);
    }
    if let Some(c) = WireConfig::decode(data) {
        assert_eq!(WireConfig::decode(&c.encode()), Some(c));
    }
    let _ = WireInfo::decode(data);
    let _ = WireStatus::decode(data);
}

/// A histogrammer that sends the fuzz input on its bulk-in endpoint (in chunks of the
/// size the input's first byte says), optionally followed by the genuine frame for
/// each `START`.
struct FuzzUsb {
    config: Vec<u8>,
    stream: Vec<u8>,
    at: usize,
    chunk: usize,
    genuine: bool,
    /// The sequence number of the last `START`.
    started: Option<u32>,
}

impl UsbTransport for FuzzUsb {
    fn control_in(
        &mut self,
        _r: u8,
        _v: u16,
        _i: u16,
        buf: &mut [u8],
        _t: Duration,
    ) -> Result<usize, TransportError> {
        let n = self.config.len().min(buf.len());
        buf[..n].copy_from_slice(&self.config[..n]);
        Ok(n)
    }
    fn control_out(
        &mut self,
        r: u8,
        v: u16,
        i: u16,
        data: &[u8],
        _t: Duration,
    ) -> Result<(), TransportError> {
        if r == 0x02 {
            self.config = data.to_vec();
        }
        if r == 0x04 {
            let seq = u32::from(v) | (u32::from(i) << 16);
            self.started = Some(seq);
            if self.genuine
                && let Some(wire) = WireConfig::decode(&self.config)
            {
                let header = FrameHeader {
                    sequence: seq,
                    flags: 0,
                    config: WireConfig {
                        sync_divider: 0,
                        ..wire
                    },
                };
                self.stream
                    .extend(encode_frame(&header, &vec![7; wire.bins as usize]));
            }
        }
        Ok(())
    }
    fn bulk_in(&mut self, _ep: u8, buf: &mut [u8], _t: Duration) -> Result<usize, TransportError> {
        if self.at >= self.stream.len() {
            return Err(TransportError::Disconnected("fuzz input exhausted".into()));
        }
        let n = self.chunk.min(buf.len()).min(self.stream.len() - self.at);
        buf[..n].copy_from_slice(&self.stream[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
    fn reopen(&mut self) -> Result<(), TransportError> {
        Err(TransportError::Disconnected("fuzz device gone".into()))
    }
    fn describe(&self) -> String {
        "fuzz".into()
    }
}

/// The TDC driver's receive loop over a device that sends arbitrary bytes: it returns
/// a histogram only for the acquisition it last asked for, with the configured bin
/// count.
pub fn tdc_receive(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let usb = FuzzUsb {
        config: Vec::new(),
        stream: rest.to_vec(),
        at: 0,
        chunk: usize::from(mode >> 1).max(1) * 8,
        genuine: mode & 1 == 1,
        started: None,
    };
    let mut tdc = UsbTdc::with_sequence(usb, Duration::from_millis(1), 0);
    let config = TdcConfig {
        bin_width: 16e-12,
        bins: 8,
        offset: 0.0,
        sync_divider: 1,
        acquisition: Duration::from_micros(100),
    };
    if tdc.configure(&config).is_err() {
        return;
    }
    if let Ok(h) = tdc.acquire() {
        // Only the acquisition last asked for: the first, or its one repeat.
        assert_eq!(Some(h.sequence), tdc.transport_mut().started);
        assert!(h.sequence == 1 || h.sequence == 2);
        assert_eq!(h.counts.len(), 8);
    }
}

/// The galvo controllers' line protocol: a line that decodes is exactly the line the
/// encoder writes for its tag and body; request and reply bodies parse or are refused.
pub fn galvo_line(data: &[u8]) {
    if let Ok((tag, body)) = decode_line(data) {
        let line = data.strip_suffix(b"\r").unwrap_or(data);
        assert_eq!(encode_line(tag, body).trim_end_matches('\n').as_bytes(), line);
    }
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = Request::parse(text);
        let _ = Reply::parse(text);
        let fields: Vec<&str> = text.split_whitespace().collect();
        let _ = parse_angles(&fields);
        let _ = parse_limits(&fields);
    }
}

/// A serial link that delivers the fuzz input (in chunks) and then breaks.
struct FuzzLink {
    data: Vec<u8>,
    at: usize,
    chunk: usize,
}

impl Link for FuzzLink {
    fn send(&mut self, _bytes: &[u8]) -> io::Result<()> {
        Ok(())
    }
    fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> io::Result<usize> {
        if self.at >= self.data.len() {
            return Err(io::Error::new(io::ErrorKind::BrokenPipe, "fuzz input exhausted"));
        }
        let n = self.chunk.min(buf.len()).min(self.data.len() - self.at);
        buf[..n].copy_from_slice(&self.data[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
    fn discard_input(&mut self) -> io::Result<()> {
        Ok(())
    }
}

struct FuzzConnector(Option<FuzzLink>);

impl Connector for FuzzConnector {
    fn connect(&mut self) -> io::Result<Box<dyn Link>> {
        match self.0.take() {
            Some(l) => Ok(Box::new(l)),
            None => Err(io::Error::new(io::ErrorKind::NotFound, "fuzz controller gone")),
        }
    }
    fn describe(&self) -> String {
        "fuzz".into()
    }
}

/// The galvo driver's receive loop over a controller that sends arbitrary bytes:
/// every request ends in an answer or an error.
pub fn galvo_receive(data: &[u8]) {
    let Some((&mode, rest)) = data.split_first() else {
        return;
    };
    let settings = SerialGalvoSettings {
        name: "fuzz".into(),
        limits: AngleLimits {
            x: [-0.3, 0.3],
            y: [-0.3, 0.3],
        },
        timeout: Duration::from_millis(2),
        settle: Duration::from_micros(10),
        watchdog: None,
    };
    let link = FuzzLink {
        data: rest.to_vec(),
        at: 0,
        chunk: usize::from(mode % 64) + 1,
    };
    let mut g = SerialGalvo::new(settings, Box::new(FuzzConnector(Some(link))));
    let _ = g.identify();
    let _ = g.position();
    let _ = g.move_to(OpticalAngles { x: 0.1, y: -0.1 });
    let _ = g.laser_state();
    let _ = g.hard_limits();
}

/// The simulated instrument every plan is checked against.
fn sim_instrument() -> &'static InstrumentConfig {
    static INSTRUMENT: std::sync::LazyLock<InstrumentConfig> = std::sync::LazyLock::new(|| {
        let text = include_str!("../../configs/instrument/sim.toml");
        InstrumentConfig::from_source(&TomlSource::from_text("sim.toml", text))
            .expect("the shipped config is valid")
    });
    &INSTRUMENT
}

/// Capture plans (TOML from operators and over HTTP) and their budget: a plan or an
/// error naming the key, and a budget that never wraps.
pub fn plan_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let src = TomlSource::from_text("fuzz.toml", text);
    let instrument = sim_instrument();
    if let Ok(plan) = Plan::from_source(&src, instrument) {
        let b = Budget::of_plan(&plan, instrument);
        let _ = b.check(&Limits::default());
        assert!(b.memory_bytes() >= b.memory.iter().map(|i| i.bytes).max().unwrap_or(0));
        // What `periscope check` and `POST /check` make of it: the durations, the
        // galvo limits and the TDC window, for any plan an observer may send.
        let c = crate::check::check(&plan, instrument);
        assert!(
            c.duration_s.total.is_finite() && c.duration_s.total >= 0.0,
            "{:?}",
            c.duration_s
        );
        assert!(c.report.contains("TDC window:"), "{}", c.report);
    }
}

/// Instrument configs and RECON.toml files: a config or an error naming the key; a
/// config that loads has a summary, and its text with the token cut out (what a run
/// stores and serves as `instrument.toml`) loads as the same instrument without it.
pub fn config_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let src = TomlSource::from_text("fuzz.toml", text);
    if let Ok(config) = InstrumentConfig::from_source(&src) {
        let _ = config.summary();
        // What a run stores and serves as its `instrument.toml`: the same instrument,
        // without its token.
        let redacted = crate::config::redact_secrets(text);
        let again = InstrumentConfig::from_source(&TomlSource::from_text("fuzz.toml", redacted.as_str()));
        let mut expected = config;
        expected.api.token = None;
        match again {
            Ok(again) => assert!(
                again == expected,
                "the redacted config is another instrument:\n{redacted}"
            ),
            Err(e) => panic!("the redacted config does not load ({e}):\n{redacted}"),
        }
    }
    let _ = load_recon(&src, None);
}

/// Scene meshes (PLY, ASCII or binary, and OBJ; the first byte picks): a mesh that
/// loads has faces whose indices are in range and finite vertices.
pub fn mesh(data: &[u8]) {
    let Some((&kind, rest)) = data.split_first() else {
        return;
    };
    let mesh = if kind & 1 == 0 {
        Mesh::from_ply_bytes(rest)
    } else {
        Mesh::from_obj_bytes(rest)
    };
    if let Ok(m) = mesh {
        assert!(!m.triangles.is_empty());
        assert!(
            m.triangles
                .iter()
                .flatten()
                .all(|&i| (i as usize) < m.vertices.len())
        );
        assert!(m.vertices.iter().all(|v| v.is_finite()));
    }
}

/// What [`http_request`] sends its requests to: the API's router over the simulated
/// instrument, its runs in a directory of its own holding one finished run, and the
/// secret of an observer's key.
struct HttpTarget {
    runtime: tokio::runtime::Runtime,
    router: axum::Router,
    run: String,
    observer: String,
}

/// The router [`http_request`] fuzzes, made once a process: the shipped simulated
/// instrument at time-scale 0 with its runs in a fresh directory under the system's
/// temporary one, a finished run of the tests' small plan (so that the run's routes
/// and files answer), and an observer's key. The fuzzer never holds the admin token,
/// so no input can start or delete a run.
fn http_target() -> &'static HttpTarget {
    use axum::http::{Method, header};
    use tower::ServiceExt as _;
    static TARGET: std::sync::OnceLock<HttpTarget> = std::sync::OnceLock::new();
    TARGET.get_or_init(|| {
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        // Each fuzzing process's own runs, and those of earlier ones that have ended.
        let prefix = "periscope-fuzz-http-";
        for entry in std::fs::read_dir(std::env::temp_dir())
            .into_iter()
            .flatten()
            .flatten()
        {
            let name = entry.file_name();
            if let Some(pid) = name.to_str().and_then(|n| n.strip_prefix(prefix))
                && !std::path::Path::new("/proc").join(pid).exists()
            {
                let _ = std::fs::remove_dir_all(entry.path());
            }
        }
        let runs = std::env::temp_dir().join(format!("{prefix}{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&runs);
        // Made here, not found: one another user made first (the name is predictable)
        // fails the setup instead of holding the runs.
        {
            use std::os::unix::fs::DirBuilderExt as _;
            std::fs::DirBuilder::new()
                .mode(0o700)
                .create(&runs)
                .unwrap_or_else(|e| panic!("{}: {e}", runs.display()));
        }
        let path = root.join("configs/instrument/sim.toml");
        let token = "fuzz-admin-token-0123456789abcdef";
        let text = std::fs::read_to_string(&path)
            .expect("configs/instrument/sim.toml")
            .replace("[sim]\n", "[sim]\ntime-scale = 0.0\n")
            + &format!(
                "\n[api]\nruns-dir = \"{}\"\ntoken = \"{token}\"\nbody-limit-kib = 64\n",
                runs.display()
            );
        let service =
            crate::service::Service::open(TomlSource::from_text(path, text), Some(token.to_owned()))
                .expect("the simulated instrument's service");
        // Detached: the worker runs the one run, then waits for runs no input can submit.
        drop(service.start_worker());
        let (_, observer) = crate::access::KeyStore::open(&runs, None)
            .create("fuzz", crate::access::Role::Observer, None, "fuzz")
            .expect("an observer's key");
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("a tokio runtime");
        let router = crate::api::app(crate::api::AppState::new(service));
        let plan =
            std::fs::read_to_string(root.join("tests/data/plans/small-fbp.toml")).expect("the small plan");
        let run = runtime.block_on(async {
            let call = |method: Method, uri: String, body: String| {
                let req = axum::http::Request::builder()
                    .method(method)
                    .uri(uri)
                    .header(header::AUTHORIZATION, format!("Bearer {token}"))
                    .header(header::CONTENT_TYPE, "application/toml")
                    .body(axum::body::Body::from(body))
                    .expect("a request");
                let router = router.clone();
                async move {
                    let resp = router.oneshot(req).await.expect("the router answers");
                    let bytes = axum::body::to_bytes(resp.into_body(), 1 << 20)
                        .await
                        .expect("a body");
                    serde_json::from_slice::<serde_json::Value>(&bytes).expect("JSON")
                }
            };
            // The dashboard's compressed files are made at their first request (seconds
            // in an unoptimised build): made here, not in a timed input.
            let page = axum::http::Request::builder()
                .uri("/")
                .body(axum::body::Body::empty())
                .expect("a request");
            let _ = router.clone().oneshot(page).await;
            let submitted = call(Method::POST, "/api/v1/runs".into(), plan).await;
            let id = submitted["id"].as_str().expect("a run id").to_owned();
            let started = std::time::Instant::now();
            loop {
                let v = call(Method::GET, format!("/api/v1/runs/{id}"), String::new()).await;
                if v["state"] == "completed" {
                    break id;
                }
                assert!(
                    v["state"] != "failed" && started.elapsed() < Duration::from_secs(120),
                    "the fuzz target's run did not complete: {v}"
                );
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        });
        HttpTarget {
            runtime,
            router,
            run,
            observer,
        }
    })
}

/// Makes [`http_request`]'s router and its finished run (seconds in an unoptimised
/// build): the fuzz target calls it at libFuzzer's initialisation, so the first input
/// is not timed with it; [`http_request`] makes them itself where it was not called.
pub fn http_request_init() {
    http_target();
}

/// The HTTP API through its router, as `daemon/tests/api.rs` drives it (no socket):
/// any method, path, query, headers and body, from this machine or another, with no
/// key or an observer's, is answered within the request timeout, never with a 500
/// (the API's `storage` and `internal` errors, which no request should cause on a
/// healthy disk; a panic anywhere aborts under libFuzzer, and where the seeds are
/// replayed by `cargo test`, one in a handler on the blocking pool comes back as a
/// 500), and every error as the API's JSON (`{"error": code, "message": ...}`).
///
/// Inputs share the service: an e-stop (any key, or none from this machine, may send
/// one) latches, and each adds to the audit trail that later reads list, so an input's
/// coverage can depend on those before it; none can start, change or delete a run.
///
/// The input: a first byte (bits 0–2 the method of GET, POST, PUT, PATCH, DELETE,
/// HEAD, OPTIONS and PURGE; bit 3 the observer's key as a bearer token; bit 4 a peer on
/// another machine), then the request target up to the first newline (`{run}` stands
/// for the finished run's id), header lines `name: value` up to an empty line, and the
/// body.
pub fn http_request(data: &[u8]) {
    use axum::http::{HeaderName, HeaderValue, Method, Request, StatusCode, header};
    use tower::ServiceExt as _;
    let Some((&flags, rest)) = data.split_first() else {
        return;
    };
    let target = http_target();
    let method = [
        Method::GET,
        Method::POST,
        Method::PUT,
        Method::PATCH,
        Method::DELETE,
        Method::HEAD,
        Method::OPTIONS,
        Method::from_bytes(b"PURGE").expect("a method"),
    ][usize::from(flags & 7)]
    .clone();
    let (line, rest) = match rest.iter().position(|&b| b == b'\n') {
        Some(i) => (&rest[..i], &rest[i + 1..]),
        None => (rest, &[][..]),
    };
    let Ok(uri) = std::str::from_utf8(line) else {
        return;
    };
    let uri = uri.replace("{run}", &target.run);
    let mut req = Request::builder().method(method.clone()).uri(uri.as_str());
    let mut body = rest;
    loop {
        let (line, after) = match body.iter().position(|&b| b == b'\n') {
            Some(i) => (&body[..i], &body[i + 1..]),
            None => (body, &[][..]),
        };
        body = after;
        if line.is_empty() {
            break;
        }
        let Some(colon) = line.iter().position(|&b| b == b':') else {
            return;
        };
        let (Ok(name), Ok(value)) = (
            HeaderName::from_bytes(&line[..colon]),
            HeaderValue::from_bytes(line[colon + 1..].trim_ascii()),
        ) else {
            return;
        };
        req = req.header(name, value);
    }
    if flags & 8 != 0 {
        req = req.header(header::AUTHORIZATION, format!("Bearer {}", target.observer));
    }
    let Ok(mut req) = req.body(axum::body::Body::from(body.to_vec())) else {
        return;
    };
    if flags & 16 != 0 {
        req.extensions_mut()
            .insert(axum::extract::ConnectInfo(std::net::SocketAddr::from((
                [192, 0, 2, 7],
                40_000,
            ))));
    }
    target.runtime.block_on(async {
        // The request timeout (30 s) answers a request that hangs; past it, the router
        // itself hangs. One deadline for the answer and its body, under .ci/fuzz's 60 s.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(40);
        let resp = tokio::time::timeout_at(deadline, target.router.clone().oneshot(req))
            .await
            .unwrap_or_else(|_| panic!("{method} {uri}: no answer within 40 s"))
            .expect("the router is infallible");
        let status = resp.status();
        let encoded = resp.headers().contains_key(header::CONTENT_ENCODING);
        let streamed = resp
            .headers()
            .get(header::CONTENT_TYPE)
            .is_some_and(|t| t.as_bytes().starts_with(b"text/event-stream"));
        if streamed {
            return;
        }
        let bytes = tokio::time::timeout_at(deadline, axum::body::to_bytes(resp.into_body(), 256 << 20))
            .await
            .unwrap_or_else(|_| {
                panic!("{method} {uri}: {status}, its body unfinished 40 s after the request")
            });
        let text = |b: &[u8]| String::from_utf8_lossy(&b[..b.len().min(500)]).into_owned();
        let bytes = match bytes {
            Ok(b) => b,
            Err(e) => panic!("{method} {uri}: {status}, its body failed: {e}"),
        };
        assert_ne!(
            status,
            StatusCode::INTERNAL_SERVER_ERROR,
            "{method} {uri}: {}",
            text(&bytes)
        );
        if (status.is_client_error() || status.is_server_error()) && method != Method::HEAD && !encoded {
            let v: serde_json::Value = serde_json::from_slice(&bytes).unwrap_or_else(|e| {
                panic!(
                    "{method} {uri}: {status} with a body that is not JSON ({e}): {}",
                    text(&bytes)
                )
            });
            assert!(
                v["error"].is_string() && v["message"].is_string(),
                "{method} {uri}: {status} without the API's error fields: {v}"
            );
        }
    });
}

//! The operator's dashboard: a single page served at `/`, its script and styles under
//! `/ui/`, all embedded in the binary (no Node toolchain at build or install time). The
//! page talks to the same JSON API as any client, with the same token and Host rules;
//! see `docs/dashboard.md`.
use super::PathParams;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::ApiError;

/// The embedded files: (path under `/ui/`, media type, contents). uPlot is vendored as
/// released (`ui/vendor/`, MIT licence beside it).
pub const ASSETS: &[(&str, &str, &str)] = &[
    (
        "app.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/app.js"),
    ),
    (
        "view3d.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/view3d.js"),
    ),
    (
        "safety.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/safety.js"),
    ),
    (
        "sse.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/sse.js"),
    ),
    // Started by app.js, not named in index.html: parses volume.npy and draws its
    // projections off the page's thread.
    (
        "volume-worker.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/volume-worker.js"),
    ),
    (
        "style.css",
        "text/css; charset=utf-8",
        include_str!("../../ui/style.css"),
    ),
    (
        "vendor/uPlot.iife.min.js",
        "text/javascript; charset=utf-8",
        include_str!("../../ui/vendor/uPlot.iife.min.js"),
    ),
    (
        "vendor/uPlot.min.css",
        "text/css; charset=utf-8",
        include_str!("../../ui/vendor/uPlot.min.css"),
    ),
    (
        "vendor/uPlot.LICENSE",
        "text/plain; charset=utf-8",
        include_str!("../../ui/vendor/uPlot.LICENSE"),
    ),
    ("favicon.svg", "image/svg+xml", FAVICON),
    (
        "plans/demo.toml",
        "application/toml; charset=utf-8",
        include_str!("../../../configs/plans/demo.toml"),
    ),
];

const INDEX: &str = include_str!("../../ui/index.html");

/// The page's policy: its own scripts only, images from blobs it made, no framing.
const CSP: &str = "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; \
                   img-src 'self' blob: data:; connect-src 'self'; frame-ancestors 'none'; \
                   base-uri 'none'; form-action 'none'";

/// Whether `path` is one of the dashboard's static files (served without a token).
pub(super) fn is_static(path: &str) -> bool {
    path == "/" || path == "/favicon.ico" || path.starts_with("/ui/")
}

/// The page's icon: a periscope's mirror and beam, as SVG (browsers take SVG from
/// `/favicon.ico` too).
const FAVICON: &str = include_str!("../../ui/favicon.svg");

/// An embedded file in each encoding a browser may ask for, compressed once per
/// process (tower-http's compression layer passes a response that has its
/// `Content-Encoding` through): a page load costs the daemon a copy, not a compression
/// of 135 KB, and a flood of them no more CPU than the copies.
struct Encoded {
    identity: axum::body::Bytes,
    gzip: axum::body::Bytes,
    br: axum::body::Bytes,
    /// A digest of the file's bytes: its strong validator, with a suffix per encoding
    /// (each encoding is a representation of its own, RFC 9110 §8.8.3).
    tag: String,
}

impl Encoded {
    fn new(body: &'static str) -> Encoded {
        use sha2::Digest as _;
        use std::io::Write as _;
        let d = sha2::Sha256::digest(body.as_bytes());
        let hex: String = d.iter().take(12).map(|b| format!("{b:02x}")).collect();
        let mut gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
        let gzip = gz
            .write_all(body.as_bytes())
            .and_then(|()| gz.finish())
            .expect("compressing into memory does not fail");
        let mut br = Vec::new();
        {
            // Quality 11 (the most), a 4 MiB window: 135 KB take about a tenth of a
            // second once.
            let mut w = brotli::CompressorWriter::new(&mut br, 4096, 11, 22);
            w.write_all(body.as_bytes())
                .expect("compressing into memory does not fail");
        }
        Encoded {
            identity: axum::body::Bytes::from_static(body.as_bytes()),
            gzip: gzip.into(),
            br: br.into(),
            tag: hex,
        }
    }
}

/// Every embedded file, encoded, by its contents' address.
static ENCODED: std::sync::LazyLock<std::collections::HashMap<usize, Encoded>> =
    std::sync::LazyLock::new(|| {
        ASSETS
            .iter()
            .map(|(_, _, body)| *body)
            .chain([INDEX, FAVICON])
            .map(|body| (body.as_ptr() as usize, Encoded::new(body)))
            .collect()
    });

/// Compresses the embedded files now (the daemon does so before it serves), instead
/// of on the first request.
pub(super) fn prepare() {
    std::sync::LazyLock::force(&ENCODED);
}

/// The encoding to send for `accept` (an `Accept-Encoding` value): brotli, else gzip,
/// where the client takes it (a `q` of 0 refuses), else none.
fn choose(accept: Option<&HeaderValue>) -> Option<&'static str> {
    let accept = accept.and_then(|v| v.to_str().ok())?;
    let takes = |coding: &str| {
        accept.split(',').any(|item| {
            let mut parts = item.split(';');
            let name = parts.next().unwrap_or("").trim();
            let q = parts
                .filter_map(|p| p.trim().strip_prefix("q="))
                .find_map(|q| q.trim().parse::<f32>().ok())
                .unwrap_or(1.0);
            name.eq_ignore_ascii_case(coding) && q > 0.0
        })
    };
    ["br", "gzip"].into_iter().find(|c| takes(c))
}

fn page(media: &'static str, body: &'static str, headers: &HeaderMap) -> Response {
    let encoded = ENCODED.get(&(body.as_ptr() as usize));
    let encoding = encoded.and(choose(headers.get(header::ACCEPT_ENCODING)));
    let (bytes, tag) = match (encoded, encoding) {
        (Some(e), Some("br")) => (e.br.clone(), format!("\"{}-br\"", e.tag)),
        (Some(e), Some(_)) => (e.gzip.clone(), format!("\"{}-gz\"", e.tag)),
        (Some(e), None) => (e.identity.clone(), format!("\"{}\"", e.tag)),
        (None, _) => (axum::body::Bytes::from_static(body.as_bytes()), String::new()),
    };
    // `no-cache` with a validator: the browser asks each time and gets a 304 (no body)
    // while the file is unchanged.
    let unchanged = !tag.is_empty()
        && headers
            .get(header::IF_NONE_MATCH)
            .and_then(|v| v.to_str().ok())
            .is_some_and(|v| v.split(',').any(|t| t.trim() == tag || t.trim() == "*"));
    let mut r = if unchanged {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, media)], bytes).into_response()
    };
    let h = r.headers_mut();
    if let Some(coding) = encoding
        && !unchanged
    {
        h.insert(header::CONTENT_ENCODING, HeaderValue::from_static(coding));
    }
    h.insert(header::VARY, HeaderValue::from_static("accept-encoding"));
    if let Ok(v) = HeaderValue::from_str(&tag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(header::CONTENT_SECURITY_POLICY, HeaderValue::from_static(CSP));
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    r
}

/// `GET /`: the dashboard.
pub(super) async fn index(headers: HeaderMap) -> Response {
    page("text/html; charset=utf-8", INDEX, &headers)
}

/// `GET /favicon.ico`: the page's icon.
pub(super) async fn favicon(headers: HeaderMap) -> Response {
    page("image/svg+xml", FAVICON, &headers)
}

/// `GET /ui/{file}`: one of [`ASSETS`].
pub(super) async fn asset(
    PathParams(file): PathParams<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    ASSETS
        .iter()
        .find(|(name, _, _)| *name == file)
        .map(|(_, media, body)| page(media, body, &headers))
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                "not-found",
                format!("the dashboard has no file `{file}`; open / for the dashboard"),
            )
        })
}

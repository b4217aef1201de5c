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

/// A strong validator of an embedded file: a digest of its bytes, so it changes with
/// every build that changes the file and never otherwise.
fn etag(body: &str) -> String {
    use sha2::Digest as _;
    let d = sha2::Sha256::digest(body.as_bytes());
    let hex: String = d.iter().take(12).map(|b| format!("{b:02x}")).collect();
    format!("\"{hex}\"")
}

fn page(media: &'static str, body: &'static str, if_none_match: Option<&HeaderValue>) -> Response {
    let tag = etag(body);
    // `no-cache` with a validator: the browser asks each time and gets a 304 (no body)
    // while the file is unchanged.
    let unchanged = if_none_match
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.split(',').any(|t| t.trim() == tag || t.trim() == "*"));
    let mut r = if unchanged {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, media)], body).into_response()
    };
    let h = r.headers_mut();
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
    page(
        "text/html; charset=utf-8",
        INDEX,
        headers.get(header::IF_NONE_MATCH),
    )
}

/// `GET /favicon.ico`: the page's icon.
pub(super) async fn favicon(headers: HeaderMap) -> Response {
    page("image/svg+xml", FAVICON, headers.get(header::IF_NONE_MATCH))
}

/// `GET /ui/{file}`: one of [`ASSETS`].
pub(super) async fn asset(
    PathParams(file): PathParams<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    ASSETS
        .iter()
        .find(|(name, _, _)| *name == file)
        .map(|(_, media, body)| page(media, body, headers.get(header::IF_NONE_MATCH)))
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                "not-found",
                format!("the dashboard has no file `{file}`; open / for the dashboard"),
            )
        })
}

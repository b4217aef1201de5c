//! The HTTP API for lab operators (`periscope serve`): JSON under `/api/v1`, a bearer
//! token on every mutating endpoint, server-sent events for progress. The contract is
//! in `docs/api.md` and served as OpenAPI at `/api/v1/openapi.json`.
//!
//! Handlers never block the runtime: run-directory reads and device access go through
//! `spawn_blocking`, and runs execute on the service's worker thread.
use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::body::Body;
use axum::extract::rejection::StringRejection;
use axum::extract::{ConnectInfo, DefaultBodyLimit, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;

mod dashboard;
mod openapi;
mod service;

pub use dashboard::ASSETS;

use crate::run_dir::file;
pub use openapi::openapi;
pub use service::{
    EstopReport, GEOMETRY_POINTS, QUEUE_FILE, RunStatus, Service, ServiceError, StreamEvent, state_name,
};

/// Files a run offers for download, with their media types.
pub const DOWNLOADS: &[(&str, &str)] = &[
    (file::VOLUME, "application/octet-stream"),
    (file::VOLUME_JSON, "application/json"),
    (file::DEPTH, "application/octet-stream"),
    (file::DEPTH_PNG, "image/png"),
    (file::ALBEDO_PNG, "image/png"),
    (file::RELAY, "application/octet-stream"),
    (file::GAUSSIANS, "application/octet-stream"),
    (file::CAPTURE, "application/x-hdf5"),
    (file::PAIRS, "application/json"),
    (file::EVENTS, "application/x-ndjson"),
    (file::PLAN, "application/toml"),
    (file::INSTRUMENT, "application/toml"),
    (file::RUN, "application/json"),
];

/// The routes, as (method, path): the router and the OpenAPI document are both checked
/// against this list by the tests.
pub const ROUTES: &[(&str, &str)] = &[
    ("GET", "/api/v1/health"),
    ("GET", "/api/v1/openapi.json"),
    ("GET", "/api/v1/instrument"),
    ("POST", "/api/v1/check"),
    ("POST", "/api/v1/runs"),
    ("GET", "/api/v1/runs"),
    ("GET", "/api/v1/runs/{id}"),
    ("POST", "/api/v1/runs/{id}/pause"),
    ("POST", "/api/v1/runs/{id}/resume"),
    ("POST", "/api/v1/runs/{id}/abort"),
    ("POST", "/api/v1/estop"),
    ("GET", "/api/v1/runs/{id}/events"),
    ("GET", "/api/v1/runs/{id}/files/{name}"),
    ("GET", "/api/v1/runs/{id}/geometry"),
];

/// Shared state of the handlers.
#[derive(Clone)]
pub struct AppState {
    service: Arc<Service>,
    /// Event-stream clients connected now.
    streams: Arc<std::sync::atomic::AtomicUsize>,
    /// Downloads in flight (a permit per download, held until its body is sent).
    downloads: Arc<tokio::sync::Semaphore>,
}

impl AppState {
    /// State over a service.
    pub fn new(service: Arc<Service>) -> AppState {
        let downloads = Arc::new(tokio::sync::Semaphore::new(
            service.instrument().api.max_downloads,
        ));
        AppState {
            service,
            streams: Arc::default(),
            downloads,
        }
    }
}

/// Holds one of the capped slots (an event stream) until dropped.
struct Slot(Arc<std::sync::atomic::AtomicUsize>);

impl Slot {
    /// Takes a slot if fewer than `max` are taken.
    fn take(count: &Arc<std::sync::atomic::AtomicUsize>, max: usize) -> Option<Slot> {
        use std::sync::atomic::Ordering;
        count
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                (n < max).then_some(n + 1)
            })
            .ok()
            .map(|_| Slot(Arc::clone(count)))
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
    }
}

/// A JSON error: `{"error": code, "message": text}` with its status.
#[derive(Debug)]
pub struct ApiError {
    status: StatusCode,
    code: &'static str,
    message: String,
}

impl ApiError {
    fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> ApiError {
        ApiError {
            status,
            code,
            message: message.into(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let body = serde_json::json!({ "error": self.code, "message": self.message });
        let mut r = (self.status, axum::Json(body)).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
    }
}

impl From<ServiceError> for ApiError {
    fn from(e: ServiceError) -> ApiError {
        let (status, code) = match &e {
            ServiceError::UnknownRun(_) => (StatusCode::NOT_FOUND, "unknown-run"),
            ServiceError::Conflict(_) => (StatusCode::CONFLICT, "conflict"),
            ServiceError::InvalidPlan(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid-plan"),
            ServiceError::Storage { .. }
            | ServiceError::QueueFile { .. }
            | ServiceError::RunFiles(_)
            | ServiceError::Export { .. } => (StatusCode::INTERNAL_SERVER_ERROR, "storage"),
            ServiceError::Prepare(p) => prepare_status(p),
            ServiceError::Config(_) => (StatusCode::INTERNAL_SERVER_ERROR, "config"),
            ServiceError::QueueFull(_) => (StatusCode::TOO_MANY_REQUESTS, "queue-full"),
            ServiceError::OverBudget(_) => (StatusCode::UNPROCESSABLE_ENTITY, "over-budget"),
        };
        ApiError::new(status, code, e.to_string())
    }
}

/// The status of a failure to prepare a submitted run, by the pipeline's error kind:
/// the plan's fault is 422, the instrument's 503, the daemon's storage 500.
fn prepare_status(e: &crate::pipeline::PipelineError) -> (StatusCode, &'static str) {
    use crate::pipeline::PipelineError as P;
    match e {
        P::Config(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid-plan"),
        P::Open(_) | P::Galvo(_) | P::Tdc(_) => (StatusCode::SERVICE_UNAVAILABLE, "device"),
        P::Storage { .. } | P::Export { .. } => (StatusCode::INTERNAL_SERVER_ERROR, "storage"),
        _ => (StatusCode::INTERNAL_SERVER_ERROR, "internal"),
    }
}

type ApiResult<T> = Result<T, ApiError>;

/// Runs `f` on the blocking pool.
async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ServiceError> + Send + 'static,
) -> ApiResult<T> {
    match tokio::task::spawn_blocking(f).await {
        Ok(r) => r.map_err(ApiError::from),
        Err(e) => Err(ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            format!("the request's worker failed: {e}"),
        )),
    }
}

/// The API's router over `state`, with authentication, body limit, timeout and JSON
/// errors for unknown routes and methods.
pub fn app(state: AppState) -> Router {
    let api = state.service.instrument().api.clone();
    let routes = Router::new()
        .route("/api/v1/health", get(health))
        .route("/api/v1/openapi.json", get(openapi_doc))
        .route("/api/v1/instrument", get(instrument))
        .route("/api/v1/check", post(check))
        .route("/api/v1/runs", post(submit).get(list))
        .route("/api/v1/runs/{id}", get(run_status))
        .route("/api/v1/runs/{id}/pause", post(pause))
        .route("/api/v1/runs/{id}/resume", post(resume))
        .route("/api/v1/runs/{id}/abort", post(abort))
        .route("/api/v1/estop", post(estop))
        .route("/api/v1/runs/{id}/events", get(events))
        .route("/api/v1/runs/{id}/files/{name}", get(file))
        .route("/api/v1/runs/{id}/geometry", get(geometry))
        .route("/", get(dashboard::index))
        .route("/ui/{*file}", get(dashboard::asset))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed);
    routes
        .layer(middleware::from_fn_with_state(state.clone(), authorise))
        .layer(middleware::from_fn_with_state(state.clone(), check_host))
        .layer(DefaultBodyLimit::max(api.body_limit))
        .layer(tower_http::timeout::TimeoutLayer::with_status_code(
            StatusCode::REQUEST_TIMEOUT,
            api.request_timeout,
        ))
        .with_state(state)
}

/// What a stop signal does to `serve`.
struct ServeSignals {
    service: Arc<Service>,
    notify: Arc<tokio::sync::Notify>,
}

impl crate::signals::OnSignal for ServeSignals {
    fn laser_off(&self) {
        self.service.laser_off_now();
    }
    fn stop(&self, _signal: &'static str) {
        // Laser off (again), run paused, event streams ended, worker told to stop;
        // then the server stops accepting and drains.
        self.service.shutdown();
        self.notify.notify_one();
    }
}

/// Serves the API on `bind` until SIGINT, SIGTERM or SIGHUP: the running run's laser
/// goes off at once, the run pauses at its next checkpoint (resume it after the
/// restart), event streams end, and the process exits within 2 s (a second signal
/// exits at once).
pub async fn serve(bind: SocketAddr, service: Arc<Service>) -> Result<(), ServeError> {
    let worker = service.start_worker();
    let listener = tokio::net::TcpListener::bind(bind)
        .await
        .map_err(|source| ServeError::Bind { bind, source })?;
    let addr = listener.local_addr().map_err(ServeError::Io)?;
    crate::logging::notice(&format!(
        "periscope dashboard on http://{addr}/, API on http://{addr}/api/v1 (runs in {})",
        service.runs_dir().display()
    ));
    let app = app(AppState::new(Arc::clone(&service)));
    let notify = Arc::new(tokio::sync::Notify::new());
    crate::signals::install(
        Arc::new(ServeSignals {
            service: Arc::clone(&service),
            notify: Arc::clone(&notify),
        }),
        crate::cli::SIGNAL_GRACE,
    );
    axum::serve(listener, app.into_make_service_with_connect_info::<SocketAddr>())
        .with_graceful_shutdown(async move { notify.notified().await })
        .await
        .map_err(ServeError::Io)?;
    service.shutdown();
    match tokio::task::spawn_blocking(move || worker.join()).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) | Err(_) => Err(ServeError::WorkerPanicked),
    }
}

/// Why `periscope serve` stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    /// The address cannot be listened on.
    #[error("cannot listen on {bind}: {source}; choose another address with --bind")]
    Bind {
        /// The address asked for.
        bind: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// The listening socket failed.
    #[error("the API socket failed: {0}")]
    Io(std::io::Error),
    /// The instrument worker thread panicked.
    #[error("the instrument worker panicked")]
    WorkerPanicked,
}

/// Whether a request may change the instrument: every method but GET and HEAD, except
/// `POST /api/v1/check`, which only reads its body.
fn is_mutating(req: &Request) -> bool {
    req.method() != axum::http::Method::GET
        && req.method() != axum::http::Method::HEAD
        && req.uri().path() != "/api/v1/check"
}

/// Bearer token on mutating requests; on read-only ones too for clients not on
/// loopback unless `[api] open-reads` is set. Requests built in-process (router tests)
/// carry no peer address and count as loopback.
async fn authorise(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let peer = req.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0);
    let local = peer.is_none_or(|p| p.ip().is_loopback());
    // The dashboard's own files hold no instrument data: a browser loads them without a
    // token (it cannot send one for a page load) and the page asks for the token.
    let static_file = !is_mutating(&req) && dashboard::is_static(req.uri().path());
    let needs_token =
        is_mutating(&req) || (!local && !static_file && !state.service.instrument().api.open_reads);
    if needs_token && let Err(e) = check_token(state.service.token(), req.headers()) {
        return e.into_response();
    }
    next.run(req).await
}

/// Refuses requests whose `Host` names this machine by a name nobody configured, and
/// mutating requests whose `Origin` is another site. A DNS-rebinding page reaches the
/// daemon under the attacker's host name, and a cross-site form posts with its own
/// origin: both stop here. IP literals and `localhost` are always accepted (a page
/// cannot make a browser send them for its own origin); further names come from
/// `[api] hosts`. Clients that send no `Origin` (curl, scripts) are not affected.
async fn check_host(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let hosts = &state.service.instrument().api.hosts;
    let host = req
        .headers()
        .get(header::HOST)
        .map(|h| h.to_str().unwrap_or("\u{fffd}"));
    if let Some(h) = host
        && !host_allowed(h, hosts)
    {
        return ApiError::new(
            StatusCode::FORBIDDEN,
            "host-not-allowed",
            format!(
                "this daemon does not answer to the host name `{h}`: reach it by IP address or \
                 localhost, or add the name to [api] hosts in the instrument config"
            ),
        )
        .into_response();
    }
    if is_mutating(&req)
        && let Some(origin) = req.headers().get(header::ORIGIN)
    {
        let origin = origin.to_str().unwrap_or("\u{fffd}");
        let authority = origin
            .strip_prefix("http://")
            .or_else(|| origin.strip_prefix("https://"))
            .unwrap_or("");
        let same = host.is_some_and(|h| h.eq_ignore_ascii_case(authority));
        if !same || !host_allowed(authority, hosts) {
            return ApiError::new(
                StatusCode::FORBIDDEN,
                "origin-not-allowed",
                format!(
                    "a page from `{origin}` may not change this instrument: send mutating requests \
                     from the daemon's own pages or from a client that sends no Origin"
                ),
            )
            .into_response();
        }
    }
    next.run(req).await
}

/// Whether `host` (a `Host` header or an origin's authority, with or without port) is
/// an IP literal, `localhost`, or one of `names`.
pub fn host_allowed(host: &str, names: &[String]) -> bool {
    let name = if let Some(rest) = host.strip_prefix('[') {
        // [v6]:port
        return rest
            .split(']')
            .next()
            .is_some_and(|a| a.parse::<std::net::Ipv6Addr>().is_ok());
    } else {
        match host.rsplit_once(':') {
            Some((n, port)) if port.chars().all(|c| c.is_ascii_digit()) && !port.is_empty() => n,
            Some(_) => return false,
            None => host,
        }
    };
    let name = name.trim_end_matches('.').to_ascii_lowercase();
    !name.is_empty()
        && (name.parse::<std::net::Ipv4Addr>().is_ok()
            || name == "localhost"
            || names.iter().any(|n| n.trim_end_matches('.') == name))
}

fn check_token(expected: Option<&str>, headers: &HeaderMap) -> Result<(), ApiError> {
    let Some(expected) = expected else {
        return Err(ApiError::new(
            StatusCode::FORBIDDEN,
            "no-token-configured",
            "this daemon has no API token: set PERISCOPE_TOKEN or [api] token and restart it",
        ));
    };
    let given = headers
        .get(header::AUTHORIZATION)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.strip_prefix("Bearer "));
    match given {
        None => Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "this request needs `Authorization: Bearer <token>` (the daemon's PERISCOPE_TOKEN)",
        )),
        Some(t) if constant_time_eq(t.trim().as_bytes(), expected.as_bytes()) => Ok(()),
        Some(_) => Err(ApiError::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "the bearer token is wrong",
        )),
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn not_found() -> ApiError {
    ApiError::new(
        StatusCode::NOT_FOUND,
        "not-found",
        "no such endpoint; the routes are listed at GET /api/v1/openapi.json",
    )
}

async fn method_not_allowed() -> ApiError {
    ApiError::new(
        StatusCode::METHOD_NOT_ALLOWED,
        "method-not-allowed",
        "this endpoint does not take that method; see GET /api/v1/openapi.json",
    )
}

async fn health(State(state): State<AppState>) -> axum::Json<serde_json::Value> {
    axum::Json(serde_json::json!({
        "status": "ok",
        "version": env!("CARGO_PKG_VERSION"),
        "instrument": state.service.instrument().name,
    }))
}

async fn openapi_doc() -> axum::Json<serde_json::Value> {
    axum::Json(openapi())
}

async fn instrument(State(state): State<AppState>) -> ApiResult<axum::Json<serde_json::Value>> {
    let s = Arc::clone(&state.service);
    blocking(move || Ok(s.instrument_status())).await.map(axum::Json)
}

/// A request body that must be a TOML capture plan.
fn plan_body(headers: &HeaderMap, body: Result<String, StringRejection>) -> ApiResult<String> {
    let text = body.map_err(|e| {
        let status = e.status();
        let code = if status == StatusCode::PAYLOAD_TOO_LARGE {
            "body-too-large"
        } else {
            "bad-body"
        };
        ApiError::new(
            status,
            code,
            format!("the body must be a TOML capture plan (UTF-8, within the size limit): {e}"),
        )
    })?;
    if let Some(ct) = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok())
        && !(ct.starts_with("application/toml") || ct.starts_with("text/"))
    {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            format!("the body is {ct}; send the plan as application/toml (curl --data-binary @plan.toml)"),
        ));
    }
    if text.trim().is_empty() {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid-plan",
            "the body is empty; send a TOML capture plan",
        ));
    }
    Ok(text)
}

async fn check(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Result<String, StringRejection>,
) -> ApiResult<axum::Json<crate::check::Check>> {
    let text = plan_body(&headers, body)?;
    let s = Arc::clone(&state.service);
    blocking(move || s.check(text)).await.map(axum::Json)
}

async fn geometry(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<axum::Json<serde_json::Value>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.geometry(&id)).await.map(axum::Json)
}

async fn submit(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Result<String, StringRejection>,
) -> ApiResult<Response> {
    let text = plan_body(&headers, body)?;
    let s = Arc::clone(&state.service);
    let status = blocking(move || s.submit(text)).await?;
    let location = format!("/api/v1/runs/{}", status.id);
    let mut r = (StatusCode::CREATED, axum::Json(status)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    Ok(r)
}

async fn list(State(state): State<AppState>) -> ApiResult<axum::Json<Vec<RunStatus>>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.list()).await.map(axum::Json)
}

async fn run_status(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<axum::Json<RunStatus>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.status(&id)).await.map(axum::Json)
}

async fn pause(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let s = Arc::clone(&state.service);
    let st = blocking(move || s.pause(&id)).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

async fn resume(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let s = Arc::clone(&state.service);
    let st = blocking(move || s.resume(&id)).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

async fn abort(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let s = Arc::clone(&state.service);
    let st = blocking(move || s.abort(&id)).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

async fn estop(State(state): State<AppState>) -> ApiResult<axum::Json<EstopReport>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.estop()).await.map(axum::Json)
}

async fn events(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> ApiResult<Sse<impl tokio_stream::Stream<Item = Result<Event, Infallible>>>> {
    let max = state.service.instrument().api.max_streams;
    let Some(slot) = Slot::take(&state.streams, max) else {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-streams",
            format!(
                "{max} event streams are open, the most this daemon serves ([api] max-streams); \
                 close one or poll GET /api/v1/runs/{id}"
            ),
        ));
    };
    let s = Arc::clone(&state.service);
    let (rx, status) = {
        let id = id.clone();
        blocking(move || {
            let rx = s.subscribe(&id)?;
            Ok((rx, s.status(&id)?))
        })
        .await?
    };
    let first = Event::default()
        .event("status")
        .json_data(&status)
        .unwrap_or_else(|_| Event::default().event("status"));
    let head = tokio_stream::once(Ok::<_, Infallible>(first));
    // A run that is not running has no channel: a closed one ends the stream after the
    // status snapshot.
    let rx = rx.unwrap_or_else(|| tokio::sync::broadcast::channel(1).1);
    let live = BroadcastStream::new(rx).map(move |item| {
        let _slot = &slot;
        Ok(match item {
            Ok(StreamEvent { name, json }) => Event::default().event(&*name).data(&*json),
            Err(BroadcastStreamRecvError::Lagged(n)) => Event::default()
                .event("lagged")
                .data(format!("{{\"skipped\":{n}}}")),
        })
    });
    Ok(Sse::new(head.chain(live)).keep_alive(KeepAlive::default()))
}

async fn file(
    State(state): State<AppState>,
    Path((id, name)): Path<(String, String)>,
) -> ApiResult<Response> {
    let Some((_, media)) = DOWNLOADS.iter().find(|(n, _)| *n == name) else {
        return Err(ApiError::new(
            StatusCode::NOT_FOUND,
            "unknown-file",
            format!(
                "`{name}` is not a run file; available names: {}",
                DOWNLOADS.iter().map(|(n, _)| *n).collect::<Vec<_>>().join(", ")
            ),
        ));
    };
    let max = state.service.instrument().api.max_downloads;
    let Ok(permit) = Arc::clone(&state.downloads).try_acquire_owned() else {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-downloads",
            format!(
                "{max} downloads are in flight, the most this daemon serves at once ([api] max-downloads); retry shortly"
            ),
        ));
    };
    let s = Arc::clone(&state.service);
    let source = blocking(move || s.download(&id, &name)).await.map_err(|e| {
        if e.status == StatusCode::CONFLICT {
            ApiError::new(StatusCode::NOT_FOUND, "file-not-ready", e.message)
        } else {
            e
        }
    })?;
    let builder = Response::builder().header(header::CONTENT_TYPE, *media);
    let response = match source {
        service::Download::Bytes(bytes) => {
            drop(permit);
            builder.body(Body::from(bytes))
        }
        service::Download::File(file, len) => {
            // The permit lives as long as the body: a slow client holds its slot.
            let stream =
                tokio_util::io::ReaderStream::new(tokio::fs::File::from_std(file)).map(move |chunk| {
                    let _permit = &permit;
                    chunk
                });
            builder
                .header(header::CONTENT_LENGTH, len)
                .body(Body::from_stream(stream))
        }
    };
    response.map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::PipelineError;
    use std::error::Error as _;
    use std::path::PathBuf;

    fn io(kind: std::io::ErrorKind) -> std::io::Error {
        std::io::Error::new(kind, "disk says no")
    }

    /// A service error keeps its cause, and its HTTP status follows the cause's kind:
    /// a failure to prepare a run is the plan's (422), the instrument's (503) or the
    /// daemon's storage (500), not a blanket 500.
    #[test]
    fn service_errors_keep_their_cause_and_map_to_statuses_by_kind() {
        let storage = ServiceError::Storage {
            path: PathBuf::from("/runs/queue.json"),
            source: io(std::io::ErrorKind::PermissionDenied),
        };
        assert!(storage.source().is_some(), "the io::Error is kept as the source");
        let api = ApiError::from(storage);
        assert_eq!(
            (api.status, api.code),
            (StatusCode::INTERNAL_SERVER_ERROR, "storage")
        );
        assert_eq!(api.message, "/runs/queue.json: disk says no");

        let queue = ServiceError::QueueFile {
            path: PathBuf::from("/runs/queue.json"),
            source: serde_json::from_str::<Vec<String>>("{").unwrap_err(),
        };
        assert!(queue.source().is_some());
        let api = ApiError::from(queue);
        assert_eq!(api.code, "storage");
        assert!(api.message.contains("fix or delete the file"), "{}", api.message);

        let cases = [
            (
                PipelineError::Storage {
                    path: PathBuf::from("/runs/x"),
                    source: io(std::io::ErrorKind::StorageFull),
                },
                StatusCode::INTERNAL_SERVER_ERROR,
                "storage",
            ),
            (
                PipelineError::Open(crate::devices::OpenError::Usb {
                    selector: "1234:5678".into(),
                    why: "no such device".into(),
                }),
                StatusCode::SERVICE_UNAVAILABLE,
                "device",
            ),
            (
                PipelineError::Aborted(3),
                StatusCode::INTERNAL_SERVER_ERROR,
                "internal",
            ),
        ];
        for (e, status, code) in cases {
            let text = e.to_string();
            let api = ApiError::from(ServiceError::Prepare(e));
            assert_eq!((api.status, api.code), (status, code), "{text}");
            assert_eq!(api.message, text, "the message is the cause's own");
        }
    }
}

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
use axum::extract::{DefaultBodyLimit, Path, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio_stream::StreamExt;
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;
use utoipa::OpenApi as _;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

pub mod access;
pub mod catalogue;
mod dashboard;
mod import;
mod openapi;
pub mod server;

pub use dashboard::ASSETS;

use crate::run_dir::DOWNLOADS;
use crate::service::{
    EstopReport, Geometry, InstrumentStatus, RunStatus, Service, ServiceError, StreamEvent,
};
pub use openapi::ErrorBody;
use openapi::status;

/// The documented routes: every API handler, registered with the router and the
/// OpenAPI document at once (the dashboard's pages are routed in [`app`]).
fn documented() -> OpenApiRouter<AppState> {
    exempt().merge(checks()).merge(limited()).merge(imports())
}

/// Imports: uploads of capture files, as large as `[api] import-limit-mib`. They take
/// no turn of the others' (one uploads at a time, by its own permit), are bounded by
/// their stall time rather than the request timeout, and take the import limit for
/// their body.
fn imports() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(import::import))
}

/// The routes that never wait for a turn: the e-stop (nothing may stand in front of
/// it) and the health check (a probe must tell a busy daemon from a dead one).
fn exempt() -> OpenApiRouter<AppState> {
    OpenApiRouter::with_openapi(openapi::ApiDoc::openapi())
        .routes(routes!(health))
        .routes(routes!(estop))
}

/// Plan checks: parsing a plan of up to the body limit takes memory and CPU, and needs
/// no token on loopback, so they take turns of their own (`[api] max-checks`).
fn checks() -> OpenApiRouter<AppState> {
    OpenApiRouter::new().routes(routes!(check))
}

/// Every other route: they take turns (`[api] max-concurrent` at once), so a flood of
/// requests waits in line instead of crowding the instrument's worker off the CPU or
/// out of the service's state.
fn limited() -> OpenApiRouter<AppState> {
    OpenApiRouter::new()
        .routes(routes!(openapi_doc))
        .routes(routes!(instrument))
        .routes(routes!(submit, catalogue::list))
        .routes(routes!(run_status, catalogue::annotate))
        .routes(routes!(catalogue::batch))
        .routes(routes!(catalogue::again))
        .routes(routes!(catalogue::catalogue))
        .routes(routes!(catalogue::queue, catalogue::reorder))
        .routes(routes!(catalogue::move_run))
        .routes(routes!(catalogue::lock))
        .routes(routes!(catalogue::unlock))
        .routes(routes!(access::whoami))
        .routes(routes!(access::keys_list, access::keys_create))
        .routes(routes!(access::keys_revoke))
        .routes(routes!(access::audit))
        .routes(routes!(catalogue::metrics))
        .routes(routes!(pause))
        .routes(routes!(resume))
        .routes(routes!(abort))
        .routes(routes!(events))
        .routes(routes!(instrument_events))
        .routes(routes!(file))
        .routes(routes!(geometry))
}

/// The OpenAPI 3.1 document `GET /api/v1/openapi.json` serves, generated from the
/// routed handlers (built once).
pub fn openapi() -> serde_json::Value {
    static DOC: std::sync::OnceLock<serde_json::Value> = std::sync::OnceLock::new();
    DOC.get_or_init(|| openapi::to_json(&documented().into_openapi()))
        .clone()
}

/// The API's routes as (method, path), read from the document: what the hardening
/// tests put through the token and Host rules.
pub fn routes() -> Vec<(String, String)> {
    let doc = openapi();
    let mut out = Vec::new();
    for (path, ops) in doc["paths"].as_object().into_iter().flatten() {
        for method in ops.as_object().into_iter().flatten().map(|(m, _)| m) {
            out.push((method.to_uppercase(), path.clone()));
        }
    }
    out
}

/// Shared state of the handlers.
#[derive(Clone)]
pub struct AppState {
    service: Arc<Service>,
    /// Event-stream clients connected now.
    streams: Arc<std::sync::atomic::AtomicUsize>,
    /// Event streams open now by remote address (loopback's are not counted).
    peer_streams: PeerCounts,
    /// Downloads in flight (a permit per download, held until its body is sent).
    downloads: Arc<tokio::sync::Semaphore>,
    /// Downloads in flight by remote address (loopback's are not counted).
    peer_downloads: PeerCounts,
    /// The one import that may upload at a time.
    imports: Arc<tokio::sync::Semaphore>,
    /// The rate limit on recording failed authentications.
    auth_audit: access::AuthAuditState,
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
            peer_streams: Arc::default(),
            downloads,
            peer_downloads: Arc::default(),
            imports: Arc::new(tokio::sync::Semaphore::new(1)),
            auth_audit: Arc::default(),
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
        let body = ErrorBody {
            error: self.code,
            message: self.message.clone(),
        };
        let mut r = (self.status, axum::Json(body)).into_response();
        r.extensions_mut().insert(ErrorMessage(self.message));
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
    }
}

/// An error response's message, kept as a response extension for the audit trail.
#[derive(Clone, Debug)]
pub(crate) struct ErrorMessage(pub String);

/// Query parameters whose rejection (`?limit=abc`, a repeated field) is a JSON 400
/// `bad-query` naming what is wrong, not axum's plain text.
pub(crate) struct QueryParams<T>(pub T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned> axum::extract::FromRequestParts<S> for QueryParams<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Self, ApiError> {
        match axum::extract::Query::<T>::from_request_parts(parts, state).await {
            Ok(axum::extract::Query(v)) => Ok(QueryParams(v)),
            Err(e) => Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                "bad-query",
                format!("the query string: {}", e.body_text()),
            )),
        }
    }
}

/// Path segments whose rejection (a segment that is not UTF-8 once decoded, `%FF`) is a
/// JSON `bad-path` error, not axum's plain text.
pub(crate) struct PathParams<T>(pub T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned + Send> axum::extract::FromRequestParts<S>
    for PathParams<T>
{
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Self, ApiError> {
        match Path::<T>::from_request_parts(parts, state).await {
            Ok(Path(v)) => Ok(PathParams(v)),
            Err(e) => {
                let status = e.status();
                let code = if status.is_client_error() {
                    "bad-path"
                } else {
                    "internal"
                };
                Err(ApiError::new(
                    status,
                    code,
                    format!("the path: {}", e.body_text()),
                ))
            }
        }
    }
}

/// A JSON request body whose rejection is a JSON error naming what is wrong.
pub(crate) struct JsonBody<T>(pub T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned> axum::extract::FromRequest<S> for JsonBody<T> {
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        match axum::Json::<T>::from_request(req, state).await {
            Ok(axum::Json(v)) => Ok(JsonBody(v)),
            Err(e) => {
                // A body that is JSON but not of the documented shape (a wrong type, a
                // missing or unknown field: axum's 422) does not parse as the request
                // either: 400 `bad-body`, as docs/api.md says, like malformed JSON.
                let (status, code) = match e.status() {
                    StatusCode::PAYLOAD_TOO_LARGE => (StatusCode::PAYLOAD_TOO_LARGE, "body-too-large"),
                    StatusCode::UNSUPPORTED_MEDIA_TYPE => {
                        (StatusCode::UNSUPPORTED_MEDIA_TYPE, "unsupported-media-type")
                    }
                    _ => (StatusCode::BAD_REQUEST, "bad-body"),
                };
                Err(ApiError::new(
                    status,
                    code,
                    format!(
                        "the body must be JSON as documented at GET /api/v1/openapi.json: {}",
                        e.body_text()
                    ),
                ))
            }
        }
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
            ServiceError::RunsDirInUse(_) => (StatusCode::INTERNAL_SERVER_ERROR, "storage"),
            ServiceError::OverBudget(_) => (StatusCode::UNPROCESSABLE_ENTITY, "over-budget"),
            ServiceError::Invalid(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid"),
            ServiceError::Locked(_) => (StatusCode::LOCKED, "queue-locked"),
            ServiceError::Busy(_) => (StatusCode::SERVICE_UNAVAILABLE, "busy"),
            ServiceError::InvalidImport(_) => (StatusCode::UNPROCESSABLE_ENTITY, "invalid-import"),
            ServiceError::Catalogue(_) => (StatusCode::INTERNAL_SERVER_ERROR, "catalogue"),
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
        P::Open(_) | P::Device(_) => (StatusCode::SERVICE_UNAVAILABLE, "device"),
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
    let (exempt, _) = exempt().split_for_parts();
    let (checks, _) = checks().split_for_parts();
    let (limited, _) = limited().split_for_parts();
    let (imports, _) = imports().split_for_parts();
    // One shared permit pool per group (a plain ConcurrencyLimitLayer would give each
    // route its own).
    let limited = limited
        .route("/", get(dashboard::index))
        .route("/favicon.ico", get(dashboard::favicon))
        .route("/ui/{*file}", get(dashboard::asset))
        .layer(tower::limit::GlobalConcurrencyLimitLayer::new(api.max_concurrent));
    let checks = checks.layer(tower::limit::GlobalConcurrencyLimitLayer::new(api.max_checks));
    let timeout =
        tower_http::timeout::TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, api.request_timeout);
    // Every route but the imports is answered within the request timeout; an upload
    // is bounded by its size and stall limits instead, and counts its own bytes. The
    // e-stop (and health) get at least ESTOP_TIMEOUT whatever the config's timeout: an
    // e-stop during a run waits up to 2 s for the run to park, and one cut off by a
    // short timeout would tell the operator it failed after the laser went off.
    let estop_timeout = tower_http::timeout::TimeoutLayer::with_status_code(
        StatusCode::REQUEST_TIMEOUT,
        api.request_timeout.max(ESTOP_TIMEOUT),
    );
    let timed: Router<AppState> = checks
        .merge(limited)
        .layer(timeout)
        .layer(middleware::map_response(timeout_as_json))
        // Outside the groups' turns: a body trickled in holds a connection, not a turn.
        .layer(middleware::from_fn_with_state(state.clone(), read_body_first))
        .merge(
            exempt
                .layer(estop_timeout)
                .layer(middleware::map_response(estop_timeout_as_json)),
        );
    let imports = imports.layer(DefaultBodyLimit::disable());
    timed
        .merge(imports)
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(middleware::from_fn_with_state(state.clone(), access::authorise))
        .layer(middleware::from_fn_with_state(state.clone(), check_host))
        .layer(middleware::from_fn_with_state(state.clone(), access::track))
        .layer(DefaultBodyLimit::max(api.body_limit))
        .layer(compression())
        .with_state(state)
}

/// Reads a request's body whole, within the body limit and `[api] request-timeout-s`,
/// before the request waits for its group's turn (`[api] max-concurrent`,
/// `max-checks`): a client trickling a body a byte at a time then holds its
/// connection, not one of the few turns every other request needs (until 2026-12-06,
/// eight such clients held every turn for the request timeout, and a read of the runs
/// list waited 26 s). Requests without a body pass straight on.
async fn read_body_first(State(state): State<AppState>, req: Request, next: Next) -> Response {
    use http_body_util::BodyExt as _;
    let has_body = req.headers().contains_key(header::CONTENT_LENGTH)
        || req.headers().contains_key(header::TRANSFER_ENCODING);
    if !has_body {
        return next.run(req).await;
    }
    let api = &state.service.instrument().api;
    let (parts, body) = req.into_parts();
    let read = tokio::time::timeout(
        api.request_timeout,
        http_body_util::Limited::new(body, api.body_limit).collect(),
    )
    .await;
    match read {
        Ok(Ok(collected)) => next.run(Request::from_parts(parts, Body::from(collected.to_bytes()))).await,
        Ok(Err(e)) if e.downcast_ref::<http_body_util::LengthLimitError>().is_some() => ApiError::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "body-too-large",
            format!(
                "the body is larger than the daemon accepts ([api] body-limit-kib: {} KiB)",
                api.body_limit / 1024
            ),
        )
        .into_response(),
        Ok(Err(e)) => {
            ApiError::new(StatusCode::BAD_REQUEST, "bad-body", format!("the body could not be read: {e}")).into_response()
        }
        Err(_) => ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            "request-timeout",
            "the request's body did not arrive within the daemon's limit ([api] request-timeout-s); nothing was done",
        )
        .into_response(),
    }
}

/// The least time the e-stop is given before its request is answered 408: its own
/// waits (the run's way out, 2 s; opening the controllers) with room to spare.
const ESTOP_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);

/// Responses compressed (gzip or brotli, as the client's `Accept-Encoding` asks) by
/// tower-http: the page, its scripts, JSON, event logs. Not compressed: event streams,
/// images, and the binary downloads (`.npy`, `.ply`, HDF5: float data that hardly
/// shrinks, and would cost the API's threads CPU for nothing).
fn compression() -> tower_http::compression::CompressionLayer<impl tower_http::compression::Predicate> {
    use tower_http::compression::predicate::{DefaultPredicate, NotForContentType, Predicate as _};
    tower_http::compression::CompressionLayer::new()
        .quality(tower_http::CompressionLevel::Precise(5))
        .compress_when(
            DefaultPredicate::new()
                .and(NotForContentType::const_new("application/octet-stream"))
                .and(NotForContentType::const_new("application/x-hdf5")),
        )
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
    fn park_now(&self) {
        self.service.park_now();
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
    // The dashboard's files compressed before the first page is asked for, off the
    // runtime's threads.
    if let Err(e) = tokio::task::spawn_blocking(dashboard::prepare).await {
        tracing::warn!(error = %e, "the dashboard's files are compressed on first request");
    }
    // Bound before the worker starts: a queued run taken up by a daemon that then fails
    // to listen was left half-opened, its devices opened and its run interrupted.
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
        crate::signals::SIGNAL_GRACE,
    );
    let worker = service.start_worker();
    let api = &service.instrument().api;
    let limits = server::ConnectionLimits {
        header_timeout: api.header_timeout,
        max_connections: server::connection_cap(api.max_connections, server::open_files_limit()),
        max_per_peer: api.max_connections_per_peer,
        write_timeout: api.request_timeout,
    };
    server::serve_connections(listener, app, limits, async move { notify.notified().await })
        .await
        .map_err(ServeError::Io)?;
    // Off the runtime: it takes the service's lock, which a request writing files may
    // hold.
    let stopping = Arc::clone(&service);
    let _ = tokio::task::spawn_blocking(move || stopping.shutdown()).await;
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

/// Refuses requests whose `Host` names this machine by a name nobody configured, and
/// mutating requests whose `Origin` is another site. A DNS-rebinding page reaches the
/// daemon under the attacker's host name, and a cross-site form posts with its own
/// origin: both stop here. IP literals and `localhost` are always accepted (a page
/// cannot make a browser send them for its own origin); further names come from
/// `[api] hosts`. Clients that send no `Origin` (curl, scripts) are not affected.
async fn check_host(State(state): State<AppState>, req: Request, next: Next) -> Response {
    match host_refusal(&state, &req) {
        Some((e, why)) => {
            let entry = access::host_refusal_entry(&req, &why);
            access::refused_for_its_host(&state, entry, e).await
        }
        None => next.run(req).await,
    }
}

/// Why [`check_host`] refuses `req` (the answer, and a line for the audit trail), if
/// it does.
fn host_refusal(state: &AppState, req: &Request) -> Option<(ApiError, String)> {
    let hosts = &state.service.instrument().api.hosts;
    let host = req
        .headers()
        .get(header::HOST)
        .map(|h| h.to_str().unwrap_or("\u{fffd}"));
    if let Some(h) = host
        && !host_allowed(h, hosts)
    {
        let e = ApiError::new(
            StatusCode::FORBIDDEN,
            "host-not-allowed",
            format!(
                "this daemon does not answer to the host name `{h}`: reach it by IP address or \
                 localhost, or add the name to [api] hosts in the instrument config"
            ),
        );
        return Some((e, format!("host name `{h}` not allowed")));
    }
    if is_mutating(req)
        && let Some(origin) = req.headers().get(header::ORIGIN)
    {
        let origin = origin.to_str().unwrap_or("\u{fffd}");
        let authority = origin
            .strip_prefix("http://")
            .or_else(|| origin.strip_prefix("https://"))
            .unwrap_or("");
        let same = host.is_some_and(|h| h.eq_ignore_ascii_case(authority));
        if !same || !host_allowed(authority, hosts) {
            let e = ApiError::new(
                StatusCode::FORBIDDEN,
                "origin-not-allowed",
                format!(
                    "a page from `{origin}` may not change this instrument: send mutating requests \
                     from the daemon's own pages or from a client that sends no Origin"
                ),
            );
            return Some((e, format!("a page from `{origin}`")));
        }
    }
    None
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

/// The timeout layer's answer (a bare 408, no content type) as the API's other errors
/// are: JSON `request-timeout` with `message`; any other response as it is.
fn timeout_json(res: axum::response::Response, message: &'static str) -> axum::response::Response {
    if res.status() == StatusCode::REQUEST_TIMEOUT
        && !res.headers().contains_key(axum::http::header::CONTENT_TYPE)
    {
        return ApiError::new(StatusCode::REQUEST_TIMEOUT, "request-timeout", message).into_response();
    }
    res
}

/// [`timeout_json`] for the routes under `[api] request-timeout-s`.
async fn timeout_as_json(res: axum::response::Response) -> axum::response::Response {
    timeout_json(
        res,
        "the request took longer than the daemon allows ([api] request-timeout-s): what it asked for may or may not have been done; look at the run's or the queue's state before trying again",
    )
}

/// [`timeout_json`] for the e-stop and the health check, whose limit is at least
/// [`ESTOP_TIMEOUT`]: an e-stop not answered in that time has an unknown outcome.
async fn estop_timeout_as_json(res: axum::response::Response) -> axum::response::Response {
    timeout_json(
        res,
        "no answer within the time limit of the e-stop and the health check (the larger of 10 s and [api] request-timeout-s): after an e-stop, whether the laser is off is not known from here; use the hardware emergency stop and read GET /api/v1/instrument",
    )
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

/// `GET /api/v1/health`.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct Health {
    /// Always `ok`.
    pub status: &'static str,
    /// The daemon's version.
    pub version: &'static str,
    /// The instrument config's name.
    pub instrument: String,
}

/// Liveness and version
#[utoipa::path(get, path = "/api/v1/health", responses((status = 200, description = "the daemon is up", body = Health)))]
async fn health(State(state): State<AppState>) -> axum::Json<Health> {
    axum::Json(Health {
        status: "ok",
        version: env!("CARGO_PKG_VERSION"),
        instrument: state.service.instrument().name.clone(),
    })
}

/// This document
#[utoipa::path(get, path = "/api/v1/openapi.json", responses((status = 200, description = "OpenAPI 3.1", body = Object)))]
async fn openapi_doc() -> axum::Json<serde_json::Value> {
    axum::Json(openapi())
}

/// The instrument's state as the worker last read it
///
/// Devices, positions, laser and interlock state and count rates, as the worker last
/// read them (`reading` says when); never touches the hardware.
#[utoipa::path(get, path = "/api/v1/instrument", responses((status = 200, description = "instrument status", body = InstrumentStatus)))]
async fn instrument(State(state): State<AppState>) -> ApiResult<axum::Json<InstrumentStatus>> {
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
    // Media types are case-insensitive (RFC 9110 §8.3.1): `Application/TOML` is TOML.
    if let Some(ct) = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok())
        && !({
            let ct = ct.to_ascii_lowercase();
            ct.starts_with("application/toml") || ct.starts_with("text/")
        })
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

/// Check a TOML capture plan without queueing it
///
/// What `periscope check` says about the plan: the report, estimated durations, the run
/// budget and targets outside the galvo limits. Nothing is queued or touched.
#[utoipa::path(
    post,
    path = "/api/v1/check",
    request_body(content = String, content_type = "application/toml", description = "a TOML capture plan"),
    responses(
        (status = 200, description = "the plan is valid; `over_budget` says whether submit would refuse it", body = crate::check::Check),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 413, description = status::TOO_LARGE, body = ErrorBody),
        (status = 415, description = status::MEDIA_TYPE, body = ErrorBody),
        (status = 422, description = status::INVALID_PLAN, body = ErrorBody),
    )
)]
async fn check(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: Result<String, StringRejection>,
) -> ApiResult<axum::Json<crate::check::Check>> {
    let text = plan_body(&headers, body)?;
    let s = Arc::clone(&state.service);
    blocking(move || s.check(text)).await.map(axum::Json)
}

/// A run's geometry for 3-D views
///
/// Relay points, planned illumination and detection points (each thinned to at most
/// 20,000), the volume box and the instrument's viewpoint, metres.
#[utoipa::path(
    get,
    path = "/api/v1/runs/{id}/geometry",
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 200, description = "geometry", body = Geometry),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
    )
)]
async fn geometry(
    State(state): State<AppState>,
    PathParams(id): PathParams<String>,
) -> ApiResult<axum::Json<Geometry>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.geometry(&id)).await.map(axum::Json)
}

/// Submit a TOML capture plan; it is validated, then queued
#[utoipa::path(
    post,
    path = "/api/v1/runs",
    security(("bearer" = [])),
    request_body(content = String, content_type = "application/toml", description = "a TOML capture plan"),
    responses(
        (status = 201, description = "queued; Location names the run", body = RunStatus),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 413, description = status::TOO_LARGE, body = ErrorBody),
        (status = 415, description = status::MEDIA_TYPE, body = ErrorBody),
        (status = 422, description = status::INVALID_PLAN, body = ErrorBody),
        (status = 423, description = status::LOCKED, body = ErrorBody),
        (status = 429, description = status::QUEUE_FULL, body = ErrorBody),
        (status = 500, description = status::STORAGE, body = ErrorBody),
        (status = 503, description = status::UNAVAILABLE, body = ErrorBody),
    )
)]
async fn submit(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<access::Caller>,
    headers: HeaderMap,
    body: Result<String, StringRejection>,
) -> ApiResult<Response> {
    let text = plan_body(&headers, body)?;
    let key = headers
        .get(catalogue::LOCK_KEY_HEADER)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let s = Arc::clone(&state.service);
    let status = blocking(move || {
        s.check_lock(key.as_deref())?;
        s.submit_as(text, &caller.name, None)
    })
    .await?;
    let location = format!("/api/v1/runs/{}", status.id);
    let mut r = (StatusCode::CREATED, axum::Json(status)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    Ok(r)
}

/// One run: state, stage, progress, ETA, files
#[utoipa::path(
    get,
    path = "/api/v1/runs/{id}",
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 200, description = "run", body = RunStatus),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
    )
)]
async fn run_status(
    State(state): State<AppState>,
    PathParams(id): PathParams<String>,
) -> ApiResult<axum::Json<RunStatus>> {
    let s = Arc::clone(&state.service);
    blocking(move || s.status(&id)).await.map(axum::Json)
}

/// Pause a running run at its next checkpoint (between pairs)
#[utoipa::path(
    post,
    path = "/api/v1/runs/{id}/pause",
    security(("bearer" = [])),
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 202, description = "pause requested", body = RunStatus),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
        (status = 409, description = status::CONFLICT, body = ErrorBody),
    )
)]
async fn pause(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<access::Caller>,
    PathParams(id): PathParams<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let s = Arc::clone(&state.service);
    let st = blocking(move || s.pause_as(&id, &caller.name)).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

/// Queue a paused or failed run again; it continues from its last stored pair
#[utoipa::path(
    post,
    path = "/api/v1/runs/{id}/resume",
    security(("bearer" = [])),
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 202, description = "queued", body = RunStatus),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
        (status = 409, description = status::CONFLICT, body = ErrorBody),
        (status = 423, description = status::LOCKED, body = ErrorBody),
    )
)]
async fn resume(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<access::Caller>,
    headers: HeaderMap,
    PathParams(id): PathParams<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let key = headers
        .get(catalogue::LOCK_KEY_HEADER)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let s = Arc::clone(&state.service);
    let st = blocking(move || {
        // A run that does not exist is 404 whether or not the queue is locked.
        s.status(&id)?;
        s.check_lock(key.as_deref())?;
        s.resume_as(&id, &caller.name)
    })
    .await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

/// Abort a run; what was captured is kept
#[utoipa::path(
    post,
    path = "/api/v1/runs/{id}/abort",
    security(("bearer" = [])),
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 202, description = "abort requested or done", body = RunStatus),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
        (status = 409, description = status::CONFLICT, body = ErrorBody),
    )
)]
async fn abort(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<access::Caller>,
    PathParams(id): PathParams<String>,
) -> ApiResult<(StatusCode, axum::Json<RunStatus>)> {
    let s = Arc::clone(&state.service);
    let st = blocking(move || s.abort_as(&id, &caller.name)).await?;
    Ok((StatusCode::ACCEPTED, axum::Json(st)))
}

/// Emergency stop
///
/// Laser off first (directly, out of band), then the running run aborted and both arms
/// parked, queued runs held; every step is tried and reported.
#[utoipa::path(
    post,
    path = "/api/v1/estop",
    security(("bearer" = [])),
    responses(
        (status = 200, description = "instrument safe", body = EstopReport),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 503, description = status::UNAVAILABLE, body = ErrorBody),
    )
)]
async fn estop(State(state): State<AppState>) -> ApiResult<axum::Json<EstopReport>> {
    // A thread of its own, not the blocking pool: requests timed out while their
    // blocking work goes on (a download's export, a disk that stalls) can fill the
    // pool, and the e-stop must never queue behind them.
    let s = Arc::clone(&state.service);
    match own_thread("periscope-estop", &ESTOP_SLOTS, move || s.estop()).await {
        Some(r) => r.map(axum::Json).map_err(ApiError::from),
        None => Err(ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "the e-stop's thread could not start or ended without a report",
        )),
    }
}

/// Slots of the e-stop's own work ([`estop`]) and its key check, which read no more
/// than `keys.json`.
static ESTOP_SLOTS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(OWN_THREADS);

/// Slots of the e-stop's audit entries, which wait for `audit.jsonl`'s sync and the
/// catalogue's lock: a catalogue another process holds (or a stalled disk) keeps
/// these, never the slots an e-stop needs to switch the laser off. Until 2026-12-06
/// the two shared one set, and sixteen e-stops pressed while the catalogue was held
/// left the seventeenth waiting for a slot.
static ESTOP_AUDIT_SLOTS: tokio::sync::Semaphore = tokio::sync::Semaphore::const_new(OWN_THREADS);

/// Runs `f` on a thread of its own, taking one of `slots`, and waits for its result
/// (`None`: the thread could not start, or panicked). For the e-stop's path, which must
/// never wait behind the blocking pool: requests whose timeout fired while their
/// blocking work went on (an export, a disk that stalls) can fill it. At most
/// [`OWN_THREADS`] of a set of slots run at once (a flood of e-stops waits for one to
/// end rather than start threads without bound); a dropped future leaves its thread to
/// finish.
async fn own_thread<T: Send + 'static>(
    name: &'static str,
    slots: &'static tokio::sync::Semaphore,
    f: impl FnOnce() -> T + Send + 'static,
) -> Option<T> {
    /// A slot, given back when the thread ends, panicking or not.
    struct Slot(&'static tokio::sync::Semaphore);
    impl Drop for Slot {
        fn drop(&mut self) {
            self.0.add_permits(1);
        }
    }
    slots.acquire().await.ok()?.forget();
    let slot = Slot(slots);
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job: OwnJob = (
        name,
        Box::new(move || {
            let _slot = slot;
            let _ = tx.send(f());
        }),
    );
    // Started by the spawner where there is one, so the thread has the instrument's
    // priority: a thread inherits its creator's nice value, and the API's are lowered.
    let job = match SPAWNER.get() {
        Some(spawner) => match spawner.send(job) {
            Ok(()) => None,
            Err(std::sync::mpsc::SendError(job)) => Some(job),
        },
        None => Some(job),
    };
    if let Some((name, work)) = job {
        spawn_own(name, work);
    }
    rx.await.ok()
}

/// Runs the e-stop's key check `f` on the standing key-check thread (started with the
/// spawner, at the instrument's priority), or on a thread of its own where there is
/// none or its queue is full. A check is a digest and a lookup, microseconds; a thread
/// started for each (as until 2026-12-06) let a flood of bogus keys from anyone spend
/// most of a core at the instrument's priority on starting threads.
pub(super) async fn estop_key_check<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Option<T> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let job: Box<dyn FnOnce() + Send> = Box::new(move || {
        let _ = tx.send(f());
    });
    let job = match KEY_CHECKS.get() {
        Some(queue) => match queue.try_send(job) {
            Ok(()) => None,
            Err(
                std::sync::mpsc::TrySendError::Full(job) | std::sync::mpsc::TrySendError::Disconnected(job),
            ) => Some(job),
        },
        None => Some(job),
    };
    if let Some(job) = job {
        own_thread("periscope-estop-auth", &ESTOP_SLOTS, job).await?;
    }
    rx.await.ok()
}

/// The standing key-check thread's queue ([`estop_key_check`]).
static KEY_CHECKS: std::sync::OnceLock<std::sync::mpsc::SyncSender<Box<dyn FnOnce() + Send>>> =
    std::sync::OnceLock::new();

/// Key checks waiting for the standing thread before one gets a thread of its own.
const KEY_CHECK_QUEUE: usize = 1024;

/// A thread of the e-stop's path: its name and its work.
type OwnJob = (&'static str, Box<dyn FnOnce() + Send>);

/// The thread that starts [`own_thread`]'s threads, made by [`start_own_threads`].
static SPAWNER: std::sync::OnceLock<std::sync::mpsc::Sender<OwnJob>> = std::sync::OnceLock::new();

/// Starts the thread that starts the e-stop path's threads, from the calling thread,
/// whose scheduling priority they keep. `periscope serve` calls it from its main
/// thread before the API's runtime (whose threads run at [`crate::priority::API_NICE`])
/// exists, so an e-stop is not weighed at a tenth of a reconstruction's threads.
/// Without it (tests, embedders), the threads are started by the API's own.
pub fn start_own_threads() -> std::io::Result<()> {
    if SPAWNER.get().is_some() {
        return Ok(());
    }
    let (tx, rx) = std::sync::mpsc::channel::<OwnJob>();
    std::thread::Builder::new()
        .name("periscope-estop-spawner".into())
        .spawn(move || {
            for (name, work) in rx {
                spawn_own(name, work);
            }
        })?;
    let _ = SPAWNER.set(tx);
    let (checks, queue) = std::sync::mpsc::sync_channel::<Box<dyn FnOnce() + Send>>(KEY_CHECK_QUEUE);
    std::thread::Builder::new()
        .name("periscope-estop-auth".into())
        .spawn(move || {
            for check in queue {
                // A check that panics is that request's failure, not the thread's end.
                let _ = std::panic::catch_unwind(std::panic::AssertUnwindSafe(check));
            }
        })?;
    let _ = KEY_CHECKS.set(checks);
    Ok(())
}

fn spawn_own(name: &'static str, work: Box<dyn FnOnce() + Send>) {
    if let Err(e) = std::thread::Builder::new().name(name.into()).spawn(work) {
        // The work, and the slot and answer with it, were dropped.
        tracing::error!(thread = name, error = %e, "a thread of the e-stop's path could not start");
    }
}

/// The most threads of the e-stop's path ([`own_thread`]) at once.
const OWN_THREADS: usize = 16;

/// A run's progress as server-sent events
///
/// A `status` snapshot, then the run's typed events (stage-started, stage-finished,
/// los-point, relay, planned, pair, histogram, initialised, data-added, epoch,
/// snapshot, pruned, output, failed, completed; `lagged` if the client fell behind).
#[utoipa::path(
    get,
    path = "/api/v1/runs/{id}/events",
    params(("id" = String, Path, description = "run id")),
    responses(
        (status = 200, description = "event stream", content_type = "text/event-stream", body = String),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
        (status = 503, description = status::STREAMS, body = ErrorBody),
    )
)]
async fn events(
    State(state): State<AppState>,
    peer: Peer,
    PathParams(id): PathParams<String>,
) -> ApiResult<Sse<impl tokio_stream::Stream<Item = Result<Event, Infallible>>>> {
    let slot = stream_slot(&state, peer, &format!("GET /api/v1/runs/{id}"))?;
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
            Ok(StreamEvent { name, json }) => Event::default().event(&*name).data(&**json),
            Err(BroadcastStreamRecvError::Lagged(n)) => Event::default()
                .event("lagged")
                .data(format!("{{\"skipped\":{n}}}")),
        })
    });
    Ok(Sse::new(head.chain(live)).keep_alive(KeepAlive::default()))
}

/// The client's address where the server gave one (requests put through the router
/// in tests may have none).
pub(crate) struct Peer(Option<std::net::IpAddr>);

impl<S: Send + Sync> axum::extract::FromRequestParts<S> for Peer {
    type Rejection = Infallible;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        _: &S,
    ) -> Result<Self, Self::Rejection> {
        Ok(Peer(
            parts
                .extensions
                .get::<axum::extract::ConnectInfo<SocketAddr>>()
                .map(|c| c.0.ip().to_canonical()),
        ))
    }
}

/// Most event streams one remote address holds at once (loopback's are not counted):
/// a dashboard tab takes two. A host that opens streams and reads them a byte at a
/// time could otherwise hold all of `[api] max-streams`.
pub const STREAMS_PER_PEER: usize = 8;

/// An event-stream slot: one of `[api] max-streams`, and one of its host's
/// [`STREAMS_PER_PEER`].
struct StreamSlot {
    _slot: Slot,
    _peer: Option<PeerSlot>,
}

/// Slots held by remote address: event streams, downloads.
type PeerCounts = Arc<std::sync::Mutex<std::collections::HashMap<std::net::IpAddr, usize>>>;

/// One of a remote host's slots of a kind, given back when dropped.
struct PeerSlot {
    counts: PeerCounts,
    ip: std::net::IpAddr,
}

impl PeerSlot {
    /// One of `peer`'s at most `limit` slots in `counts`: `Ok(None)` for loopback and
    /// unknown peers (not counted), `Err(())` when the host holds `limit` already.
    fn take(counts: &PeerCounts, peer: &Peer, limit: usize) -> Result<Option<PeerSlot>, ()> {
        let Some(ip) = peer.0.filter(|ip| !ip.is_loopback()) else {
            return Ok(None);
        };
        let mut held = counts.lock().unwrap_or_else(|p| p.into_inner());
        let n = held.entry(ip).or_insert(0);
        if *n >= limit {
            return Err(());
        }
        *n += 1;
        Ok(Some(PeerSlot {
            counts: Arc::clone(counts),
            ip,
        }))
    }
}

impl Drop for PeerSlot {
    fn drop(&mut self) {
        let mut counts = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = counts.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                counts.remove(&self.ip);
            }
        }
    }
}

/// One of the capped event-stream slots (`[api] max-streams`, [`STREAMS_PER_PEER`] a
/// remote host), or a 503 that names what to poll instead.
fn stream_slot(state: &AppState, peer: Peer, instead: &str) -> ApiResult<StreamSlot> {
    let max = state.service.instrument().api.max_streams;
    let slot = Slot::take(&state.streams, max).ok_or_else(|| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-streams",
            format!(
                "{max} event streams are open, the most this daemon serves ([api] max-streams); \
                 close one or poll {instead}"
            ),
        )
    })?;
    let peer = PeerSlot::take(&state.peer_streams, &peer, STREAMS_PER_PEER).map_err(|()| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-streams",
            format!(
                "this host has {STREAMS_PER_PEER} event streams open, the most one host may hold; \
                 close one (each dashboard tab holds two) or poll {instead}"
            ),
        )
    })?;
    Ok(StreamSlot {
        _slot: slot,
        _peer: peer,
    })
}

/// Most downloads one remote address has in flight at once: half of `[api]
/// max-downloads`, at least one (loopback's are not counted). A host that reads its
/// downloads a little at a time, just inside the write timeout, could otherwise hold
/// every slot and leave the operator's results unserved.
pub fn downloads_per_peer(max_downloads: usize) -> usize {
    (max_downloads / 2).max(1)
}

/// How often `GET /api/v1/instrument/events` sends the safety state.
const SAFETY_INTERVAL: std::time::Duration = std::time::Duration::from_millis(500);

/// The live safety state as server-sent events
///
/// A `safety` event every 0.5 s: laser emission, interlock, diffuser, arm angles,
/// signal and detector rates, counts per pulse, pair rate, from the running run's own
/// readings or the idle reading, with the reading's age and the age past which it says
/// nothing (`stale_after_s`): a client shows UNKNOWN then, or when the stream stops.
#[utoipa::path(
    get,
    path = "/api/v1/instrument/events",
    responses(
        (status = 200, description = "event stream of `safety` events", content_type = "text/event-stream", body = crate::service::Safety),
        (status = 503, description = status::STREAMS, body = ErrorBody),
    )
)]
async fn instrument_events(
    State(state): State<AppState>,
    peer: Peer,
) -> ApiResult<Sse<impl tokio_stream::Stream<Item = Result<Event, Infallible>>>> {
    let slot = stream_slot(&state, peer, "GET /api/v1/instrument")?;
    let service = Arc::clone(&state.service);
    let ticks = tokio_stream::wrappers::IntervalStream::new(tokio::time::interval(SAFETY_INTERVAL));
    let stream = ticks
        .then(move |_| {
            let service = Arc::clone(&service);
            let _slot = &slot;
            async move {
                // The stream ends with the service's shutdown, as the runs' streams
                // do (it went on until the server's grace ran out).
                let safety =
                    tokio::task::spawn_blocking(move || (!service.is_shut_down()).then(|| service.safety()))
                        .await;
                match safety {
                    Ok(None) => None,
                    Ok(Some(s)) => Some(Ok(Event::default()
                        .event("safety")
                        .json_data(&s)
                        .unwrap_or_else(|_| Event::default().event("safety")))),
                    Err(_) => Some(Ok(Event::default().event("error").data("{}"))),
                }
            }
        })
        .map_while(|e| e);
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// Download a run file
///
/// The volume (.npy), depth and albedo (PNG), the relay point cloud and the Gaussians
/// (PLY), the y-tal HDF5 capture, the plan, the logs.
#[utoipa::path(
    get,
    path = "/api/v1/runs/{id}/files/{name}",
    params(
        ("id" = String, Path, description = "run id"),
        ("name" = String, Path, description = "file name"),
    ),
    responses(
        (status = 200, description = "the file, with its media type (`application/octet-stream` for .npy and .ply, `image/png`, `application/x-hdf5`, `application/json`, `application/toml`, `application/x-ndjson`)", content_type = "application/octet-stream", body = [u8]),
        (status = 206, description = "the bytes a `Range` header asks for", content_type = "application/octet-stream", body = [u8]),
        (status = 404, description = status::NOT_FOUND, body = ErrorBody),
        (status = 412, description = "the file changed since the `If-Unmodified-Since` time (`precondition-failed`)", body = ErrorBody),
        (status = 416, description = "the `Range` header asks for no one range inside the file: past its end, unparsable, or several ranges (`range-not-satisfiable`; `Content-Range: bytes */length` says its length)", body = ErrorBody),
        (status = 503, description = status::DOWNLOADS, body = ErrorBody),
    )
)]
async fn file(
    State(state): State<AppState>,
    PathParams((id, name)): PathParams<(String, String)>,
    peer: Peer,
    request: Request,
) -> ApiResult<Response> {
    let Some((known, media)) = DOWNLOADS.iter().find(|(n, _)| *n == name) else {
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
    let per_peer = downloads_per_peer(max);
    let Ok(peer_slot) = PeerSlot::take(&state.peer_downloads, &peer, per_peer) else {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-downloads",
            format!(
                "this host has {per_peer} downloads in flight, the most one host may ([api] max-downloads / 2); \
                 finish one, then retry"
            ),
        ));
    };
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
    match source {
        crate::service::Download::Bytes(bytes) => {
            drop((permit, peer_slot));
            Response::builder()
                .header(header::CONTENT_TYPE, *media)
                .body(Body::from(bytes))
                .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))
        }
        crate::service::Download::Path(path) => {
            // tower-http's ServeFile answers with the file's validators (Last-Modified,
            // so a second view of the same result is a 304), ranges and HEAD. The permit
            // lives as long as the body: a slow client holds its slot.
            use tower::ServiceExt as _;
            let asked = request
                .headers()
                .get(header::RANGE)
                .map(|r| String::from_utf8_lossy(r.as_bytes()).into_owned());
            let Ok(response) = tower_http::services::ServeFile::new(&path).oneshot(request).await;
            let gone = response.status() == StatusCode::NOT_FOUND
                && matches!(tokio::fs::metadata(&path).await, Err(e) if e.kind() == std::io::ErrorKind::NotFound);
            if let Some(refused) = serve_file_error(&response, known, gone, asked.as_deref()) {
                return Ok(refused);
            }
            let (mut parts, body) = response.into_parts();
            parts
                .headers
                .insert(header::CONTENT_TYPE, HeaderValue::from_static(media));
            parts
                .headers
                .insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
            let stream = Body::new(body).into_data_stream().map(move |chunk| {
                let _held = (&permit, &peer_slot);
                chunk
            });
            Ok(Response::from_parts(parts, Body::from_stream(stream)))
        }
    }
}

/// The API's JSON error for a run file that tower-http's `ServeFile` refused (it answers
/// with an empty body, which the caller would label with the file's media type), with
/// its status: a `Range` header, `asked`, that it does not serve (416, keeping the
/// `Content-Range: bytes */length` it gives: a range past the end, one it cannot parse
/// and several ranges alike), a file changed since an `If-Unmodified-Since` (412), a
/// file gone since it was found (404, `gone`: the caller found no file there; any other
/// 404, a file it may not read, is 500), any other request it refuses (its 4xx), or a
/// file it could not read (500). `None` for a file served.
fn serve_file_error<B>(
    response: &Response<B>,
    name: &str,
    gone: bool,
    asked: Option<&str>,
) -> Option<Response> {
    let status = response.status();
    if !(status.is_client_error() || status.is_server_error()) {
        return None;
    }
    let error = match status {
        StatusCode::RANGE_NOT_SATISFIABLE => {
            let length = response
                .headers()
                .get(header::CONTENT_RANGE)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.strip_prefix("bytes */"))
                .unwrap_or("?");
            ApiError::new(
                status,
                "range-not-satisfiable",
                format!(
                    "the Range header `{}` asks for no one range of `{name}`, which holds {length} bytes (a \
                     range past its end, one that does not parse, or several, which are not served): ask \
                     for one `bytes=first-last` within them, or leave Range out for the whole file",
                    asked.unwrap_or_default().chars().take(100).collect::<String>()
                ),
            )
        }
        StatusCode::PRECONDITION_FAILED => ApiError::new(
            status,
            "precondition-failed",
            format!("`{name}` has changed since the If-Unmodified-Since time: download it again whole"),
        ),
        StatusCode::NOT_FOUND if gone => ApiError::new(
            status,
            "file-not-ready",
            format!("`{name}` is gone from the run since it was asked for; ask again"),
        ),
        s if s.is_client_error() && s != StatusCode::NOT_FOUND => ApiError::new(
            s,
            "bad-request",
            format!("`{name}` could not be served as the request asks ({s})"),
        ),
        _ => ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "storage",
            format!("`{name}` could not be read from the run directory ({status})"),
        ),
    };
    let mut refused = error.into_response();
    if let Some(range) = response.headers().get(header::CONTENT_RANGE) {
        refused.headers_mut().insert(header::CONTENT_RANGE, range.clone());
    }
    Some(refused)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::PipelineError;
    use std::error::Error as _;
    use std::path::PathBuf;
    use std::time::Duration;

    fn io(kind: std::io::ErrorKind) -> std::io::Error {
        std::io::Error::new(kind, "disk says no")
    }

    /// The e-stop's threads keep the priority of the thread that started the spawner,
    /// not the lowered one of the API thread that asks for them.
    #[test]
    fn the_estops_threads_keep_the_instruments_priority() {
        if !cfg!(target_os = "linux") {
            return;
        }
        let instrument = crate::priority::current_nice();
        start_own_threads().unwrap();
        let (api, estop) = std::thread::spawn(|| {
            crate::priority::lower_current_thread(crate::priority::current_nice() + 5).unwrap();
            let rt = tokio::runtime::Builder::new_current_thread().build().unwrap();
            let estop = rt.block_on(own_thread(
                "test-estop",
                &ESTOP_SLOTS,
                crate::priority::current_nice,
            ));
            (crate::priority::current_nice(), estop)
        })
        .join()
        .unwrap();
        assert_eq!(api, instrument + 5);
        assert_eq!(
            estop,
            Some(instrument),
            "the e-stop's thread ran at the API's priority"
        );
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

    /// A request the timeout layer cuts off is answered as every other error is: JSON
    /// `request-timeout` naming the key (until 2026-12-06 a bare 408 with no body);
    /// a 408 that is already JSON (an import's `upload-stalled`) is left as it is.
    #[test]
    fn a_request_timeout_is_a_json_error() {
        use tower::ServiceExt as _;
        let slow = Router::new()
            .route(
                "/slow",
                get(|| async {
                    tokio::time::sleep(Duration::from_secs(5)).await;
                    "late"
                }),
            )
            .route(
                "/stalled",
                get(|| async { ApiError::new(StatusCode::REQUEST_TIMEOUT, "upload-stalled", "no bytes") }),
            )
            .layer(tower_http::timeout::TimeoutLayer::with_status_code(
                StatusCode::REQUEST_TIMEOUT,
                Duration::from_millis(20),
            ))
            .layer(middleware::map_response(timeout_as_json));
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        for (uri, code) in [("/slow", "request-timeout"), ("/stalled", "upload-stalled")] {
            let res = rt
                .block_on(
                    slow.clone().oneshot(
                        axum::http::Request::get(uri)
                            .body(axum::body::Body::empty())
                            .unwrap(),
                    ),
                )
                .unwrap();
            assert_eq!(res.status(), StatusCode::REQUEST_TIMEOUT);
            let body = rt
                .block_on(axum::body::to_bytes(res.into_body(), 1 << 16))
                .unwrap();
            let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
            assert_eq!(v["error"], code, "{v}");
            if code == "request-timeout" {
                assert!(
                    v["message"].as_str().unwrap().contains("request-timeout-s"),
                    "{v}"
                );
            }
        }
    }
}

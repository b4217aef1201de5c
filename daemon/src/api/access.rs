//! The API's side of roles, keys and the audit trail: which role each route needs, the
//! middleware that authenticates a request's key and records what it changed, the
//! latency and error metrics of every request, and the key and audit endpoints.
//! `crate::access` holds the roles and keys themselves; `docs/api.md` the matrix.
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use super::{PathParams, QueryParams};
use axum::extract::{ConnectInfo, MatchedPath, Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::{ApiError, ApiResult, AppState, ErrorBody, ErrorMessage, blocking, status};
use crate::access::{AuthError, Identity, KeyRecord, Role};
use crate::catalogue::{AuditEntry, AuditPage, AuditQuery};

/// Who made a request, as the handlers see it (a request extension).
#[derive(Clone, Debug)]
pub struct Caller {
    /// The key's name, or `loopback` / `open-reads` for a keyless read.
    pub name: String,
    /// Its role.
    pub role: Role,
    /// The client's address.
    pub peer: Option<SocketAddr>,
}

/// Failed authentications recorded in the audit trail per minute, and per hour; the
/// rest are counted and the count recorded with the next one, so a flood of bad keys
/// cannot grow the trail without bound (a day of it: at most 2,880 entries, where 30
/// a minute alone allowed 43,200).
const AUTH_AUDIT_PER_MINUTE: u32 = 30;
const AUTH_AUDIT_PER_HOUR: u32 = 120;

/// The rate limit on recording failed authentications.
#[derive(Default)]
pub struct AuthAuditLimit {
    minute: Option<Instant>,
    in_minute: u32,
    hour: Option<Instant>,
    in_hour: u32,
    suppressed: u64,
}

impl AuthAuditLimit {
    /// Whether a refusal at `now` is recorded: `Some(n)`, with the `n` refusals left
    /// unrecorded since the last one that was; `None` (counted) past either cap.
    fn admit(&mut self, now: Instant) -> Option<u64> {
        let renew = |start: &mut Option<Instant>, count: &mut u32, span: Duration| {
            if start.is_none_or(|w| now.duration_since(w) >= span) {
                *start = Some(now);
                *count = 0;
            }
        };
        renew(&mut self.minute, &mut self.in_minute, Duration::from_secs(60));
        renew(&mut self.hour, &mut self.in_hour, Duration::from_secs(3600));
        if self.in_minute < AUTH_AUDIT_PER_MINUTE && self.in_hour < AUTH_AUDIT_PER_HOUR {
            self.in_minute += 1;
            self.in_hour += 1;
            Some(std::mem::take(&mut self.suppressed))
        } else {
            self.suppressed += 1;
            None
        }
    }
}

/// The role a route needs, by method and route template: `None` for the dashboard's
/// static files (they hold no instrument data).
pub fn required_role(method: &Method, route: &str) -> Option<Role> {
    if super::dashboard::is_static(route) {
        return None;
    }
    let read = method == Method::GET || method == Method::HEAD;
    let admin = route.starts_with("/api/v1/keys") || route.starts_with("/api/v1/queue") && !read;
    if admin {
        return Some(Role::Admin);
    }
    // Any key may e-stop, and may ask what it is (the dashboard shows whether its
    // e-stop is armed).
    if route == "/api/v1/estop" || route == "/api/v1/whoami" {
        return Some(Role::Estop);
    }
    if read || route == "/api/v1/check" {
        return Some(Role::Observer);
    }
    Some(Role::Operator)
}

/// What a changing request is called in the audit trail.
fn action(method: &Method, route: &str) -> Option<&'static str> {
    Some(match (method.as_str(), route) {
        ("POST", "/api/v1/runs") => "submit",
        ("POST", "/api/v1/imports") => "import",
        ("POST", "/api/v1/runs/batch") => "submit-batch",
        ("POST", "/api/v1/runs/{id}/pause") => "pause",
        ("POST", "/api/v1/runs/{id}/resume") => "resume",
        ("POST", "/api/v1/runs/{id}/abort") => "abort",
        ("POST", "/api/v1/runs/{id}/again") => "again",
        ("PATCH", "/api/v1/runs/{id}") => "annotate",
        ("POST", "/api/v1/estop") => "estop",
        ("PUT", "/api/v1/queue") => "queue-order",
        ("POST", "/api/v1/queue/move") => "queue-move",
        ("POST", "/api/v1/queue/lock") => "queue-lock",
        ("POST", "/api/v1/queue/unlock") => "queue-unlock",
        ("POST", "/api/v1/keys") => "key-create",
        ("DELETE", "/api/v1/keys/{name}") => "key-revoke",
        _ => return None,
    })
}

/// The path segment a route template's `{…}` parameter matched.
fn path_target(route: &str, path: &str) -> Option<String> {
    route
        .split('/')
        .zip(path.split('/'))
        .find(|(t, _)| t.starts_with('{'))
        .map(|(_, v)| v.to_owned())
}

/// The secret of an `Authorization: Bearer …` header (the scheme is case-insensitive,
/// RFC 9110 §11.1), or `Err` for an Authorization header of another shape.
fn bearer(headers: &HeaderMap) -> Result<Option<&str>, ()> {
    let Some(v) = headers.get(header::AUTHORIZATION) else {
        return Ok(None);
    };
    v.to_str()
        .ok()
        .and_then(|v| v.trim_start().split_once(' '))
        .filter(|(scheme, _)| scheme.eq_ignore_ascii_case("bearer"))
        .map(|(_, t)| Some(t.trim()))
        .ok_or(())
}

/// Whether a request comes from this machine: a loopback peer, whether the socket
/// reports it as IPv4 or, on a dual-stack listener (`[::]`), as the IPv4-mapped
/// `::ffff:127.0.0.1`. Requests built in-process (router tests) carry no peer and
/// count as loopback.
fn is_local(peer: Option<SocketAddr>) -> bool {
    peer.is_none_or(|p| p.ip().to_canonical().is_loopback())
}

/// Authenticates and authorises every request (see `crate::access` for the roles),
/// and records changing requests, e-stops and failed authentications in the audit
/// trail.
pub(super) async fn authorise(State(state): State<AppState>, mut req: Request, next: Next) -> Response {
    let peer = req.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0);
    let local = is_local(peer);
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| req.uri().path().to_owned(), |m| m.as_str().to_owned());
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let Some(need) = required_role(&method, &route) else {
        return next.run(req).await;
    };
    let service = Arc::clone(&state.service);
    let audited = action(&method, &route);
    // The e-stop's key check and audit entry run on threads of their own, never
    // queued behind the blocking pool (`super::own_thread`).
    let estop = route == "/api/v1/estop";
    // A refused authentication: recorded as `authenticate` with the route in the
    // detail (kept short: at most 30 a minute are recorded one by one).
    let refuse = |e: ApiError, actor: &str, why: String| {
        let request = crate::catalogue::audit::cut(format!("{method} {path}"), 200);
        let entry = AuditEntry::new(actor, "none", "authenticate", Some(&route), "refused")
            .detail(format!("{request}: {why}"))
            .peer(peer);
        (e, entry)
    };
    let given = match bearer(req.headers()) {
        Ok(g) => g,
        Err(()) => {
            let (e, entry) = refuse(
                ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    "the Authorization header must be `Bearer <key>`",
                ),
                "unknown",
                "malformed Authorization header".into(),
            );
            return refused(&state, e, entry).await;
        }
    };
    // The key of an authenticated request, for event streams to check again.
    let mut stream_key: Option<String> = None;
    // A loopback e-stop's refused key, recorded once the laser is off (the audit
    // writes and syncs a file and waits for the catalogue's lock).
    let mut late_refusal: Option<AuditEntry> = None;
    let checked = match check_key(&service, given, need >= Role::Operator, estop, local).await {
        Ok(c) => c,
        Err(e) => return e.into_response(),
    };
    let caller = match (given, checked.who) {
        _ if checked.no_keys => {
            return ApiError::new(
                StatusCode::FORBIDDEN,
                "no-token-configured",
                "this daemon has no API token or key: set PERISCOPE_TOKEN or [api] token, or make a key with `periscope keys create`, and restart it",
            )
            .into_response();
        }
        (Some(secret), Some(who)) => match who {
            Ok(Identity { name, role }) => {
                stream_key = Some(secret.to_owned());
                Caller { name, role, peer }
            }
            // The e-stop from the instrument's own computer works whatever key the
            // page sends (a revoked or expired one, a typo): stopping needs none there.
            // The refused key is still recorded.
            Err(e) if local && need == Role::Estop && route == "/api/v1/estop" => {
                let (_, entry) = refuse(
                    ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", ""),
                    "unknown",
                    format!("{e}; the e-stop went ahead as loopback"),
                );
                late_refusal = Some(entry);
                Caller {
                    name: "loopback".into(),
                    role: Role::Observer,
                    peer,
                }
            }
            Err(e) => {
                let actor = match &e {
                    AuthError::Expired(n) | AuthError::Revoked(n) => n.clone(),
                    AuthError::Unknown => "unknown".into(),
                };
                let message = match &e {
                    AuthError::Unknown => {
                        "the bearer key is wrong: it is not the daemon's token nor a key it knows".to_owned()
                    }
                    other => other.to_string(),
                };
                let (e, entry) = refuse(
                    ApiError::new(StatusCode::UNAUTHORIZED, "unauthorized", message),
                    &actor,
                    e.to_string(),
                );
                return refused(&state, e, entry).await;
            }
        },
        // Loopback reads and e-stops need no key: whoever is at the instrument's
        // computer can see it and stop it (docs/safety.md).
        (None, _) if local && need <= Role::Observer => Caller {
            name: "loopback".into(),
            role: Role::Observer,
            peer,
        },
        (None, _) if need == Role::Observer && service.instrument().api.open_reads => Caller {
            name: "open-reads".into(),
            role: Role::Observer,
            peer,
        },
        // A key given is always checked (`check_key`), so `who` is there.
        (Some(_), None) | (None, _) => {
            let (e, entry) = refuse(
                ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    format!(
                        "this request needs `Authorization: Bearer <key>` with a key of role {} or above (the daemon's PERISCOPE_TOKEN, or a key from `periscope keys create`)",
                        need.name()
                    ),
                ),
                "unknown",
                "no key".into(),
            );
            return refused(&state, e, entry).await;
        }
    };
    if caller.role < need {
        let e = ApiError::new(
            StatusCode::FORBIDDEN,
            "forbidden-role",
            format!(
                "key `{}` has role {}; this request needs {} (ask an admin for a key with that role)",
                caller.name,
                caller.role.name(),
                need.name()
            ),
        );
        let entry = AuditEntry::new(
            &caller.name,
            caller.role.name(),
            audited.unwrap_or("authorise"),
            Some(&route),
            "refused",
        )
        .detail(format!(
            "{method} {path}: role {} < {}",
            caller.role.name(),
            need.name()
        ))
        .peer(peer);
        // A read refused for its role is not recorded (a wall panel's e-stop key
        // polling the status would fill the trail); a refused change is, rate-limited.
        state.service.metrics().role_refused();
        if audited.is_some() {
            return record_refusal(&state, e, entry).await;
        }
        return e.into_response();
    }
    let target = path_target(&route, &path);
    req.extensions_mut().insert(caller.clone());
    let mut response = next.run(req).await;
    if let Some(entry) = late_refusal {
        record(&state, entry, estop).await;
    }
    let streaming = response
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"text/event-stream"));
    if streaming && let Some(secret) = stream_key {
        response = end_when_key_lapses(response, Arc::clone(&state.service), secret);
    }
    if let Some(action) = audited {
        let outcome = match response.status() {
            s if s.is_success() => "ok",
            s if s.is_client_error() => "refused",
            _ => "failed",
        };
        // A new run's id is in Location.
        let target = target
            .or_else(|| {
                response
                    .headers()
                    .get(header::LOCATION)
                    .and_then(|l| l.to_str().ok())
                    .and_then(|l| l.rsplit('/').next())
                    .map(str::to_owned)
            })
            .or_else(|| response.extensions().get::<AuditTarget>().map(|t| t.0.clone()));
        let mut entry = AuditEntry::new(
            &caller.name,
            caller.role.name(),
            action,
            target.as_deref(),
            outcome,
        )
        .peer(caller.peer);
        if let Some(ErrorMessage(m)) = response.extensions().get::<ErrorMessage>() {
            entry = entry.detail(m.clone());
        } else if let Some(AuditDetail(d)) = response.extensions().get::<AuditDetail>() {
            entry = entry.detail(d.clone());
        }
        record(&state, entry, estop).await;
    }
    response
}

/// How often an event stream opened with a key checks the key again.
const KEY_RECHECK: Duration = Duration::from_secs(2);

/// An event stream opened with a key ends when the key stops working (revoked,
/// expired, its file damaged): it was authorised once, at its start, and may run for
/// hours. The check runs beside the stream, not in front of it: the stream's events
/// are taken only as the client reads them, so a client that stops reading holds no
/// more than the display budget lets the service keep (a task that forwarded them
/// held 16 more a stream, outside the budget, until 2026-12-08).
fn end_when_key_lapses(
    response: Response,
    service: Arc<crate::service::Service>,
    secret: String,
) -> Response {
    use tokio_stream::StreamExt as _;
    enum Next {
        Chunk(Result<axum::body::Bytes, axum::Error>),
        End,
    }
    let (parts, body) = response.into_parts();
    let data = body
        .into_data_stream()
        .map(Next::Chunk)
        .chain(tokio_stream::once(Next::End));
    let lapsed = tokio_stream::once(()).then(move |()| {
        let (service, secret) = (Arc::clone(&service), secret.clone());
        async move {
            let mut check = tokio::time::interval(KEY_RECHECK);
            check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            check.tick().await;
            loop {
                check.tick().await;
                // A check the busy blocking pool holds past the request timeout is tried
                // again at the next tick.
                if let Ok(KeyCheck {
                    who: Some(Err(e)), ..
                }) = check_key(&service, Some(&secret), false, false, false).await
                {
                    tracing::info!("an event stream ends: {e}");
                    return Next::End;
                }
            }
        }
    });
    let stream = data.merge(lapsed).map_while(|next| match next {
        Next::Chunk(c) => Some(c),
        Next::End => None,
    });
    Response::from_parts(parts, axum::body::Body::from_stream(stream))
}

/// What the key store says of a request's key.
struct KeyCheck {
    /// The daemon accepts no key at all (no token, no key in `keys.json`); asked only
    /// where the route needs an operator or more.
    no_keys: bool,
    /// Who holds the key given, where one was.
    who: Option<Result<Identity, AuthError>>,
}

/// Asks the key store about `secret`. The daemon's token is answered at once, on this
/// thread: it reads no file. A key from `keys.json` (which is read again when it
/// changes) and whether any key exists (`need_any`) are asked on the blocking pool, or
/// for an e-stop on a thread of its own. The check runs before the request timeout's
/// layer, so it has a timeout of its own, the same `[api] request-timeout-s`: a check
/// still waiting for the pool then is answered with the same JSON `request-timeout`,
/// instead of holding the request for as long as the pool stays busy.
async fn check_key(
    service: &Arc<crate::service::Service>,
    secret: Option<&str>,
    need_any: bool,
    estop: bool,
    local: bool,
) -> Result<KeyCheck, ApiError> {
    let keys = service.keys();
    if let Some(id) = secret.and_then(|s| keys.token_identity(s)) {
        return Ok(KeyCheck {
            no_keys: false,
            who: Some(Ok(id)),
        });
    }
    if secret.is_none() && (!need_any || keys.has_token()) {
        return Ok(KeyCheck {
            no_keys: false,
            who: None,
        });
    }
    let unknown = KeyCheck {
        no_keys: false,
        who: secret.map(|_| Err(AuthError::Unknown)),
    };
    let s = Arc::clone(service);
    let secret = secret.map(str::to_owned);
    let check = move || {
        let keys = s.keys();
        KeyCheck {
            no_keys: need_any && !keys.any(),
            who: secret.map(|x| keys.authenticate(&x, crate::run_dir::unix_now())),
        }
    };
    if estop {
        // Bounded: a check stuck reading keys.json (a stalled disk) held every later
        // keyed e-stop, which never reached the laser. From this machine the e-stop
        // then goes ahead as loopback (its key is recorded as refused); from another,
        // the caller is told to stop the instrument another way.
        return match tokio::time::timeout(ESTOP_KEY_WAIT, super::estop_key_check(check)).await {
            Ok(checked) => Ok(checked.unwrap_or(unknown)),
            Err(_) if local => Ok(unknown),
            Err(_) => Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                "key-check-timeout",
                "the e-stop's key could not be checked within 2 s (the keys file is not being read): nothing was done; stop the instrument at its own computer or with the hardware e-stop",
            )),
        };
    }
    let limit = service.instrument().api.request_timeout;
    match tokio::time::timeout(limit, tokio::task::spawn_blocking(check)).await {
        Ok(checked) => Ok(checked.unwrap_or(unknown)),
        Err(_) => Err(ApiError::new(
            StatusCode::REQUEST_TIMEOUT,
            "request-timeout",
            "the key check waited longer than the daemon allows ([api] request-timeout-s) for a free worker: the daemon is busy, and nothing was done; try again",
        )),
    }
}

/// The longest an e-stop waits for its key to be checked ([`check_key`]).
const ESTOP_KEY_WAIT: std::time::Duration = std::time::Duration::from_secs(2);

/// What a successful changing request did, for its audit entry (a response
/// extension handlers may set).
#[derive(Clone, Debug)]
pub(super) struct AuditDetail(pub String);

/// What a successful changing request acted on, where its path does not name it (a
/// key made, a run moved in the queue): its audit entry's target, so that `target=`
/// finds it (a response extension handlers may set).
#[derive(Clone, Debug)]
pub(super) struct AuditTarget(pub String);

/// Answers a refused authentication, recording it (rate-limited).
async fn refused(state: &AppState, e: ApiError, entry: AuditEntry) -> Response {
    state.service.metrics().auth_failed();
    record_refusal(state, e, entry).await
}

/// Answers a request refused for its `Host` or `Origin` before any key is read
/// (`super::check_host`): a changing one (an e-stop or a submission from a cross-site
/// page, say) is recorded as its action, refused, under the same rate limit as failed
/// authentications, so a flood of them writes no more; reads are not recorded.
pub(super) async fn refused_for_its_host(
    state: &AppState,
    entry: Option<AuditEntry>,
    e: ApiError,
) -> Response {
    match entry {
        Some(entry) => record_refusal(state, e, entry).await,
        None => e.into_response(),
    }
}

/// The audit entry of a request refused for its `Host` or `Origin`
/// ([`refused_for_its_host`]): `None` for a request that changes nothing.
pub(super) fn host_refusal_entry(req: &Request, why: &str) -> Option<AuditEntry> {
    let method = req.method();
    let path = req.uri().path();
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or_else(|| path.to_owned(), |m| m.as_str().to_owned());
    let action = action(method, &route)?;
    let peer = req.extensions().get::<ConnectInfo<SocketAddr>>().map(|c| c.0);
    let request = crate::catalogue::audit::cut(format!("{method} {path}"), 200);
    Some(
        AuditEntry::new(
            "unknown",
            "none",
            action,
            path_target(&route, path).as_deref(),
            "refused",
        )
        .detail(format!("{request}: {why}"))
        .peer(peer),
    )
}

/// Records a refusal's entry if the rate limit admits it, then answers.
async fn record_refusal(state: &AppState, e: ApiError, entry: AuditEntry) -> Response {
    let admitted = state
        .auth_audit
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .admit(Instant::now());
    let entry = admitted.map(|suppressed| {
        if suppressed > 0 {
            let d = entry.detail.clone().unwrap_or_default();
            entry.detail(format!(
                "{d} (and {suppressed} more refused requests not recorded one by one)"
            ))
        } else {
            entry
        }
    });
    if let Some(entry) = entry {
        record(state, entry, false).await;
    }
    e.into_response()
}

/// How long an e-stop's answer waits for its audit entry: the laser is off by then,
/// and an operator waiting for the report of a stop may press again.
const ESTOP_AUDIT_WAIT: Duration = Duration::from_secs(1);

/// Records an audit entry on the blocking pool (it is flushed to disk), and the
/// response waits for it. An e-stop's (`estop`) goes on a thread of its own, of the
/// e-stop audit's slots, and its response waits at most [`ESTOP_AUDIT_WAIT`]: a
/// catalogue another process holds delays the entry, not the report that the laser is
/// off. The entry is written all the same once the catalogue lets it.
async fn record(state: &AppState, entry: AuditEntry, estop: bool) {
    let s = Arc::clone(&state.service);
    if estop {
        let written = tokio::spawn(super::own_thread(
            "periscope-estop-audit",
            &super::ESTOP_AUDIT_SLOTS,
            move || s.audit(entry),
        ));
        let _ = tokio::time::timeout(ESTOP_AUDIT_WAIT, written).await;
        return;
    }
    let _ = tokio::task::spawn_blocking(move || s.audit(entry)).await;
}

/// Records each request's latency and, for statuses of 400 and above, an error, by
/// method and route template.
pub(super) async fn track(State(state): State<AppState>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map_or("unmatched", |m| m.as_str())
        .to_owned();
    // Methods from a closed list: a client inventing methods must not add series.
    let method = match *req.method() {
        Method::GET => "GET",
        Method::HEAD => "HEAD",
        Method::POST => "POST",
        Method::PUT => "PUT",
        Method::PATCH => "PATCH",
        Method::DELETE => "DELETE",
        Method::OPTIONS => "OPTIONS",
        _ => "other",
    };
    let t = Instant::now();
    let response = next.run(req).await;
    state.service.metrics().request(
        method,
        &route,
        response.status().as_u16(),
        t.elapsed().as_secs_f64(),
    );
    response
}

/// The shared mutex type of [`AuthAuditLimit`].
pub type AuthAuditState = Arc<Mutex<AuthAuditLimit>>;

/// `GET /api/v1/whoami`.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct WhoAmI {
    /// The key's name (`loopback` without a key from this machine).
    pub name: String,
    /// Its role.
    pub role: Role,
}

/// Who this request is from, and what it may do
#[utoipa::path(get, path = "/api/v1/whoami", responses((status = 200, description = "the caller", body = WhoAmI), (status = 401, description = status::UNAUTHORISED, body = ErrorBody)))]
pub(super) async fn whoami(axum::Extension(caller): axum::Extension<Caller>) -> axum::Json<WhoAmI> {
    axum::Json(WhoAmI {
        name: caller.name,
        role: caller.role,
    })
}

/// A key as the API shows it: without its digest.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct KeyView {
    /// Name.
    pub name: String,
    /// Role.
    pub role: Role,
    /// Made (Unix seconds).
    pub created_unix_s: f64,
    /// By.
    pub created_by: String,
    /// Expires (Unix seconds).
    pub expires_unix_s: Option<f64>,
    /// Revoked (Unix seconds).
    pub revoked_unix_s: Option<f64>,
}

impl From<KeyRecord> for KeyView {
    fn from(k: KeyRecord) -> KeyView {
        KeyView {
            name: k.name,
            role: k.role,
            created_unix_s: k.created_unix_s,
            created_by: k.created_by,
            expires_unix_s: k.expires_unix_s,
            revoked_unix_s: k.revoked_unix_s,
        }
    }
}

/// The API keys (admin)
#[utoipa::path(get, path = "/api/v1/keys", security(("bearer" = [])), responses((status = 200, description = "keys, without their secrets or digests", body = Vec<KeyView>), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody)))]
pub(super) async fn keys_list(State(state): State<AppState>) -> ApiResult<axum::Json<Vec<KeyView>>> {
    let s = Arc::clone(&state.service);
    blocking(move || Ok(s.keys().keys().into_iter().map(KeyView::from).collect()))
        .await
        .map(axum::Json)
}

/// `POST /api/v1/keys`. An unknown field is refused: a misspelt `expires` would
/// otherwise make a key that never expires.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct NewKey {
    /// Name (1–64 letters, digits, `-`, `_`, `.`, `@`).
    pub name: String,
    /// Role: estop, observer, operator or admin.
    pub role: String,
    /// Expiry: a duration (`90d`, `12h`) or a time (`2027-01-31`); none if absent.
    pub expires: Option<String>,
}

/// A new key and its secret (shown once).
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct CreatedKey {
    /// The key.
    pub key: KeyView,
    /// Its secret: send it as `Authorization: Bearer <secret>`. Not stored; not shown again.
    pub secret: String,
}

/// Make an API key (admin)
#[utoipa::path(post, path = "/api/v1/keys", security(("bearer" = [])), request_body = NewKey, responses((status = 201, description = "made", body = CreatedKey), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 422, description = "bad name, role or expiry", body = ErrorBody), (status = 500, description = "the keys file could not be read or written", body = ErrorBody)))]
pub(super) async fn keys_create(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<Caller>,
    body: super::JsonBody<NewKey>,
) -> ApiResult<Response> {
    let NewKey { name, role, expires } = body.0;
    let s = Arc::clone(&state.service);
    let created = blocking(move || {
        let role = Role::parse(&role).map_err(crate::service::ServiceError::Invalid)?;
        let expires = expires
            .map(|e| crate::access::parse_expiry(&e, crate::run_dir::unix_now()))
            .transpose()
            .map_err(crate::service::ServiceError::Invalid)?;
        s.keys()
            .create(&name, role, expires, &caller.name)
            .map_err(crate::service::ServiceError::from)
    })
    .await?;
    let detail = format!("role {}", created.0.role.name());
    let target = created.0.name.clone();
    let mut r = (
        StatusCode::CREATED,
        axum::Json(CreatedKey {
            key: created.0.into(),
            secret: created.1,
        }),
    )
        .into_response();
    r.extensions_mut()
        .insert(AuditDetail(format!("{target}: {detail}")));
    r.extensions_mut().insert(AuditTarget(target));
    Ok(r)
}

/// Revoke an API key (admin)
#[utoipa::path(delete, path = "/api/v1/keys/{name}", security(("bearer" = [])), params(("name" = String, Path, description = "key name")), responses((status = 200, description = "revoked", body = KeyView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 422, description = "no such key", body = ErrorBody), (status = 500, description = "the keys file could not be read or written", body = ErrorBody)))]
pub(super) async fn keys_revoke(
    State(state): State<AppState>,
    PathParams(name): PathParams<String>,
) -> ApiResult<axum::Json<KeyView>> {
    let s = Arc::clone(&state.service);
    blocking(move || {
        s.keys()
            .revoke(&name)
            .map(KeyView::from)
            .map_err(crate::service::ServiceError::from)
    })
    .await
    .map(axum::Json)
}

/// `GET /api/v1/audit`'s filters.
#[derive(Debug, Default, serde::Deserialize, utoipa::IntoParams)]
// A misspelt filter (`stat=paused`) is refused, not ignored: it would answer with
// every run as if it had matched.
#[serde(deny_unknown_fields)]
pub struct AuditParams {
    /// At or after (RFC 3339 time or date).
    pub since: Option<String>,
    /// Before (RFC 3339 time or date).
    pub until: Option<String>,
    /// By this actor (key name).
    pub actor: Option<String>,
    /// This action (`submit`, `abort`, `estop`, `authenticate`, ...).
    pub action: Option<String>,
    /// On this run id or key name.
    pub target: Option<String>,
    /// Entries per page (1–1000, default 100).
    pub limit: Option<usize>,
    /// Entries skipped.
    pub offset: Option<usize>,
}

/// The audit trail, newest first
///
/// Who submitted, paused, resumed, aborted, e-stopped, reordered or locked the queue,
/// made or revoked keys, and every refused authentication (at most 30 a minute one by
/// one, the rest counted).
#[utoipa::path(get, path = "/api/v1/audit", params(AuditParams), responses((status = 200, description = "entries", body = AuditPage), (status = 400, description = "bad filter", body = ErrorBody)))]
pub(super) async fn audit(
    State(state): State<AppState>,
    QueryParams(p): QueryParams<AuditParams>,
) -> ApiResult<axum::Json<AuditPage>> {
    let time = |v: &Option<String>, field: &str| -> ApiResult<Option<f64>> {
        v.as_deref()
            .map(|t| {
                crate::access::parse_time(t)
                    .map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, "bad-query", format!("{field}: {m}")))
            })
            .transpose()
    };
    let q = AuditQuery {
        since: time(&p.since, "since")?,
        until: time(&p.until, "until")?,
        actor: p.actor,
        action: p.action,
        target: p.target,
        limit: match p.limit.unwrap_or(100) {
            l @ 1..=crate::catalogue::query::MAX_PAGE => l,
            l => {
                return Err(ApiError::new(
                    StatusCode::BAD_REQUEST,
                    "bad-query",
                    format!("limit: {l}: expected 1 to {}", crate::catalogue::query::MAX_PAGE),
                ));
            }
        },
        offset: super::catalogue::offset(p.offset)?,
    };
    q.check()
        .map_err(|(field, m)| ApiError::new(StatusCode::BAD_REQUEST, "bad-query", format!("{field}: {m}")))?;
    let s = Arc::clone(&state.service);
    blocking(move || {
        s.catalogue()
            .audit(&q)
            .map_err(crate::service::ServiceError::Catalogue)
    })
    .await
    .map(axum::Json)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `HEAD` reads as a `GET` does: the queue's order is an observer's to read,
    /// whatever the method; changing it, and anything of the keys, is an admin's.
    #[test]
    fn head_needs_what_get_needs() {
        for method in [Method::GET, Method::HEAD] {
            assert_eq!(required_role(&method, "/api/v1/queue"), Some(Role::Observer));
            assert_eq!(required_role(&method, "/api/v1/runs"), Some(Role::Observer));
            assert_eq!(required_role(&method, "/api/v1/keys"), Some(Role::Admin));
        }
        assert_eq!(required_role(&Method::PUT, "/api/v1/queue"), Some(Role::Admin));
        assert_eq!(
            required_role(&Method::POST, "/api/v1/queue/lock"),
            Some(Role::Admin)
        );
    }

    /// A key's body with a field it does not know is refused by name: `expiry` for
    /// `expires` made a key that never expires.
    #[test]
    fn a_new_keys_unknown_field_is_refused() {
        let e = serde_json::from_str::<NewKey>(r#"{"name":"k","role":"admin","expiry":"1h"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown field `expiry`"), "{e}");
        assert!(serde_json::from_str::<NewKey>(r#"{"name":"k","role":"admin","expires":"1h"}"#).is_ok());
    }

    /// Refusals are recorded 30 a minute and 120 an hour; the rest are counted into the
    /// next recorded one. A day's flood of one refusal a second records 2,880 entries
    /// (until 2026-12-06, with the minute's cap alone, 43,200), and every refusal is
    /// accounted for.
    #[test]
    fn a_flood_of_refusals_is_recorded_within_both_caps() {
        let mut limit = AuthAuditLimit::default();
        let start = Instant::now();
        let (mut recorded, mut counted) = (0u64, 0u64);
        for s in 0..86_400u64 {
            if let Some(n) = limit.admit(start + Duration::from_secs(s)) {
                recorded += 1;
                counted += n + 1;
            }
            if s == 59 {
                assert_eq!(recorded, 30, "the first minute");
            }
        }
        assert_eq!(recorded, 24 * 120);
        assert_eq!(counted + limit.suppressed, 86_400);
    }
}

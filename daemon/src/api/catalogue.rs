//! The run catalogue, the queue's operations and the metrics over HTTP: runs filtered,
//! sorted and paged; tags and notes; batch submit and run-again; the queue's order and
//! maintenance lock; `GET /metrics` for Prometheus.
use std::sync::Arc;

use super::{PathParams, QueryParams};
use axum::extract::State;
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};

use super::access::{AuditDetail, Caller};
use super::{ApiError, ApiResult, AppState, ErrorBody, JsonBody, blocking, status};
use crate::catalogue::{RunPage, RunQuery, SortKey};
use crate::run_dir::Annotations;
use crate::service::{QueueView, RunStatus, ServiceError};

/// The header that carries the queue's lock key past a maintenance lock.
pub const LOCK_KEY_HEADER: &str = "x-periscope-lock-key";

/// The filters, sort and page of `GET /api/v1/runs` and `GET /api/v1/catalogue`.
#[derive(Debug, Default, serde::Deserialize, utoipa::IntoParams)]
// A misspelt filter (`stat=paused`) is refused, not ignored: it would answer with
// every run as if it had matched.
#[serde(deny_unknown_fields)]
pub struct RunParams {
    /// States, comma-separated (`completed,failed`).
    pub state: Option<String>,
    /// Made at or after (RFC 3339 time or date, `2026-11-01`).
    pub since: Option<String>,
    /// Made before (RFC 3339 time or date).
    pub until: Option<String>,
    /// Plan name.
    pub plan: Option<String>,
    /// Tag.
    pub tag: Option<String>,
    /// Submitted by (key name).
    pub submitted_by: Option<String>,
    /// Text in the id, plan, note, error, submitter or tags (case-insensitive).
    pub q: Option<String>,
    /// Sort key: created (default), id, plan, state, updated, pairs.
    pub sort: Option<String>,
    /// `asc` (default) or `desc`.
    pub order: Option<String>,
    /// Rows per page, 1–1000 (default 1000).
    pub limit: Option<usize>,
    /// Rows skipped.
    pub offset: Option<usize>,
}

fn bad(field: &str, m: impl std::fmt::Display) -> ApiError {
    ApiError::new(StatusCode::BAD_REQUEST, "bad-query", format!("{field}: {m}"))
}

/// A page's `offset` (default 0), at most what the catalogue's SQL takes (an `i64`).
pub(super) fn offset(v: Option<usize>) -> ApiResult<usize> {
    let offset = v.unwrap_or(0);
    if i64::try_from(offset).is_err() {
        return Err(bad("offset", format!("{offset}: expected 0 to {}", i64::MAX)));
    }
    Ok(offset)
}

impl RunParams {
    /// The catalogue query these parameters ask for.
    pub fn query(&self) -> ApiResult<RunQuery> {
        let time = |v: &Option<String>, field: &str| -> ApiResult<Option<f64>> {
            v.as_deref()
                .map(|t| crate::access::parse_time(t).map_err(|m| bad(field, m)))
                .transpose()
        };
        let states = match &self.state {
            Some(s) => s
                .split(',')
                .map(str::trim)
                .filter(|s| !s.is_empty())
                .map(|s| crate::run_dir::parse_state(s).map_err(|m| bad("state", m)))
                .collect::<ApiResult<Vec<_>>>()?,
            None => Vec::new(),
        };
        let q = RunQuery {
            states,
            since: time(&self.since, "since")?,
            until: time(&self.until, "until")?,
            plan: self.plan.clone(),
            tag: self.tag.clone(),
            submitted_by: self.submitted_by.clone(),
            text: self.q.clone(),
            sort: self
                .sort
                .as_deref()
                .map(SortKey::parse)
                .transpose()
                .map_err(|m| bad("sort", m))?
                .unwrap_or_default(),
            descending: match self.order.as_deref() {
                None | Some("asc") => false,
                Some("desc") => true,
                Some(o) => return Err(bad("order", format!("`{o}`: expected asc or desc"))),
            },
            limit: self.limit.unwrap_or(crate::catalogue::query::MAX_PAGE),
            offset: self.offset.unwrap_or(0),
        };
        q.check().map_err(|(field, m)| bad(field, m))?;
        Ok(q)
    }
}

/// Runs from the catalogue, oldest first unless sorted otherwise
///
/// Filtered (state, dates, plan, tag, submitter, text), sorted and paged; the total
/// matching is in `X-Total-Count`. Queued and running runs carry their live progress.
#[utoipa::path(get, path = "/api/v1/runs", params(RunParams), responses((status = 200, description = "runs; `X-Total-Count` has the number matching in all pages", body = Vec<RunStatus>), (status = 400, description = "bad filter", body = ErrorBody)))]
pub(super) async fn list(
    State(state): State<AppState>,
    QueryParams(p): QueryParams<RunParams>,
) -> ApiResult<Response> {
    let q = p.query()?;
    let s = Arc::clone(&state.service);
    let (page, statuses) = blocking(move || s.query(&q)).await?;
    let mut r = axum::Json(statuses).into_response();
    r.headers_mut()
        .insert("x-total-count", HeaderValue::from(page.total));
    Ok(r)
}

/// The run catalogue: runs with tags, note, state history, outputs and scores
#[utoipa::path(get, path = "/api/v1/catalogue", params(RunParams), responses((status = 200, description = "a page of runs", body = RunPage), (status = 400, description = "bad filter", body = ErrorBody)))]
pub(super) async fn catalogue(
    State(state): State<AppState>,
    QueryParams(p): QueryParams<RunParams>,
) -> ApiResult<axum::Json<RunPage>> {
    let q = p.query()?;
    let s = Arc::clone(&state.service);
    blocking(move || s.catalogue().query(&q).map_err(ServiceError::Catalogue))
        .await
        .map(axum::Json)
}

/// `PATCH /api/v1/runs/{id}`.
#[derive(Debug, Default, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Annotate {
    /// Tags to add.
    #[serde(default)]
    pub add_tags: Vec<String>,
    /// Tags to remove.
    #[serde(default)]
    pub remove_tags: Vec<String>,
    /// The new note (absent: unchanged).
    pub note: Option<String>,
}

/// A run's tags and note.
#[derive(Debug, serde::Serialize, utoipa::ToSchema)]
pub struct AnnotationsView {
    /// Tags.
    pub tags: Vec<String>,
    /// Note.
    pub note: String,
}

/// Tag a run and set its note (operator)
#[utoipa::path(patch, path = "/api/v1/runs/{id}", security(("bearer" = [])), params(("id" = String, Path, description = "run id")), request_body = Annotate, responses((status = 200, description = "the run's tags and note", body = AnnotationsView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 404, description = status::NOT_FOUND, body = ErrorBody), (status = 422, description = "a tag or note over its limits", body = ErrorBody)))]
pub(super) async fn annotate(
    State(state): State<AppState>,
    PathParams(id): PathParams<String>,
    body: JsonBody<Annotate>,
) -> ApiResult<axum::Json<AnnotationsView>> {
    let a = body.0;
    let s = Arc::clone(&state.service);
    let Annotations { tags, note } =
        blocking(move || s.annotate(&id, &a.add_tags, &a.remove_tags, a.note.as_deref())).await?;
    Ok(axum::Json(AnnotationsView { tags, note }))
}

fn lock_key(headers: &HeaderMap) -> Option<String> {
    headers
        .get(LOCK_KEY_HEADER)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned)
}

/// `POST /api/v1/runs/batch`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Batch {
    /// TOML capture plans, queued in this order.
    pub plans: Vec<String>,
}

/// Submit several plans at once (operator)
///
/// Every plan is checked first; one invalid plan (named by its place, `batch plan N`)
/// refuses the batch and queues none.
#[utoipa::path(post, path = "/api/v1/runs/batch", security(("bearer" = [])), request_body = Batch, responses((status = 201, description = "queued, in order", body = Vec<RunStatus>), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 422, description = status::INVALID_PLAN, body = ErrorBody), (status = 423, description = status::LOCKED, body = ErrorBody), (status = 429, description = status::QUEUE_FULL, body = ErrorBody)))]
pub(super) async fn batch(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<Caller>,
    headers: HeaderMap,
    body: JsonBody<Batch>,
) -> ApiResult<Response> {
    let plans = body.0.plans;
    let key = lock_key(&headers);
    let s = Arc::clone(&state.service);
    let runs = blocking(move || {
        s.check_lock(key.as_deref())?;
        s.submit_batch(plans, &caller.name)
    })
    .await?;
    let ids: Vec<&str> = runs.iter().map(|r| r.id.as_str()).collect();
    let detail = format!("queued {}", ids.join(", "));
    let mut r = (StatusCode::CREATED, axum::Json(&runs)).into_response();
    r.extensions_mut().insert(AuditDetail(detail));
    Ok(r)
}

/// Run a past run's exact plan again as a new run (operator)
#[utoipa::path(post, path = "/api/v1/runs/{id}/again", security(("bearer" = [])), params(("id" = String, Path, description = "the run to repeat")), responses((status = 201, description = "queued; Location names the new run", body = RunStatus), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 404, description = status::NOT_FOUND, body = ErrorBody), (status = 409, description = "an imported run has no plan to run again", body = ErrorBody), (status = 422, description = status::INVALID_PLAN, body = ErrorBody), (status = 423, description = status::LOCKED, body = ErrorBody), (status = 429, description = status::QUEUE_FULL, body = ErrorBody)))]
pub(super) async fn again(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<Caller>,
    headers: HeaderMap,
    PathParams(id): PathParams<String>,
) -> ApiResult<Response> {
    let key = lock_key(&headers);
    let s = Arc::clone(&state.service);
    let st = blocking(move || {
        // A run that does not exist is 404 whether or not the queue is locked.
        s.status(&id)?;
        s.check_lock(key.as_deref())?;
        s.again(&id, &caller.name)
    })
    .await?;
    let detail = format!("queued {}", st.id);
    let mut r = (StatusCode::CREATED, axum::Json(&st)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/api/v1/runs/{}", st.id)) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    r.extensions_mut().insert(AuditDetail(detail));
    Ok(r)
}

/// The queue: the running run, the waiting runs in order, the maintenance lock
#[utoipa::path(get, path = "/api/v1/queue", responses((status = 200, description = "the queue", body = QueueView)))]
pub(super) async fn queue(State(state): State<AppState>) -> ApiResult<axum::Json<QueueView>> {
    let s = Arc::clone(&state.service);
    blocking(move || Ok(s.queue())).await.map(axum::Json)
}

/// `PUT /api/v1/queue`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Order {
    /// Every waiting run's id, once, in the new order.
    pub order: Vec<String>,
}

/// Reorder the waiting runs (admin)
#[utoipa::path(put, path = "/api/v1/queue", security(("bearer" = [])), request_body = Order, responses((status = 200, description = "the new queue", body = QueueView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 422, description = "the order does not name each waiting run once", body = ErrorBody), (status = 423, description = status::LOCKED, body = ErrorBody)))]
pub(super) async fn reorder(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: JsonBody<Order>,
) -> ApiResult<axum::Json<QueueView>> {
    let order = body.0.order;
    let key = lock_key(&headers);
    let s = Arc::clone(&state.service);
    blocking(move || {
        s.check_lock(key.as_deref())?;
        s.reorder(&order)
    })
    .await
    .map(axum::Json)
}

/// `POST /api/v1/queue/move`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Move {
    /// The waiting run.
    pub run: String,
    /// Its new place among the waiting runs (0 = next).
    pub position: usize,
}

/// Move a waiting run to a place in the queue, 0 for the front (admin)
#[utoipa::path(post, path = "/api/v1/queue/move", security(("bearer" = [])), request_body = Move, responses((status = 200, description = "the new queue", body = QueueView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 409, description = "the run is not waiting", body = ErrorBody), (status = 423, description = status::LOCKED, body = ErrorBody)))]
pub(super) async fn move_run(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: JsonBody<Move>,
) -> ApiResult<Response> {
    let Move { run, position } = body.0;
    let key = lock_key(&headers);
    let s = Arc::clone(&state.service);
    let detail = format!("{run} to place {position}");
    let target = run.clone();
    let q = blocking(move || {
        s.check_lock(key.as_deref())?;
        s.move_run(&run, position)
    })
    .await?;
    let mut r = axum::Json(q).into_response();
    r.extensions_mut().insert(AuditDetail(detail));
    r.extensions_mut().insert(super::access::AuditTarget(target));
    Ok(r)
}

/// `POST /api/v1/queue/lock`.
#[derive(Debug, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Lock {
    /// Why (shown to everyone the lock refuses).
    pub reason: String,
    /// The lock key (8 characters or more): needed to unlock, and to change the queue
    /// meanwhile (header `X-Periscope-Lock-Key`).
    pub key: String,
}

/// Lock the queue for maintenance: no run starts until it is unlocked (admin)
#[utoipa::path(post, path = "/api/v1/queue/lock", security(("bearer" = [])), request_body = Lock, responses((status = 200, description = "locked", body = QueueView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 409, description = "already locked", body = ErrorBody), (status = 422, description = "lock key too short", body = ErrorBody)))]
pub(super) async fn lock(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<Caller>,
    body: JsonBody<Lock>,
) -> ApiResult<Response> {
    let Lock { reason, key } = body.0;
    let detail = reason.clone();
    let s = Arc::clone(&state.service);
    let q = blocking(move || s.lock_queue(&caller.name, &reason, &key)).await?;
    let mut r = axum::Json(q).into_response();
    r.extensions_mut().insert(AuditDetail(detail));
    Ok(r)
}

/// `POST /api/v1/queue/unlock`.
#[derive(Debug, Default, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Unlock {
    /// The key the queue was locked with.
    pub key: Option<String>,
    /// Unlock without the key (recorded in the audit trail).
    #[serde(default)]
    pub force: bool,
}

/// Unlock the queue with its key, or by force (admin)
#[utoipa::path(post, path = "/api/v1/queue/unlock", security(("bearer" = [])), request_body = Unlock, responses((status = 200, description = "unlocked", body = QueueView), (status = 401, description = status::UNAUTHORISED, body = ErrorBody), (status = 403, description = status::FORBIDDEN, body = ErrorBody), (status = 409, description = "not locked", body = ErrorBody), (status = 423, description = "wrong lock key", body = ErrorBody)))]
pub(super) async fn unlock(State(state): State<AppState>, body: JsonBody<Unlock>) -> ApiResult<Response> {
    let Unlock { key, force } = body.0;
    let s = Arc::clone(&state.service);
    let q = blocking(move || s.unlock_queue(key.as_deref(), force)).await?;
    let mut r = axum::Json(q).into_response();
    if force {
        r.extensions_mut()
            .insert(AuditDetail("forced, without the lock key".into()));
    }
    Ok(r)
}

/// Metrics in the Prometheus text format
///
/// Emission, interlock, diffuser and count rates as last read, the reading's age, the
/// capture's pair and count rates, queue length and lock, runs per state, stage and
/// reconstruction durations, request latencies and errors (`docs/metrics.md`).
#[utoipa::path(get, path = "/metrics", responses((status = 200, description = "Prometheus text format 0.0.4", content_type = "text/plain", body = String)))]
pub(super) async fn metrics(State(state): State<AppState>) -> ApiResult<Response> {
    let s = Arc::clone(&state.service);
    let text = blocking(move || Ok(s.metrics_text())).await?;
    let mut r = text.into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(crate::metrics::CONTENT_TYPE),
    );
    Ok(r)
}

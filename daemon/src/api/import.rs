//! `POST /api/v1/imports`: a capture file of any public format, uploaded as a form
//! (`multipart/form-data`, what a browser's file input sends), queued as a run that
//! reconstructs it ([`crate::service`]'s imports).
//!
//! The upload streams to disk chunk by chunk, so it never holds more than a chunk in
//! memory whatever its size; it is capped at `[api] import-limit-mib` in all, dropped
//! when no byte arrives for `[api] import-stall-s` (not by the API's request timeout:
//! a large file on a slow link may take minutes), and one import uploads at a time.
use std::sync::Arc;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use axum::body::Body;
use axum::extract::multipart::{Field, Multipart};
use axum::extract::{FromRequest, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use tokio::io::AsyncWriteExt as _;
use tokio_stream::StreamExt as _;

use super::openapi::{ErrorBody, status};
use super::{ApiError, ApiResult, AppState, access, blocking};
use crate::service::{ImportTicket, RunStatus, Upload, stored_name};

/// The form `POST /imports` takes.
#[derive(utoipa::ToSchema)]
#[allow(dead_code)]
pub(super) struct ImportForm {
    /// The capture file (`.hdf5`/`.h5`: y-tal, ZNLOS; `.mat`: Stanford LCT and f-k,
    /// phasor field), with its file name.
    #[schema(value_type = String, format = Binary)]
    capture: Vec<u8>,
    /// A file its reader looks for beside it (an f-k measurement's `tof.mat`); repeat
    /// the field for more.
    #[schema(value_type = Option<String>, format = Binary)]
    sidecar: Option<Vec<u8>>,
    /// Reconstruction settings, as a RECON.toml (docs/recon.md); without, the defaults
    /// derived for the capture.
    recon: Option<String>,
    /// The run's name; without, the capture file's stem.
    name: Option<String>,
}

/// Longest `recon` and `name` fields, bytes.
const MAX_TEXT_FIELD: usize = 1 << 20;

/// Most bytes a form may send while it is looked through for its next part: that
/// part's boundary and headers (and, before the first, the preamble), which the
/// multipart parser holds in memory until the headers end, plus the one chunk that
/// carries them in (hyper hands an HTTP/1.1 body over in chunks of at most a few
/// hundred KiB, so a legitimate part's first chunk stays under the bound).
const MAX_PART_HEAD: u64 = 1 << 20;

/// The least average rate an upload must keep once [`PACE_GRACE_STALLS`] stall
/// windows have passed, bytes a second: a client sending one byte just inside each
/// stall window would otherwise hold the one import slot for ever. A lab link of a
/// megabit a second carries eight times this.
const MIN_IMPORT_RATE: f64 = 16.0 * 1024.0;

/// Stall windows (`[api] import-stall-s`) an upload has before its average rate is
/// judged.
const PACE_GRACE_STALLS: u32 = 2;

/// The bytes the form's body delivers while the parser looks for the next part
/// ([`MAX_PART_HEAD`]): counted only while `armed`, so a file's data is not. And the
/// whole body's pace ([`MIN_IMPORT_RATE`]).
#[derive(Default)]
struct PartHead {
    armed: AtomicBool,
    seen: AtomicU64,
    /// Set once the body failed for its pace, so the answer says so.
    slow: AtomicBool,
}

impl PartHead {
    fn arm(&self, on: bool) {
        self.seen.store(0, Ordering::SeqCst);
        self.armed.store(on, Ordering::SeqCst);
    }

    /// `req`'s body, which fails once more than [`MAX_PART_HEAD`] bytes arrive while
    /// armed: the parser then reports the form malformed instead of buffering on. It
    /// also fails once, after `grace`, the body's average rate falls under
    /// [`MIN_IMPORT_RATE`] (`slow` says so).
    fn watch(self: &Arc<Self>, req: Request, grace: std::time::Duration) -> Request {
        let head = Arc::clone(self);
        let started = std::time::Instant::now();
        let mut total = 0u64;
        req.map(|body| {
            Body::from_stream(body.into_data_stream().map(move |chunk| {
                let chunk = chunk?;
                let n = chunk.len() as u64;
                total += n;
                let elapsed = started.elapsed();
                if elapsed > grace && (total as f64) < MIN_IMPORT_RATE * elapsed.as_secs_f64() {
                    head.slow.store(true, Ordering::SeqCst);
                    return Err(axum::Error::new(std::io::Error::other("the upload is too slow")));
                }
                if head.armed.load(Ordering::SeqCst) && head.seen.fetch_add(n, Ordering::SeqCst) + n > MAX_PART_HEAD {
                    return Err(axum::Error::new(std::io::Error::other(format!(
                        "more than {} KiB arrived before the next part's headers ended (a part's boundary and \
                         headers, or the preamble before the first)",
                        MAX_PART_HEAD >> 10
                    ))));
                }
                Ok(chunk)
            }))
        })
    }
}

/// Most `sidecar` files one import takes (every other field at most once, so the
/// whole form is bounded by the import limit and these).
const MAX_SIDECARS: usize = 16;

/// Import a capture file and queue its reconstruction
#[utoipa::path(
    post,
    path = "/api/v1/imports",
    security(("bearer" = [])),
    request_body(content = ImportForm, content_type = "multipart/form-data"),
    responses(
        (status = 201, description = "imported and queued", body = RunStatus),
        (status = 400, description = "not a multipart/form-data upload, an unknown field, a file without a name", body = ErrorBody),
        (status = 401, description = status::UNAUTHORISED, body = ErrorBody),
        (status = 403, description = status::FORBIDDEN, body = ErrorBody),
        (status = 408, description = "no byte arrived for `[api] import-stall-s`, or the upload averaged under 16 KiB/s after twice that", body = ErrorBody),
        (status = 413, description = "over `[api] import-limit-mib`", body = ErrorBody),
        (status = 422, description = "not a capture file, or invalid settings (`invalid-import`)", body = ErrorBody),
        (status = 500, description = status::STORAGE, body = ErrorBody),
        (status = 423, description = status::LOCKED, body = ErrorBody),
        (status = 429, description = status::QUEUE_FULL, body = ErrorBody),
        (status = 503, description = "another import is uploading", body = ErrorBody),
    )
)]
pub(super) async fn import(
    State(state): State<AppState>,
    axum::Extension(caller): axum::Extension<access::Caller>,
    headers: HeaderMap,
    req: Request,
) -> ApiResult<Response> {
    let head = Arc::new(PartHead::default());
    let api = &state.service.instrument().api;
    let grace = api.import_stall * PACE_GRACE_STALLS;
    let form = Multipart::from_request(head.watch(req, grace), &()).await;
    let limit = api.import_limit;
    let declared = headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    // The form's own bytes (boundaries, part headers, settings) come on top of the files.
    if declared.is_some_and(|n| n > limit + MAX_TEXT_FIELD as u64 * 2) {
        return Err(too_large(limit));
    }
    let mut form = form.map_err(|e| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad-body",
            format!(
                "an import is a multipart/form-data upload with the capture file in the field `capture` ({})",
                e.body_text()
            ),
        )
    })?;
    let Ok(_permit) = Arc::clone(&state.imports).try_acquire_owned() else {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "too-many-imports",
            "another import is uploading; one uploads at a time: try again when it has finished",
        ));
    };
    let key = headers
        .get(super::catalogue::LOCK_KEY_HEADER)
        .and_then(|v| v.to_str().ok())
        .map(str::to_owned);
    let s = Arc::clone(&state.service);
    let ticket = blocking(move || s.begin_import(key.as_deref())).await?;
    let stall = api.import_stall;
    let upload = match receive(&mut form, &head, &ticket, limit, stall).await {
        Ok(u) => u,
        Err(e) => {
            // What was written goes before the answer does.
            let _ = tokio::task::spawn_blocking(move || ticket.discard()).await;
            if head.slow.load(Ordering::SeqCst) {
                return Err(ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    "upload-too-slow",
                    format!(
                        "the upload averaged under {} KiB/s after its first {} s (twice [api] import-stall-s), \
                         the least an import keeps, so another may upload; nothing was kept: send it again \
                         over a faster link, or reconstruct the file where it is with `periscope recon`",
                        MIN_IMPORT_RATE as u64 >> 10,
                        grace.as_secs_f64()
                    ),
                ));
            }
            return Err(e);
        }
    };
    let detail = format!(
        "capture {} ({} bytes{})",
        upload.capture.as_deref().unwrap_or("-"),
        upload.bytes,
        if upload.sidecars.is_empty() {
            String::new()
        } else {
            format!(", with {}", upload.sidecars.join(", "))
        }
    );
    let s = Arc::clone(&state.service);
    let by = caller.name.clone();
    let status = blocking(move || s.admit_import(ticket, upload, &by)).await?;
    let location = format!("/api/v1/runs/{}", status.id);
    let mut r = (StatusCode::CREATED, axum::Json(status)).into_response();
    if let Ok(v) = HeaderValue::from_str(&location) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    r.extensions_mut().insert(access::AuditDetail(detail));
    Ok(r)
}

fn too_large(limit: u64) -> ApiError {
    ApiError::new(
        StatusCode::PAYLOAD_TOO_LARGE,
        "body-too-large",
        format!(
            "the upload is over {}, the most this daemon takes ([api] import-limit-mib): raise the limit, \
             or reconstruct the file where it is with `periscope recon`",
            // A limit under a MiB (the config takes a KiB) is not said as 0 MiB.
            if limit >= 1 << 20 {
                format!("{} MiB", limit >> 20)
            } else {
                format!("{} KiB", limit >> 10)
            }
        ),
    )
}

fn stalled(stall: std::time::Duration) -> ApiError {
    ApiError::new(
        StatusCode::REQUEST_TIMEOUT,
        "upload-stalled",
        format!(
            "no byte of the upload arrived for {} s ([api] import-stall-s); nothing was kept: send it again",
            stall.as_secs_f64()
        ),
    )
}

/// The parser's own words, with their causes (its `Display` says only that parsing
/// failed, and a failed read of the body only that reading failed).
fn bad_form(e: axum::extract::multipart::MultipartError) -> ApiError {
    let mut why = e.body_text();
    let mut cause = std::error::Error::source(&e);
    while let Some(c) = cause {
        let said = c.to_string();
        if !why.contains(&said) {
            why = format!("{why}: {said}");
        }
        cause = c.source();
    }
    ApiError::new(
        StatusCode::BAD_REQUEST,
        "bad-body",
        format!("the upload is not a well-formed multipart/form-data body: {why}"),
    )
}

/// Reads the form's fields: files to the ticket's directory, settings and name into
/// memory (capped).
async fn receive(
    form: &mut Multipart,
    head: &PartHead,
    ticket: &ImportTicket,
    limit: u64,
    stall: std::time::Duration,
) -> ApiResult<Upload> {
    let mut upload = Upload::default();
    loop {
        head.arm(true);
        let next = tokio::time::timeout(stall, form.next_field()).await;
        head.arm(false);
        let field = match next {
            Err(_) => return Err(stalled(stall)),
            Ok(Err(e)) => return Err(bad_form(e)),
            Ok(Ok(None)) => break,
            Ok(Ok(Some(f))) => f,
        };
        let name = field.name().unwrap_or_default().to_owned();
        match name.as_str() {
            "capture" | "sidecar" => {
                let given = field.file_name().map(str::to_owned).ok_or_else(|| {
                    ApiError::new(
                        StatusCode::BAD_REQUEST,
                        "bad-body",
                        format!("the field `{name}` must be a file, with its file name"),
                    )
                })?;
                if name == "sidecar" && upload.sidecars.len() >= MAX_SIDECARS {
                    return Err(ApiError::new(
                        StatusCode::BAD_REQUEST,
                        "bad-body",
                        format!(
                            "more than {MAX_SIDECARS} `sidecar` files: a capture's reader needs a few at most"
                        ),
                    ));
                }
                let stored =
                    stored_name(&given).map_err(|m| ApiError::new(StatusCode::BAD_REQUEST, "bad-body", m))?;
                let taken =
                    upload.capture.as_deref() == Some(stored.as_str()) || upload.sidecars.contains(&stored);
                if taken || (name == "capture" && upload.capture.is_some()) {
                    return Err(ApiError::new(
                        StatusCode::BAD_REQUEST,
                        "bad-body",
                        format!(
                            "`{stored}` is sent twice, or a second `capture`: send one capture file and each sidecar once"
                        ),
                    ));
                }
                let path = ticket.files_dir().join(&stored);
                upload.bytes = save(field, &path, upload.bytes, limit, stall).await?;
                if name == "capture" {
                    upload.capture = Some(stored);
                } else {
                    upload.sidecars.push(stored);
                }
            }
            "recon" | "name" => {
                let seen = if name == "recon" {
                    upload.recon.is_some()
                } else {
                    upload.name.is_some()
                };
                if seen {
                    return Err(ApiError::new(
                        StatusCode::BAD_REQUEST,
                        "bad-body",
                        format!("the field `{name}` is sent twice: send it once"),
                    ));
                }
                let text = text(field, &name, stall).await?;
                if name == "recon" {
                    upload.recon = Some(text);
                } else {
                    upload.name = Some(text);
                }
            }
            other => {
                return Err(ApiError::new(
                    StatusCode::BAD_REQUEST,
                    "bad-body",
                    format!(
                        "unknown form field `{other}`: an import takes `capture`, `sidecar`, `recon` and `name`"
                    ),
                ));
            }
        }
    }
    Ok(upload)
}

/// How much of an upload may wait in the page cache before it is written out. The
/// capture's histogram log syncs every half second, and on a journalling file system
/// (ext4's ordered mode) that sync also waits for other files' dirty data: a whole
/// unsynced 64 MiB upload held a capture's sync for long enough to cost it a sixth of
/// its pace on a 2-core machine (`tests/load.rs`). Synced in steps of this size, an
/// upload leaves at most this much for the capture's sync to wait on.
const SYNC_EVERY_BYTES: usize = 4 << 20;

/// Streams a file field to `path`, synced to disk before it counts as received;
/// returns the upload's bytes so far.
async fn save(
    mut field: Field<'_>,
    path: &std::path::Path,
    mut total: u64,
    limit: u64,
    stall: std::time::Duration,
) -> ApiResult<u64> {
    let storage = |e: std::io::Error| {
        ApiError::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "storage",
            format!("{}: {e}; nothing of the upload was kept", path.display()),
        )
    };
    let mut out = tokio::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(path)
        .await
        .map_err(storage)?;
    let mut unsynced = 0;
    while let Some(chunk) = next_chunk(&mut field, stall).await? {
        total += chunk.len() as u64;
        if total > limit {
            return Err(too_large(limit));
        }
        out.write_all(&chunk).await.map_err(storage)?;
        unsynced += chunk.len();
        if unsynced >= SYNC_EVERY_BYTES {
            out.sync_data().await.map_err(storage)?;
            unsynced = 0;
        }
    }
    out.sync_all().await.map_err(storage)?;
    Ok(total)
}

/// A field's next chunk (`None` at its end), or the upload's error: stalled for
/// `stall`, or not a well-formed form.
async fn next_chunk(
    field: &mut Field<'_>,
    stall: std::time::Duration,
) -> ApiResult<Option<axum::body::Bytes>> {
    match tokio::time::timeout(stall, field.chunk()).await {
        Err(_) => Err(stalled(stall)),
        Ok(r) => r.map_err(bad_form),
    }
}

/// A text field, at most [`MAX_TEXT_FIELD`] bytes of UTF-8.
async fn text(mut field: Field<'_>, name: &str, stall: std::time::Duration) -> ApiResult<String> {
    let mut bytes = Vec::new();
    while let Some(chunk) = next_chunk(&mut field, stall).await? {
        if bytes.len() + chunk.len() > MAX_TEXT_FIELD {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                "body-too-large",
                format!("the field `{name}` is over {} KiB", MAX_TEXT_FIELD >> 10),
            ));
        }
        bytes.extend_from_slice(&chunk);
    }
    String::from_utf8(bytes).map_err(|_| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad-body",
            format!("the field `{name}` is not UTF-8 text"),
        )
    })
}

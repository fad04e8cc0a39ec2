//! The HTTP JSON transport (axum): the one `Error → response` mapping and thin handlers over
//! [`Service`], plus health, readiness, metrics, the Server-Sent-Events result stream and the
//! live viewer's page ([`viewer`]).
pub mod viewer;

use std::convert::Infallible;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::rejection::QueryRejection;
use axum::extract::{DefaultBodyLimit, FromRequest, Path, Query, Request, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures::StreamExt;
use serde::de::DeserializeOwned;

use crate::error::Error;
use crate::metrics::UncountedError;
use crate::service::Service;
use crossview_api::types::{AssociateRequest, BatchAck, EventsQuery};
use crossview_core::Batch;

/// The HTTP status of each error.
pub(crate) fn status_of(e: &Error) -> StatusCode {
    use crossview_core::Error as Core;
    match e {
        Error::Core(c) => match c {
            Core::InvalidArgument { .. } | Core::Format { .. } => StatusCode::UNPROCESSABLE_ENTITY,
            Core::UnknownScene(_) | Core::UnknownCamera { .. } => StatusCode::NOT_FOUND,
            Core::DuplicateBatch { .. } => StatusCode::CONFLICT,
            Core::Io { .. }
            | Core::Model { .. }
            | Core::Runtime { .. }
            | Core::Encoder(_)
            | Core::Internal { .. }
            | Core::Training(_) => StatusCode::INTERNAL_SERVER_ERROR,
        },
        Error::FrameOutOfRange { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        Error::LateBatch { .. } | Error::NoModel(_) => StatusCode::CONFLICT,
        Error::ResourceExhausted(_) | Error::DeadlineExceeded(_) | Error::SubscriberStalled(_) => {
            StatusCode::TOO_MANY_REQUESTS
        }
        Error::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
        Error::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
    }
}

/// An [`Error`] as an HTTP response: the status of [`status_of`] and a JSON body
/// `{"error": {"kind", "message", "field"}}`.
#[derive(Debug)]
pub(crate) struct HttpError(pub(crate) Error);

impl From<Error> for HttpError {
    fn from(e: Error) -> Self {
        HttpError(e)
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let HttpError(e) = self;
        let status = status_of(&e);
        let field = match &e {
            Error::Core(crossview_core::Error::InvalidArgument { field, .. }) => {
                Some(field.clone())
            }
            _ => None,
        };
        let message = crate::echo::truncate_echo(&e.report()).into_owned();
        let body = serde_json::json!({
            "error": { "kind": e.kind(), "message": message, "field": field }
        });
        let mut resp = (status, Json(body)).into_response();
        if status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                http::header::WWW_AUTHENTICATE,
                http::HeaderValue::from_static("Bearer"),
            );
        }
        resp
    }
}

/// The media type of a request body (`Content-Type` without parameters, lower case).
fn media_type(headers: &http::HeaderMap) -> Option<String> {
    let v = headers.get(http::header::CONTENT_TYPE)?.to_str().ok()?;
    Some(
        v.split(';')
            .next()
            .unwrap_or("")
            .trim()
            .to_ascii_lowercase(),
    )
}

/// True for `application/json` and `application/*+json`.
fn is_json(media: Option<&str>) -> bool {
    media.is_some_and(|m| {
        m == "application/json" || (m.starts_with("application/") && m.ends_with("+json"))
    })
}

/// 415 for a body that is not of the media types a route takes. Requiring JSON (or JSON
/// Lines) is what keeps a web page of another origin from writing with a "simple" request
/// (`text/plain`, forms) that browsers send without a CORS preflight.
fn unsupported_media_type(got: Option<&str>, want: &str) -> Response {
    let kind = "unsupported_media_type";
    let message = format!(
        "Content-Type {} is not accepted here; send {want}",
        got.map_or_else(
            || "(none)".to_string(),
            |g| format!("'{}'", crate::echo::truncate_echo(g))
        )
    );
    let body = serde_json::json!({ "error": { "kind": kind, "message": message, "field": "content-type" } });
    let mut resp = (StatusCode::UNSUPPORTED_MEDIA_TYPE, Json(body)).into_response();
    resp.extensions_mut().insert(UncountedError(kind));
    resp
}

/// A JSON body (`Content-Type: application/json`, else 415) whose decoding errors are
/// `InvalidArgument` (422, naming `body`), while the body-size limit still answers 413.
pub(crate) struct JsonBody<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for JsonBody<T> {
    type Rejection = Response;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let media = media_type(req.headers());
        if !is_json(media.as_deref()) {
            return Err(unsupported_media_type(media.as_deref(), "application/json"));
        }
        let bytes = Bytes::from_request(req, state)
            .await
            .map_err(IntoResponse::into_response)?;
        serde_json::from_slice(&bytes).map(JsonBody).map_err(|e| {
            let e = Error::invalid("body", e.to_string());
            let kind = e.kind();
            let mut resp = HttpError(e).into_response();
            resp.extensions_mut().insert(UncountedError(kind));
            resp
        })
    }
}

async fn healthz() -> &'static str {
    "ok"
}

async fn readyz(State(svc): State<Arc<Service>>) -> Response {
    if svc.is_ready() {
        "ready".into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "not ready").into_response()
    }
}

async fn metrics(State(svc): State<Arc<Service>>) -> Response {
    (
        [(
            http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        svc.metrics().render(),
    )
        .into_response()
}

async fn list_scenes(State(svc): State<Arc<Service>>) -> Response {
    Json(serde_json::json!({ "scenes": svc.scenes() })).into_response()
}

/// `POST /v1/admin/reload`: re-reads every scene's model file (as `SIGHUP` does) and answers
/// with one outcome per file, `{"reloads": [{"scene", "outcome", "version", "error"}]}`.
async fn reload(State(svc): State<Arc<Service>>) -> Response {
    Json(serde_json::json!({ "reloads": svc.reload().await })).into_response()
}

async fn get_scene(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
) -> Result<Response, HttpError> {
    Ok(Json(svc.describe(&scene)?).into_response())
}

async fn associate(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
    JsonBody(req): JsonBody<AssociateRequest>,
) -> Result<Response, HttpError> {
    Ok(Json(svc.associate(&scene, req).await?).into_response())
}

/// True when the body is JSON Lines (a SPEC §7 recording or several batch lines).
fn is_json_lines(media: Option<&str>) -> bool {
    matches!(
        media,
        Some("application/x-ndjson" | "application/jsonl" | "application/jsonlines")
    )
}

async fn push_batch(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
    headers: http::HeaderMap,
    body: Bytes,
) -> Result<Response, HttpError> {
    let media = media_type(&headers);
    if is_json_lines(media.as_deref()) {
        let max_rejected = svc.scene(&scene)?.limits().max_rejected_lines;
        let lines = LineRun::new(svc, scene, body, max_rejected);
        return Ok((
            [(http::header::CONTENT_TYPE, "application/json")],
            axum::body::Body::from_stream(lines.into_stream()),
        )
            .into_response());
    }
    if !is_json(media.as_deref()) {
        return Ok(unsupported_media_type(
            media.as_deref(),
            "application/json (one batch) or application/x-ndjson (batch lines)",
        ));
    }
    let batch: Batch = serde_json::from_slice(&body)
        .map_err(|e| Error::invalid("body", e.to_string()))
        .inspect_err(|e| svc.metrics().error(e))?;
    let ack = svc.push(&scene, batch)?;
    Ok((StatusCode::ACCEPTED, Json(ack)).into_response())
}

/// Input bytes one step of a [`LineRun`] may parse before it yields.
const LINES_STEP_BYTES: usize = 64 << 10;
/// Output bytes after which a step yields its chunk.
const LINES_CHUNK_BYTES: usize = 16 << 10;

/// A JSON Lines body pushed line by line (a recording's scene header line is skipped), its
/// answer streamed as it goes: `{"results": [{"line", "accepted", ...}, ...], "accepted": N,
/// "rejected": M}` plus `"stopped_at_line"` and `"stopped"` when it stopped early.
///
/// Bounded by construction: each step parses at most [`LINES_STEP_BYTES`] of input on the
/// async worker thread and yields one output chunk; the next step runs only when the client
/// has taken the previous chunk (HTTP backpressure), so neither the results nor the time of
/// one step grow with the body. Once more than `max_rejected` lines were rejected and rejected
/// lines outnumber accepted ones, the rest of the body is skipped.
struct LineRun {
    svc: Arc<Service>,
    scene: String,
    body: Bytes,
    pos: usize,
    line_no: usize,
    accepted: usize,
    rejected: usize,
    max_rejected: usize,
    first: bool,
    done: bool,
}

impl LineRun {
    fn new(svc: Arc<Service>, scene: String, body: Bytes, max_rejected: usize) -> Self {
        LineRun {
            svc,
            scene,
            body,
            pos: 0,
            line_no: 0,
            accepted: 0,
            rejected: 0,
            max_rejected,
            first: true,
            done: false,
        }
    }

    fn into_stream(self) -> impl futures::Stream<Item = Result<Bytes, Infallible>> + Send {
        futures::stream::unfold(self, |mut run| async move {
            if run.done {
                return None;
            }
            // Let other tasks on this worker run between steps.
            tokio::task::coop::consume_budget().await;
            let chunk = run.step();
            Some((Ok(chunk), run))
        })
    }

    /// One line's outcome: `None` for skipped lines (blank, scene header).
    fn line(&self, line: &[u8]) -> Option<Result<BatchAck, Error>> {
        if line.iter().all(u8::is_ascii_whitespace) {
            return None;
        }
        let v = match serde_json::from_slice::<serde_json::Value>(line) {
            Ok(v) => v,
            Err(e) => return Some(Err(Error::invalid("body", e.to_string()))),
        };
        if v.get("scene").is_some() && v.get("camera").is_none() {
            return None;
        }
        Some(
            serde_json::from_value::<Batch>(v)
                .map_err(|e| Error::invalid("body", e.to_string()))
                .and_then(|b| self.svc.push(&self.scene, b)),
        )
    }

    /// Processes lines until the step's input or output budget is spent; returns the output.
    fn step(&mut self) -> Bytes {
        let mut out = Vec::with_capacity(LINES_CHUNK_BYTES + 1024);
        if self.first {
            out.extend_from_slice(b"{\"results\":[");
        }
        let start = self.pos;
        while self.pos < self.body.len()
            && self.pos - start < LINES_STEP_BYTES
            && out.len() < LINES_CHUNK_BYTES
        {
            if self.rejected > self.max_rejected && self.rejected > self.accepted {
                break;
            }
            let rest = &self.body[self.pos..];
            let len = rest.iter().position(|&b| b == b'\n').unwrap_or(rest.len());
            let line = self.body.slice(self.pos..self.pos + len);
            self.pos += len + 1;
            self.line_no += 1;
            let item = match self.line(&line) {
                None => continue,
                Some(Ok(ack)) => {
                    self.accepted += 1;
                    serde_json::json!({ "line": self.line_no, "accepted": true, "camera": ack.camera, "frame_id": ack.frame_id })
                }
                Some(Err(e)) => {
                    if matches!(e, Error::Core(crossview_core::Error::InvalidArgument { ref field, .. }) if field == "body")
                    {
                        self.svc.metrics().error(&e);
                    }
                    self.rejected += 1;
                    serde_json::json!({
                        "line": self.line_no, "accepted": false,
                        "error": { "kind": e.kind(), "message": crate::echo::truncate_echo(&e.to_string()) },
                    })
                }
            };
            if !self.first {
                out.push(b',');
            }
            self.first = false;
            serde_json::to_writer(&mut out, &item).expect("JSON values serialize");
        }
        let stop = self.rejected > self.max_rejected && self.rejected > self.accepted;
        if self.pos >= self.body.len() || stop {
            self.done = true;
            let mut tail =
                serde_json::json!({ "accepted": self.accepted, "rejected": self.rejected });
            if self.pos < self.body.len() {
                tail["stopped_at_line"] = (self.line_no + 1).into();
                tail["stopped"] = format!(
                    "more than {} lines rejected, more than were accepted (--max-rejected-lines); the rest of the body was not read",
                    self.max_rejected
                )
                .into();
            }
            let tail = serde_json::to_string(&tail).expect("JSON values serialize");
            out.extend_from_slice(b"],");
            out.extend_from_slice(&tail.as_bytes()[1..]);
        }
        // Drop what the body no longer needs as soon as possible.
        if self.done {
            self.body = Bytes::new();
        }
        Bytes::from(out)
    }
}

/// `GET /v1/scenes/{scene}/events[?boxes=true]`: the scene's results as Server-Sent Events
/// (`event: frame`, `id: <frame_id>`); with `boxes=true` each event's data also carries the
/// frame's boxes ([`crossview_api::types::FrameWithBoxes`]), otherwise it is the bare result.
async fn events(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
    query: Result<Query<EventsQuery>, QueryRejection>,
    conn: Option<axum::Extension<crate::conn::ConnHandle>>,
) -> Result<Response, HttpError> {
    let Query(query) = query
        .map_err(|e| Error::invalid("boxes", e.body_text()))
        .inspect_err(|e| svc.metrics().error(e))?;
    let stall = svc.stall_timeout();
    let results = svc.subscribe(&scene, conn.map(|c| c.0), stall)?;
    let events = results.map(move |r| {
        Ok::<_, Infallible>(match r {
            Ok(r) => {
                let frame = Event::default()
                    .event("frame")
                    .id(r.result.frame_id.to_string());
                // Encoded once per frame, whatever the number of subscribers.
                frame.data(r.json(query.boxes))
            }
            Err(e) => Event::default().event("error").data(e.to_string()),
        })
    });
    Ok(Sse::new(events)
        .keep_alive(KeepAlive::default())
        .into_response())
}

/// Routes of the HTTP API (JSON bodies capped at `max_body` bytes).
pub(crate) fn router(svc: Arc<Service>, max_body: usize) -> Router {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/scenes", get(list_scenes))
        .route("/v1/scenes/{scene}", get(get_scene))
        .route("/v1/scenes/{scene}/associate", post(associate))
        .route("/v1/scenes/{scene}/batches", post(push_batch))
        .route("/v1/scenes/{scene}/events", get(events))
        .route("/v1/admin/reload", post(reload))
        .merge(viewer::router())
        .layer(DefaultBodyLimit::max(max_body))
        .with_state(svc)
}

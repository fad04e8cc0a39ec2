//! The HTTP JSON transport (axum): the one `Error → response` mapping and thin handlers over
//! [`Service`], plus health, readiness, metrics and the Server-Sent-Events result stream.
use std::convert::Infallible;
use std::sync::Arc;

use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, FromRequest, Path, Request, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures::StreamExt;
use serde::de::DeserializeOwned;

use super::api::AssociateRequest;
use super::service::Service;
use crate::Error;
use crate::core::Batch;

/// The HTTP status of each error.
pub fn status_of(e: &Error) -> StatusCode {
    match e {
        Error::InvalidArgument { .. } | Error::Format { .. } => StatusCode::UNPROCESSABLE_ENTITY,
        Error::UnknownScene(_) | Error::UnknownCamera { .. } => StatusCode::NOT_FOUND,
        Error::LateBatch { .. } | Error::DuplicateBatch { .. } => StatusCode::CONFLICT,
        Error::ResourceExhausted(_) => StatusCode::TOO_MANY_REQUESTS,
        Error::Unauthenticated(_) => StatusCode::UNAUTHORIZED,
        Error::Unavailable(_) => StatusCode::SERVICE_UNAVAILABLE,
        Error::Io { .. } | Error::Model { .. } | Error::Runtime(_) | Error::Training(_) => {
            StatusCode::INTERNAL_SERVER_ERROR
        }
    }
}

impl IntoResponse for Error {
    fn into_response(self) -> Response {
        let status = status_of(&self);
        let field = match &self {
            Error::InvalidArgument { field, .. } => Some(field.clone()),
            _ => None,
        };
        let body = serde_json::json!({
            "error": { "kind": self.kind(), "message": self.to_string(), "field": field }
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

/// Marks a response whose error was produced outside [`Service`] (so not yet counted);
/// the request-accounting middleware counts it.
#[derive(Debug, Clone, Copy)]
pub struct UncountedError(pub &'static str);

/// A JSON body whose decoding errors are [`Error::InvalidArgument`] (422, naming `body`), while
/// the body-size limit still answers 413.
pub struct JsonBody<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for JsonBody<T> {
    type Rejection = Response;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        let bytes = Bytes::from_request(req, state)
            .await
            .map_err(IntoResponse::into_response)?;
        serde_json::from_slice(&bytes).map(JsonBody).map_err(|e| {
            let e = Error::invalid("body", e.to_string());
            let kind = e.kind();
            let mut resp = e.into_response();
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

async fn get_scene(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
) -> Result<Response, Error> {
    Ok(Json(svc.describe(&scene)?).into_response())
}

async fn associate(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
    JsonBody(req): JsonBody<AssociateRequest>,
) -> Result<Response, Error> {
    Ok(Json(svc.associate(&scene, req).await?).into_response())
}

/// True when the body is JSON Lines (a SPEC §7 recording or several batch lines).
fn is_json_lines(headers: &http::HeaderMap) -> bool {
    headers
        .get(http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| {
            v.starts_with("application/x-ndjson") || v.starts_with("application/jsonl")
        })
}

async fn push_batch(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
    headers: http::HeaderMap,
    body: Bytes,
) -> Result<Response, Error> {
    if is_json_lines(&headers) {
        return push_lines(&svc, &scene, &body);
    }
    let batch: Batch = serde_json::from_slice(&body).map_err(|e| {
        svc.metrics().error("invalid_argument");
        Error::invalid("body", e.to_string())
    })?;
    let ack = svc.push(&scene, batch)?;
    Ok((StatusCode::ACCEPTED, Json(ack)).into_response())
}

/// JSON Lines body: every batch line is pushed in order (a recording's scene header line is
/// skipped); the answer lists each line's outcome, so one bad line rejects only itself.
fn push_lines(svc: &Service, scene: &str, body: &[u8]) -> Result<Response, Error> {
    svc.scene(scene)?;
    let (mut accepted, mut rejected, mut results) = (0usize, 0usize, Vec::new());
    for (i, line) in body.split(|&b| b == b'\n').enumerate() {
        if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        let outcome = serde_json::from_slice::<serde_json::Value>(line)
            .map_err(|e| Error::invalid("body", e.to_string()))
            .and_then(|v| {
                if v.get("scene").is_some() && v.get("camera").is_none() {
                    return Ok(None);
                }
                let batch: Batch =
                    serde_json::from_value(v).map_err(|e| Error::invalid("body", e.to_string()))?;
                svc.push(scene, batch).map(Some)
            });
        let line_no = i + 1;
        match outcome {
            Ok(None) => {}
            Ok(Some(ack)) => {
                accepted += 1;
                results.push(serde_json::json!({ "line": line_no, "accepted": true, "camera": ack.camera, "frame_id": ack.frame_id }));
            }
            Err(e) => {
                if matches!(e, Error::InvalidArgument { ref field, .. } if field == "body") {
                    svc.metrics().error(e.kind());
                }
                rejected += 1;
                results.push(serde_json::json!({
                    "line": line_no, "accepted": false,
                    "error": { "kind": e.kind(), "message": e.to_string() },
                }));
            }
        }
    }
    Ok(
        Json(serde_json::json!({ "accepted": accepted, "rejected": rejected, "results": results }))
            .into_response(),
    )
}

async fn events(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
) -> Result<Response, Error> {
    let results = svc.subscribe(&scene)?;
    let events = results.map(|r| {
        Ok::<_, Infallible>(match r {
            Ok(r) => Event::default()
                .event("frame")
                .id(r.frame_id.to_string())
                .json_data(&*r)
                .unwrap_or_else(|e| Event::default().event("error").data(e.to_string())),
            Err(e) => Event::default().event("error").data(e.to_string()),
        })
    });
    Ok(Sse::new(events)
        .keep_alive(KeepAlive::default())
        .into_response())
}

/// Routes of the HTTP API (JSON bodies capped at `max_body` bytes).
pub fn router(svc: Arc<Service>, max_body: usize) -> Router {
    Router::new()
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics))
        .route("/v1/scenes", get(list_scenes))
        .route("/v1/scenes/{scene}", get(get_scene))
        .route("/v1/scenes/{scene}/associate", post(associate))
        .route("/v1/scenes/{scene}/batches", post(push_batch))
        .route("/v1/scenes/{scene}/events", get(events))
        .layer(DefaultBodyLimit::max(max_body))
        .with_state(svc)
}

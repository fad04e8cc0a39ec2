//! The HTTP routes: thin handlers over [`Service`], each with its OpenAPI description
//! (`#[utoipa::path]`), collected by [`api_routes`] into the router and the document at once,
//! so the description cannot name a route the server lacks or miss one it has. The document
//! ([`openapi_json`]) lists every status a route really answers with.
use std::convert::Infallible;
use std::sync::{Arc, OnceLock};

use axum::body::Bytes;
use axum::extract::rejection::QueryRejection;
use axum::extract::{DefaultBodyLimit, Path, Query, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::{Json, Router};
use futures::StreamExt;
use utoipa::OpenApi;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use super::lines::LineRun;
use super::openapi::{ApiDoc, tags};
use super::{HttpError, JsonBody, is_json, media_type, unsupported_media_type, viewer};
use crate::error::Error;
use crate::service::Service;
use crossview_api::types::{
    AssociateRequest, BatchAck, ErrorBody, EventsQuery, FrameResult, LinesReport, ReloadReport,
    SceneDescription, SceneList,
};
use crossview_core::Batch;

/// `GET /healthz`: the process is up (no token needed).
#[utoipa::path(get, path = "/healthz", tag = tags::OPS, security(()),
    responses((status = 200, description = "The process is up", body = String,
        content_type = "text/plain", example = "ok")))]
async fn healthz() -> &'static str {
    "ok"
}

/// `GET /readyz`: the server accepts work (no token needed).
#[utoipa::path(get, path = "/readyz", tag = tags::OPS, security(()),
    responses((status = 200, description = "Ready: every scene is loaded and the server is not \
        shutting down (while it starts or drains it answers 503 `not ready`)", body = String,
        content_type = "text/plain", example = "ready")))]
async fn readyz(State(svc): State<Arc<Service>>) -> Response {
    if svc.is_ready() {
        "ready".into_response()
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "not ready").into_response()
    }
}

/// `GET /metrics`: Prometheus metrics (no token needed).
#[utoipa::path(get, path = "/metrics", tag = tags::OPS, security(()),
    responses((status = 200, description = "Prometheus text exposition format 0.0.4 \
        (docs/serve.md lists the metrics)", body = String, content_type = "text/plain")))]
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

/// `GET /openapi.json`: this document.
#[utoipa::path(get, path = "/openapi.json", tag = tags::OPS,
    responses(
        (status = 200, description = "The OpenAPI 3.1 description of this API",
            body = Object, content_type = "application/json"),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
    ))]
async fn openapi_doc() -> Response {
    (
        [(http::header::CONTENT_TYPE, "application/json")],
        openapi_json(),
    )
        .into_response()
}

/// `GET /v1/scenes`: every loaded scene.
#[utoipa::path(get, path = "/v1/scenes", tag = tags::SCENES,
    responses(
        (status = 200, description = "Every scene, by name", body = SceneList),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
    ))]
async fn list_scenes(State(svc): State<Arc<Service>>) -> Response {
    Json(SceneList {
        scenes: svc.scenes(),
    })
    .into_response()
}

/// `POST /v1/admin/reload`: re-reads every scene's model file (as `SIGHUP` does) and answers
/// with one outcome per file.
#[utoipa::path(post, path = "/v1/admin/reload", tag = tags::ADMIN,
    responses(
        (status = 200, description = "One outcome per model file", body = ReloadReport),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
        (status = 403, description = "Refused: sent by a web page of another origin",
            body = ErrorBody),
    ))]
async fn reload(State(svc): State<Arc<Service>>) -> Response {
    Json(ReloadReport {
        reloads: svc.reload().await,
    })
    .into_response()
}

/// `GET /v1/scenes/{scene}`: one scene.
#[utoipa::path(get, path = "/v1/scenes/{scene}", tag = tags::SCENES,
    params(("scene" = String, Path, description = "The scene's name", min_length = 1,
        example = "lab")),
    responses(
        (status = 200, description = "The scene", body = SceneDescription),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
        (status = 404, description = "No such scene", body = ErrorBody),
    ))]
async fn get_scene(
    State(svc): State<Arc<Service>>,
    Path(scene): Path<String>,
) -> Result<Response, HttpError> {
    Ok(Json(svc.describe(&scene)?).into_response())
}

/// `POST /v1/scenes/{scene}/associate`: associates one whole, already synchronized frame.
#[utoipa::path(post, path = "/v1/scenes/{scene}/associate", tag = tags::SCENES,
    params(("scene" = String, Path, description = "The scene's name", min_length = 1,
        example = "lab")),
    request_body(content = AssociateRequest, content_type = "application/json",
        example = json!({"frame_id": 7, "views": [
            {"camera": "c0", "detections": [{"bbox": [100.0, 200.0, 180.0, 420.0]}]},
            {"camera": "c1", "detections": [{"bbox": [50.0, 90.0, 110.0, 300.0], "score": 0.9}]}
        ]})),
    responses(
        (status = 200, description = "The frame's identities (not tracked: no `track_id`)",
            body = FrameResult),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
        (status = 403, description = "Refused: sent by a web page of another origin",
            body = ErrorBody),
        (status = 404, description = "No such scene, or a view names no camera of it",
            body = ErrorBody),
        (status = 409, description = "The scene has no model yet (declared by its cameras)",
            body = ErrorBody),
        (status = 413, description = "Body larger than `--max-request-bytes`",
            body = ErrorBody),
        (status = 415, description = "Body not `application/json`", body = ErrorBody),
        (status = 422, description = "Invalid body; `field` names the culprit",
            body = ErrorBody),
        (status = 429, description = "The scene's inference queue is full; back off and retry",
            body = ErrorBody),
    ))]
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

/// `POST /v1/scenes/{scene}/batches`: one camera batch (JSON), or many (JSON Lines).
#[utoipa::path(post, path = "/v1/scenes/{scene}/batches", tag = tags::SCENES,
    params(("scene" = String, Path, description = "The scene's name", min_length = 1,
        example = "lab")),
    request_body(description = "One batch as `application/json`, or batch lines (a SPEC §7 \
        recording, whose scene header line is skipped) as `application/x-ndjson` (also \
        `application/jsonl`, `application/jsonlines`)",
        content(
            (Batch = "application/json", example = json!({"camera": "c0", "frame_id": 0,
                "detections": [{"bbox": [100.0, 200.0, 180.0, 420.0]}]})),
            (String = "application/x-ndjson"),
        )),
    responses(
        (status = 200, description = "JSON Lines: each line's outcome, streamed as the lines \
            are pushed", body = LinesReport),
        (status = 202, description = "The batch was accepted; its frame's result will be \
            published on the scene's events", body = BatchAck),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
        (status = 403, description = "Refused: sent by a web page of another origin",
            body = ErrorBody),
        (status = 404, description = "No such scene, or no such camera in it",
            body = ErrorBody),
        (status = 409, description = "This camera's batch of the frame was already received, \
            or the frame was already published", body = ErrorBody),
        (status = 413, description = "Body larger than `--max-request-bytes`",
            body = ErrorBody),
        (status = 415, description = "Body neither JSON nor JSON Lines", body = ErrorBody),
        (status = 422, description = "Invalid batch, or a frame id outside the scene's window; \
            `field` names the culprit", body = ErrorBody),
        (status = 429, description = "Overload: kind `overloaded` — the scene is over its queue \
            budget (`--max-queue-delay`) and this batch's frame is shed whole (published with \
            status `shed`); wait the `Retry-After` seconds before sending more. Kind \
            `resource_exhausted`: the scene's queue is full (`--queue-capacity`)",
            headers(("Retry-After" = u64, description = "Seconds to wait (kind `overloaded`)")),
            body = ErrorBody),
    ))]
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

/// `GET /v1/scenes/{scene}/events[?boxes=true]`: the scene's results as Server-Sent Events
/// (`event: frame`, `id: <frame_id>`); with `boxes=true` each event's data also carries the
/// frame's boxes ([`crossview_api::types::FrameWithBoxes`]), otherwise it is the bare result.
#[utoipa::path(get, path = "/v1/scenes/{scene}/events", tag = tags::SCENES,
    params(("scene" = String, Path, description = "The scene's name", min_length = 1),
        EventsQuery),
    responses(
        (status = 200, description = "An endless Server-Sent-Events stream: one `event: frame` \
            (`id:` the frame id) per published frame, its data a `FrameResult` (with \
            `?boxes=true` a `FrameWithBoxes`); a subscriber that falls behind gets one \
            `event: error` (its data an `ErrorBody`) and the stream ends", body = String,
            content_type = "text/event-stream"),
        (status = 401, description = "Missing or wrong API key", body = ErrorBody),
        (status = 404, description = "No such scene", body = ErrorBody),
        (status = 422, description = "Invalid query (`boxes` not a boolean)", body = ErrorBody),
        (status = 429, description = "The subscriber budget is spent; try again later",
            body = ErrorBody),
    ))]
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
            Err(e) => Event::default()
                .event("error")
                .json_data(super::error_body(&e))
                .unwrap_or_else(|_| Event::default().event("error").data(e.kind())),
        })
    });
    Ok(Sse::new(events)
        .keep_alive(KeepAlive::default())
        .into_response())
}

/// Every documented route, with its description.
fn api_routes() -> OpenApiRouter<Arc<Service>> {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(healthz))
        .routes(routes!(readyz))
        .routes(routes!(metrics))
        .routes(routes!(openapi_doc))
        .routes(routes!(list_scenes))
        .routes(routes!(get_scene))
        .routes(routes!(associate))
        .routes(routes!(push_batch))
        .routes(routes!(events))
        .routes(routes!(reload))
}

/// The OpenAPI 3.1 description of the HTTP API, pretty-printed JSON (what `/openapi.json`
/// serves, `crossview openapi` prints and `docs/openapi.json` holds). Built once.
pub fn openapi_json() -> &'static str {
    static DOC: OnceLock<String> = OnceLock::new();
    DOC.get_or_init(|| {
        let (_, doc) = api_routes().split_for_parts();
        // utoipa spells the unsigned formats `u-int32`/`u-int64`; the usual names are
        // `uint32`/`uint64` (a u64 must not be `int64`, which would cap it at 2^63 - 1).
        doc.to_pretty_json()
            .expect("the OpenAPI document serializes")
            .replace("\"format\": \"u-int", "\"format\": \"uint")
    })
}

/// Routes of the HTTP API (JSON bodies capped at `max_body` bytes) and the viewer's pages.
pub(crate) fn router(svc: Arc<Service>, max_body: usize) -> Router {
    let (routes, _) = api_routes().split_for_parts();
    routes
        .merge(viewer::router())
        .layer(DefaultBodyLimit::max(max_body))
        .with_state(svc)
}

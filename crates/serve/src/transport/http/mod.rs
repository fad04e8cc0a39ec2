//! The HTTP JSON transport (axum): the one `Error → response` mapping and thin handlers over
//! [`Service`], plus health, readiness, metrics, the Server-Sent-Events result stream and the
//! live viewer's page ([`viewer`]). The routes and their OpenAPI 3.1 description, generated
//! from the handlers and the wire types, are in [`routes`]: the server serves it at
//! `/openapi.json`, `crossview openapi` prints it, and `docs/openapi.json` is a copy a test
//! keeps equal.
mod lines;
mod openapi;
pub mod routes;
pub mod viewer;

pub(crate) use routes::router;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{FromRequest, Request};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::de::DeserializeOwned;

use crate::error::Error;
use crate::metrics::UncountedError;
use crossview_api::types::{ErrorBody, ErrorDetail};

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
        Error::ResourceExhausted(_)
        | Error::Overloaded { .. }
        | Error::DeadlineExceeded(_)
        | Error::SubscriberStalled(_) => StatusCode::TOO_MANY_REQUESTS,
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

/// The JSON body of an error, `{"error": {"kind", "message", "field"}}`: of every HTTP error
/// response, and the data of an SSE `error` event.
pub(crate) fn error_body(e: &Error) -> ErrorBody {
    let field = match e {
        Error::Core(crossview_core::Error::InvalidArgument { field, .. }) => Some(field.clone()),
        _ => None,
    };
    ErrorBody {
        error: ErrorDetail {
            kind: e.kind().to_string(),
            message: crate::echo::truncate_echo(&e.report()).into_owned(),
            field,
        },
    }
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let HttpError(e) = self;
        let status = status_of(&e);
        let mut resp = (status, Json(error_body(&e))).into_response();
        if status == StatusCode::UNAUTHORIZED {
            resp.headers_mut().insert(
                http::header::WWW_AUTHENTICATE,
                http::HeaderValue::from_static("Bearer"),
            );
        }
        if let Error::Overloaded { retry_after, .. } = &e {
            // Whole seconds (RFC 9110), rounded up: a client never comes back too early.
            let secs = retry_after.as_secs() + u64::from(retry_after.subsec_nanos() > 0);
            resp.headers_mut().insert(
                http::header::RETRY_AFTER,
                http::HeaderValue::from(secs.max(1)),
            );
        }
        resp
    }
}

/// The media type of a request body (`Content-Type` without parameters, lower case).
pub(super) fn media_type(headers: &http::HeaderMap) -> Option<String> {
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
pub(super) fn is_json(media: Option<&str>) -> bool {
    media.is_some_and(|m| {
        m == "application/json" || (m.starts_with("application/") && m.ends_with("+json"))
    })
}

/// 415 for a body that is not of the media types a route takes. Requiring JSON (or JSON
/// Lines) is what keeps a web page of another origin from writing with a "simple" request
/// (`text/plain`, forms) that browsers send without a CORS preflight.
pub(super) fn unsupported_media_type(got: Option<&str>, want: &str) -> Response {
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

//! Request-body time bounds (`--body-timeout`), so half-sent bodies cannot hold memory and
//! connections forever:
//! - an HTTP (non-gRPC) request body is read whole, within `body_timeout` of its head and at
//!   most the size limit, before any handler runs ([`buffer_body`]); too slow answers 408 and
//!   closes the connection, too large 413;
//! - a gRPC request is a stream of length-prefixed messages that may legitimately stay open
//!   for hours, so the bound is per message: once a message has started, its last byte must
//!   arrive within `body_timeout` ([`GrpcMessageDeadline`]), otherwise the call ends with
//!   `DEADLINE_EXCEEDED`. Between messages a stream may be quiet for as long as it likes.
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, Bytes, HttpBody};
use axum::extract::{Request, State};
use axum::http::StatusCode;
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use http_body_util::{BodyExt, LengthLimitError, Limited};

use super::metrics::UncountedError;

/// The settings [`buffer_body`] needs.
#[derive(Debug, Clone, Copy)]
pub(crate) struct BodyLimits {
    /// Largest body in bytes.
    pub max_bytes: usize,
    /// Time for the whole body.
    pub timeout: Duration,
}

fn error_response(status: StatusCode, kind: &'static str, message: String) -> Response {
    let body =
        serde_json::json!({ "error": { "kind": kind, "message": message, "field": "body" } });
    let mut resp = (status, axum::Json(body)).into_response();
    resp.extensions_mut().insert(UncountedError(kind));
    resp
}

/// axum middleware: reads an HTTP request body whole within the limits (see the module docs)
/// and hands the handler the buffered body. gRPC requests pass through untouched.
pub(crate) async fn buffer_body(
    State(limits): State<BodyLimits>,
    req: Request,
    next: Next,
) -> Response {
    if super::auth::is_grpc(&req) || req.body().is_end_stream() {
        return next.run(req).await;
    }
    let (parts, body) = req.into_parts();
    let limited = Limited::new(body, limits.max_bytes);
    match tokio::time::timeout(limits.timeout, limited.collect()).await {
        Ok(Ok(collected)) => {
            next.run(Request::from_parts(parts, Body::from(collected.to_bytes())))
                .await
        }
        Ok(Err(e)) if e.downcast_ref::<LengthLimitError>().is_some() => error_response(
            StatusCode::PAYLOAD_TOO_LARGE,
            "payload_too_large",
            format!(
                "request body is larger than {} bytes (--max-request-bytes)",
                limits.max_bytes
            ),
        ),
        Ok(Err(e)) => error_response(
            StatusCode::BAD_REQUEST,
            "invalid_argument",
            format!("could not read the request body: {e}"),
        ),
        Err(_) => {
            let mut resp = error_response(
                StatusCode::REQUEST_TIMEOUT,
                "timeout",
                format!(
                    "request body not received within {:?} (--body-timeout)",
                    limits.timeout
                ),
            );
            resp.headers_mut().insert(
                http::header::CONNECTION,
                http::HeaderValue::from_static("close"),
            );
            resp
        }
    }
}

/// A gRPC request body in which every message, once started, must be complete within a
/// deadline (see the module docs). Parses only the 5-byte message prefixes.
pub(crate) struct GrpcMessageDeadline {
    inner: Body,
    timeout: Duration,
    /// Bytes of the current message prefix seen so far (0..5) and the prefix itself.
    prefix: [u8; 5],
    prefix_len: usize,
    /// Payload bytes of the current message still to come.
    remaining: u64,
    /// Set while a message is incomplete.
    deadline: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl GrpcMessageDeadline {
    /// Wraps a gRPC request body.
    pub fn new(inner: Body, timeout: Duration) -> Self {
        GrpcMessageDeadline {
            inner,
            timeout,
            prefix: [0; 5],
            prefix_len: 0,
            remaining: 0,
            deadline: None,
        }
    }

    /// Advances the message framing over `data`; true when a message is left incomplete.
    fn advance(&mut self, mut data: &[u8]) -> bool {
        while !data.is_empty() {
            if self.remaining > 0 {
                let take = (self.remaining.min(data.len() as u64)) as usize;
                self.remaining -= take as u64;
                data = &data[take..];
                continue;
            }
            let take = (5 - self.prefix_len).min(data.len());
            self.prefix[self.prefix_len..self.prefix_len + take].copy_from_slice(&data[..take]);
            self.prefix_len += take;
            data = &data[take..];
            if self.prefix_len == 5 {
                let len = u32::from_be_bytes([
                    self.prefix[1],
                    self.prefix[2],
                    self.prefix[3],
                    self.prefix[4],
                ]);
                self.remaining = u64::from(len);
                self.prefix_len = 0;
            }
        }
        self.remaining > 0 || self.prefix_len > 0
    }
}

impl HttpBody for GrpcMessageDeadline {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(Some(Ok(frame))) => {
                if let Some(data) = frame.data_ref() {
                    if this.advance(data) {
                        if this.deadline.is_none() {
                            this.deadline = Some(Box::pin(tokio::time::sleep(this.timeout)));
                        }
                    } else {
                        this.deadline = None;
                    }
                }
                Poll::Ready(Some(Ok(frame)))
            }
            Poll::Pending => {
                if let Some(d) = this.deadline.as_mut()
                    && d.as_mut().poll(cx).is_ready()
                {
                    let status = tonic::Status::deadline_exceeded(format!(
                        "a gRPC message was not completed within {:?} (--body-timeout)",
                        this.timeout
                    ));
                    return Poll::Ready(Some(Err(axum::Error::new(status))));
                }
                Poll::Pending
            }
            other => other,
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn framing_tracks_incomplete_messages_across_chunks() {
        let mut b = GrpcMessageDeadline::new(Body::empty(), Duration::from_secs(1));
        // Two complete messages in one chunk.
        assert!(!b.advance(&[0, 0, 0, 0, 2, 7, 7, 0, 0, 0, 0, 0]));
        // A prefix split over chunks, then its payload in pieces.
        assert!(b.advance(&[0, 0, 0]));
        assert!(b.advance(&[0, 3, 1]));
        assert!(b.advance(&[2]));
        assert!(!b.advance(&[3]));
    }
}

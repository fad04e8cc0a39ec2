//! Optional bearer-token authentication for every API call on both transports. Health,
//! readiness, metrics, the gRPC health service and the live viewer's page and assets (they
//! hold no data; the page asks for the token and sends it on its API calls) are exempt. A gRPC caller gets an
//! `UNAUTHENTICATED` status, an HTTP caller a 401.
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::metrics::Metrics;
use crossview_core::Error;

/// The accepted keys (empty = authentication off).
#[derive(Clone)]
pub(crate) struct ApiKeys {
    keys: Arc<Vec<Vec<u8>>>,
    metrics: Metrics,
}

impl std::fmt::Debug for ApiKeys {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "ApiKeys({} keys)", self.keys.len())
    }
}

/// Equal-time comparison, so response timing does not reveal how much of a key matched.
fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// Paths that never need a token.
fn exempt(path: &str) -> bool {
    matches!(path, "/healthz" | "/readyz" | "/metrics")
        || path.starts_with("/grpc.health.v1.")
        || crate::viewer::is_asset(path)
}

/// True for gRPC requests (content-type `application/grpc[+proto]`).
pub(crate) fn is_grpc(req: &Request) -> bool {
    req.headers()
        .get(http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"))
}

impl ApiKeys {
    /// Accepts any of `keys` (blank entries ignored).
    pub fn new(keys: &[String], metrics: Metrics) -> Self {
        ApiKeys {
            keys: Arc::new(
                keys.iter()
                    .map(|k| k.trim())
                    .filter(|k| !k.is_empty())
                    .map(|k| k.as_bytes().to_vec())
                    .collect(),
            ),
            metrics,
        }
    }

    /// Checks the `authorization: Bearer <key>` header of a request.
    pub fn check(&self, req: &Request) -> Result<(), Error> {
        if self.keys.is_empty() || exempt(req.uri().path()) {
            return Ok(());
        }
        let header = req
            .headers()
            .get(http::header::AUTHORIZATION)
            .ok_or_else(|| Error::Unauthenticated("missing bearer token".into()))?;
        let token = header
            .to_str()
            .ok()
            .and_then(|h| {
                h.strip_prefix("Bearer ")
                    .or_else(|| h.strip_prefix("bearer "))
            })
            .map(str::trim)
            .ok_or_else(|| Error::Unauthenticated("expected 'Bearer <token>'".into()))?;
        if self.keys.iter().any(|k| ct_eq(k, token.as_bytes())) {
            Ok(())
        } else {
            Err(Error::Unauthenticated("invalid token".into()))
        }
    }
}

/// The axum middleware enforcing [`ApiKeys`].
pub(crate) async fn require_token(
    State(keys): State<ApiKeys>,
    req: Request,
    next: Next,
) -> Response {
    match keys.check(&req) {
        Ok(()) => next.run(req).await,
        Err(e) => {
            keys.metrics.error(&e);
            if is_grpc(&req) {
                crate::grpc::status(e).into_http::<axum::body::Body>()
            } else {
                crate::http::HttpError(e).into_response()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(path: &str, auth: Option<&str>) -> Request {
        let mut b = http::Request::builder().uri(path);
        if let Some(a) = auth {
            b = b.header("authorization", a);
        }
        b.body(axum::body::Body::empty()).unwrap()
    }

    #[test]
    fn tokens_are_checked_except_on_exempt_paths() {
        let keys = ApiKeys::new(&["s3cret".into(), " other ".into()], Metrics::new());
        assert!(
            keys.check(&req("/v1/scenes", Some("Bearer s3cret")))
                .is_ok()
        );
        assert!(keys.check(&req("/v1/scenes", Some("Bearer other"))).is_ok());
        assert!(
            keys.check(&req("/v1/scenes", Some("Bearer s3cre")))
                .is_err()
        );
        assert!(keys.check(&req("/v1/scenes", Some("s3cret"))).is_err());
        assert!(keys.check(&req("/v1/scenes", None)).is_err());
        assert!(keys.check(&req("/healthz", None)).is_ok());
        assert!(keys.check(&req("/", None)).is_ok());
        assert!(keys.check(&req("/viewer.js", None)).is_ok());
        assert!(keys.check(&req("/v1/scenes/x/events", None)).is_err());
        assert!(
            keys.check(&req("/grpc.health.v1.Health/Check", None))
                .is_ok()
        );
        let open = ApiKeys::new(&[], Metrics::new());
        assert!(open.check(&req("/v1/scenes", None)).is_ok());
    }
}

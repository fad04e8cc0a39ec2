//! Optional bearer-token authentication for every API call on both transports. Health,
//! readiness, metrics, the gRPC health service and the live viewer's page and assets (they
//! hold no data; the page asks for the token and sends it on its API calls) are exempt. A gRPC caller gets an
//! `UNAUTHENTICATED` status, an HTTP caller a 401.
//!
//! Authentication fails closed: a key source that yields a blank key is a start-up error
//! ([`ApiKeys::new`]), never "no key, so no authentication". Independently of keys, a browser
//! page of another origin cannot write: a state-changing request (anything but GET, HEAD and
//! OPTIONS) that a browser marks as cross-origin (`Origin` not this server, or
//! `Sec-Fetch-Site: cross-site`/`same-site`) is refused with 403 ([`same_origin`]).
use std::sync::Arc;

use axum::extract::{Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

use super::metrics::Metrics;
use crate::error::Error;

/// The accepted keys (empty = authentication off).
#[derive(Clone)]
pub(crate) struct ApiKeys {
    keys: Arc<Vec<Vec<u8>>>,
    metrics: Metrics,
    /// Paths the transports serve without data (the viewer's page and assets).
    public: fn(&str) -> bool,
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

/// Paths that never need a token (besides the transports' `public` ones).
fn exempt(path: &str) -> bool {
    matches!(path, "/healthz" | "/readyz" | "/metrics") || path.starts_with("/grpc.health.v1.")
}

/// True for gRPC requests (content-type `application/grpc[+proto]`).
pub(crate) fn is_grpc(req: &Request) -> bool {
    req.headers()
        .get(http::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/grpc"))
}

impl ApiKeys {
    /// [`Self::check`], counting a refusal (once, here).
    pub(crate) fn admit(&self, req: &Request) -> Result<(), Error> {
        self.check(req).inspect_err(|e| self.metrics.error(e))
    }

    /// Accepts any of `keys` (surrounding white space trimmed); no keys = authentication off.
    /// A blank key is an error: it would otherwise turn authentication off silently. `public`
    /// says which further paths hold no data (the viewer's page and assets).
    pub fn new(keys: &[String], metrics: Metrics, public: fn(&str) -> bool) -> Result<Self, Error> {
        let mut out = Vec::with_capacity(keys.len());
        for (i, k) in keys.iter().enumerate() {
            let k = k.trim();
            if k.is_empty() {
                return Err(Error::invalid(
                    "--api-key",
                    format!(
                        "API key {} of {} is blank; refusing to start",
                        i + 1,
                        keys.len()
                    ),
                ));
            }
            out.push(k.as_bytes().to_vec());
        }
        Ok(ApiKeys {
            keys: Arc::new(out),
            metrics,
            public,
        })
    }

    /// Checks the `authorization: Bearer <key>` header of a request.
    pub fn check(&self, req: &Request) -> Result<(), Error> {
        let path = req.uri().path();
        if self.keys.is_empty() || exempt(path) || (self.public)(path) {
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
                // The scheme is case-insensitive (RFC 9110 §11.1).
                let (scheme, token) = h.trim_start().split_once(' ')?;
                scheme.eq_ignore_ascii_case("bearer").then_some(token)
            })
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .ok_or_else(|| Error::Unauthenticated("expected 'Bearer <token>'".into()))?;
        if self.keys.iter().any(|k| ct_eq(k, token.as_bytes())) {
            Ok(())
        } else {
            Err(Error::Unauthenticated("invalid token".into()))
        }
    }
}

/// True when a browser marks `req` as made by a page of another origin: `Sec-Fetch-Site`
/// says `cross-site` or `same-site`, or `Origin` is present and names another host than the
/// request's `Host` (`null` included). Non-browser clients send neither header.
fn cross_origin(req: &Request) -> bool {
    let headers = req.headers();
    if let Some(site) = headers.get("sec-fetch-site").and_then(|v| v.to_str().ok())
        && (site.eq_ignore_ascii_case("cross-site") || site.eq_ignore_ascii_case("same-site"))
    {
        return true;
    }
    let Some(origin) = headers.get(http::header::ORIGIN) else {
        return false;
    };
    let host = headers
        .get(http::header::HOST)
        .and_then(|v| v.to_str().ok())
        .map(str::to_string)
        .or_else(|| req.uri().authority().map(|a| a.to_string()));
    let origin_host = origin
        .to_str()
        .ok()
        .and_then(|o| o.split_once("://"))
        .map(|(_, rest)| rest.trim_end_matches('/'));
    match (origin_host, host) {
        (Some(o), Some(h)) => !o.eq_ignore_ascii_case(&h),
        _ => true,
    }
}

/// The axum middleware refusing state-changing requests from pages of other origins (see
/// the module docs): without it, any web page a user of the server's network opens could
/// push batches or trigger reloads with a "simple" request that needs no CORS preflight.
pub(crate) async fn same_origin(
    State(metrics): State<Metrics>,
    req: Request,
    next: Next,
) -> Response {
    let safe = matches!(
        *req.method(),
        http::Method::GET | http::Method::HEAD | http::Method::OPTIONS
    );
    if safe || is_grpc(&req) || !cross_origin(&req) {
        return next.run(req).await;
    }
    metrics.error_kind("forbidden");
    let body = serde_json::json!({ "error": {
        "kind": "forbidden",
        "message": "cross-origin request refused: this API does not accept writes from web pages of other origins",
        "field": null,
    }});
    (http::StatusCode::FORBIDDEN, axum::Json(body)).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transport::http::viewer::is_asset as viewer;

    fn req(path: &str, auth: Option<&str>) -> Request {
        let mut b = http::Request::builder().uri(path);
        if let Some(a) = auth {
            b = b.header("authorization", a);
        }
        b.body(axum::body::Body::empty()).unwrap()
    }

    #[test]
    fn tokens_are_checked_except_on_exempt_paths() {
        let keys =
            ApiKeys::new(&["s3cret".into(), " other ".into()], Metrics::new(), viewer).unwrap();
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
        let open = ApiKeys::new(&[], Metrics::new(), viewer).unwrap();
        assert!(open.check(&req("/v1/scenes", None)).is_ok());
        // The scheme is case-insensitive; an empty token is no token.
        assert!(
            keys.check(&req("/v1/scenes", Some("BEARER s3cret")))
                .is_ok()
        );
        assert!(
            keys.check(&req("/v1/scenes", Some("bEaReR  s3cret")))
                .is_ok()
        );
        assert!(
            keys.check(&req("/v1/scenes", Some("Basic s3cret")))
                .is_err()
        );
        assert!(keys.check(&req("/v1/scenes", Some("Bearer "))).is_err());
    }

    #[test]
    fn a_blank_key_is_an_error_not_authentication_off() {
        for keys in [
            vec![String::new()],
            vec![" ".into()],
            vec!["k".into(), "\t".into()],
        ] {
            assert!(
                ApiKeys::new(&keys, Metrics::new(), viewer).is_err(),
                "{keys:?}"
            );
        }
    }

    #[test]
    fn pages_of_other_origins_are_told_apart() {
        let r = |headers: &[(&str, &str)]| {
            let mut b = http::Request::builder()
                .uri("/v1/admin/reload")
                .method("POST");
            for (k, v) in headers {
                b = b.header(*k, *v);
            }
            b.body(axum::body::Body::empty()).unwrap()
        };
        assert!(!cross_origin(&r(&[("host", "127.0.0.1:8080")])));
        assert!(!cross_origin(&r(&[
            ("host", "a:1"),
            ("origin", "http://a:1")
        ])));
        assert!(cross_origin(&r(&[
            ("host", "a:1"),
            ("origin", "http://evil.example")
        ])));
        assert!(cross_origin(&r(&[("host", "a:1"), ("origin", "null")])));
        assert!(cross_origin(&r(&[("sec-fetch-site", "cross-site")])));
        assert!(!cross_origin(&r(&[("sec-fetch-site", "same-origin")])));
    }
}

//! The one router of gRPC and HTTP on a port: the gRPC services (association with its own
//! `Push`/`Stream` framing, health, reflection) and the HTTP routes, and the middleware every
//! request passes (request accounting, same-origin check, API keys, body limits), with each
//! rejection in its transport's form.
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{MatchedPath, Request, State};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use tower::ServiceExt;

use crate::config::ServeConfig;
use crate::error::{Error, Result};
use crate::service::Service;
use crate::transport::grpc::{self, push};
use crate::transport::http;
use crate::{auth, body, metrics};

/// A tonic service mounted on an axum path prefix; each request body is bounded per message
/// by `body_timeout` ([`body::GrpcMessageDeadline`]).
fn grpc_route<S>(router: Router, svc: S, body_timeout: Duration) -> Router
where
    S: tower::Service<::http::Request<tonic::body::Body>, Error = std::convert::Infallible>
        + tonic::server::NamedService
        + Clone
        + Send
        + Sync
        + 'static,
    S::Response: IntoResponse,
    S::Future: Send + 'static,
{
    router.route_service(
        &format!("/{}/{{*rest}}", S::NAME),
        svc.map_request(move |r: Request| {
            r.map(|b| tonic::body::Body::new(body::GrpcMessageDeadline::new(b, body_timeout)))
        }),
    )
}

async fn fallback(req: Request) -> Response {
    if auth::is_grpc(&req) {
        tonic::Status::unimplemented(format!("no such method {}", req.uri().path()))
            .into_http::<axum::body::Body>()
    } else {
        let body = crossview_api::types::ErrorBody {
            error: crossview_api::types::ErrorDetail {
                kind: "not_found".into(),
                message: format!(
                    "no such route: {}",
                    crate::echo::truncate_echo(req.uri().path())
                ),
                field: None,
            },
        };
        (::http::StatusCode::NOT_FOUND, axum::Json(body)).into_response()
    }
}

pub(crate) async fn build_router(svc: &Arc<Service>, config: &ServeConfig) -> Result<Router> {
    use crossview_api::pb;
    use pb::association_server::AssociationServer;
    let limit = config.limits.max_request_bytes;
    let (reporter, health) = tonic_health::server::health_reporter();
    // The reporter starts with "" = SERVING; mark the service itself too.
    reporter
        .set_serving::<AssociationServer<grpc::GrpcService>>()
        .await;
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(|e| Error::internal_from("cannot build the gRPC reflection service", e))?;
    let grpc = grpc::GrpcService::new(svc.clone(), config.connections.subscriber_stall_timeout);
    let generated = AssociationServer::new(grpc.clone())
        .max_decoding_message_size(limit)
        .max_encoding_message_size(usize::MAX);
    let association = push::Routes::new(generated, grpc, limit);
    let mut router = Router::new();
    let body_timeout = config.connections.body_timeout;
    router = grpc_route(router, association, body_timeout);
    router = grpc_route(router, health, body_timeout);
    router = grpc_route(router, reflection, body_timeout);
    let body_limits = body::BodyLimits {
        max_bytes: limit,
        timeout: body_timeout,
    };
    let keys = auth::ApiKeys::new(
        &config.api_keys,
        svc.metrics().clone(),
        http::viewer::is_asset,
    )?;
    Ok(router
        .merge(
            http::router(svc.clone(), limit).layer(middleware::from_fn_with_state(
                body_limits,
                body::buffer_body,
            )),
        )
        .fallback(fallback)
        .layer(middleware::from_fn_with_state(keys, require_token))
        .layer(middleware::from_fn_with_state(
            svc.metrics().clone(),
            auth::same_origin,
        ))
        .layer(middleware::from_fn_with_state(
            svc.metrics().clone(),
            track_requests,
        )))
}

/// Counts every request by transport, route and outcome, and times it to the response head.
async fn track_requests(State(m): State<metrics::Metrics>, req: Request, next: Next) -> Response {
    let grpc = auth::is_grpc(&req);
    let method = request_label(&req, grpc);
    let t = Instant::now();
    let resp = next.run(req).await;
    let status = if grpc {
        // Server-made, but parsed into the closed set of gRPC codes all the same.
        let code = resp
            .headers()
            .get("grpc-status")
            .and_then(|v| v.to_str().ok())
            .map_or(Some(0), |v| v.parse::<u8>().ok().filter(|c| *c <= 16));
        code.map_or_else(|| "other".to_string(), |c| c.to_string())
    } else {
        resp.status().as_u16().to_string()
    };
    if let Some(metrics::UncountedError(kind)) = resp.extensions().get() {
        m.error_kind(kind);
    }
    let transport = if grpc { "grpc" } else { "http" };
    m.request(transport, &method, &status, t.elapsed());
    resp
}

/// The `method` label of a request, from a closed set: a known gRPC method path or `other`;
/// for HTTP a standard verb (else `OTHER`) and the matched route template, or `unmatched`.
fn request_label(req: &Request, grpc: bool) -> String {
    if grpc {
        let path = req.uri().path();
        return grpc::METHODS
            .iter()
            .find(|m| **m == path)
            .map_or("other", |m| m)
            .to_string();
    }
    match req.extensions().get::<MatchedPath>() {
        Some(p) => {
            let verb = match req.method().as_str() {
                v @ ("GET" | "POST" | "HEAD" | "PUT" | "DELETE" | "PATCH" | "OPTIONS") => v,
                _ => "OTHER",
            };
            format!("{verb} {}", p.as_str())
        }
        None => "unmatched".to_string(),
    }
}

/// The axum middleware enforcing [`ApiKeys`].
async fn require_token(State(keys): State<auth::ApiKeys>, req: Request, next: Next) -> Response {
    match keys.admit(&req) {
        Ok(()) => next.run(req).await,
        Err(e) => {
            if auth::is_grpc(&req) {
                grpc::status(e).into_http::<axum::body::Body>()
            } else {
                http::HttpError(e).into_response()
            }
        }
    }
}

//! The streaming association service: gRPC (tonic) and HTTP JSON (axum) over one port.
//!
//! Layout (one job per module): [`config`] settings; [`registry`] model loading; [`sync`] the
//! pure frame synchronizer; [`scene`] a live scene (synchronizer + encoder worker thread +
//! results broadcast); [`engine`] association of one frame; [`service`] the one domain API;
//! [`grpc`] and [`http`] thin transports with the error mappings; [`auth`], [`tls`],
//! [`metrics`]; this module binds them into one listener with graceful shutdown.
//!
//! Tests and the CLI start it the same way: [`Server::load`] (or [`run`]) then
//! [`Server::serve`] on a bound listener with a shutdown future.

pub mod api;
pub mod auth;
pub mod config;
pub mod engine;
pub mod grpc;
pub mod http;
pub mod metrics;
pub mod registry;
pub mod scene;
pub mod service;
pub mod sync;
pub mod tls;

/// Generated protobuf and tonic code for `crossview.v1`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("crossview.v1");
    /// The encoded file descriptor set (for gRPC reflection).
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        tonic::include_file_descriptor_set!("crossview_descriptor");
}

use std::future::Future;
use std::sync::Arc;
use std::time::Instant;

use axum::Router;
use axum::extract::{MatchedPath, Request, State};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tower::ServiceExt;

pub use config::{Limits, ModelSpec, ServeConfig, TlsConfig};
pub use scene::{Scene, SceneInfo};
pub use service::Service;

use crate::model::Encoder;
use crate::{Error, Result};

/// A configured server with its scenes started, ready to [`serve`](Server::serve).
#[derive(Debug)]
pub struct Server {
    service: Arc<Service>,
    config: ServeConfig,
}

impl Server {
    /// Loads every model of `config` (blocking: ONNX Runtime sessions) and starts its scenes.
    pub fn load(config: ServeConfig) -> Result<Self> {
        let mut scenes = Vec::new();
        for m in &config.models {
            scenes.push(registry::load_model(m, &config.limits)?);
        }
        Self::from_scenes(config, scenes)
    }

    /// Starts a server over already loaded encoders (tests, fuzzing, embedding).
    pub fn from_scenes(
        config: ServeConfig,
        scenes: Vec<(SceneInfo, Box<dyn Encoder>)>,
    ) -> Result<Self> {
        let metrics = metrics::Metrics::new();
        let mut started = Vec::new();
        let mut names = std::collections::BTreeSet::new();
        for (info, encoder) in scenes {
            if !names.insert(info.spec.name.clone()) {
                return Err(Error::invalid(
                    "--model",
                    format!("scene '{}' given twice", info.spec.name),
                ));
            }
            tracing::info!(scene = %info.spec.name, cameras = info.spec.cameras.len(), version = %info.version, "scene loaded");
            started.push(Scene::start(
                info,
                encoder,
                config.sync_timeout,
                config.max_pending_frames,
                config.limits,
                metrics.clone(),
            )?);
        }
        Ok(Server {
            service: Arc::new(Service::new(started, metrics)),
            config,
        })
    }

    /// The domain service (for in-process use).
    pub fn service(&self) -> &Arc<Service> {
        &self.service
    }

    /// The combined gRPC + HTTP router with auth and request accounting.
    pub async fn router(&self) -> Result<Router> {
        build_router(&self.service, &self.config).await
    }

    /// Serves gRPC and HTTP on `listener` until `shutdown` resolves, then shuts down gracefully:
    /// stops intake, flushes pending frames as partial results to subscribers, waits up to
    /// `shutdown_grace` for open connections and returns.
    pub async fn serve(
        self,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<()> {
        let router = self.router().await?;
        let tls = self.config.tls.as_ref().map(tls::acceptor).transpose()?;
        let addr = listener.local_addr().ok();
        tracing::info!(?addr, tls = tls.is_some(), "serving gRPC + HTTP");
        for scene in self.service.scene_list() {
            spawn_timer(scene, self.service.shutting_down());
        }
        let graceful = hyper_util::server::graceful::GracefulShutdown::new();
        let builder = auto::Builder::new(TokioExecutor::new());
        tokio::pin!(shutdown);
        loop {
            let (stream, peer) = tokio::select! {
                r = listener.accept() => match r {
                    Ok(c) => c,
                    Err(e) => {
                        tracing::warn!(error = %e, "accept failed");
                        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                        continue;
                    }
                },
                _ = &mut shutdown => break,
            };
            let _ = stream.set_nodelay(true);
            let svc = TowerToHyperService::new(
                router
                    .clone()
                    .map_request(|r: Request<hyper::body::Incoming>| r.map(axum::body::Body::new)),
            );
            let builder = builder.clone();
            let watcher = graceful.watcher();
            let tls = tls.clone();
            tokio::spawn(async move {
                let r = match tls {
                    Some(acc) => match acc.accept(stream).await {
                        Ok(s) => {
                            let conn = builder.serve_connection_with_upgrades(TokioIo::new(s), svc);
                            watcher.watch(conn.into_owned()).await
                        }
                        Err(e) => {
                            tracing::debug!(%peer, error = %e, "TLS handshake failed");
                            return;
                        }
                    },
                    None => {
                        let conn =
                            builder.serve_connection_with_upgrades(TokioIo::new(stream), svc);
                        watcher.watch(conn.into_owned()).await
                    }
                };
                if let Err(e) = r {
                    tracing::debug!(%peer, error = %e, "connection ended with error");
                }
            });
        }
        drop(listener);
        tracing::info!("shutdown: stopping intake and flushing pending frames");
        let service = self.service.clone();
        tokio::task::spawn_blocking(move || service.close())
            .await
            .map_err(|e| Error::Runtime(format!("shutdown task failed: {e}")))?;
        tracing::info!("shutdown: frames flushed, closing connections");
        if tokio::time::timeout(self.config.shutdown_grace, graceful.shutdown())
            .await
            .is_err()
        {
            tracing::warn!("shutdown: grace period over, dropping open connections");
        }
        Ok(())
    }
}

/// Loads the models (off the async runtime) and serves until `shutdown` (see [`Server::serve`]).
pub async fn run(
    config: ServeConfig,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<()> {
    let server = tokio::task::spawn_blocking(move || Server::load(config))
        .await
        .map_err(|e| Error::Runtime(format!("model loading task failed: {e}")))??;
    server.serve(listener, shutdown).await
}

/// Resolves on Ctrl-C or SIGTERM (the binary's shutdown trigger).
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
    tracing::info!("shutdown signal received");
}

/// Drives a scene's synchronizer timeouts: wakes at the earliest deadline or when a batch
/// arrives, until shutdown.
fn spawn_timer(scene: Arc<Scene>, stop: impl Future<Output = ()> + Send + 'static) {
    tokio::spawn(async move {
        tokio::pin!(stop);
        loop {
            let next = scene.tick(Instant::now());
            let sleep = async {
                match next {
                    Some(t) => tokio::time::sleep_until(tokio::time::Instant::from_std(t)).await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                _ = scene.wake.notified() => {},
                _ = sleep => {},
                _ = &mut stop => break,
            }
        }
    });
}

/// A tonic service mounted on an axum path prefix.
fn grpc_route<S>(router: Router, svc: S) -> Router
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
        svc.map_request(|r: Request| r.map(tonic::body::Body::new)),
    )
}

async fn fallback(req: Request) -> Response {
    if auth::is_grpc(&req) {
        tonic::Status::unimplemented(format!("no such method {}", req.uri().path()))
            .into_http::<axum::body::Body>()
    } else {
        (::http::StatusCode::NOT_FOUND, "not found").into_response()
    }
}

async fn build_router(svc: &Arc<Service>, config: &ServeConfig) -> Result<Router> {
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
        .map_err(|e| Error::Runtime(format!("gRPC reflection: {e}")))?;
    let association = AssociationServer::new(grpc::GrpcService::new(svc.clone()))
        .max_decoding_message_size(limit)
        .max_encoding_message_size(usize::MAX);
    let mut router = Router::new();
    router = grpc_route(router, association);
    router = grpc_route(router, health);
    router = grpc_route(router, reflection);
    let keys = auth::ApiKeys::new(&config.api_keys, svc.metrics().clone());
    Ok(router
        .merge(http::router(svc.clone(), limit))
        .fallback(fallback)
        .layer(middleware::from_fn_with_state(keys, auth::require_token))
        .layer(middleware::from_fn_with_state(
            svc.metrics().clone(),
            track_requests,
        )))
}

/// Counts every request by transport, route and outcome, and times it to the response head.
async fn track_requests(State(m): State<metrics::Metrics>, req: Request, next: Next) -> Response {
    let grpc = auth::is_grpc(&req);
    let method = match req.extensions().get::<MatchedPath>() {
        Some(_) if grpc => req.uri().path().to_string(),
        Some(p) => format!("{} {}", req.method(), p.as_str()),
        None => "unmatched".to_string(),
    };
    let t = Instant::now();
    let resp = next.run(req).await;
    let status = if grpc {
        resp.headers()
            .get("grpc-status")
            .and_then(|v| v.to_str().ok())
            .unwrap_or("0")
            .to_string()
    } else {
        resp.status().as_u16().to_string()
    };
    if let Some(http::UncountedError(kind)) = resp.extensions().get() {
        m.error(kind);
    }
    let transport = if grpc { "grpc" } else { "http" };
    m.request(transport, &method, &status, t.elapsed());
    resp
}

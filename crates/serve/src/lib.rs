//! The streaming association service: gRPC (tonic) and HTTP JSON (axum) over one port.
//!
//! Layout (one job per module; imports run down these layers): the domain — [`sync`] the pure
//! frame synchronizer, [`scene`] a live scene (validation, admission, the encoder worker
//! thread, the clock watch, results broadcast), [`registry`] model loading, [`reload`] live
//! model swaps, [`record`] the recording of accepted batches (`--record`), [`heal`] retraining
//! and swapping in a model when a camera stopped fitting (`--auto-retrain`), [`service`] the one
//! domain API; the [`transport`]s, one folder each — [`transport::grpc`] (with the `Push` and
//! `Stream` calls' own request framing), [`transport::http`] (with the live viewer) and
//! [`transport::kafka`] — each mapping the one server [`Error`] in its own way (wire types and
//! conversions: `crossview-api`); cross-cutting — [`error`] (the method's errors, wrapped,
//! and serving's own), [`config`], [`auth`], [`body`], `conn`, [`tls`], [`metrics`]; `router`
//! binds the transports and the middleware into one router, and this module runs it on one
//! listener with graceful shutdown. The layers drawn, for a newcomer: the crate's `README.md`.
//!
//! Where things go: a new transport in `transport/<name>/`, calling [`Service`]; a new scene
//! setting in [`scene::SceneOptions`] (and the flag in [`config`]); a new Kafka option in
//! `transport/kafka/config.rs`.
//!
//! Tests and the CLI start it the same way: [`Server::load`] (or [`run`]) then
//! [`Server::serve`] on a bound listener with a shutdown future.

pub mod auth;
pub mod body;
pub mod config;
pub(crate) mod conn;
pub mod cost;
mod echo;
pub mod error;
pub mod heal;
mod locks;
pub mod metrics;
pub mod record;
pub mod registry;
pub mod reload;
mod router;
pub mod scene;
pub mod service;
pub(crate) mod subscribers;
pub mod sync;
pub mod tls;
pub mod transport;

use std::future::Future;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::Request;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::service::TowerToHyperService;
use tokio::net::TcpListener;
use tower::ServiceExt;

pub use config::{ConnectionLimits, Limits, ModelSpec, ServeConfig, TlsConfig};
pub use error::{Error, Result};
pub use heal::HealConfig;
pub use record::RecordConfig;
pub use registry::SceneInfo;
pub use scene::Scene;
pub use service::Service;
pub use transport::http::routes::openapi_json;
pub use transport::kafka::{GroupProtocol, KafkaConfig, TimestampSource, ValueFormat};

use crossview_core::Encoder;

/// A configured server with its scenes started, ready to [`serve`](Server::serve).
#[derive(Debug)]
pub struct Server {
    service: Arc<Service>,
    config: ServeConfig,
    recorder: Option<Arc<record::Recorder>>,
    /// `SIGHUP` listener taken before the models loaded ([`run`]), so a reload asked for
    /// while they load is served once the server runs.
    #[cfg(unix)]
    hangup: Option<tokio::signal::unix::Signal>,
}

/// Refuses healing settings that cannot heal, and healing without a recording to learn from.
fn check_heal(config: &ServeConfig) -> Result<()> {
    let Some(h) = &config.heal else {
        return Ok(());
    };
    h.validate()?;
    if config.record.is_none() {
        return Err(Error::invalid(
            "--auto-retrain",
            "needs --record: a retrain learns from what the server recorded",
        ));
    }
    Ok(())
}

/// Logs a scene as it starts: its model's version, or that it has none yet.
fn log_scene(spec: &crossview_core::SceneSpec, model: Option<&SceneInfo>) {
    match model {
        Some(info) => {
            tracing::info!(scene = %spec.name, cameras = spec.cameras.len(), version = %info.version, "scene loaded")
        }
        None => {
            tracing::info!(scene = %spec.name, cameras = spec.cameras.len(), "scene declared without a model: frames are published unassociated")
        }
    }
}

impl Server {
    /// Loads every model of `config` (blocking: ONNX Runtime sessions) and starts its scenes
    /// and its declared ones. A model of a declared scene whose file does not exist yet is
    /// loaded on the first reload that finds it.
    pub fn load(config: ServeConfig) -> Result<Self> {
        let mut scenes = Vec::new();
        for m in &config.models {
            let declared = config.scenes.iter().any(|d| d.spec.name == m.name);
            if declared && !m.path.exists() {
                tracing::info!(scene = %m.name, path = %m.path.display(), "no model file yet; the scene starts without one");
                continue;
            }
            scenes.push(registry::load_model(m, &config.limits)?);
        }
        Self::from_scenes(config, scenes)
    }

    /// Starts a server over already loaded encoders (tests, fuzzing, embedding), plus the
    /// scenes `config` declares by their cameras (a loaded model of the same name must fit
    /// the declared cameras).
    pub fn from_scenes(
        config: ServeConfig,
        scenes: Vec<(SceneInfo, Box<dyn Encoder>)>,
    ) -> Result<Self> {
        let metrics = metrics::Metrics::new();
        let mut models: std::collections::BTreeMap<String, (SceneInfo, Box<dyn Encoder>)> =
            Default::default();
        for (info, encoder) in scenes {
            let name = info.spec.name.clone();
            if models.insert(name.clone(), (info, encoder)).is_some() {
                return Err(Error::invalid(
                    "--model",
                    format!("scene '{name}' given twice"),
                ));
            }
        }
        let mut specs: Vec<crossview_core::SceneSpec> = Vec::new();
        // Each scene's frame rate: declared, else the model's training rate.
        let mut rates: Vec<record::SceneRate> = Vec::new();
        for d in &config.scenes {
            if specs.iter().any(|s| s.name == d.spec.name) {
                return Err(Error::invalid(
                    "--scene",
                    format!("scene '{}' declared twice", d.spec.name),
                ));
            }
            specs.push(d.spec.clone());
            rates.push(record::SceneRate {
                declared: d.fps,
                clock: d
                    .fps
                    .or_else(|| models.get(&d.spec.name).and_then(|m| m.0.fps)),
            });
        }
        for (name, (info, _)) in &models {
            if !specs.iter().any(|s| &s.name == name) {
                specs.push(info.spec.clone());
                rates.push(record::SceneRate {
                    declared: None,
                    clock: info.fps,
                });
            }
        }
        check_heal(&config)?;
        let recorder = match &config.record {
            Some(rc) => Some(record::Recorder::start(
                rc.clone(),
                &specs,
                &rates,
                metrics.clone(),
            )?),
            None => None,
        };
        let threads = match config.inference_threads {
            0 => std::thread::available_parallelism().map_or(1, usize::from),
            n => n,
        };
        let pool = Arc::new(scene::Pool::start(threads)?);
        tracing::info!(threads, "inference pool started");
        let mut started = Vec::new();
        for (k, (spec, rate)) in specs.into_iter().zip(rates).enumerate() {
            let model = models.remove(&spec.name);
            log_scene(&spec, model.as_ref().map(|(info, _)| info));
            let options = scene::SceneOptions {
                sync_timeout: config.sync_timeout,
                max_pending_frames: config.max_pending_frames,
                limits: config.limits,
                tracker: config.tracker.clone(),
                memory: config.memory.clone(),
                pool: pool.clone(),
                fps: rate.clock,
                time_tolerance: config.time_tolerance,
            };
            started.push(Scene::start(
                spec,
                model,
                options,
                metrics.clone(),
                recorder.as_ref().map(|r| r.scene(k)),
            )?);
        }
        let reloader = reload::Reloader::new(config.models.clone(), config.limits);
        Ok(Server {
            service: Arc::new(
                Service::new(started, metrics)
                    .with_subscriber_limits(&config.connections)
                    .with_stall_timeout(config.connections.subscriber_stall_timeout)
                    .with_reloader(reloader),
            ),
            config,
            recorder,
            #[cfg(unix)]
            hangup: None,
        })
    }

    /// The domain service (for in-process use).
    pub fn service(&self) -> &Arc<Service> {
        &self.service
    }

    /// The combined gRPC + HTTP router with auth and request accounting.
    pub(crate) async fn router(&self) -> Result<Router> {
        router::build_router(&self.service, &self.config).await
    }

    /// Serves gRPC and HTTP on `listener` until `shutdown` resolves, then shuts down gracefully:
    /// stops intake, flushes pending frames as partial results to subscribers, waits up to
    /// `shutdown_grace` for open connections and returns.
    pub async fn serve(
        mut self,
        listener: TcpListener,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<()> {
        let router = self.router().await?;
        let tls = self.config.tls.as_ref().map(tls::acceptor).transpose()?;
        let addr = listener.local_addr().ok();
        check_exposure(&self.config, addr)?;
        tracing::info!(?addr, tls = tls.is_some(), "serving gRPC + HTTP");
        for scene in self.service.scene_list() {
            spawn_timer(scene, self.service.shutting_down());
        }
        let kafka = match &self.config.kafka {
            Some(k) => Some(transport::kafka::start(self.service.clone(), k.clone())?),
            None => None,
        };
        #[cfg(unix)]
        if self.config.reload_on_sighup {
            let hup = match self.hangup.take() {
                Some(h) => h,
                None => reload::listen_sighup()?,
            };
            service::spawn_reload_on_sighup(self.service.clone(), hup);
        }
        if let Some(h) = &self.config.heal {
            heal::spawn(self.service.clone(), h.clone());
        }
        let limits = self.config.connections;
        let connections = conn::Connections::new(limits, self.service.metrics().clone());
        let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
        let builder = connection_builder(&limits);
        tokio::pin!(shutdown);
        let mut refused_logged: Option<Instant> = None;
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
            let Some(guard) = connections.admit() else {
                // Refused at the cap: close at once. Log at most once a second.
                if refused_logged.is_none_or(|t| t.elapsed() >= Duration::from_secs(1)) {
                    tracing::warn!(%peer, max = limits.max_connections, "connection cap reached, refusing connections");
                    refused_logged = Some(Instant::now());
                }
                drop(stream);
                continue;
            };
            let connection = Connection {
                router: router.clone(),
                builder: builder.clone(),
                tls: tls.clone(),
                limits,
                stop: stop_rx.clone(),
            };
            connection.spawn(stream, peer, guard);
        }
        drop(listener);
        self.shut_down(kafka, &connections, stop_tx).await
    }

    /// Graceful shutdown once the listener is closed: stops intake and flushes pending frames
    /// (and the recording queue), lets Kafka produce the flushed results, then closes the
    /// connections, dropping those still open after the grace period.
    async fn shut_down(
        &self,
        kafka: Option<tokio::task::JoinHandle<()>>,
        connections: &conn::Connections,
        stop_tx: tokio::sync::watch::Sender<bool>,
    ) -> Result<()> {
        let deadline = Instant::now() + self.config.shutdown_grace;
        tracing::info!("shutdown: stopping intake and flushing pending frames");
        let service = self.service.clone();
        let recorder = self.recorder.clone();
        tokio::task::spawn_blocking(move || {
            service.close_by(Some(deadline));
            // No batch is accepted any more: write out the recording queue.
            if let Some(r) = recorder {
                r.close();
            }
        })
        .await
        .map_err(|e| Error::internal_from("shutdown task failed", e))?;
        if let Some(task) = kafka {
            // The flushed results are produced and their offsets committed.
            let until = deadline.max(Instant::now() + Duration::from_secs(5));
            if tokio::time::timeout_at(until.into(), task).await.is_err() {
                tracing::warn!("shutdown: kafka results not all produced in the grace period");
            }
        }
        tracing::info!("shutdown: frames flushed, closing connections");
        let _ = stop_tx.send(true);
        let until = deadline.max(Instant::now() + Duration::from_millis(200));
        if tokio::time::timeout_at(until.into(), connections.drained())
            .await
            .is_err()
        {
            tracing::warn!(
                open = connections.len(),
                "shutdown: grace period over, dropping open connections"
            );
            connections.kill_all();
        }
        Ok(())
    }
}

/// The HTTP/1 + HTTP/2 connection builder with the connection limits. Encoded results a
/// stream that is not read may hold in the transport are bounded
/// (`subscribers::TRANSPORT_BUFFER`): the subscriber budget charges each stream for it.
fn connection_builder(limits: &ConnectionLimits) -> auto::Builder<TokioExecutor> {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .max_buf_size(subscribers::TRANSPORT_BUFFER)
        .header_read_timeout(limits.header_read_timeout);
    builder
        .http2()
        .timer(TokioTimer::new())
        .max_send_buf_size(subscribers::TRANSPORT_BUFFER)
        .max_concurrent_streams(limits.http2_max_streams)
        .keep_alive_interval(limits.http2_keepalive)
        .keep_alive_timeout(limits.http2_keepalive);
    builder
}

/// What serving one accepted connection needs.
struct Connection {
    router: Router,
    builder: auto::Builder<TokioExecutor>,
    tls: Option<tokio_rustls::TlsAcceptor>,
    limits: ConnectionLimits,
    stop: tokio::sync::watch::Receiver<bool>,
}

impl Connection {
    /// Serves `stream` on its own task (TLS handshake first when configured) until it ends or
    /// the server stops; `guard` holds its slot under the connection cap.
    fn spawn(
        self,
        stream: tokio::net::TcpStream,
        peer: std::net::SocketAddr,
        guard: conn::ConnGuard,
    ) {
        let Connection {
            router,
            builder,
            tls,
            limits,
            stop,
        } = self;
        let _ = stream.set_nodelay(true);
        let state = guard.state.clone();
        let svc = TowerToHyperService::new(tower::service_fn(
            move |r: Request<hyper::body::Incoming>| {
                let active = state.begin();
                let mut r = r.map(axum::body::Body::new);
                r.extensions_mut().insert(conn::ConnHandle(state.clone()));
                let router = router.clone();
                async move {
                    let resp = router.oneshot(r).await?;
                    Ok::<_, std::convert::Infallible>(
                        resp.map(|b| axum::body::Body::new(conn::Tracked::new(b, active))),
                    )
                }
            },
        ));
        tokio::spawn(async move {
            let state = guard.state.clone();
            let r = match tls {
                Some(acc) => {
                    match tokio::time::timeout(limits.header_read_timeout, acc.accept(stream)).await
                    {
                        Ok(Ok(s)) => {
                            let conn = builder.serve_connection_with_upgrades(TokioIo::new(s), svc);
                            conn::drive(conn.into_owned(), state, limits, stop).await
                        }
                        Ok(Err(e)) => {
                            tracing::debug!(%peer, error = %e, "TLS handshake failed");
                            return;
                        }
                        Err(_) => {
                            tracing::debug!(%peer, "TLS handshake timed out");
                            return;
                        }
                    }
                }
                None => {
                    let conn = builder.serve_connection_with_upgrades(TokioIo::new(stream), svc);
                    conn::drive(conn.into_owned(), state, limits, stop).await
                }
            };
            if let Err(e) = r {
                tracing::debug!(%peer, error = %e, "connection ended with error");
            }
            drop(guard);
        });
    }
}

/// Refuses to serve without API keys on an address beyond loopback unless the configuration
/// says so explicitly (`allow_unauthenticated`): anyone who can reach the port could otherwise
/// push, read and reload.
fn check_exposure(config: &ServeConfig, addr: Option<std::net::SocketAddr>) -> Result<()> {
    let exposed = addr.is_none_or(|a| !a.ip().is_loopback());
    if config.api_keys.is_empty() && exposed && !config.allow_unauthenticated {
        return Err(Error::invalid(
            "--listen",
            format!(
                "refusing to serve without an API key on {}, beyond loopback: give --api-key / --api-key-file, listen on 127.0.0.1, or pass --allow-unauthenticated",
                addr.map_or_else(|| "an unknown address".to_string(), |a| a.to_string())
            ),
        ));
    }
    if config.api_keys.is_empty() && exposed {
        tracing::warn!(
            ?addr,
            "serving WITHOUT authentication beyond loopback (--allow-unauthenticated)"
        );
    }
    Ok(())
}

/// Loads the models (off the async runtime) and serves until `shutdown` (see [`Server::serve`]).
pub async fn run(
    config: ServeConfig,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<()> {
    // Listen for SIGHUP before the (slow) model loading: a reload asked for meanwhile must
    // neither end the process (the signal's default) nor be lost.
    #[cfg(unix)]
    let hangup = match config.reload_on_sighup {
        true => Some(reload::listen_sighup()?),
        false => None,
    };
    #[allow(unused_mut)]
    let mut server = tokio::task::spawn_blocking(move || Server::load(config))
        .await
        .map_err(|e| Error::internal_from("model loading task failed", e))??;
    #[cfg(unix)]
    {
        server.hangup = hangup;
    }
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

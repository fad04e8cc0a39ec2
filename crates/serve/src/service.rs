//! The one domain API both transports call: scene lookup, push, subscribe, unary association,
//! readiness and shutdown. gRPC and HTTP only translate their wire formats to these calls.
use std::collections::BTreeMap;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use futures::{Stream, StreamExt};
use tokio::sync::watch;
use tokio_stream::wrappers::BroadcastStream;
use tokio_stream::wrappers::errors::BroadcastStreamRecvError;

use super::config::ConnectionLimits;
use super::conn::ConnHandle;
use super::metrics::Metrics;
use super::reload::{ReloadOutcome, Reloader};
use super::scene::{Published, Scene};
use super::subscribers::Subscribers;
use crate::error::{Error, Result};
use crossview_api::types::{AssociateRequest, BatchAck, FrameResult, SceneDescription};
use crossview_core::Batch;

/// A stream of one scene's frame results (each with the frame's boxes: `.result` is what
/// subscribers get unless they asked for the boxes), in frame-id order. It ends after
/// shutdown has published the last flushed frame, or with `ResourceExhausted` when the
/// subscriber fell more than the subscriber buffer behind.
pub(crate) type ResultStream = Pin<Box<dyn Stream<Item = Result<Arc<Published>>> + Send>>;

/// The service shared by all connections of a server.
#[derive(Debug)]
pub struct Service {
    scenes: BTreeMap<String, Arc<Scene>>,
    metrics: Metrics,
    ready: AtomicBool,
    /// False while a Kafka consumer has not yet joined its group (see [`crate::transport::kafka`]).
    consumer_ready: AtomicBool,
    shutdown: watch::Sender<bool>,
    stall_timeout: Option<Duration>,
    reloader: Option<Reloader>,
    /// The subscriber budget ([`crate::subscribers`]).
    subscribers: Arc<Subscribers>,
}

impl Service {
    /// A service over started scenes.
    pub fn new(scenes: Vec<Arc<Scene>>, metrics: Metrics) -> Self {
        let (shutdown, _) = watch::channel(false);
        Service {
            scenes: scenes
                .into_iter()
                .map(|s| (s.name().to_string(), s))
                .collect(),
            metrics: metrics.clone(),
            ready: AtomicBool::new(true),
            consumer_ready: AtomicBool::new(true),
            shutdown,
            stall_timeout: None,
            reloader: None,
            subscribers: Subscribers::new(&ConnectionLimits::default(), metrics),
        }
    }

    /// Bounds the result subscribers by `limits`' subscriber budget.
    pub(crate) fn with_subscriber_limits(mut self, limits: &ConnectionLimits) -> Self {
        self.subscribers = Subscribers::new(limits, self.metrics.clone());
        self
    }

    /// Reloads these model files on [`Self::reload`].
    pub(crate) fn with_reloader(mut self, reloader: Reloader) -> Self {
        self.reloader = Some(reloader);
        self
    }

    /// Re-reads every scene's model file and swaps in the ones that changed (see
    /// [`crate::reload`]); one outcome per model file.
    pub async fn reload(&self) -> Vec<ReloadOutcome> {
        match &self.reloader {
            Some(r) => {
                let scene_of = |name: &str| self.scene(name).cloned();
                r.reload(scene_of, &self.metrics).await
            }
            None => Vec::new(),
        }
    }

    /// The model file `scene` is served from (and reloaded from), when it has one.
    pub(crate) fn model_path(&self, scene: &str) -> Option<std::path::PathBuf> {
        self.reloader.as_ref()?.path_of(scene)
    }

    /// Swaps the model file `path` into `scene` as a reload does and makes it the scene's
    /// file from then on, unless the scene is no longer served from `expected` (healing,
    /// [`crate::heal`]).
    pub(crate) async fn adopt_model(
        &self,
        scene: &str,
        path: &std::path::Path,
        expected: &std::path::Path,
    ) -> ReloadOutcome {
        let found = self.scene(scene).cloned();
        match &self.reloader {
            Some(r) => r.adopt(found, path, expected, &self.metrics).await,
            None => ReloadOutcome {
                scene: scene.to_string(),
                outcome: "refused".into(),
                version: None,
                error: Some("this server reloads no model files".into()),
            },
        }
    }

    /// Disconnects result subscribers that stop reading for `stall` (see [`Self::subscribe`]).
    pub(crate) fn with_stall_timeout(mut self, stall: Duration) -> Self {
        self.stall_timeout = Some(stall);
        self
    }

    /// The subscriber stall timeout, if any.
    pub(crate) fn stall_timeout(&self) -> Option<Duration> {
        self.stall_timeout
    }

    /// The metrics registry.
    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Counts an error by kind on its way out.
    fn track<T>(&self, r: Result<T>) -> Result<T> {
        if let Err(e) = &r {
            self.metrics.error(e);
        }
        r
    }

    /// The scene called `name`, or `UnknownScene` (counted: a client asked for it).
    pub fn scene(&self, name: &str) -> Result<&Arc<Scene>> {
        self.track(
            self.find_scene(name)
                .ok_or_else(|| crossview_core::Error::UnknownScene(name.to_string()).into()),
        )
    }

    /// The scene called `name`, if served; not counted as an error when it is not (a
    /// transport's own bookkeeping, e.g. Kafka mode's scenes by partition, may name scenes
    /// whose records were already refused and counted).
    pub(crate) fn find_scene(&self, name: &str) -> Option<&Arc<Scene>> {
        self.scenes.get(name)
    }

    /// Every scene, by name.
    pub fn scenes(&self) -> Vec<SceneDescription> {
        self.scenes.values().map(|s| s.describe()).collect()
    }

    /// One scene's description.
    pub fn describe(&self, name: &str) -> Result<SceneDescription> {
        Ok(self.scene(name)?.describe())
    }

    /// Pushes one camera batch of scene `scene` into its synchronizer.
    pub fn push(&self, scene: &str, batch: Batch) -> Result<BatchAck> {
        let s = self.scene(scene)?;
        let Batch {
            camera,
            frame_id,
            time,
            detections,
        } = batch;
        let frame_id = self.track(s.push(&camera, frame_id, time, detections))?;
        Ok(BatchAck {
            scene: scene.to_string(),
            camera,
            frame_id,
            accepted: true,
        })
    }

    /// The frame `batch` of `scene` would be grouped into now (its frame id less its camera's
    /// clock offset, or its capture time's tick), without pushing it or counting anything;
    /// `None` where [`push`](Self::push) would refuse it for its scene, camera or stamps.
    pub(crate) fn frame_of(&self, scene: &str, batch: &Batch) -> Option<u64> {
        self.find_scene(scene)?
            .frame_of_batch(&batch.camera, batch.frame_id, batch.time)
            .ok()
    }

    /// Associates one already synchronized frame.
    pub async fn associate(&self, scene: &str, req: AssociateRequest) -> Result<FrameResult> {
        let s = self.scene(scene)?;
        let views = req
            .views
            .into_iter()
            .map(|v| (v.camera, v.detections))
            .collect();
        self.track(s.associate(req.frame_id, req.time, views).await)
    }

    /// The results of `scene` from now on. With `conn` (the subscriber's connection) and a
    /// stall timeout, a subscriber that has not taken a waiting result for that long is
    /// disconnected (see [`watch_stall`]).
    pub fn subscribe(
        &self,
        scene: &str,
        conn: Option<ConnHandle>,
        stall_timeout: Option<Duration>,
    ) -> Result<ResultStream> {
        let s = self.scene(scene)?;
        let taken = Arc::new(AtomicU64::new(0));
        // Network subscribers live within the budget; in-process ones (Kafka mode's
        // forwarders) hold no transport buffer and are never refused by it.
        let ticket = match &conn {
            Some(c) => Some(self.track(self.subscribers.admit(s, Some(c), &taken))?),
            None => None,
        };
        let (rx, guard) = self.track(s.subscribe())?;
        let metrics = self.metrics.clone();
        let mut failed = false;
        if let (Some(conn), Some(stall)) = (conn, stall_timeout) {
            tokio::spawn(watch_stall(
                s.clone(),
                s.published(),
                Arc::downgrade(&taken),
                conn,
                stall,
                self.metrics.clone(),
            ));
        }
        let stream = BroadcastStream::new(rx)
            .map(move |item| {
                // The stream owns the guard and the ticket: the subscriber is counted (and
                // charged against the budget) while it lives.
                let _ = (&guard, &ticket);
                taken.fetch_add(1, Ordering::AcqRel);
                item
            })
            .map(move |item| match item {
                Ok(r) => Ok(r),
                Err(BroadcastStreamRecvError::Lagged(n)) => {
                    let e = Error::ResourceExhausted(format!(
                        "subscriber fell {n} frames behind and was dropped"
                    ));
                    metrics.error(&e);
                    Err(e)
                }
            })
            .take_while(move |item| {
                // Stop after the first error.
                let go = !failed;
                failed |= item.is_err();
                futures::future::ready(go)
            });
        Ok(Box::pin(stream))
    }

    /// True while models are loaded and the service accepts work.
    pub(crate) fn is_ready(&self) -> bool {
        self.ready.load(Ordering::Acquire) && self.consumer_ready.load(Ordering::Acquire)
    }

    /// True until shutdown begins (whatever a Kafka consumer's state).
    pub(crate) fn accepting(&self) -> bool {
        self.ready.load(Ordering::Acquire)
    }

    /// Readiness as far as the Kafka consumer goes (false until it joined its group).
    pub(crate) fn set_consumer_ready(&self, ready: bool) {
        self.consumer_ready.store(ready, Ordering::Release);
    }

    /// The smallest per-subscriber result buffer of the scenes.
    pub(crate) fn subscriber_buffer(&self) -> usize {
        self.scenes
            .values()
            .map(|s| s.limits().subscriber_buffer)
            .min()
            .unwrap_or(1)
    }

    /// Resolves once shutdown has begun (for ending long-lived request streams).
    pub(crate) fn shutting_down(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut rx = self.shutdown.subscribe();
        async move {
            let _ = rx.wait_for(|v| *v).await;
        }
    }

    /// Emits every scene's timed-out frames; returns the earliest next deadline.
    pub fn tick(&self, now: Instant) -> Option<Instant> {
        self.scenes.values().filter_map(|s| s.tick(now)).min()
    }

    /// All scenes (for the timer task).
    pub(crate) fn scene_list(&self) -> Vec<Arc<Scene>> {
        self.scenes.values().cloned().collect()
    }

    /// Graceful shutdown: stops intake, flushes every scene's pending frames as partial results,
    /// waits for them to be published and closes the result streams. Blocking.
    pub fn close(&self) {
        self.close_by(None);
    }

    /// [`close`](Self::close), but frames still queued at `deadline` are published with an
    /// error instead of being associated (shutdown respects its grace period).
    pub(crate) fn close_by(&self, deadline: Option<Instant>) {
        self.ready.store(false, Ordering::Release);
        self.shutdown.send_replace(true);
        for s in self.scenes.values() {
            s.close(deadline);
        }
    }
}

/// Watches one subscriber (until its stream is dropped): when results have waited for it,
/// untaken, for `stall` — it stopped reading, so its transport stopped polling it — its
/// connection is closed (for HTTP/2 that ends the connection's other streams too).
async fn watch_stall(
    scene: Arc<Scene>,
    start: u64,
    taken: std::sync::Weak<AtomicU64>,
    conn: ConnHandle,
    stall: Duration,
    metrics: Metrics,
) {
    let tick = (stall / 4).max(Duration::from_millis(10));
    let mut stuck_since: Option<(Instant, u64)> = None;
    loop {
        tokio::time::sleep(tick).await;
        let Some(taken) = taken.upgrade() else { return };
        let t = taken.load(Ordering::Acquire);
        let waiting = scene.published().saturating_sub(start) > t;
        stuck_since = match stuck_since {
            Some((since, at)) if waiting && at == t => Some((since, at)),
            _ if waiting => Some((Instant::now(), t)),
            _ => None,
        };
        if let Some((since, _)) = stuck_since
            && since.elapsed() >= stall
        {
            tracing::info!(
                scene = scene.name(),
                "dropping a subscriber that stopped reading"
            );
            metrics.error(&Error::SubscriberStalled(format!(
                "no result read for {stall:?} (--subscriber-stall-timeout)"
            )));
            conn.kill();
            return;
        }
    }
}

/// Reloads on every `SIGHUP` of `hup` until the service shuts down (the usual Unix
/// convention).
#[cfg(unix)]
pub(crate) fn spawn_reload_on_sighup(service: Arc<Service>, mut hup: tokio::signal::unix::Signal) {
    let stop = service.shutting_down();
    tokio::spawn(async move {
        tokio::pin!(stop);
        loop {
            tokio::select! {
                got = hup.recv() => {
                    if got.is_none() { break; }
                    tracing::info!("SIGHUP: reloading model files");
                    service.reload().await;
                }
                _ = &mut stop => break,
            }
        }
    });
}

//! One served scene: its description, synchronizer, inference worker and results broadcast.
//!
//! Data flow: `push` validates a batch and feeds the scene's [`Synchronizer`] under one lock;
//! frames that leave go, still under that lock (so in frame-id order), into the worker's queue.
//! The worker — a dedicated thread owning the encoder — associates each frame with one encoder
//! call and publishes the result on a broadcast channel, in queue order. Admission is bounded:
//! when `queue_capacity` frames are queued, new batches and unary requests are shed with
//! [`Error::ResourceExhausted`] before anything is accepted.
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::{Notify, broadcast, oneshot};

use super::api::{FrameResult, IdentityOut, Member, SceneDescription};
use super::config::Limits;
use super::engine::{self, EngineConfig};
use super::metrics::Metrics;
use super::sync::{Emitted, Rejection, Synchronizer};
use crate::core::{Detection, Frame, SceneSpec};
use crate::model::Encoder;
use crate::{Error, Result};

/// Largest accepted magnitude of a box coordinate (pixels) or appearance value: far beyond any
/// real image, small enough that squared distances stay finite in `f32`.
pub const MAX_MAGNITUDE: f32 = 1e6;

/// Static facts about a scene (from its model file).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneInfo {
    /// Name and cameras.
    pub spec: SceneSpec,
    /// Association settings (SPEC §3 threshold and alpha, identity confidence).
    pub engine: EngineConfig,
    /// Model version string.
    pub version: String,
}

enum Job {
    /// A frame from the synchronizer: publish its result.
    Stream(Emitted),
    /// A unary request: answer it.
    Unary {
        frame: Frame,
        started: Instant,
        reply: oneshot::Sender<FrameResult>,
    },
}

struct Intake {
    sync: Synchronizer,
    jobs: Option<std::sync::mpsc::Sender<Job>>,
}

/// A live scene (see the module docs).
pub struct Scene {
    info: SceneInfo,
    limits: Limits,
    sync_timeout: Duration,
    metrics: Metrics,
    intake: Mutex<Intake>,
    /// Frames queued for or inside the worker.
    queued: Arc<AtomicUsize>,
    /// Appearance length fixed by the first vector accepted (0 = unknown).
    appearance_len: AtomicUsize,
    closed: AtomicBool,
    subscribers: Arc<AtomicUsize>,
    results: Mutex<Option<broadcast::Sender<Arc<FrameResult>>>>,
    /// Wakes the timer task when a new frame starts waiting.
    pub(crate) wake: Notify,
    worker: Mutex<Option<std::thread::JoinHandle<()>>>,
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene").field("info", &self.info).finish()
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Scene {
    /// Starts a scene: its worker thread takes ownership of `encoder`.
    pub fn start(
        info: SceneInfo,
        encoder: Box<dyn Encoder>,
        sync_timeout: Duration,
        max_pending: usize,
        limits: Limits,
        metrics: Metrics,
    ) -> Result<Arc<Scene>> {
        let n = info.spec.cameras.len();
        if n == 0 || n > limits.max_cameras {
            return Err(Error::invalid(
                "cameras",
                format!(
                    "scene '{}' has {n} cameras; 1..={} are supported",
                    info.spec.name, limits.max_cameras
                ),
            ));
        }
        let (tx, rx) = std::sync::mpsc::channel::<Job>();
        let (results, _) = broadcast::channel(limits.subscriber_buffer.max(1));
        let queued = Arc::new(AtomicUsize::new(0));
        let worker = Worker {
            info: info.clone(),
            encoder,
            results: results.clone(),
            queued: queued.clone(),
            metrics: metrics.clone(),
        };
        let handle = std::thread::Builder::new()
            .name(format!("encoder-{}", info.spec.name))
            .spawn(move || worker.run(rx))
            .map_err(|e| Error::Runtime(format!("cannot start encoder thread: {e}")))?;
        Ok(Arc::new(Scene {
            intake: Mutex::new(Intake {
                sync: Synchronizer::new(n, sync_timeout, max_pending),
                jobs: Some(tx),
            }),
            info,
            limits,
            sync_timeout,
            metrics,
            queued,
            appearance_len: AtomicUsize::new(0),
            closed: AtomicBool::new(false),
            subscribers: Arc::new(AtomicUsize::new(0)),
            results: Mutex::new(Some(results)),
            wake: Notify::new(),
            worker: Mutex::new(Some(handle)),
        }))
    }

    /// Static facts.
    pub fn info(&self) -> &SceneInfo {
        &self.info
    }

    /// Scene name.
    pub fn name(&self) -> &str {
        &self.info.spec.name
    }

    /// The public description (`GetScene`).
    pub fn describe(&self) -> SceneDescription {
        let app = self.appearance_len.load(Ordering::Relaxed);
        SceneDescription {
            name: self.info.spec.name.clone(),
            cameras: self.info.spec.cameras.clone(),
            threshold: self.info.engine.threshold,
            alpha: self.info.engine.alpha,
            model_version: self.info.version.clone(),
            appearance_length: (app > 0).then_some(app),
            sync_timeout_ms: self.sync_timeout.as_millis() as u64,
        }
    }

    /// Checks one camera's detections: count cap, every box, one appearance length per scene.
    /// `field` prefixes error fields (e.g. `views[1].detections`).
    fn validate(&self, field: &str, detections: &[Detection]) -> Result<()> {
        if detections.len() > self.limits.max_detections {
            return Err(Error::invalid(
                field,
                format!(
                    "at most {} detections per batch, got {}",
                    self.limits.max_detections,
                    detections.len()
                ),
            ));
        }
        let mut expected = match self.appearance_len.load(Ordering::Relaxed) {
            0 => None,
            n => Some(n),
        };
        let mut with_app = 0;
        for (i, d) in detections.iter().enumerate() {
            let f = format!("{field}[{i}]");
            if let Some(app) = &d.appearance {
                if app.len() > self.limits.max_appearance_len {
                    return Err(Error::invalid(
                        format!("{f}.appearance"),
                        format!(
                            "at most {} values, got {}",
                            self.limits.max_appearance_len,
                            app.len()
                        ),
                    ));
                }
                expected.get_or_insert(app.len());
                with_app += 1;
            }
            d.validate(&f, expected)?;
            if d.bbox.iter().any(|v| v.abs() > MAX_MAGNITUDE) {
                return Err(Error::invalid(
                    format!("{f}.bbox"),
                    format!(
                        "coordinates must be at most {MAX_MAGNITUDE} pixels, got {:?}",
                        d.bbox
                    ),
                ));
            }
            if let Some(app) = &d.appearance
                && let Some(k) = app.iter().position(|v| v.abs() > MAX_MAGNITUDE)
            {
                return Err(Error::invalid(
                    format!("{f}.appearance[{k}]"),
                    format!("magnitude must be at most {MAX_MAGNITUDE}"),
                ));
            }
        }
        if with_app != 0 && with_app != detections.len() {
            return Err(Error::invalid(
                format!("{field}[].appearance"),
                "present on some detections of the batch but not all",
            ));
        }
        if let Some(n) = expected
            && with_app > 0
            && let Err(known) =
                self.appearance_len
                    .compare_exchange(0, n, Ordering::Relaxed, Ordering::Relaxed)
            && known != n
        {
            return Err(Error::invalid(
                format!("{field}[0].appearance"),
                format!("expected {known} values, got {n}"),
            ));
        }
        Ok(())
    }

    fn admit(&self, extra: usize) -> Result<()> {
        if self.closed.load(Ordering::Acquire) {
            return Err(Error::Unavailable("server is shutting down".into()));
        }
        let q = self.queued.load(Ordering::Acquire);
        if q + extra > self.limits.queue_capacity {
            return Err(Error::ResourceExhausted(format!(
                "scene '{}' has {q} frames queued for inference (capacity {})",
                self.name(),
                self.limits.queue_capacity
            )));
        }
        Ok(())
    }

    fn enqueue(&self, intake: &mut Intake, emitted: Vec<Emitted>) {
        for e in emitted {
            self.metrics.frame(self.name(), e.complete());
            match &intake.jobs {
                Some(tx) => {
                    self.queued.fetch_add(1, Ordering::AcqRel);
                    if tx.send(Job::Stream(e)).is_err() {
                        self.queued.fetch_sub(1, Ordering::AcqRel);
                        tracing::error!(scene = self.name(), "encoder worker is gone");
                    }
                }
                None => tracing::error!(scene = self.name(), "frame emitted after close"),
            }
        }
        self.metrics
            .pending(self.name(), intake.sync.pending_frames());
    }

    /// Accepts one camera batch into the synchronizer (see the module docs). Late and duplicate
    /// batches are rejected and counted.
    pub fn push(&self, camera: &str, frame_id: u64, detections: Vec<Detection>) -> Result<()> {
        let cam = self.info.spec.camera_index(camera)?;
        self.validate("detections", &detections)?;
        let mut intake = lock(&self.intake);
        // Shed before accepting anything. One batch can release several frames at once, so the
        // queue may overshoot the capacity by at most `max_pending_frames`: still bounded.
        self.admit(1)?;
        let emitted = match intake.sync.push(cam, frame_id, detections, Instant::now()) {
            Ok(e) => e,
            Err(r) => {
                let (scene, camera) = (self.name().to_string(), camera.to_string());
                return Err(match r {
                    Rejection::Late => {
                        self.metrics.late(self.name());
                        Error::LateBatch {
                            scene,
                            camera,
                            frame_id,
                        }
                    }
                    Rejection::Duplicate => {
                        self.metrics.duplicate(self.name());
                        Error::DuplicateBatch {
                            scene,
                            camera,
                            frame_id,
                        }
                    }
                });
            }
        };
        self.metrics.batch(self.name());
        self.enqueue(&mut intake, emitted);
        drop(intake);
        // The earliest deadline may have changed.
        self.wake.notify_one();
        Ok(())
    }

    /// Emits whatever timed out by `now`; returns the next deadline.
    pub fn tick(&self, now: Instant) -> Option<Instant> {
        let mut intake = lock(&self.intake);
        let emitted = intake.sync.poll(now);
        if !emitted.is_empty() {
            self.enqueue(&mut intake, emitted);
        }
        intake.sync.next_deadline()
    }

    /// Associates one already synchronized frame (unary call); bypasses the synchronizer.
    pub async fn associate(
        &self,
        frame_id: u64,
        views: Vec<(String, Vec<Detection>)>,
    ) -> Result<FrameResult> {
        let started = Instant::now();
        let n = self.info.spec.cameras.len();
        let mut frame = Frame::new(frame_id, n);
        for (k, (camera, dets)) in views.into_iter().enumerate() {
            let c = self.info.spec.camera_index(&camera)?;
            if frame.views[c].is_some() {
                return Err(Error::invalid(
                    format!("views[{k}].camera"),
                    format!("camera '{camera}' appears twice"),
                ));
            }
            self.validate(&format!("views[{k}].detections"), &dets)?;
            frame.views[c] = Some(dets);
        }
        let (tx, rx) = oneshot::channel();
        {
            let intake = lock(&self.intake);
            self.admit(1)?;
            let jobs = intake
                .jobs
                .as_ref()
                .ok_or_else(|| Error::Unavailable("server is shutting down".into()))?;
            self.queued.fetch_add(1, Ordering::AcqRel);
            if jobs
                .send(Job::Unary {
                    frame,
                    started,
                    reply: tx,
                })
                .is_err()
            {
                self.queued.fetch_sub(1, Ordering::AcqRel);
                return Err(Error::Unavailable("encoder worker is gone".into()));
            }
        }
        let result = rx
            .await
            .map_err(|_| Error::Unavailable("encoder worker stopped".into()))?;
        match &result.error {
            Some(e) => Err(Error::Runtime(e.clone())),
            None => Ok(result),
        }
    }

    /// A receiver of this scene's frame results from now on, or `Unavailable` after shutdown;
    /// the guard keeps the subscriber counted (`crossview_subscribers`) until dropped.
    pub fn subscribe(&self) -> Result<(broadcast::Receiver<Arc<FrameResult>>, SubscriberGuard)> {
        let rx = lock(&self.results)
            .as_ref()
            .map(broadcast::Sender::subscribe)
            .ok_or_else(|| Error::Unavailable("server is shutting down".into()))?;
        let n = self.subscribers.fetch_add(1, Ordering::AcqRel) + 1;
        self.metrics.subscribers(self.name(), n);
        Ok((
            rx,
            SubscriberGuard {
                count: self.subscribers.clone(),
                metrics: self.metrics.clone(),
                scene: self.name().to_string(),
            },
        ))
    }

    /// Graceful shutdown of this scene: refuses new work, flushes pending frames as partial
    /// results, lets the worker finish its queue and publish them, then closes the broadcast
    /// so subscriber streams end. Blocking (joins the worker thread).
    pub fn close(&self) {
        self.closed.store(true, Ordering::Release);
        {
            let mut intake = lock(&self.intake);
            let emitted = intake.sync.flush();
            let n = emitted.len();
            self.enqueue(&mut intake, emitted);
            intake.jobs = None;
            tracing::info!(scene = self.name(), flushed = n, "scene intake closed");
        }
        if let Some(h) = lock(&self.worker).take()
            && h.join().is_err()
        {
            tracing::error!(scene = self.name(), "encoder worker panicked");
        }
        lock(&self.results).take();
    }
}

/// Keeps one subscriber counted in the `crossview_subscribers` gauge while alive.
#[derive(Debug)]
pub struct SubscriberGuard {
    count: Arc<AtomicUsize>,
    metrics: Metrics,
    scene: String,
}

impl Drop for SubscriberGuard {
    fn drop(&mut self) {
        let n = self.count.fetch_sub(1, Ordering::AcqRel).saturating_sub(1);
        self.metrics.subscribers(&self.scene, n);
    }
}

struct Worker {
    info: SceneInfo,
    encoder: Box<dyn Encoder>,
    results: broadcast::Sender<Arc<FrameResult>>,
    queued: Arc<AtomicUsize>,
    metrics: Metrics,
}

impl Worker {
    fn run(mut self, rx: std::sync::mpsc::Receiver<Job>) {
        while let Ok(job) = rx.recv() {
            match job {
                Job::Stream(e) => {
                    let r = self.process(&e.frame, e.first_seen);
                    self.metrics
                        .frame_latency(&self.info.spec.name, e.first_seen.elapsed());
                    self.queued.fetch_sub(1, Ordering::AcqRel);
                    // No subscriber is not an error.
                    let _ = self.results.send(Arc::new(r));
                }
                Job::Unary {
                    frame,
                    started,
                    reply,
                } => {
                    let r = self.process(&frame, started);
                    self.queued.fetch_sub(1, Ordering::AcqRel);
                    let _ = reply.send(r);
                }
            }
        }
        tracing::debug!(scene = %self.info.spec.name, "encoder worker done");
    }

    fn process(&mut self, frame: &Frame, started: Instant) -> FrameResult {
        let spec = &self.info.spec;
        let t = Instant::now();
        let encoder = self.encoder.as_mut();
        let engine = &self.info.engine;
        // A bug in the method must not take the scene down with it.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            engine::associate(encoder, spec, frame, engine)
        }))
        .unwrap_or_else(|_| Err(Error::Runtime("association panicked".into())));
        self.metrics.inference(&spec.name, t.elapsed());
        let (identities, error) = match outcome {
            Ok(ids) => (
                ids.into_iter()
                    .map(|id| IdentityOut {
                        id: id.id,
                        confidence: id.confidence,
                        members: id
                            .members
                            .into_iter()
                            .map(|(c, index)| Member {
                                camera: spec.cameras[c].name.clone(),
                                camera_index: c,
                                index,
                            })
                            .collect(),
                    })
                    .collect(),
                None,
            ),
            Err(e) => {
                tracing::error!(scene = %spec.name, frame_id = frame.frame_id, error = %e, "association failed");
                self.metrics.error(e.kind());
                (Vec::new(), Some(e.to_string()))
            }
        };
        FrameResult {
            scene: spec.name.clone(),
            frame_id: frame.frame_id,
            complete: frame.is_complete(),
            missing_cameras: frame
                .views
                .iter()
                .zip(&spec.cameras)
                .filter(|(v, _)| v.is_none())
                .map(|(_, c)| c.name.clone())
                .collect(),
            identities,
            latency_ms: started.elapsed().as_secs_f64() * 1e3,
            error,
        }
    }
}

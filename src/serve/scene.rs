//! One served scene: its description, synchronizer, inference worker and results broadcast.
//!
//! Data flow: `push` validates a batch and feeds the scene's [`Synchronizer`] under one lock;
//! frames that leave go, still under that lock (so in frame-id order), into the worker's queue.
//! The worker — a dedicated thread owning the encoder — associates each frame with one encoder
//! call and publishes the result on a broadcast channel, in queue order. Admission is bounded:
//! when `queue_capacity` frames are queued, new batches and unary requests are shed with
//! [`Error::ResourceExhausted`] before anything is accepted; a batch (or unary request) that
//! would make its frame cost more than `max_frame_cost` ([`super::cost`]) is refused; and a
//! frame whose association has not started `frame_deadline` after its first batch (or after
//! the shutdown deadline) is published with an error instead of identities, so every accepted
//! batch still appears in exactly one result.
//!
//! Boxes overlapping their image's edge are clipped to the image
//! ([`Detection::clip_to_image`]) and counted (`crossview_clipped_boxes_total`); boxes
//! entirely outside it are refused. The scene's appearance length is fixed by the first
//! *accepted* batch carrying appearance vectors.
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use tokio::sync::{Notify, broadcast, oneshot};

use super::api::{FrameResult, IdentityOut, Member, SceneDescription};
use super::config::Limits;
use super::cost::frame_cost;
use super::engine::{self, EngineConfig};
use super::metrics::Metrics;
use super::sync::{Emitted, Rejection, Synchronizer};
use crate::core::{Detection, Frame, SceneSpec};
use crate::model::Encoder;
use crate::{Error, Result};

/// Largest accepted magnitude of an appearance value: small enough that squared distances stay
/// finite in `f32`. (Box coordinates are bounded by clipping to the image.)
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
        reply: oneshot::Sender<Result<FrameResult>>,
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
    /// Appearance length fixed by the first accepted batch with vectors (0 = unknown).
    appearance_len: AtomicUsize,
    /// After this instant (set at shutdown) queued frames are published without association.
    close_by: Arc<Mutex<Option<Instant>>>,
    closed: AtomicBool,
    subscribers: Arc<AtomicUsize>,
    results: Mutex<Option<broadcast::Sender<Arc<FrameResult>>>>,
    /// Results published so far (for spotting subscribers that stopped reading).
    published: Arc<AtomicU64>,
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
        let close_by = Arc::new(Mutex::new(None));
        let published = Arc::new(AtomicU64::new(0));
        let worker = Worker {
            info: info.clone(),
            encoder,
            results: results.clone(),
            queued: queued.clone(),
            metrics: metrics.clone(),
            frame_deadline: limits.frame_deadline,
            close_by: close_by.clone(),
            published: published.clone(),
        };
        let handle = std::thread::Builder::new()
            .name(format!("encoder-{}", info.spec.name))
            .spawn(move || worker.run(rx))
            .map_err(|e| Error::Runtime(format!("cannot start encoder thread: {e}")))?;
        Ok(Arc::new(Scene {
            intake: Mutex::new(Intake {
                sync: Synchronizer::new(n, sync_timeout, max_pending)
                    .with_window(limits.frame_window),
                jobs: Some(tx),
            }),
            info,
            limits,
            sync_timeout,
            metrics,
            queued,
            appearance_len: AtomicUsize::new(0),
            close_by,
            closed: AtomicBool::new(false),
            subscribers: Arc::new(AtomicUsize::new(0)),
            results: Mutex::new(Some(results)),
            published,
            wake: Notify::new(),
            worker: Mutex::new(Some(handle)),
        }))
    }

    /// Static facts.
    pub fn info(&self) -> &SceneInfo {
        &self.info
    }

    /// The size and cost limits the scene enforces.
    pub fn limits(&self) -> &Limits {
        &self.limits
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

    /// Checks one camera's detections and clips boxes overlapping the image edge: count cap,
    /// every box and value, one appearance length within the batch and equal to the scene's
    /// once known. Returns the batch's appearance length (when its detections carry vectors);
    /// it does not fix the scene's (only an accepted batch does, see [`Self::push`]).
    /// `field` prefixes error fields (e.g. `views[1].detections`).
    fn validate(
        &self,
        field: &str,
        camera: usize,
        detections: &mut [Detection],
    ) -> Result<Option<usize>> {
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
        let cam = &self.info.spec.cameras[camera];
        let mut expected = match self.appearance_len.load(Ordering::Relaxed) {
            0 => None,
            n => Some(n),
        };
        let (mut with_app, mut clipped) = (0, 0);
        for (i, d) in detections.iter_mut().enumerate() {
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
            if let Some(app) = &d.appearance
                && let Some(k) = app.iter().position(|v| v.abs() > MAX_MAGNITUDE)
            {
                return Err(Error::invalid(
                    format!("{f}.appearance[{k}]"),
                    format!("magnitude must be at most {MAX_MAGNITUDE}"),
                ));
            }
            clipped += usize::from(d.clip_to_image(&f, cam)?);
        }
        if with_app != 0 && with_app != detections.len() {
            return Err(Error::invalid(
                format!("{field}[].appearance"),
                "present on some detections of the batch but not all",
            ));
        }
        if clipped > 0 {
            self.metrics.clipped(self.name(), clipped);
        }
        Ok(expected.filter(|_| with_app > 0))
    }

    /// Checks a batch's appearance length against the scene's (known or not yet).
    fn check_appearance(&self, field: &str, len: Option<usize>) -> Result<()> {
        match (self.appearance_len.load(Ordering::Relaxed), len) {
            (known, Some(n)) if known != 0 && known != n => Err(Error::invalid(
                format!("{field}[0].appearance"),
                format!("expected {known} values, got {n}"),
            )),
            _ => Ok(()),
        }
    }

    /// Refuses a frame that would cost more than the budget ([`super::cost`]).
    fn check_cost(&self, field: &str, frame_id: u64, counts: &[usize]) -> Result<()> {
        let cost = frame_cost(counts);
        if cost > self.limits.max_frame_cost {
            return Err(Error::invalid(
                field,
                format!(
                    "frame {frame_id} with {counts:?} boxes per camera would cost {cost} \
                     association units, over the limit of {} (--max-frame-cost): send fewer \
                     detections per camera",
                    self.limits.max_frame_cost
                ),
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

    /// Accepts one camera batch into the synchronizer (see the module docs). Late, duplicate
    /// and out-of-range batches are rejected and counted.
    pub fn push(&self, camera: &str, frame_id: u64, mut detections: Vec<Detection>) -> Result<()> {
        let cam = self.info.spec.camera_index(camera)?;
        let app_len = self.validate("detections", cam, &mut detections)?;
        let n_boxes = detections.len();
        let mut intake = lock(&self.intake);
        // Shed before accepting anything. One batch can release several frames at once, so the
        // queue may overshoot the capacity by at most `max_pending_frames`: still bounded.
        self.admit(1)?;
        // Under the intake lock: no other batch can fix the length or grow the frame meanwhile.
        self.check_appearance("detections", app_len)?;
        if let Some(f) = intake.sync.pending_frame(frame_id)
            && f.views[cam].is_none()
        {
            let mut counts: Vec<usize> = f
                .views
                .iter()
                .map(|v| v.as_ref().map_or(0, Vec::len))
                .collect();
            counts[cam] = n_boxes;
            self.check_cost("detections", frame_id, &counts)?;
        }
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
                    Rejection::OutOfRange => {
                        self.metrics.out_of_range(self.name());
                        let w = intake.sync.window();
                        let reason = match intake.sync.last_emitted() {
                            Some(last) => format!(
                                "more than {w} (--frame-window) from the last emitted frame \
                                 {last}; the scene follows new ids once a majority of its \
                                 cameras send them"
                            ),
                            None => format!(
                                "more than {w} (--frame-window) from the oldest pending frame; \
                                 the scene follows new ids once a majority of its cameras \
                                 send them"
                            ),
                        };
                        Error::FrameOutOfRange {
                            scene,
                            camera,
                            frame_id,
                            reason,
                        }
                    }
                });
            }
        };
        if let Some(n) = app_len {
            // Only an accepted batch fixes the scene's appearance length.
            let _ =
                self.appearance_len
                    .compare_exchange(0, n, Ordering::Relaxed, Ordering::Relaxed);
        }
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
        let mut app_len: Option<usize> = None;
        for (k, (camera, mut dets)) in views.into_iter().enumerate() {
            let c = self.info.spec.camera_index(&camera)?;
            if frame.views[c].is_some() {
                return Err(Error::invalid(
                    format!("views[{k}].camera"),
                    format!("camera '{camera}' appears twice"),
                ));
            }
            let field = format!("views[{k}].detections");
            let len = self.validate(&field, c, &mut dets)?;
            // One length over the whole request; a unary call never fixes the scene's.
            if let (Some(a), Some(b)) = (app_len, len)
                && a != b
            {
                return Err(Error::invalid(
                    format!("{field}[0].appearance"),
                    format!("expected {a} values, got {b}"),
                ));
            }
            app_len = app_len.or(len);
            self.check_appearance(&field, len)?;
            frame.views[c] = Some(dets);
        }
        let counts: Vec<usize> = frame
            .views
            .iter()
            .map(|v| v.as_ref().map_or(0, Vec::len))
            .collect();
        self.check_cost("views", frame_id, &counts)?;
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
            .map_err(|_| Error::Unavailable("encoder worker stopped".into()))??;
        match &result.error {
            Some(e) => Err(Error::Runtime(e.clone())),
            None => Ok(result),
        }
    }

    /// Results published so far.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Acquire)
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
    ///
    /// With `deadline`, frames still queued after it are published with an error instead of
    /// being associated, so shutdown ends within about one frame's cost of it.
    pub fn close(&self, deadline: Option<Instant>) {
        *lock(&self.close_by) = deadline;
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
    frame_deadline: Duration,
    close_by: Arc<Mutex<Option<Instant>>>,
    published: Arc<AtomicU64>,
}

/// Why a queued frame is published without association.
enum Skip {
    Deadline(Duration),
    Shutdown,
}

impl Worker {
    /// Whether a frame first seen at `first_seen` must be skipped now.
    fn skip(&self, first_seen: Instant) -> Option<Skip> {
        let now = Instant::now();
        let waited = now.saturating_duration_since(first_seen);
        if lock(&self.close_by).is_some_and(|t| now >= t) {
            Some(Skip::Shutdown)
        } else if waited > self.frame_deadline {
            Some(Skip::Deadline(waited))
        } else {
            None
        }
    }

    fn skipped_error(&self, skip: &Skip) -> Error {
        match skip {
            Skip::Deadline(waited) => {
                self.metrics.error("deadline_exceeded");
                Error::ResourceExhausted(format!(
                    "frame not associated: it waited {:.3}s for inference, over the frame \
                     deadline of {:?} (--frame-deadline)",
                    waited.as_secs_f64(),
                    self.frame_deadline
                ))
            }
            Skip::Shutdown => {
                self.metrics.error("unavailable");
                Error::Unavailable(
                    "frame not associated: the server is shutting down and its \
                     --shutdown-grace is over"
                        .into(),
                )
            }
        }
    }

    fn run(mut self, rx: std::sync::mpsc::Receiver<Job>) {
        while let Ok(job) = rx.recv() {
            match job {
                Job::Stream(e) => {
                    let r = match self.skip(e.first_seen) {
                        None => self.process(&e.frame, e.first_seen),
                        Some(skip) => {
                            let err = self.skipped_error(&skip);
                            let mut r = self.result(&e.frame, e.first_seen, Vec::new());
                            r.error = Some(err.to_string());
                            r
                        }
                    };
                    self.metrics
                        .frame_latency(&self.info.spec.name, e.first_seen.elapsed());
                    self.queued.fetch_sub(1, Ordering::AcqRel);
                    // Count first, so a subscriber never sees more results than published.
                    self.published.fetch_add(1, Ordering::AcqRel);
                    // No subscriber is not an error.
                    let _ = self.results.send(Arc::new(r));
                }
                Job::Unary {
                    frame,
                    started,
                    reply,
                } => {
                    let r = match self.skip(started) {
                        None => Ok(self.process(&frame, started)),
                        Some(skip) => Err(self.skipped_error(&skip)),
                    };
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
        let mut r = self.result(frame, started, identities);
        r.error = error;
        r
    }

    /// The published form of `frame` with `identities`.
    fn result(&self, frame: &Frame, started: Instant, identities: Vec<IdentityOut>) -> FrameResult {
        let spec = &self.info.spec;
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
            error: None,
        }
    }
}

//! One served scene: its description, synchronizer, inference worker and results broadcast.
//! One job per module: [`validate`] what a batch may contain, [`admission`] the bounded
//! inference queue, [`worker`] the encoder thread; this module drives the synchronizer and
//! owns the broadcast.
//!
//! Data flow: `push` validates a batch and feeds the scene's [`Synchronizer`] under one lock;
//! frames that leave go, still under that lock (so in frame-id order), into the scene's lane
//! of the inference pool ([`pool`]: one thread per core, so intake always has its share of the
//! cores and a batch is synchronized however busy inference is), whose threads associate each
//! frame with one encoder call and publish the result on a broadcast channel, in queue order.
//!
//! Overload costs whole frames, never cameras ([`admission`]): while the scene's queue delay
//! (how long its oldest queued job has waited) is over `--max-queue-delay`, a *new* frame is
//! shed at intake — its batches refused with [`Error::Overloaded`] (429 / `RESOURCE_EXHAUSTED`
//! with a retry-after), the frame published with status `shed` — while frames already begun
//! are still taken whole; a frame that waited in the queue past the budget anyway is shed
//! there. A Kafka-fed scene never sheds: its batches are refused and retried (the partition
//! waits). Admission is also bounded: when `queue_capacity` frames are queued, new batches and
//! unary requests are refused with [`Error::ResourceExhausted`]; a batch (or unary request)
//! that would make its frame cost more than `max_frame_cost` ([`crate::cost`]) is refused; a
//! frame still queued after the shutdown deadline is published with an error. Every accepted
//! batch appears in exactly one result.
//!
//! Boxes overlapping their image's edge are clipped to the image
//! ([`Detection::clip_to_image`]) and counted (`crossview_clipped_boxes_total`); boxes
//! entirely outside it are refused. The scene's appearance length is fixed by the first
//! *accepted* batch carrying appearance vectors.
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::{Notify, broadcast, oneshot};

use crossview_api::types::{ClockEstimate, FitEstimate, RetrainStatus, SceneDescription};
use crossview_core::capture::{CaptureTime, Ticks};
use crossview_core::memory::MemoryConfig;
use crossview_core::tracking::{Tracker, TrackerConfig};
use crossview_core::{Detection, Encoder, SceneSpec};

use crate::config::Limits;
use crate::error::{Error, Result};
use crate::metrics::Metrics;
use crate::record::SceneRecorder;
use crate::sync::{Rejection, Synchronizer};

mod admission;
mod clock;
mod fit;
mod memory;
mod placement;
mod pool;
mod priority;
mod published;
mod timebase;
mod timing;
mod unary;
mod validate;
mod worker;

pub use crate::registry::SceneInfo;
pub(crate) use pool::Pool;
use priority::run_in_background;
pub use published::Published;
pub use timebase::StreamClock;

use admission::PartialCause;
use pool::Lane;
pub(crate) use worker::Model;
use worker::{Job, Worker};

/// A scene's settings, from the server configuration (a new one goes here, and in
/// [`crate::config::ServeConfig`] or [`Limits`] where the operator sets it).
#[derive(Debug, Clone)]
pub struct SceneOptions {
    /// A frame waits this long for missing cameras (`--sync-timeout`).
    pub sync_timeout: Duration,
    /// Frames waiting for cameras at most (`--max-pending-frames`).
    pub max_pending_frames: usize,
    /// Size, cost, queue and clock-watch limits.
    pub limits: Limits,
    /// Track ids over time (`None`: off).
    pub tracker: Option<TrackerConfig>,
    /// Identities with memory of the past frames (`None`: each frame alone).
    pub memory: Option<MemoryConfig>,
    /// The inference pool the scene's work runs on (shared by the server's scenes).
    pub(crate) pool: Arc<Pool>,
    /// The scene's frame rate (`@10fps`, a recording header's `fps`, the model's training
    /// rate), which capture times need ([`timing`]); `None`: it takes frame ids only.
    pub fps: Option<f64>,
    /// How far a capture time may fall from its tick (`--time-tolerance`; `None`: half a
    /// period).
    pub time_tolerance: Option<Duration>,
}

struct Intake {
    sync: Synchronizer,
    /// The scene's clock and its cameras', for capture times.
    timing: timing::Timing,
    /// The clock sync timeouts run on: wall time, or the stream time of a Kafka partition.
    timebase: timebase::Timebase,
}

/// A live scene (see the module docs).
pub struct Scene {
    spec: SceneSpec,
    /// The model serving the scene as of the last applied swap (`None`: no model yet).
    serving: Arc<Mutex<Option<SceneInfo>>>,
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
    results: Mutex<Option<broadcast::Sender<Arc<Published>>>>,
    /// Results published so far (for spotting subscribers that stopped reading).
    published: Arc<AtomicU64>,
    /// Wakes the timer task when a new frame starts waiting.
    pub(crate) wake: Notify,
    /// The scene's lane of the inference pool (closed and drained at close).
    lane: Arc<Lane>,
    /// The pool itself, kept running while a scene uses it (its threads end with the last).
    _pool: Arc<Pool>,
    /// Where accepted batches are recorded (`--record`), if anywhere.
    recorder: Option<SceneRecorder>,
    /// The live clock watch's latest estimate ([`clock`]).
    clock: Arc<Mutex<Option<ClockEstimate>>>,
    /// The live watch's latest look at the cameras' fit ([`fit`]).
    fit: Arc<Mutex<Option<FitEstimate>>>,
    /// What healing (`--auto-retrain`) is doing for the scene, as it last said.
    retrain: Mutex<Option<RetrainStatus>>,
    /// Each camera's clock offset as applied now (declared, or changed by `--auto-align`).
    offsets: clock::Offsets,
    /// The scene's clock once it is fed capture times (results then carry their tick time).
    timed: Arc<OnceLock<Ticks>>,
    /// The scene's clock, if it declared a rate.
    ticks: Option<Ticks>,
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene")
            .field("spec", &self.spec)
            .field("serving", &*lock(&self.serving))
            .finish()
    }
}

use crate::locks::lock;

impl Scene {
    /// Starts scene `spec`: its worker thread takes ownership of the model (`None`: a scene
    /// declared by its cameras, published unassociated until a model is swapped in). With
    /// `recorder`, every accepted batch is also recorded ([`crate::record`]).
    pub fn start(
        spec: SceneSpec,
        model: Option<(SceneInfo, Box<dyn Encoder>)>,
        options: SceneOptions,
        metrics: Metrics,
        recorder: Option<SceneRecorder>,
    ) -> Result<Arc<Scene>> {
        let SceneOptions {
            sync_timeout,
            max_pending_frames: max_pending,
            limits,
            tracker,
            memory,
            pool,
            fps,
            time_tolerance,
        } = options;
        let n = spec.cameras.len();
        let model = checked_model(&spec, &limits, model)?;
        let serving = Arc::new(Mutex::new(model.as_ref().map(|m| m.info.clone())));
        let (results, _) = broadcast::channel(limits.subscriber_buffer.max(1));
        let queued = Arc::new(AtomicUsize::new(0));
        let close_by = Arc::new(Mutex::new(None));
        let published = Arc::new(AtomicU64::new(0));
        let clock = Arc::new(Mutex::new(None));
        let fit = Arc::new(Mutex::new(None));
        let fence = fit::fence(n);
        let timed = Arc::new(OnceLock::new());
        let offsets: clock::Offsets = spec
            .cameras
            .iter()
            .map(|c| std::sync::atomic::AtomicI64::new(c.offset))
            .collect();
        let worker = Worker {
            spec: spec.clone(),
            model,
            serving: serving.clone(),
            results: results.clone(),
            queued: queued.clone(),
            metrics: metrics.clone(),
            max_queue_delay: limits.max_queue_delay,
            close_by: close_by.clone(),
            published: published.clone(),
            tracker: tracker.map(Tracker::new),
            memory: memory.map(|m| memory::SceneMemory::new(m, offsets.clone())),
            clock: clock::ClockWatch::start(
                &spec,
                limits.clock_watch,
                metrics.clone(),
                clock.clone(),
                fit.clone(),
                offsets.clone(),
                fence.clone(),
            ),
            fenced: fence,
            fenced_now: Vec::new(),
            timed: timed.clone(),
        };
        let lane = pool.lane(worker);
        let timing = timing::Timing::new(&spec, fps, time_tolerance);
        let ticks = timing.ticks();
        Ok(Arc::new(Scene {
            intake: Mutex::new(Intake {
                sync: Synchronizer::new(n, sync_timeout, max_pending)
                    .with_window(limits.frame_window),
                timebase: timebase::Timebase::default(),
                timing,
            }),
            spec,
            serving,
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
            lane,
            _pool: pool,
            recorder,
            clock,
            fit,
            retrain: Mutex::new(None),
            offsets,
            timed,
            ticks,
        }))
    }

    /// Name and cameras (never change: a model for other cameras is refused).
    pub fn spec(&self) -> &SceneSpec {
        &self.spec
    }

    /// The model serving the scene as of the last applied swap; `None` while it has none.
    pub fn serving(&self) -> Option<SceneInfo> {
        lock(&self.serving).clone()
    }

    /// Queues a model swap behind the frames already queued (they are associated by the old
    /// model, every later one by the new) and waits until the worker applies it. A model for
    /// other cameras is refused and the old one keeps serving.
    pub async fn swap(&self, info: SceneInfo, encoder: Box<dyn Encoder>) -> Result<()> {
        crate::registry::check_fits(&self.spec, &info)?;
        let (applied, done) = oneshot::channel();
        let model = Box::new(Model { info, encoder });
        self.lane
            .push(Job::Swap { model, applied })
            .map_err(|_| Error::Unavailable("server is shutting down".into()))?;
        done.await
            .map_err(|_| Error::Unavailable("encoder worker stopped".into()))?;
        // The new model is judged afresh: nothing is known of its fit until the next look.
        *lock(&self.fit) = None;
        Ok(())
    }

    /// The size and cost limits the scene enforces.
    pub fn limits(&self) -> &Limits {
        &self.limits
    }

    /// Scene name.
    pub fn name(&self) -> &str {
        &self.spec.name
    }

    /// The public description (`GetScene`).
    pub fn describe(&self) -> SceneDescription {
        let app = self.appearance_len.load(Ordering::Relaxed);
        let serving = self.serving();
        let association = serving
            .as_ref()
            .map(|i| i.association.clone())
            .unwrap_or_default();
        SceneDescription {
            name: self.spec.name.clone(),
            cameras: self.cameras(),
            threshold: association.threshold,
            alpha: association.alpha,
            model_version: serving.map(|i| i.version),
            appearance_length: (app > 0).then_some(app),
            sync_timeout_ms: self.sync_timeout.as_millis() as u64,
            clock: self.clock_estimate(),
            fit: self.fit(),
            retrain: lock(&self.retrain).clone(),
        }
    }

    /// The fit watch's latest look at the cameras (`None` before the first, or since a swap).
    pub(crate) fn fit(&self) -> Option<FitEstimate> {
        lock(&self.fit).clone()
    }

    /// Publishes what healing is doing for the scene (in [`Self::describe`]).
    pub(crate) fn set_retrain(&self, status: RetrainStatus) {
        *lock(&self.retrain) = Some(status);
    }

    /// Where the scene's accepted batches are recorded, if anywhere.
    pub(crate) fn recorder(&self) -> Option<&SceneRecorder> {
        self.recorder.as_ref()
    }

    /// Accepts one camera batch into the synchronizer (see the module docs) and returns the
    /// camera's own frame id it was placed at (`frame_id`, or its capture time's tick). Late,
    /// duplicate and out-of-range batches are rejected and counted.
    pub fn push(
        &self,
        camera: &str,
        frame_id: u64,
        time: Option<CaptureTime>,
        mut detections: Vec<Detection>,
    ) -> Result<u64> {
        let cam = self.spec.camera_index(camera)?;
        let app_len = self.validate("detections", cam, &mut detections)?;
        let n_boxes = detections.len();
        // The recorder's copy, taken before the lock (the synchronizer takes the original).
        let recorded = self.recorder.as_ref().map(|_| detections.clone());
        let mut intake = lock(&self.intake);
        // The camera's own frame id (the one given, or its capture time's tick) and the frame
        // it belongs to: that id less the camera's clock offset.
        let placement::Place {
            own: frame_id,
            placed,
            offset,
            frame,
        } = self.place(&intake, cam, frame_id, time)?;
        // Shed before accepting anything. One batch can release several frames at once, so the
        // queue may overshoot the capacity by at most `max_pending_frames`: still bounded.
        self.admit(1)?;
        // Under the intake lock: no other batch can fix the length or grow the frame meanwhile.
        self.check_appearance("detections", app_len)?;
        if let Some(f) = intake.sync.pending_frame(frame)
            && f.views[cam].is_none()
        {
            let mut counts: Vec<usize> = f
                .views
                .iter()
                .map(|v| v.as_ref().map_or(0, Vec::len))
                .collect();
            counts[cam] = n_boxes;
            self.check_cost("detections", frame, &counts)?;
        }
        let now = Instant::now();
        let clock = intake.timebase.at(now);
        if intake.sync.pending_frame(frame).is_none() {
            self.shed_if_over_budget(&mut intake, camera, (frame_id, frame), now, clock)?;
        }
        let emitted = match intake.sync.push_at(cam, frame, detections, now, clock) {
            Ok(e) => e,
            Err(r) => return Err(self.rejected(&intake, r, camera, frame_id)),
        };
        if let Some(n) = app_len {
            // Only an accepted batch fixes the scene's appearance length.
            let _ =
                self.appearance_len
                    .compare_exchange(0, n, Ordering::Relaxed, Ordering::Relaxed);
        }
        intake.timing.accepted(cam, placed);
        if intake.timing.timed()
            && let Some(t) = intake.timing.ticks()
        {
            let _ = self.timed.set(t);
        }
        self.metrics.batch(self.name());
        // Accepted: recorded exactly once, under the lock, so in acceptance order (never blocks).
        if let (Some(r), Some(dets)) = (&self.recorder, recorded) {
            r.record(cam, offset, frame_id, time, dets);
        }
        self.enqueue(&mut intake, emitted, PartialCause::Timeout);
        drop(intake);
        // The earliest deadline may have changed.
        self.wake.notify_one();
        Ok(frame_id)
    }

    /// The error for a batch the synchronizer refused, counted by rejection kind.
    fn rejected(&self, intake: &Intake, r: Rejection, camera: &str, frame_id: u64) -> Error {
        let (scene, camera) = (self.name().to_string(), camera.to_string());
        match r {
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
                crossview_core::Error::DuplicateBatch {
                    scene,
                    camera,
                    frame_id,
                }
                .into()
            }
            Rejection::Shed => {
                let budget = self.limits.max_queue_delay;
                let excess = self.lane.delay(Instant::now()).saturating_sub(budget);
                let message = format!(
                    "frame {frame_id} of scene '{scene}' was shed under overload (queue delay \
                     over --max-queue-delay {budget:?}): the batch of camera '{camera}' is \
                     refused"
                );
                self.overloaded(message, excess)
            }
            Rejection::OutOfRange => {
                self.metrics.out_of_range(self.name());
                let w = intake.sync.window();
                let from = match intake.sync.last_emitted() {
                    Some(last) => format!("the last emitted frame {last}"),
                    None => "the oldest pending frame".to_string(),
                };
                Error::FrameOutOfRange {
                    scene,
                    camera,
                    frame_id,
                    reason: format!(
                        "more than {w} (--frame-window) from {from}; the scene follows new ids \
                         once a majority of its cameras send them"
                    ),
                }
            }
        }
    }

    /// Emits whatever timed out by wall time `now` (or by the scene's stream time, when it
    /// follows one); returns when to look again (none: when woken).
    pub fn tick(&self, now: Instant) -> Option<Instant> {
        let mut intake = lock(&self.intake);
        let clock = intake.timebase.at(now);
        let emitted = intake.sync.poll(clock);
        if !emitted.is_empty() {
            // Without a new batch: on stream time only the idle fallback moves the clock here.
            let cause = if intake.timebase.is_stream() {
                PartialCause::Idle
            } else {
                PartialCause::Timeout
            };
            self.enqueue(&mut intake, emitted, cause);
        }
        let deadline = intake.sync.next_deadline()?;
        intake.timebase.wake_at(deadline)
    }

    /// Runs the scene's sync timeouts on `clock`, a Kafka partition's stream time
    /// ([`timebase`]), until the next [`restart`](Self::restart) (back to wall time), which
    /// is also how a transport drops the frames pending on the previous timebase first.
    pub fn follow_stream(&self, clock: StreamClock) {
        lock(&self.intake).timebase = timebase::Timebase::Stream(clock);
        self.wake.notify_one();
    }

    /// The stream time the scene follows has moved: look at its timeouts.
    pub fn stream_moved(&self) {
        self.wake.notify_one();
    }

    /// Drops the frames pending in the synchronizer (never published) and resumes as if
    /// `last_emitted` were the last frame emitted; returns how many frames were dropped. Kafka
    /// mode calls it when the scene's input partition leaves this replica or comes to it.
    pub fn restart(&self, last_emitted: Option<u64>) -> usize {
        let mut intake = lock(&self.intake);
        let n = intake.sync.restart(last_emitted);
        intake.timing.restart();
        intake.timebase = timebase::Timebase::Wall;
        self.metrics.pending(self.name(), 0);
        n
    }

    /// Results published so far.
    pub fn published(&self) -> u64 {
        self.published.load(Ordering::Acquire)
    }

    /// A receiver of this scene's frame results (each with the frame's boxes) from now on, or
    /// `Unavailable` after shutdown; the guard keeps the subscriber counted
    /// (`crossview_subscribers`) until dropped.
    pub fn subscribe(&self) -> Result<(broadcast::Receiver<Arc<Published>>, SubscriberGuard)> {
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
    /// results (a scene on a Kafka partition's stream time leaves them to the partition's next
    /// owner instead), lets the pool finish the scene's queue and publish it, then closes the
    /// broadcast so subscriber streams end. Blocking (waits for the scene's queue).
    ///
    /// With `deadline`, frames still queued after it are published with an error instead of
    /// being associated, so shutdown ends within about one frame's cost of it.
    pub fn close(&self, deadline: Option<Instant>) {
        *lock(&self.close_by) = deadline;
        self.closed.store(true, Ordering::Release);
        {
            let mut intake = lock(&self.intake);
            if intake.timebase.is_stream() {
                // Fed by a Kafka partition: its incomplete frames are not cut here but left to
                // the partition's next owner, which re-reads their batches (their offsets are
                // never committed) and forms them whole.
                let last = intake.sync.last_emitted();
                let left = intake.sync.restart(last);
                tracing::info!(
                    scene = self.name(),
                    left,
                    "scene intake closed; incomplete frames left to the partition's next owner"
                );
            } else {
                let emitted = intake.sync.flush();
                let n = emitted.len();
                self.enqueue(&mut intake, emitted, PartialCause::Timeout);
                tracing::info!(scene = self.name(), flushed = n, "scene intake closed");
            }
            self.lane.close();
        }
        self.lane.drain();
        lock(&self.results).take();
    }
}

/// The scene's model, once its cameras are checked: 1..=`max_cameras` of them, and the
/// model's the same.
fn checked_model(
    spec: &SceneSpec,
    limits: &Limits,
    model: Option<(SceneInfo, Box<dyn Encoder>)>,
) -> Result<Option<Model>> {
    let n = spec.cameras.len();
    if n == 0 || n > limits.max_cameras {
        return Err(Error::invalid(
            "cameras",
            format!(
                "scene '{}' has {n} cameras; 1..={} are supported",
                spec.name, limits.max_cameras
            ),
        ));
    }
    model
        .map(|(info, encoder)| {
            crate::registry::check_fits(spec, &info)?;
            Ok(Model { info, encoder })
        })
        .transpose()
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

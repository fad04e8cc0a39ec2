//! A scene's inference worker: the state that owns the scene's encoder, run one job at a time
//! by the inference pool ([`super::pool`]); it associates each queued frame with one encoder
//! call and publishes the results in queue order. A frame that waited in the queue longer than
//! `--max-queue-delay` is shed (published with status `shed`, never associated), and one
//! still queued after the shutdown grace is published with an error, so every accepted batch
//! still appears in exactly one result.
//!
//! A model swap is one more job in the same queue: the frames queued before it are associated
//! by the old model, those after it by the new one, none twice or lost. A scene declared by its
//! cameras alone has no model: its frames are published unassociated (`no_model`) until one
//! arrives.
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use tokio::sync::{broadcast, oneshot};

use crossview_api::convert::{frame_boxes, identity_out};
use crossview_api::types::{FrameResult, FrameWithBoxes, IdentityOut, ResultStatus};
use crossview_core::association::{embed_frame, frame_identities_with};
use crossview_core::capture::Ticks;
use crossview_core::identity::Identity;
use crossview_core::tracking::Tracker;
use crossview_core::{Encoder, Frame, FrameEmbeddings, SceneSpec};

use super::{SceneInfo, lock};
use crate::error::{Error, Result};
use crate::metrics::Metrics;
use crate::sync::Emitted;

/// The reason a frame shed at intake is published with.
const SHED_AT_INTAKE: &str = "shed at intake: the scene's queue delay was over its budget \
     (--max-queue-delay) when the frame's first batch came; its batches were refused";

/// Work for the worker.
pub(super) enum Job {
    /// A frame from the synchronizer: publish its result. With `may_shed`, it is shed once it
    /// waited in the queue longer than the scene's budget (a Kafka-fed scene never sheds: its
    /// partition waits instead).
    Stream { frame: Emitted, may_shed: bool },
    /// A unary request: answer it (its error, with its kind, goes back to the caller).
    Unary {
        frame: Frame,
        started: Instant,
        reply: oneshot::Sender<Result<FrameResult>>,
    },
    /// Serve with this model from the next job on; `applied` hears when it does.
    Swap {
        model: Box<Model>,
        applied: oneshot::Sender<()>,
    },
}

/// A loaded model: what it says about the scene and its encoder.
pub(crate) struct Model {
    pub(crate) info: SceneInfo,
    pub(crate) encoder: Box<dyn Encoder>,
}

/// The worker's state; [`Worker::run`] consumes it on its thread.
pub(super) struct Worker {
    pub(super) spec: SceneSpec,
    /// `None` while the scene has no model.
    pub(super) model: Option<Model>,
    /// What the scene describes as its model: the worker's, updated when a swap is applied.
    pub(super) serving: Arc<Mutex<Option<SceneInfo>>>,
    /// Published results, each with the frame's boxes (for `events?boxes=true`).
    pub(super) results: broadcast::Sender<Arc<super::Published>>,
    pub(super) queued: Arc<AtomicUsize>,
    pub(super) metrics: Metrics,
    /// A frame that waited longer in the queue is shed (`--max-queue-delay`).
    pub(super) max_queue_delay: Duration,
    pub(super) close_by: Arc<Mutex<Option<Instant>>>,
    pub(super) published: Arc<AtomicU64>,
    /// Track ids for the synchronized frames, in frame order (unary frames are not tracked;
    /// `None`: tracking is off).
    pub(super) tracker: Option<Tracker>,
    /// What the past streamed frames said about each pair of people (`None`: each frame
    /// alone; unary frames never use it).
    pub(super) memory: Option<super::memory::SceneMemory>,
    /// The live clock watch (`None`: off).
    pub(super) clock: Option<super::clock::ClockWatch>,
    /// Cameras the watch found no longer fitting the model, left out of association
    /// (`--fence-moved-cameras`; all false when off).
    pub(super) fenced: super::fit::Fence,
    /// The cameras fenced when the frame being served was associated (what its result says).
    pub(super) fenced_now: Vec<bool>,
    /// The scene's clock once it is fed capture times: results carry their tick time.
    pub(super) timed: Arc<OnceLock<Ticks>>,
}

impl Worker {
    /// Runs one job, queued at `queued_at`.
    pub(super) fn handle(&mut self, job: Job, queued_at: Instant) {
        let waited = queued_at.elapsed();
        if !matches!(job, Job::Swap { .. }) {
            self.metrics.queue_delay(&self.spec.name, waited);
        }
        match job {
            Job::Stream { frame: e, may_shed } => {
                let shed = if e.shed {
                    Some(("intake", SHED_AT_INTAKE.to_string()))
                } else if may_shed && waited > self.max_queue_delay {
                    let why = format!(
                        "shed: it waited {:.3}s in the inference queue, over the budget of \
                         {:?} (--max-queue-delay)",
                        waited.as_secs_f64(),
                        self.max_queue_delay
                    );
                    Some(("queue", why))
                } else {
                    None
                };
                let (r, embeddings) = match shed {
                    Some((stage, why)) => {
                        self.metrics.shed(&self.spec.name, stage);
                        (self.shed_result(&e.frame, e.first_seen, why), None)
                    }
                    None => self.stream_result(&e.frame, e.first_seen),
                };
                self.publish(&e, r, embeddings);
            }
            Job::Unary {
                frame,
                started,
                reply,
            } => {
                self.fenced_now.clear();
                // The caller counts the error (the service does, once).
                let r = self
                    .check_grace()
                    .and_then(|()| self.check_queue_wait(waited))
                    .and_then(|()| self.associate(&frame, false))
                    .map(|(ids, _)| {
                        let spec = &self.spec;
                        let ids = ids.into_iter().map(|id| identity_out(spec, id, None));
                        self.result(&frame, started, ids.collect())
                    });
                self.queued.fetch_sub(1, Ordering::AcqRel);
                let _ = reply.send(r);
            }
            Job::Swap { model, applied } => {
                self.swap(*model);
                let _ = applied.send(());
            }
        }
    }

    /// Publishes a synchronized frame's result `r` (in queue order) and hands its embeddings
    /// to the clock watch.
    fn publish(&mut self, e: &Emitted, r: FrameResult, embeddings: Option<FrameEmbeddings>) {
        self.metrics
            .frame_latency(&self.spec.name, e.first_seen.elapsed());
        self.queued.fetch_sub(1, Ordering::AcqRel);
        // Count first, so a subscriber never sees more results than published.
        self.published.fetch_add(1, Ordering::AcqRel);
        let views = frame_boxes(&self.spec, &e.frame);
        // No subscriber is not an error.
        let _ = self
            .results
            .send(Arc::new(super::Published::new(FrameWithBoxes {
                result: r,
                views,
            })));
        // After publishing: the clock watch's copy is off the latency path. It keeps the
        // leading block only (an ensemble's first member): a window of frames at the full
        // width of an ensemble costs its width in memory.
        if let (Some(c), Some(embeddings), Some(m)) = (&mut self.clock, embeddings, &self.model) {
            let width = m.encoder.leading_width();
            c.observe(e.frame.frame_id, embeddings.leading(width));
        }
    }

    /// The published form of a shed frame: no identities, status `shed`, `why` in `error`.
    fn shed_result(&mut self, frame: &Frame, first_seen: Instant, why: String) -> FrameResult {
        self.fenced_now.clear();
        let mut r = self.result(frame, first_seen, Vec::new());
        r.status = ResultStatus::Shed;
        r.error = Some(why);
        r.error_kind = Some("shed".to_string());
        r
    }

    /// Serves with `model` from now on. The tracks end (a new model's embedding space is not
    /// the old one's); track ids go on counting, so no id is reused.
    fn swap(&mut self, model: Model) {
        let from = self.model.as_ref().map(|m| m.info.version.clone());
        tracing::info!(scene = %self.spec.name, from = from.as_deref().unwrap_or("none"), to = %model.info.version, "model swapped in");
        *lock(&self.serving) = Some(model.info.clone());
        self.model = Some(model);
        if let Some(t) = &mut self.tracker {
            t.end_tracks();
        }
        if let Some(m) = &mut self.memory {
            m.clear();
        }
        if let Some(c) = &mut self.clock {
            c.reset();
        }
    }

    /// The published result of a synchronized frame: its identities with their track ids, or
    /// the error (message and kind, counted here: no caller sees it) without identities; and
    /// the frame's embeddings when it was associated.
    fn stream_result(
        &mut self,
        frame: &Frame,
        first_seen: Instant,
    ) -> (FrameResult, Option<FrameEmbeddings>) {
        self.fenced_now.clear();
        if self.model.is_none() {
            self.metrics.unassociated(&self.spec.name);
            let mut r = self.result(frame, first_seen, Vec::new());
            r.status = ResultStatus::NoModel;
            return (r, None);
        }
        match self
            .check_grace()
            .and_then(|()| self.associate(frame, true))
        {
            Ok((ids, embeddings)) => {
                let tracks = match &mut self.tracker {
                    Some(tracker) => tracker
                        .update(frame, &ids, &embeddings)
                        .into_iter()
                        .map(Some)
                        .collect(),
                    None => vec![None; ids.len()],
                };
                let spec = &self.spec;
                let ids = ids
                    .into_iter()
                    .zip(tracks)
                    .map(|(id, t)| identity_out(spec, id, t))
                    .collect();
                (self.result(frame, first_seen, ids), Some(embeddings))
            }
            Err(e) => {
                self.metrics.error(&e);
                let mut r = self.result(frame, first_seen, Vec::new());
                r.error = Some(e.report());
                r.error_kind = Some(e.kind().to_string());
                r.status = ResultStatus::Failed;
                (r, None)
            }
        }
    }

    /// Refuses a job once past the shutdown grace.
    fn check_grace(&self) -> Result<()> {
        if lock(&self.close_by).is_some_and(|t| Instant::now() >= t) {
            Err(Error::Unavailable(
                "frame not associated: the server is shutting down and its --shutdown-grace \
                 is over"
                    .into(),
            ))
        } else {
            Ok(())
        }
    }

    /// Refuses a unary request that `waited` in the queue longer than the budget (a stream
    /// frame is shed instead, or — Kafka — associated however long it waited).
    fn check_queue_wait(&self, waited: Duration) -> Result<()> {
        if waited > self.max_queue_delay {
            Err(Error::DeadlineExceeded(format!(
                "frame not associated: it waited {:.3}s in the inference queue, over the \
                 budget of {:?} (--max-queue-delay)",
                waited.as_secs_f64(),
                self.max_queue_delay
            )))
        } else {
            Ok(())
        }
    }

    /// Embeds the frame in one encoder call and builds its identities (SPEC §3), with the
    /// scene's memory when `streamed` (a unary frame is associated alone); a panic in the
    /// method becomes a [`crossview_core::Error::Internal`] instead of taking the scene down.
    fn associate(
        &mut self,
        frame: &Frame,
        streamed: bool,
    ) -> Result<(Vec<Identity>, FrameEmbeddings)> {
        let spec = &self.spec;
        let model = self
            .model
            .as_mut()
            .ok_or_else(|| Error::NoModel(spec.name.clone()))?;
        let t = Instant::now();
        let encoder = model.encoder.as_mut();
        let config = &model.info.association;
        self.fenced_now = super::fit::fenced(&self.fenced);
        let fenced = &self.fenced_now;
        let memory = match (&mut self.memory, streamed) {
            (Some(m), true) => Some(m.for_frame()),
            _ => None,
        };
        let outcome: crossview_core::Result<_> =
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                let embeddings = embed_frame(encoder, spec, frame)?;
                let identities = frame_identities_with(frame, &embeddings, config, fenced, memory);
                Ok((identities, embeddings))
            }))
            .unwrap_or_else(|_| Err(crossview_core::Error::internal("association panicked")));
        self.metrics.inference(&spec.name, t.elapsed());
        match outcome {
            Ok(done) => Ok(done),
            Err(e) => {
                tracing::error!(
                    scene = %spec.name,
                    frame_id = frame.frame_id,
                    error = %e.report(),
                    "association failed"
                );
                // A panic may have left the memory half-written: start it over.
                if let Some(m) = &mut self.memory {
                    m.clear();
                }
                Err(e.into())
            }
        }
    }

    /// The published form of `frame` with `identities`.
    fn result(&self, frame: &Frame, started: Instant, identities: Vec<IdentityOut>) -> FrameResult {
        let spec = &self.spec;
        FrameResult {
            scene: spec.name.clone(),
            frame_id: frame.frame_id,
            time: self.timed.get().map(|t| t.time_of(frame.frame_id)),
            complete: frame.is_complete(),
            missing_cameras: frame
                .views
                .iter()
                .zip(&spec.cameras)
                .filter(|(v, _)| v.is_none())
                .map(|(_, c)| c.name.clone())
                .collect(),
            fenced_cameras: spec
                .cameras
                .iter()
                .zip(&self.fenced_now)
                .filter(|(_, f)| **f)
                .map(|(c, _)| c.name.clone())
                .collect(),
            identities,
            latency_ms: started.elapsed().as_secs_f64() * 1e3,
            error: None,
            error_kind: None,
            status: ResultStatus::Associated,
            model_version: self.model.as_ref().map(|m| m.info.version.clone()),
        }
    }
}

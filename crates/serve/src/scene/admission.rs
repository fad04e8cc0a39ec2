//! Admission to a scene's inference queue: a new frame is shed whole while the scene's queue
//! delay is over its budget ([`Scene::shed_if_over_budget`]); new work is refused with
//! [`Error::ResourceExhausted`] once `queue_capacity` frames wait (or with
//! [`Error::Unavailable`] after shutdown began); and frames the synchronizer releases are
//! queued for the worker in frame-id order.
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::worker::Job;
use super::{Intake, Scene};
use crate::error::{Error, Result};
use crate::sync::{EmitReason, Emitted};

impl Scene {
    /// Refuses `extra` more frames when the queue is full or the scene is closing.
    pub(super) fn admit(&self, extra: usize) -> Result<()> {
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

    /// Sheds frame `frame` — which camera `camera`'s batch `frame_id` would begin — when the
    /// scene's queue delay (how long its oldest queued job has waited) is over
    /// `--max-queue-delay`: the frame is shed whole (published with status `shed`, every batch
    /// of it refused) and the batch refused with [`Error::Overloaded`], whose retry-after is
    /// the excess. A Kafka-fed scene sheds nothing: the batch is refused, to be retried (its
    /// partition waits). `now` is wall time, `clock` the scene's sync clock.
    pub(super) fn shed_if_over_budget(
        &self,
        intake: &mut Intake,
        camera: &str,
        (frame_id, frame): (u64, u64),
        now: Instant,
        clock: Instant,
    ) -> Result<()> {
        let budget = self.limits.max_queue_delay;
        let delay = self.lane.delay(now);
        if delay <= budget {
            return Ok(());
        }
        let what = if intake.timebase.is_stream() {
            "retry it"
        } else {
            match intake.sync.shed(frame, now, clock) {
                Ok(emitted) => self.enqueue(intake, emitted, PartialCause::Timeout),
                // Late or out of range: that refusal says more.
                Err(r) => return Err(self.rejected(intake, r, camera, frame_id)),
            }
            "its frame is shed"
        };
        Err(self.overloaded(
            format!(
                "scene '{}' is over its queue budget: its oldest queued frame has waited {:.3}s \
                 (--max-queue-delay {budget:?}); the batch of camera '{camera}' for frame \
                 {frame_id} is refused, {what}",
                self.name(),
                delay.as_secs_f64(),
            ),
            delay - budget,
        ))
    }

    /// An [`Error::Overloaded`] saying `message`, retry after `excess` (at least 10 ms).
    pub(super) fn overloaded(&self, message: String, excess: Duration) -> Error {
        Error::Overloaded {
            message,
            retry_after: excess.max(Duration::from_millis(10)),
        }
    }

    /// Queues the frames the synchronizer released for the worker (under the intake lock, so
    /// in frame-id order) and updates the frame and pending gauges; a partial frame that timed
    /// out is counted under `timed_out`.
    pub(super) fn enqueue(
        &self,
        intake: &mut Intake,
        emitted: Vec<Emitted>,
        timed_out: PartialCause,
    ) {
        let may_shed = !intake.timebase.is_stream();
        for e in emitted {
            if e.shed {
                self.metrics.frame_shed(self.name());
            } else {
                self.metrics.frame(self.name(), e.complete());
                if !e.complete() {
                    tracing::debug!(
                        scene = self.name(),
                        frame = e.frame.frame_id,
                        reason = ?e.reason,
                        waited = ?e.waited,
                        "partial frame"
                    );
                    self.metrics
                        .partial(self.name(), partial_cause(e.reason, timed_out));
                }
            }
            self.queued.fetch_add(1, Ordering::AcqRel);
            if self.lane.push(Job::Stream { frame: e, may_shed }).is_err() {
                self.queued.fetch_sub(1, Ordering::AcqRel);
                tracing::error!(scene = self.name(), "frame emitted after close");
            }
        }
        self.metrics
            .pending(self.name(), intake.sync.pending_frames());
    }
}

/// Why a frame that timed out did: the clock moved on without its missing cameras.
#[derive(Debug, Clone, Copy)]
pub(super) enum PartialCause {
    /// Wall time, or a stream's records, moved past its timeout.
    Timeout,
    /// Stream time: its partition was caught up and quiet for the timeout.
    Idle,
}

/// The `cause` label of `crossview_frames_partial_total` for a partial frame.
fn partial_cause(reason: EmitReason, timed_out: PartialCause) -> &'static str {
    match (reason, timed_out) {
        (EmitReason::Timeout, PartialCause::Timeout) => "camera_missing",
        (EmitReason::Timeout, PartialCause::Idle) => "idle",
        (EmitReason::Overflow, _) => "frame_cap",
        (EmitReason::Restart, _) => "restart",
        (EmitReason::Flush, _) => "shutdown",
        (EmitReason::Complete, _) => "complete",
        (EmitReason::Shed, _) => "shed",
    }
}

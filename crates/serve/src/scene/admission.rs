//! Admission to a scene's inference queue: new work is shed with
//! [`Error::ResourceExhausted`] once `queue_capacity` frames wait (or refused with
//! [`Error::Unavailable`] after shutdown began), and frames the synchronizer releases are
//! queued for the worker in frame-id order.
use std::sync::atomic::Ordering;
use std::time::Instant;

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

    /// Queues the frames the synchronizer released at wall time `now` for the worker (under
    /// the intake lock, so in frame-id order) and updates the frame and pending gauges; a
    /// partial frame that timed out is counted under `timed_out`.
    pub(super) fn enqueue(
        &self,
        intake: &mut Intake,
        emitted: Vec<Emitted>,
        now: Instant,
        timed_out: PartialCause,
    ) {
        for e in emitted {
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
            // The frame deadline runs from when the frame began to wait by its own clock: a
            // frame held while a stream's delivery was held is not charged for the hold.
            let waited = e.waited.min(self.sync_timeout);
            let deadline_from = now
                .checked_sub(waited)
                .map_or(e.first_seen, |t| t.max(e.first_seen));
            match &intake.jobs {
                Some(tx) => {
                    self.queued.fetch_add(1, Ordering::AcqRel);
                    let job = Job::Stream {
                        frame: e,
                        deadline_from,
                    };
                    if tx.send(job).is_err() {
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
    }
}

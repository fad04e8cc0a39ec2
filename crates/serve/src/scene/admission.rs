//! Admission to a scene's inference queue: new work is shed with
//! [`Error::ResourceExhausted`] once `queue_capacity` frames wait (or refused with
//! [`Error::Unavailable`] after shutdown began), and frames the synchronizer releases are
//! queued for the worker in frame-id order.
use std::sync::atomic::Ordering;

use super::worker::Job;
use super::{Intake, Scene};
use crate::error::{Error, Result};
use crate::sync::Emitted;

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

    /// Queues the frames the synchronizer released for the worker (under the intake lock, so
    /// in frame-id order) and updates the frame and pending gauges.
    pub(super) fn enqueue(&self, intake: &mut Intake, emitted: Vec<Emitted>) {
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
}

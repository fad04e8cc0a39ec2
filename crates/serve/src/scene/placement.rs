//! Which frame a batch goes to: its frame id less its camera's clock offset, or its capture
//! time's tick ([`super::timing`]); and the cameras' clocks as the scene describes them.
use std::sync::atomic::Ordering;

use crossview_api::types::ClockEstimate;
use crossview_core::capture::{CaptureTime, Placement};

use super::{Scene, lock};
use crate::error::{Error, Result};

/// Where a batch goes ([`Scene::place`]).
pub(super) struct Place {
    /// The camera's own frame id.
    pub own: u64,
    /// A timestamped batch's placement, for [`super::timing::Timing::accepted`].
    pub placed: Option<Placement>,
    /// The camera's clock offset in frame ids, as read for this batch.
    pub offset: i64,
    /// The frame it belongs to.
    pub frame: u64,
}

impl Scene {
    /// The live clock estimate; for a scene fed capture times, with each camera's offset in
    /// milliseconds, drift and jitter.
    pub(super) fn clock_estimate(&self) -> Option<ClockEstimate> {
        let mut estimate = lock(&self.clock).clone()?;
        let applied: Vec<i64> = self
            .offsets
            .iter()
            .map(|o| o.load(Ordering::Acquire))
            .collect();
        lock(&self.intake).timing.fill(&mut estimate, &applied);
        Some(estimate)
    }

    /// The frame camera `camera`'s batch stamped `frame_id` and `time` would go to now (see
    /// [`Service::frame_of`](crate::Service::frame_of)).
    pub fn frame_of_batch(
        &self,
        camera: &str,
        frame_id: u64,
        time: Option<CaptureTime>,
    ) -> Result<u64> {
        let cam = self.spec.camera_index(camera)?;
        Ok(self.place(&lock(&self.intake), cam, frame_id, time)?.frame)
    }

    /// Where camera `cam`'s batch stamped `frame_id` and `time` goes now (under the intake
    /// lock, as [`Self::push`] places it): its own id (the one given, or its capture time's
    /// tick, [`super::timing`]), the clock offset read for it and the frame it belongs to
    /// (its id less that offset).
    pub(super) fn place(
        &self,
        intake: &super::Intake,
        cam: usize,
        frame_id: u64,
        time: Option<CaptureTime>,
    ) -> Result<Place> {
        let (own, placed) =
            intake
                .timing
                .place(self.name(), &self.spec.cameras[cam], cam, frame_id, time)?;
        let offset = self.offsets[cam].load(Ordering::Acquire);
        Ok(Place {
            own,
            placed,
            offset,
            frame: self.frame_of(cam, own, offset)?,
        })
    }

    /// The cameras with the clock offsets applied now.
    pub fn cameras(&self) -> Vec<crossview_core::CameraSpec> {
        let mut cameras = self.spec.cameras.clone();
        for (c, o) in cameras.iter_mut().zip(self.offsets.iter()) {
            c.offset = o.load(Ordering::Acquire);
        }
        cameras
    }

    /// The frame camera `cam`'s batch `frame_id` belongs to: `frame_id` less `offset`, the
    /// camera's clock offset as read for this batch (its `@±N` in the scene declaration, or
    /// what `--auto-align` set; the recorder is told the same value).
    fn frame_of(&self, cam: usize, frame_id: u64, offset: i64) -> Result<u64> {
        crossview_core::types::frame_less_offset(frame_id, offset).ok_or_else(|| {
            Error::invalid(
                "frame_id",
                format!(
                    "frame id {frame_id} of camera '{}' less its clock offset {offset} falls \
                     outside 0..=2^64-1",
                    self.spec.cameras[cam].name
                ),
            )
        })
    }
}

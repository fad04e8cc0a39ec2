//! Batches gathered into frames by frame id, each camera's clock offset applied.
use std::collections::BTreeMap;

use crossview_core::{CameraSpec, Detection, Frame, SceneSpec};

/// Collects batches into frames keyed (and so sorted) by frame id: a camera's batch `N`
/// goes to frame `N − offset` (its clock offset, [`CameraSpec::frame_of`]).
pub(super) struct FrameAssembler {
    cameras: Vec<CameraSpec>,
    frames: BTreeMap<u64, Frame>,
}

/// What [`FrameAssembler::insert`] made of a batch.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum Inserted {
    Added,
    /// The camera had already reported the frame.
    Duplicate,
    /// The frame id less the camera's offset falls outside `0..=u64::MAX`.
    OutOfRange,
}

impl FrameAssembler {
    pub(super) fn new(scene: &SceneSpec) -> Self {
        FrameAssembler {
            cameras: scene.cameras.clone(),
            frames: BTreeMap::new(),
        }
    }

    /// Groups the batches inserted from now on by `scene`'s clock offsets (the same cameras,
    /// in the same order).
    pub(super) fn use_offsets(&mut self, scene: &SceneSpec) {
        for (c, s) in self.cameras.iter_mut().zip(&scene.cameras) {
            c.offset = s.offset;
        }
    }

    /// Stores camera `cam`'s detections of its frame id `frame_id`.
    pub(super) fn insert(
        &mut self,
        cam: usize,
        frame_id: u64,
        detections: Vec<Detection>,
    ) -> Inserted {
        let n = self.cameras.len();
        let Some(frame_id) = self.cameras[cam].frame_of(frame_id) else {
            return Inserted::OutOfRange;
        };
        let frame = self
            .frames
            .entry(frame_id)
            .or_insert_with(|| Frame::new(frame_id, n));
        if frame.views[cam].is_some() {
            return Inserted::Duplicate;
        }
        frame.views[cam] = Some(detections);
        Inserted::Added
    }

    pub(super) fn finish(self) -> Vec<Frame> {
        self.frames.into_values().collect()
    }
}

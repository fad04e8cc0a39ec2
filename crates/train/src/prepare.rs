//! How a recording is prepared for training — one frame in [`frame_step`](crate::data::frame_step) of it, then the
//! training-box filter — and what a model file records of that, so that whatever reads the
//! recording again for the model (`crossview model calibrate`) prepares it the same way.
use crossview_core::Result;
use crossview_model::ModelMetadata;

use crate::TrainingSet;
use crate::clean::{BoxFilter, FilterStats};

/// Brings a recording's set to the frames and boxes training uses: one frame in
/// [`frame_step`](crate::data::frame_step)`(fps)` (at least `min_frames` left), then `filter`. Training and
/// `crossview model calibrate` both prepare their recordings with it, so a calibration fitted
/// afterwards sees the boxes its model was trained on.
pub fn prepare(
    set: &mut TrainingSet,
    fps: f64,
    filter: &BoxFilter,
    min_frames: usize,
) -> Result<FilterStats> {
    set.thin_to_reference_rate(fps, min_frames)?;
    Ok(filter.apply(set))
}

/// The frame rate a model file says its training recording had (`crossview.train_fps`, which
/// [`crate::run::run`] writes), when it records one.
pub fn trained_fps(meta: &ModelMetadata) -> Option<f64> {
    let v: serde_json::Value = serde_json::from_str(meta.extra.get(KEY_TRAIN_FPS)?).ok()?;
    v["fps"].as_f64()
}

/// The training-box filter a model file says its training used
/// (`crossview.train_box_filter`, which [`crate::run::run`] writes), when it records one.
pub fn trained_filter(meta: &ModelMetadata) -> Option<BoxFilter> {
    serde_json::from_str(meta.extra.get(KEY_TRAIN_BOX_FILTER)?).ok()
}

/// Metadata key of the training recording's frame rate and the step it was thinned by.
pub(crate) const KEY_TRAIN_FPS: &str = "crossview.train_fps";

/// Metadata key of the training-box filter.
pub(crate) const KEY_TRAIN_BOX_FILTER: &str = "crossview.train_box_filter";

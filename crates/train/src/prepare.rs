//! How a recording is prepared for training — read ([`read_training_set`]), one frame in
//! [`frame_step`](crate::data::frame_step) of it at the rate given or declared in its header,
//! then the training-box filter — and what a model file records of that, so that whatever
//! reads a recording again for the model ([`prepare_as_trained`]) prepares it the same way.
use std::path::PathBuf;

use crossview_core::{Error, Result};
use crossview_data::recording::{Recording, read_recordings};
use crossview_model::ModelMetadata;

use crate::TrainingSet;
use crate::clean::{BoxFilter, FilterStats};
use crate::sampler::MIN_FRAMES;

/// A training recording read and prepared ([`read_training_set`]).
pub(crate) struct Loaded {
    /// The recording as read (ids included).
    pub rec: Recording,
    /// Its frames and boxes as training uses them.
    pub set: TrainingSet,
    /// What reading clipped and skipped, in words.
    pub read_summary: String,
    /// The frame rate it was prepared at: `fps` if given, else the one its header declares,
    /// else [`REFERENCE_FPS`](crate::data::REFERENCE_FPS) (WILDTRACK's).
    pub fps: f64,
}

/// The training data's paths, for messages.
fn data_label(data: &[PathBuf]) -> String {
    data.iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Reads the training recording (`strict`: fail on the first broken box or line) and turns
/// it into the cleaned training set ([`prepare`] at the frame rate of [`Loaded::fps`]).
pub(crate) fn read_training_set(
    data: &[PathBuf],
    strict: bool,
    fps: Option<f64>,
    filter: &BoxFilter,
) -> Result<Loaded> {
    let (rec, read) = read_recordings(data, strict)?;
    let mut read_summary = format!(
        "{} boxes clipped at the image edge, {} broken boxes and {} broken lines skipped",
        read.clipped_boxes, read.skipped_boxes, read.skipped_lines
    );
    if read.torn_lines > 0 {
        read_summary += &format!(
            ", {} torn last line(s) dropped (cut short by a crash)",
            read.torn_lines
        );
    }
    if read.skipped_boxes + read.skipped_lines > 0 {
        tracing::warn!(
            clipped = read.clipped_boxes,
            skipped_boxes = read.skipped_boxes,
            skipped_lines = read.skipped_lines,
            first = read.first_problem.as_deref().unwrap_or(""),
            "training data had broken boxes or lines (skipped; --strict aborts instead)"
        );
    }
    let label = |m: String| Error::Training(format!("training data {}: {m}", data_label(data)));
    let mut set = TrainingSet::from_recording(&rec.without_ids(), MIN_FRAMES)
        .map_err(|e| label(e.report()))?;
    let fps = fps.or(rec.fps).unwrap_or(crate::data::REFERENCE_FPS);
    let removed = prepare(&mut set, fps, filter, MIN_FRAMES).map_err(|e| match e {
        Error::Training(m) => label(m),
        e => e,
    })?;
    if !filter.is_off() {
        tracing::info!(
            before = removed.before,
            small = removed.small,
            stationary = removed.stationary,
            kept = set.num_boxes(),
            "filtered training boxes"
        );
    }
    if set.num_boxes() == 0 {
        return Err(Error::Training(format!(
            "no training boxes left after --min-box-height {} / --drop-static-iou {}",
            filter.min_height, filter.static_iou
        )));
    }
    Ok(Loaded {
        rec,
        set,
        read_summary,
        fps,
    })
}

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

/// `recording`'s frames and boxes as the model `meta` was trained on — what a later step that
/// fits or scores the model (`crossview model calibrate`, `model distil`, `model gate`) reads:
/// thinned at `fps`, else the recording's declared rate, else the model's own training rate
/// (so that time-shifted pairs lie as far apart in seconds as in training), then `filter`,
/// else the model's own training filter when it records one. Also returns what the filter
/// kept.
pub fn prepare_as_trained(
    recording: &Recording,
    meta: &ModelMetadata,
    fps: Option<f64>,
    filter: Option<BoxFilter>,
) -> Result<(TrainingSet, FilterStats)> {
    let mut set = TrainingSet::from_recording(recording, 1)?;
    let fps = fps
        .or(recording.fps)
        .or_else(|| meta.train_fps())
        .unwrap_or(crate::data::REFERENCE_FPS);
    let filter = filter.or_else(|| trained_filter(meta)).unwrap_or_default();
    let stats = prepare(&mut set, fps, &filter, 1)?;
    Ok((set, stats))
}

/// The training-box filter a model file says its training used
/// (`crossview.train_box_filter`, which [`crate::run::run`] writes), when it records one.
pub fn trained_filter(meta: &ModelMetadata) -> Option<BoxFilter> {
    serde_json::from_str(meta.extra.get(KEY_TRAIN_BOX_FILTER)?).ok()
}

/// Metadata key of the training recording's frame rate and the step it was thinned by.
pub(crate) use crossview_model::metadata::KEY_TRAIN_FPS;

/// Metadata key of the training-box filter.
pub(crate) const KEY_TRAIN_BOX_FILTER: &str = "crossview.train_box_filter";

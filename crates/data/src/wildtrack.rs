//! WILDTRACK importers (SPEC §6): the ground-truth `annotations_positions/` folder and the
//! Self-MVA detections JSON, both turned into a [`Recording`] of scene `wildtrack`.
//!
//! Cameras CVLab1..CVLab4, IDIAP1..IDIAP3 are `viewNum` 0..6, all 1920x1080. The full sequence
//! is frames 0..=1995 step 5 (400 frames); its chronological split ([`super::split`]) is
//! train 0..=1435, validation 1440..=1795, test 1800..=1995. Every camera gets a batch for every
//! imported frame (empty when it saw nobody), so every frame is complete.
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::split::{Part, split_bounds};
use crate::imported::{
    Imported, clip_box, dataset_scene, empty_frame, finish, format_err, view_index,
};
use crate::selfmva::read_detections;
use crossview_core::{Detection, SceneSpec};
use crossview_core::{Error, Result};

/// Scene name of WILDTRACK recordings.
pub const SCENE_NAME: &str = "wildtrack";
/// Camera names in `viewNum` order.
pub const CAMERA_NAMES: [&str; 7] = [
    "CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3",
];
/// Image width of every camera, pixels.
pub(crate) const WIDTH: u32 = 1920;
/// Image height of every camera, pixels.
pub(crate) const HEIGHT: u32 = 1080;
/// Frame-id step between annotated frames.
pub(crate) const FRAME_STEP: u64 = 5;
/// Frames per second of the imported recordings: one annotated frame every 0.5 s (the
/// videos' 10 frames per second, one in [`FRAME_STEP`]), written into their header.
pub const ANNOTATED_FPS: f64 = 2.0;
/// The last frame id of the full annotated sequence.
pub(crate) const LAST_FRAME: u64 = 1995;

/// The WILDTRACK scene: 7 cameras of 1920x1080 in `viewNum` order.
pub fn scene() -> SceneSpec {
    dataset_scene(SCENE_NAME, &CAMERA_NAMES, WIDTH, HEIGHT)
}

/// The full sequence's frame ids, 0..=1995 step 5 — including the test frames that the public
/// annotation folder lacks, so splits are computed on the whole sequence.
pub fn sequence_frame_ids() -> Vec<u64> {
    (0..=LAST_FRAME).step_by(FRAME_STEP as usize).collect()
}

/// Inclusive frame-id bounds of `part` of the full WILDTRACK sequence
/// (train 0..=1435, val 1440..=1795, test 1800..=1995).
pub fn part_bounds(part: Part) -> (u64, u64) {
    split_bounds(&sequence_frame_ids(), part)
        .expect("the WILDTRACK sequence is sorted")
        .expect("every part of 400 frames is non-empty")
}

/// One person of an annotation file.
#[derive(Debug, Deserialize)]
struct AnnotatedPerson {
    #[serde(rename = "personID")]
    person_id: i64,
    views: Vec<AnnotatedView>,
}

/// One person's box in one view; all four coordinates -1 means "not visible".
#[derive(Debug, Deserialize)]
struct AnnotatedView {
    #[serde(rename = "viewNum")]
    view_num: i64,
    xmin: f64,
    ymin: f64,
    xmax: f64,
    ymax: f64,
}

/// Lists the annotation files of `dir` as (frame id, path), sorted by frame id. A file's
/// number (`00001440.json`) is its frame id; other files are ignored.
fn annotation_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let mut files = Vec::new();
    for entry in entries {
        let path = entry.map_err(|e| Error::io(dir, e))?.path();
        if path.extension().and_then(|e| e.to_str()) != Some("json") {
            continue;
        }
        match path
            .file_stem()
            .and_then(|s| s.to_str())
            .and_then(|s| s.parse::<u64>().ok())
        {
            Some(frame_id) => files.push((frame_id, path)),
            None => {
                tracing::warn!(file = %path.display(), "ignoring a non-numeric annotation file name")
            }
        }
    }
    files.sort();
    Ok(files)
}

/// Imports ground truth from a WILDTRACK `annotations_positions/` folder, frames with
/// `from <= frame_id <= to` (either bound optional). Boxes carry the `personID` as `id`.
/// Views with -1 coordinates (not visible) are skipped; boxes are clipped to the image;
/// boxes still empty after clipping are dropped and counted (a `tracing` warning).
/// Fails when no annotated frame falls in the range.
pub fn import_ground_truth(dir: &Path, from: Option<u64>, to: Option<u64>) -> Result<Imported> {
    let (lo, hi) = (from.unwrap_or(0), to.unwrap_or(u64::MAX));
    if lo > hi {
        return Err(Error::invalid(
            "from",
            format!("frame range is empty: from {lo} > to {hi}"),
        ));
    }
    let files = annotation_files(dir)?;
    if files.is_empty() {
        return Err(format_err(
            dir,
            0,
            "no annotation files (NNNNNNNN.json) found",
        ));
    }
    let (first, last) = (files[0].0, files[files.len() - 1].0);
    let n = CAMERA_NAMES.len();
    let (mut clipped, mut dropped) = (0usize, 0usize);
    let mut frames = Vec::new();
    for (frame_id, path) in files.iter().filter(|(f, _)| (lo..=hi).contains(f)) {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let people: Vec<AnnotatedPerson> = serde_json::from_str(&text)
            .map_err(|e| format_err(path, e.line(), format!("malformed annotation file: {e}")))?;
        let mut frame = empty_frame(*frame_id, n);
        for (p, person) in people.iter().enumerate() {
            let id = u64::try_from(person.person_id).map_err(|_| {
                format_err(
                    path,
                    0,
                    format!("person [{p}]: personID {} is negative", person.person_id),
                )
            })?;
            for view in &person.views {
                let cam = view_index(path, view.view_num, n, &format!("personID {id}"))?;
                let coords = [view.xmin, view.ymin, view.xmax, view.ymax];
                if coords.iter().all(|&c| c == -1.0) {
                    continue;
                }
                if coords.iter().any(|c| !c.is_finite()) {
                    return Err(format_err(
                        path,
                        0,
                        format!(
                            "personID {id} view {}: non-finite box {coords:?}",
                            view.view_num
                        ),
                    ));
                }
                let (bbox, was_clipped) = clip_box(coords, WIDTH, HEIGHT);
                clipped += usize::from(was_clipped);
                let Some(bbox) = bbox else {
                    dropped += 1;
                    continue;
                };
                let mut det = Detection::new(bbox);
                det.id = Some(id);
                frame.views[cam].as_mut().expect("all views set").push(det);
            }
        }
        frames.push(frame);
    }
    if frames.is_empty() {
        return Err(Error::invalid(
            "frames",
            format!(
                "no annotated frame in {lo}..={hi}: {} holds frames {first}..={last}",
                dir.display()
            ),
        ));
    }
    if dropped > 0 {
        tracing::warn!(dropped, dir = %dir.display(), "dropped ground-truth boxes that were empty after clipping");
    }
    tracing::debug!(clipped, "clipped boxes to the image");
    finish(scene(), Some(ANNOTATED_FPS), frames, clipped, dropped)
}

/// Imports Self-MVA detections of WILDTRACK `{"<index>": [[x, y, w, h, id, viewNum], ...]}`:
/// frame id = `stride * index`, bbox `[x, y, x + w, y + h]`, id kept unless -1. Boxes are
/// clipped to the image and boxes empty afterwards are dropped and counted. Every camera gets a
/// batch for every frame of the file.
pub fn import_detections(file: &Path, stride: u64) -> Result<Imported> {
    let read = read_detections(file, stride, &scene())?;
    finish(
        scene(),
        Some(ANNOTATED_FPS),
        read.frames.into_values().collect(),
        read.clipped,
        read.dropped,
    )
}

//! WILDTRACK importers (SPEC §6): the ground-truth `annotations_positions/` folder and the
//! Self-MVA detections JSON, both turned into a [`Recording`] of scene `wildtrack`.
//!
//! Cameras CVLab1..CVLab4, IDIAP1..IDIAP3 are `viewNum` 0..6, all 1920x1080. The full sequence
//! is frames 0..=1995 step 5 (400 frames); its chronological split ([`super::split`]) is
//! train 0..=1435, validation 1440..=1795, test 1800..=1995. Every camera gets a batch for every
//! imported frame (empty when it saw nobody), so every frame is complete.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::Recording;
use super::split::{Part, split_bounds};
use crossview_core::{CameraSpec, Detection, Frame, SceneSpec};
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
    SceneSpec {
        name: SCENE_NAME.to_string(),
        cameras: CAMERA_NAMES
            .iter()
            .map(|name| CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: name.to_string(),
                width: WIDTH,
                height: HEIGHT,
            })
            .collect(),
    }
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

/// An imported recording with what the importer had to repair.
#[derive(Debug, Clone)]
pub struct Imported {
    /// The recording (scene `wildtrack`, every frame complete).
    pub recording: Recording,
    /// Boxes clipped to the image (negative x1/y1, or past the right or bottom edge).
    pub clipped: usize,
    /// Boxes dropped because they were empty or inverted (after clipping).
    pub dropped: usize,
}

/// Clips the box to the 1920x1080 image (the one edge rule, [`Detection::clip_to_image`]:
/// WILDTRACK has negative xmin/ymin and boxes past the right and bottom edges); returns the box
/// and whether it was clipped, or `None` when it is empty/inverted (or entirely outside)
/// afterwards.
///
/// [`Detection::clip_to_image`]: crossview_core::Detection::clip_to_image
fn clip_box(x1: f64, y1: f64, x2: f64, y2: f64) -> (Option<[f32; 4]>, bool) {
    let (w, h) = (f64::from(WIDTH), f64::from(HEIGHT));
    let clipped = x1 < 0.0 || y1 < 0.0 || x2 > w || y2 > h;
    let (x1, y1, x2, y2) = (x1.max(0.0), y1.max(0.0), x2.min(w), y2.min(h));
    if x2 <= x1 || y2 <= y1 {
        return (None, clipped);
    }
    (Some([x1 as f32, y1 as f32, x2 as f32, y2 as f32]), clipped)
}

fn format_err(source: &Path, line: usize, message: impl Into<String>) -> Error {
    Error::Format {
        source_name: source.display().to_string(),
        line,
        message: message.into(),
    }
}

/// Maps a `viewNum` to a camera index, or a format error naming it.
fn view_index(source: &Path, view_num: i64, what: &str) -> Result<usize> {
    usize::try_from(view_num)
        .ok()
        .filter(|&v| v < CAMERA_NAMES.len())
        .ok_or_else(|| {
            format_err(
                source,
                0,
                format!("{what}: viewNum {view_num} is outside 0..=6"),
            )
        })
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
        let mut frame = Frame::new(*frame_id, n);
        frame.views.iter_mut().for_each(|v| *v = Some(Vec::new()));
        for (p, person) in people.iter().enumerate() {
            let id = u64::try_from(person.person_id).map_err(|_| {
                format_err(
                    path,
                    0,
                    format!("person [{p}]: personID {} is negative", person.person_id),
                )
            })?;
            for view in &person.views {
                let cam = view_index(path, view.view_num, &format!("personID {id}"))?;
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
                let (bbox, was_clipped) = clip_box(view.xmin, view.ymin, view.xmax, view.ymax);
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
    finish(frames, clipped, dropped)
}

/// Validates every box (a guard against importer bugs) and wraps the frames.
fn finish(frames: Vec<Frame>, clipped: usize, dropped: usize) -> Result<Imported> {
    let recording = Recording {
        scene: scene(),
        frames,
        fps: Some(ANNOTATED_FPS),
    };
    for frame in &recording.frames {
        for (c, view) in frame.views.iter().enumerate() {
            for (i, det) in view.iter().flatten().enumerate() {
                det.validate(
                    &format!("{}@{}.detections[{i}]", CAMERA_NAMES[c], frame.frame_id),
                    None,
                )?;
            }
        }
    }
    Ok(Imported {
        recording,
        clipped,
        dropped,
    })
}

/// Imports Self-MVA detections `{"<index>": [[x, y, w, h, id, viewNum], ...]}`: frame id =
/// `stride * index`, bbox `[x, y, x + w, y + h]`, id kept unless -1. Boxes are clipped to the image
/// and boxes empty afterwards are dropped and counted. Every camera gets a batch for
/// every frame of the file.
pub fn import_detections(file: &Path, stride: u64) -> Result<Imported> {
    if stride == 0 {
        return Err(Error::invalid("stride", "must be at least 1"));
    }
    let text = std::fs::read_to_string(file).map_err(|e| Error::io(file, e))?;
    let raw: BTreeMap<String, Vec<Vec<f64>>> = serde_json::from_str(&text).map_err(|e| {
        format_err(
            file,
            e.line(),
            format!("expected {{\"<index>\": [[x, y, w, h, id, viewNum], ...]}}: {e}"),
        )
    })?;
    let n = CAMERA_NAMES.len();
    let (mut clipped, mut dropped) = (0usize, 0usize);
    let mut frames = BTreeMap::new();
    for (key, rows) in &raw {
        let index: u64 = key
            .parse()
            .map_err(|_| format_err(file, 0, format!("key \"{key}\" is not a frame index")))?;
        let frame_id = index.checked_mul(stride).ok_or_else(|| {
            format_err(
                file,
                0,
                format!("frame index {index} x stride {stride} overflows"),
            )
        })?;
        let mut frame = Frame::new(frame_id, n);
        frame.views.iter_mut().for_each(|v| *v = Some(Vec::new()));
        for (k, row) in rows.iter().enumerate() {
            let what = format!("\"{key}\"[{k}]");
            let &[x, y, w, h, id, view] = row.as_slice() else {
                return Err(format_err(
                    file,
                    0,
                    format!(
                        "{what}: expected 6 values [x, y, w, h, id, viewNum], got {}",
                        row.len()
                    ),
                ));
            };
            if [x, y, w, h].iter().any(|v| !v.is_finite()) {
                return Err(format_err(
                    file,
                    0,
                    format!("{what}: non-finite box {row:?}"),
                ));
            }
            if view.fract() != 0.0 {
                return Err(format_err(
                    file,
                    0,
                    format!("{what}: viewNum {view} is not an integer"),
                ));
            }
            let cam = view_index(file, view as i64, &what)?;
            let id = if id == -1.0 {
                None
            } else if id >= 0.0 && id.fract() == 0.0 {
                Some(id as u64)
            } else {
                return Err(format_err(
                    file,
                    0,
                    format!("{what}: id {id} is neither -1 nor a non-negative integer"),
                ));
            };
            let (bbox, was_clipped) = clip_box(x, y, x + w, y + h);
            clipped += usize::from(was_clipped);
            let Some(bbox) = bbox else {
                dropped += 1;
                continue;
            };
            let mut det = Detection::new(bbox);
            det.id = id;
            frame.views[cam].as_mut().expect("all views set").push(det);
        }
        if frames.insert(frame_id, frame).is_some() {
            return Err(format_err(
                file,
                0,
                format!("two keys map to frame {frame_id} (key \"{key}\")"),
            ));
        }
    }
    if dropped > 0 {
        tracing::warn!(dropped, file = %file.display(), "dropped detections that were empty after clipping");
    }
    tracing::debug!(clipped, "clipped boxes to the image");
    finish(frames.into_values().collect(), clipped, dropped)
}

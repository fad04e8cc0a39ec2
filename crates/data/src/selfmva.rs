//! The Self-MVA detections JSON: the format the method's reference code ships each dataset's
//! detector boxes in (`detections_train.json`), read for any scene whose cameras it numbers.
use std::collections::BTreeMap;
use std::path::Path;

use crate::imported::{clip_box, empty_frame, format_err, view_index};
use crossview_core::{Detection, Error, Frame, Result, SceneSpec};

/// The frames of a detections file, by frame id, with what reading them repaired.
#[derive(Debug)]
pub(crate) struct Detections {
    /// Every frame of the file, each camera with a batch (empty when it saw nobody).
    pub frames: BTreeMap<u64, Frame>,
    /// Boxes clipped to the image.
    pub clipped: usize,
    /// Boxes dropped because they were empty after clipping.
    pub dropped: usize,
}

/// Reads Self-MVA detections `{"<index>": [[x, y, w, h, id, viewNum], ...]}` of `scene`
/// (`viewNum` = camera index): frame id = `stride * index`, bbox `[x, y, x + w, y + h]`, id kept
/// unless -1. Boxes are clipped to their camera's image and boxes empty afterwards are dropped
/// and counted. Every camera gets a batch for every frame of the file.
pub(crate) fn read_detections(file: &Path, stride: u64, scene: &SceneSpec) -> Result<Detections> {
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
    let n = scene.cameras.len();
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
        let mut frame = empty_frame(frame_id, n);
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
            let cam = view_index(file, view as i64, n, &what)?;
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
            let camera = &scene.cameras[cam];
            let (bbox, was_clipped) = clip_box([x, y, x + w, y + h], camera.width, camera.height);
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
    Ok(Detections {
        frames,
        clipped,
        dropped,
    })
}

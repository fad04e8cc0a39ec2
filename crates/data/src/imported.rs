//! What every dataset importer shares: the imported recording with the repairs it needed, the
//! one clipping rule, and the final check of every box.
use std::path::Path;

use super::Recording;
use crossview_core::{CameraSpec, Error, Frame, Result, SceneSpec};

/// An imported recording with what the importer had to repair.
#[derive(Debug, Clone)]
pub struct Imported {
    /// The recording (every frame complete: a camera that saw nobody has an empty batch).
    pub recording: Recording,
    /// Boxes clipped to the image (negative x1/y1, or past the right or bottom edge).
    pub clipped: usize,
    /// Boxes dropped: empty or inverted after clipping, or (MVOR) linked to no person.
    pub dropped: usize,
}

/// Clips the box to a `width` x `height` image (the one edge rule, [`Detection::clip_to_image`]:
/// datasets ship negative corners and boxes past the right and bottom edges); returns the box
/// and whether it was clipped, or `None` when it is empty/inverted (or entirely outside)
/// afterwards.
///
/// [`Detection::clip_to_image`]: crossview_core::Detection::clip_to_image
pub(crate) fn clip_box(
    [x1, y1, x2, y2]: [f64; 4],
    width: u32,
    height: u32,
) -> (Option<[f32; 4]>, bool) {
    let (w, h) = (f64::from(width), f64::from(height));
    let clipped = x1 < 0.0 || y1 < 0.0 || x2 > w || y2 > h;
    let (x1, y1, x2, y2) = (x1.max(0.0), y1.max(0.0), x2.min(w), y2.min(h));
    if x2 <= x1 || y2 <= y1 {
        return (None, clipped);
    }
    (Some([x1 as f32, y1 as f32, x2 as f32, y2 as f32]), clipped)
}

/// A format error naming the file (and the line, 0 when unknown).
pub(crate) fn format_err(source: &Path, line: usize, message: impl Into<String>) -> Error {
    Error::Format {
        source_name: source.display().to_string(),
        line,
        message: message.into(),
    }
}

/// Maps a 0-based view number to a camera index of a scene of `cameras` cameras, or a format
/// error naming it.
pub(crate) fn view_index(
    source: &Path,
    view_num: i64,
    cameras: usize,
    what: &str,
) -> Result<usize> {
    usize::try_from(view_num)
        .ok()
        .filter(|&v| v < cameras)
        .ok_or_else(|| {
            format_err(
                source,
                0,
                format!(
                    "{what}: viewNum {view_num} is outside 0..={}",
                    cameras.saturating_sub(1)
                ),
            )
        })
}

/// A dataset's fixed scene: `cameras` in view-number order, all of one image size, in sync.
pub(crate) fn dataset_scene(name: &str, cameras: &[&str], width: u32, height: u32) -> SceneSpec {
    SceneSpec {
        name: name.to_string(),
        cameras: cameras
            .iter()
            .map(|c| CameraSpec::new(*c, width, height))
            .collect(),
    }
}

/// A frame of `cameras` empty batches: every camera reported, nobody seen yet.
pub(crate) fn empty_frame(frame_id: u64, cameras: usize) -> Frame {
    let mut frame = Frame::new(frame_id, cameras);
    frame.views.iter_mut().for_each(|v| *v = Some(Vec::new()));
    frame
}

/// Validates every box (a guard against importer bugs) and wraps the frames.
pub(crate) fn finish(
    scene: SceneSpec,
    fps: Option<f64>,
    frames: Vec<Frame>,
    clipped: usize,
    dropped: usize,
) -> Result<Imported> {
    for frame in &frames {
        for (c, view) in frame.views.iter().enumerate() {
            for (i, det) in view.iter().flatten().enumerate() {
                det.validate(
                    &format!(
                        "{}@{}.detections[{i}]",
                        scene.cameras[c].name, frame.frame_id
                    ),
                    None,
                )?;
            }
        }
    }
    Ok(Imported {
        recording: Recording { scene, frames, fps },
        clipped,
        dropped,
    })
}

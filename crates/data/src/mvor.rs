//! MVOR importers (SPEC §6's reference threshold 0.1 is this dataset's): the ground truth of
//! `camma_mvor_2018_v2.json` and the Self-MVA detections of its multi-view frames, both
//! turned into a [`Recording`] of scene `mvor`.
//!
//! MVOR is 732 synchronized triples of 640x480 images from three ceiling cameras of one
//! operating room, taken over four days, seconds to hours apart (75 s apart at the median): a
//! scene the default model never saw, and no video. Frame id = the triple's index in the file's
//! `multiview_images` (time order, as the Self-MVA detections number them); cameras `cam1`..
//! `cam3` are the file's `cam_id` 1..3 and the detections' `viewNum` 0..2. The recordings
//! declare no frame rate. Every camera gets a batch for every one of the 732 frames (empty
//! when it saw nobody), so both recordings share one frame sequence and `crossview split`
//! cuts them alike.
use std::collections::HashMap;
use std::path::Path;

use serde::Deserialize;

use crate::imported::{Imported, clip_box, dataset_scene, empty_frame, finish, format_err};
use crate::selfmva::read_detections;
use crossview_core::{Detection, Error, Result, SceneSpec};

/// Scene name of MVOR recordings.
pub const SCENE_NAME: &str = "mvor";
/// Camera names in `viewNum` order (`cam_id` 1..3).
pub const CAMERA_NAMES: [&str; 3] = ["cam1", "cam2", "cam3"];
/// Image width of every camera, pixels.
const WIDTH: u32 = 640;
/// Image height of every camera, pixels.
const HEIGHT: u32 = 480;
/// Multi-view frames of the dataset (`multiview_images` of `camma_mvor_2018_v2.json`).
pub const FRAMES: u64 = 732;

/// The MVOR scene: 3 cameras of 640x480.
pub fn scene() -> SceneSpec {
    dataset_scene(SCENE_NAME, &CAMERA_NAMES, WIDTH, HEIGHT)
}

/// The parts of the annotation file the import reads.
#[derive(Debug, Deserialize)]
struct AnnotationFile {
    multiview_images: Vec<MultiviewImage>,
    annotations: Vec<Annotation>,
}

/// One synchronized triple.
#[derive(Debug, Deserialize)]
struct MultiviewImage {
    images: Vec<Image>,
}

/// One camera's image of a triple.
#[derive(Debug, Deserialize)]
struct Image {
    id: u64,
    cam_id: i64,
    width: u32,
    height: u32,
}

/// One person's box in one image; `person_id` -1 links it to nobody.
#[derive(Debug, Deserialize)]
struct Annotation {
    image_id: u64,
    bbox: [f64; 4],
    person_id: i64,
}

/// Imports the ground truth of `camma_mvor_2018_v2.json`: every multi-view frame, boxes
/// `[x, y, x + w, y + h]` clipped to the image, each carrying its `person_id` (the same person
/// has the same id in the three views of a frame). Boxes of person -1 (the dataset's own
/// "not linked across views") and boxes empty after clipping are dropped and counted.
pub fn import_ground_truth(file: &Path) -> Result<Imported> {
    let text = std::fs::read_to_string(file).map_err(|e| Error::io(file, e))?;
    let data: AnnotationFile = serde_json::from_str(&text).map_err(|e| {
        format_err(
            file,
            e.line(),
            format!("expected MVOR's annotation file (multiview_images, annotations): {e}"),
        )
    })?;
    let n = CAMERA_NAMES.len();
    let mut frames = Vec::with_capacity(data.multiview_images.len());
    // image id -> (frame index, camera index)
    let mut images = HashMap::new();
    for (index, triple) in data.multiview_images.iter().enumerate() {
        frames.push(empty_frame(index as u64, n));
        for image in &triple.images {
            let cam = usize::try_from(image.cam_id - 1)
                .ok()
                .filter(|&c| c < n)
                .ok_or_else(|| {
                    format_err(
                        file,
                        0,
                        format!(
                            "image {}: cam_id {} is outside 1..=3",
                            image.id, image.cam_id
                        ),
                    )
                })?;
            if (image.width, image.height) != (WIDTH, HEIGHT) {
                return Err(format_err(
                    file,
                    0,
                    format!(
                        "image {}: {}x{}, MVOR's cameras are {WIDTH}x{HEIGHT}",
                        image.id, image.width, image.height
                    ),
                ));
            }
            if images.insert(image.id, (index, cam)).is_some() {
                return Err(format_err(
                    file,
                    0,
                    format!("image {} appears twice", image.id),
                ));
            }
        }
    }
    if frames.is_empty() {
        return Err(format_err(file, 0, "no multi-view frame"));
    }
    let (mut clipped, mut dropped) = (0usize, 0usize);
    for (k, ann) in data.annotations.iter().enumerate() {
        let &(index, cam) = images.get(&ann.image_id).ok_or_else(|| {
            format_err(
                file,
                0,
                format!(
                    "annotation [{k}]: image {} is in no multi-view frame",
                    ann.image_id
                ),
            )
        })?;
        let Ok(id) = u64::try_from(ann.person_id) else {
            dropped += 1;
            continue;
        };
        let [x, y, w, h] = ann.bbox;
        if [x, y, w, h].iter().any(|v| !v.is_finite()) {
            return Err(format_err(
                file,
                0,
                format!("annotation [{k}]: non-finite box {:?}", ann.bbox),
            ));
        }
        let (bbox, was_clipped) = clip_box([x, y, x + w, y + h], WIDTH, HEIGHT);
        clipped += usize::from(was_clipped);
        let Some(bbox) = bbox else {
            dropped += 1;
            continue;
        };
        let mut det = Detection::new(bbox);
        det.id = Some(id);
        frames[index].views[cam]
            .as_mut()
            .expect("all views set")
            .push(det);
    }
    if dropped > 0 {
        tracing::info!(dropped, file = %file.display(), "dropped ground-truth boxes linked to no person or empty after clipping");
    }
    finish(scene(), None, frames, clipped, dropped)
}

/// Imports Self-MVA detections of MVOR (`data/MVOR/sequence1/output/detections_train.json`):
/// frame id = the key (the multi-view frame's index), `viewNum` 0..2 = `cam1`..`cam3`. Frames
/// the file lacks are imported empty, so the recording holds all [`FRAMES`] frames.
pub fn import_detections(file: &Path) -> Result<Imported> {
    let mut read = read_detections(file, 1, &scene())?;
    if let Some((&last, _)) = read.frames.last_key_value()
        && last >= FRAMES
    {
        return Err(format_err(
            file,
            0,
            format!("frame {last} is past MVOR's {FRAMES} multi-view frames"),
        ));
    }
    let n = CAMERA_NAMES.len();
    let frames = (0..FRAMES)
        .map(|id| {
            read.frames
                .remove(&id)
                .unwrap_or_else(|| empty_frame(id, n))
        })
        .collect();
    finish(scene(), None, frames, read.clipped, read.dropped)
}

//! The training view of a recording: per frame and camera, the normalised boxes (SPEC §2),
//! checked for what self-supervised training needs (≥ 2 cameras, enough frames, boxes).
use crossview_core::{CameraSpec, SceneSpec};
use crossview_core::{Error, Result};
use crossview_data::Recording;

/// One image: the normalised boxes `[x1, y1, x2, y2]` of one camera at one frame, plus their
/// appearance vectors when every box has one.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Image {
    /// Normalised boxes.
    pub boxes: Vec<[f32; 4]>,
    /// Appearance vectors (one per box) when all boxes carry one.
    pub appearance: Option<Vec<Vec<f32>>>,
}

/// The frames of a recording as images indexed `[frame position][camera]`.
#[derive(Debug, Clone, PartialEq)]
pub struct TrainingSet {
    /// The scene (camera order = camera index).
    pub scene: SceneSpec,
    /// Frame ids, in recording order.
    pub frame_ids: Vec<u64>,
    /// `images[t][c]`; a camera that did not report a frame has an empty image.
    pub images: Vec<Vec<Image>>,
}

impl TrainingSet {
    /// Builds the training set and rejects recordings training cannot use: fewer than two
    /// cameras, fewer than `min_frames` frames (the negative offsets need frames 5–19 away),
    /// or no boxes at all. Invalid boxes are reported with frame and camera.
    pub fn from_recording(rec: &Recording, min_frames: usize) -> Result<Self> {
        let cams = &rec.scene.cameras;
        if cams.len() < 2 {
            return Err(Error::Training(format!(
                "scene '{}' has {} camera(s); self-supervised training needs at least two \
                 synchronized cameras",
                rec.scene.name,
                cams.len()
            )));
        }
        for c in cams {
            if c.width == 0 || c.height == 0 {
                return Err(Error::invalid(
                    format!("scene.cameras[{}]", c.name),
                    "image width and height must be positive",
                ));
            }
        }
        if rec.frames.len() < min_frames {
            return Err(Error::Training(format!(
                "recording has {} frame(s); training needs at least {min_frames} so that \
                 negatives can be drawn 5 to 19 frames away",
                rec.frames.len()
            )));
        }
        let mut images = Vec::with_capacity(rec.frames.len());
        let mut total = 0usize;
        for f in &rec.frames {
            let mut row = Vec::with_capacity(cams.len());
            for (c, cam) in cams.iter().enumerate() {
                let dets = f.views.get(c).and_then(Option::as_ref);
                let img = match dets {
                    Some(d) => image_of(d, cam, f.frame_id)?,
                    None => Image::default(),
                };
                total += img.boxes.len();
                row.push(img);
            }
            images.push(row);
        }
        if total == 0 {
            return Err(Error::Training(
                "recording has no boxes: nothing to learn from".into(),
            ));
        }
        Ok(TrainingSet {
            scene: rec.scene.clone(),
            frame_ids: rec.frames.iter().map(|f| f.frame_id).collect(),
            images,
        })
    }

    /// Removes the last `n` frames (all of them when `n` exceeds the count) and returns them
    /// as their own set: frames held out from training for label-free scoring.
    pub fn split_off_tail(&mut self, n: usize) -> TrainingSet {
        let at = self.images.len().saturating_sub(n);
        TrainingSet {
            scene: self.scene.clone(),
            frame_ids: self.frame_ids.split_off(at),
            images: self.images.split_off(at),
        }
    }

    /// Number of frames.
    pub fn num_frames(&self) -> usize {
        self.images.len()
    }

    /// Number of cameras.
    pub fn num_cameras(&self) -> usize {
        self.scene.cameras.len()
    }

    /// Total number of boxes.
    pub fn num_boxes(&self) -> usize {
        self.images.iter().flatten().map(|i| i.boxes.len()).sum()
    }
}

fn image_of(dets: &[crossview_core::Detection], cam: &CameraSpec, frame: u64) -> Result<Image> {
    let mut boxes = Vec::with_capacity(dets.len());
    for (i, d) in dets.iter().enumerate() {
        d.validate(
            &format!("frame {frame} camera '{}' detections[{i}]", cam.name),
            None,
        )?;
        boxes.push(d.normalized(cam));
    }
    let appearance = if !dets.is_empty() && dets.iter().all(|d| d.appearance.is_some()) {
        Some(dets.iter().filter_map(|d| d.appearance.clone()).collect())
    } else {
        None
    };
    Ok(Image { boxes, appearance })
}

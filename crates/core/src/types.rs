//! Scene, camera, detection and frame types shared by every layer. Their serde form is the
//! SPEC §7 recording/API format.
use serde::{Deserialize, Serialize};

use crate::capture::CaptureTime;
use crate::{Error, Result};

/// The frame a camera's frame id `frame_id` belongs to when its clock runs `offset` ids late
/// (`frame_id − offset`), or `None` outside `0..=u64::MAX`.
pub fn frame_less_offset(frame_id: u64, offset: i64) -> Option<u64> {
    frame_id.checked_add_signed(offset.checked_neg()?)
}

/// One camera of a scene: its name, image size in pixels and clock offset.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct CameraSpec {
    pub name: String,
    pub width: u32,
    pub height: u32,
    /// Clock offset in frame ids (`crossview sync-check` measures it): the camera's frame id
    /// `N` shows what the others show in frame `N − offset`, so its batches are grouped into
    /// that frame. 0 (the default, left out of JSON) for a camera in sync.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[cfg_attr(feature = "openapi", schema(default = 0))]
    pub offset: i64,
    /// **[ours]** Clock offset in milliseconds, for a camera that sends capture times: its
    /// batch captured at `t` goes to the tick nearest `t − offset_ms` (less `offset` whole
    /// frames). 0 (the default, left out of JSON) for a camera in sync.
    #[serde(default, skip_serializing_if = "is_zero")]
    #[cfg_attr(feature = "openapi", schema(default = 0))]
    pub offset_ms: i64,
}

fn is_zero(v: &i64) -> bool {
    *v == 0
}

impl CameraSpec {
    /// Longest camera name in bytes (names travel in every result and in `/v1/scenes`).
    pub const MAX_NAME_BYTES: usize = 128;
    /// Largest image width or height in pixels.
    pub const MAX_SIDE: u32 = 100_000;
    /// Largest clock offset either way, in frame ids.
    pub const MAX_OFFSET: i64 = 1_000_000;
    /// Largest clock offset in milliseconds either way (a day).
    pub const MAX_OFFSET_MS: i64 = 86_400_000;

    /// A camera in sync (offset 0).
    pub fn new(name: impl Into<String>, width: u32, height: u32) -> Self {
        CameraSpec {
            name: name.into(),
            width,
            height,
            offset: 0,
            offset_ms: 0,
        }
    }

    /// Same name and image size (the clock offset aside): what a model must agree on with
    /// the scene it serves.
    pub fn same_camera(&self, other: &CameraSpec) -> bool {
        self.name == other.name && self.width == other.width && self.height == other.height
    }

    /// The frame this camera's frame id `frame_id` belongs to (`frame_id − offset`), or `None`
    /// when that falls outside `0..=u64::MAX`.
    pub fn frame_of(&self, frame_id: u64) -> Option<u64> {
        frame_less_offset(frame_id, self.offset)
    }

    /// The one rule for a camera wherever it is declared (`--scene`, a recording header, a
    /// model file): a name of 1..=[`Self::MAX_NAME_BYTES`] bytes without control characters,
    /// and an image of 1..=[`Self::MAX_SIDE`] pixels a side. The error says what is wrong.
    pub fn check(&self) -> std::result::Result<(), String> {
        let shown: String = self.name.chars().take(32).collect();
        if self.name.trim().is_empty() {
            return Err("a camera name is empty".into());
        }
        if self.name.len() > Self::MAX_NAME_BYTES {
            return Err(format!(
                "camera name '{shown}…' is {} bytes, more than {}",
                self.name.len(),
                Self::MAX_NAME_BYTES
            ));
        }
        if self.name.chars().any(char::is_control) {
            return Err(format!(
                "camera name '{}' holds a control character",
                shown.escape_debug()
            ));
        }
        for (side, v) in [("width", self.width), ("height", self.height)] {
            if v == 0 || v > Self::MAX_SIDE {
                return Err(format!(
                    "camera '{shown}' has {side} {v}; it must be 1..={}",
                    Self::MAX_SIDE
                ));
            }
        }
        if self.offset_ms.unsigned_abs() > Self::MAX_OFFSET_MS.unsigned_abs() {
            return Err(format!(
                "camera '{shown}' has offset {} ms; it must be within ±{} ms",
                self.offset_ms,
                Self::MAX_OFFSET_MS
            ));
        }
        if self.offset.unsigned_abs() > Self::MAX_OFFSET.unsigned_abs() {
            return Err(format!(
                "camera '{shown}' has offset {}; it must be within ±{}",
                self.offset,
                Self::MAX_OFFSET
            ));
        }
        Ok(())
    }
}

/// A scene: a named set of synchronized static cameras, in camera-index order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct SceneSpec {
    pub name: String,
    pub cameras: Vec<CameraSpec>,
}

impl SceneSpec {
    /// Index of the camera called `name`, or [`Error::UnknownCamera`].
    pub fn camera_index(&self, name: &str) -> Result<usize> {
        self.cameras
            .iter()
            .position(|c| c.name == name)
            .ok_or_else(|| Error::UnknownCamera {
                scene: self.name.clone(),
                camera: name.to_string(),
            })
    }
}

fn default_score() -> f32 {
    1.0
}

fn is_default_score(s: &f32) -> bool {
    *s == 1.0
}

/// One detected box. `bbox` is `[x1, y1, x2, y2]` in pixels of its camera's image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Detection {
    /// `[x1, y1, x2, y2]` in pixels of the camera's image, finite, `x2 > x1` and `y2 > y1`;
    /// a box overlapping the image's edge is clipped to it, one entirely outside is refused.
    #[cfg_attr(feature = "openapi", schema(min_items = 4, max_items = 4))]
    pub bbox: [f32; 4],
    /// Detector confidence, default 1.
    #[serde(default = "default_score", skip_serializing_if = "is_default_score")]
    #[cfg_attr(
        feature = "openapi",
        schema(default = 1.0, minimum = 0.0, maximum = 1.0)
    )]
    pub score: f32,
    /// Ground-truth identity (evaluation only; never used by training or inference).
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "crate::integral::option_u64"
    )]
    #[cfg_attr(
        feature = "openapi",
        schema(minimum = 0, maximum = 18446744073709551615_u64)
    )]
    pub id: Option<u64>,
    /// Optional Re-ID appearance vector; all vectors of a scene share one length.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub appearance: Option<Vec<f32>>,
}

impl Detection {
    /// A detection with score 1 and no id or appearance.
    pub fn new(bbox: [f32; 4]) -> Self {
        Detection {
            bbox,
            score: 1.0,
            id: None,
            appearance: None,
        }
    }

    /// The box normalised by its camera's image size (SPEC §2): `[x1/W, y1/H, x2/W, y2/H]`.
    /// Values outside [0, 1] are kept (no clamping here; boxes are clipped to the image once,
    /// when they enter, by [`clip_to_image`](Self::clip_to_image)).
    pub fn normalized(&self, cam: &CameraSpec) -> [f32; 4] {
        let (w, h) = (cam.width as f32, cam.height as f32);
        [
            self.bbox[0] / w,
            self.bbox[1] / h,
            self.bbox[2] / w,
            self.bbox[3] / h,
        ]
    }

    /// Rejects boxes and values that would poison the matcher: non-finite coordinates,
    /// inverted or empty boxes, scores outside [0, 1], non-finite appearance values or an
    /// appearance length other than `appearance_len` (when given). Where the box lies relative
    /// to its image is [`clip_to_image`](Self::clip_to_image)'s rule.
    /// `field` prefixes error messages, e.g. `detections[3]`.
    pub fn validate(&self, field: &str, appearance_len: Option<usize>) -> Result<()> {
        let [x1, y1, x2, y2] = self.bbox;
        if self.bbox.iter().any(|v| !v.is_finite()) {
            return Err(Error::invalid(
                format!("{field}.bbox"),
                format!("coordinates must be finite, got {:?}", self.bbox),
            ));
        }
        if x2 <= x1 || y2 <= y1 {
            return Err(Error::invalid(
                format!("{field}.bbox"),
                format!("box must have x2 > x1 and y2 > y1, got {:?}", self.bbox),
            ));
        }
        if !self.score.is_finite() || !(0.0..=1.0).contains(&self.score) {
            return Err(Error::invalid(
                format!("{field}.score"),
                format!("must be within [0, 1], got {}", self.score),
            ));
        }
        if let Some(app) = &self.appearance {
            if let Some(len) = appearance_len
                && app.len() != len
            {
                return Err(Error::invalid(
                    format!("{field}.appearance"),
                    format!("expected {len} values, got {}", app.len()),
                ));
            }
            if app.is_empty() {
                return Err(Error::invalid(format!("{field}.appearance"), "is empty"));
            }
            if let Some(i) = app.iter().position(|v| !v.is_finite()) {
                return Err(Error::invalid(
                    format!("{field}.appearance[{i}]"),
                    "must be finite",
                ));
            }
        }
        Ok(())
    }
}

impl Detection {
    /// The one rule for boxes and the image edge (serving, training and import alike): a
    /// valid box (see [`validate`](Self::validate)) that overlaps the edge of `cam`'s
    /// `width × height` image is clipped to the image — real detectors emit boxes a pixel or
    /// two outside it (WILDTRACK's own have `y1 = -1`) — and a box entirely outside the image
    /// (no overlap of positive area) is rejected. Returns whether the box was clipped.
    pub fn clip_to_image(&mut self, field: &str, cam: &CameraSpec) -> Result<bool> {
        let (w, h) = (cam.width as f32, cam.height as f32);
        let [x1, y1, x2, y2] = self.bbox;
        if x2 <= 0.0 || y2 <= 0.0 || x1 >= w || y1 >= h {
            return Err(Error::invalid(
                format!("{field}.bbox"),
                format!(
                    "box {:?} lies entirely outside the {}x{} image of camera '{}'",
                    self.bbox, cam.width, cam.height, cam.name
                ),
            ));
        }
        let clipped = [x1.max(0.0), y1.max(0.0), x2.min(w), y2.min(h)];
        let changed = clipped != self.bbox;
        self.bbox = clipped;
        Ok(changed)
    }
}

/// A recording's first line, `{"scene": {...}}` (SPEC §7), borrowed for writing: the one
/// definition of the line every writer uses. **[ours]** `"fps"`, when the writer knows it, is
/// the recording's frame rate (frames per second of its frame ids), so that training and
/// clock-offset estimates need not be told it.
#[derive(Debug, Serialize)]
pub struct HeaderLine<'a> {
    pub scene: &'a SceneSpec,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fps: Option<f64>,
}

pub use crate::capture::{MAX_FPS, check_fps};

/// One batch line of a recording (SPEC §7): the JSON of a [`Batch`], borrowed for writing
/// without cloning the detections.
#[derive(Debug, Serialize)]
pub struct BatchLine<'a> {
    pub camera: &'a str,
    pub frame_id: u64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time: Option<CaptureTime>,
    pub detections: &'a [Detection],
}

/// One camera's detections for one frame: a line of a recording, or one pushed batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "BatchWire")]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Batch {
    /// The camera's name in its scene.
    pub camera: String,
    /// The camera's frame id (its own clock; see [`CameraSpec::offset`]): a whole number
    /// within `0..=2^64 − 1` (`7` or `7.0`). May be left out when `time` is given (0 then
    /// stands for "none", as in protobuf); given with a time, it must be the camera's own tick
    /// of that time (`round(time · fps)`, within the scene's tolerance).
    #[serde(default, deserialize_with = "crate::integral::u64")]
    #[cfg_attr(
        feature = "openapi",
        schema(minimum = 0, maximum = 18446744073709551615_u64)
    )]
    pub frame_id: u64,
    /// **[ours]** When the camera captured the frame (RFC 3339, or seconds since the Unix
    /// epoch): the scene groups it into the tick nearest this time less the camera's clock
    /// offset ([`crate::capture`]; the scene must declare its frame rate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(value_type = Option<String>, format = DateTime))]
    pub time: Option<CaptureTime>,
    /// The boxes the camera saw (none: it saw nobody).
    pub detections: Vec<Detection>,
}

/// The wire form of a [`Batch`]: a frame id, a capture time or both.
#[derive(Deserialize)]
struct BatchWire {
    camera: String,
    #[serde(default, deserialize_with = "crate::integral::option_u64")]
    frame_id: Option<u64>,
    #[serde(default)]
    time: Option<CaptureTime>,
    detections: Vec<Detection>,
}

impl TryFrom<BatchWire> for Batch {
    type Error = String;

    fn try_from(w: BatchWire) -> std::result::Result<Self, String> {
        if w.frame_id.is_none() && w.time.is_none() {
            return Err("missing field `frame_id` (or `time`, a capture time)".into());
        }
        Ok(Batch {
            camera: w.camera,
            frame_id: w.frame_id.unwrap_or(0),
            time: w.time,
            detections: w.detections,
        })
    }
}

/// All cameras' detections for one synchronized frame, indexed by camera index.
/// `views[c] == None` means camera `c` did not report this frame (a partial frame);
/// `Some(vec![])` means it reported and saw nobody.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Frame {
    pub frame_id: u64,
    pub views: Vec<Option<Vec<Detection>>>,
}

impl Frame {
    /// An empty frame with `num_cameras` unreported views.
    pub fn new(frame_id: u64, num_cameras: usize) -> Self {
        Frame {
            frame_id,
            views: vec![None; num_cameras],
        }
    }

    /// True when every camera reported.
    pub fn is_complete(&self) -> bool {
        self.views.iter().all(Option::is_some)
    }

    /// Total number of boxes over all reported views.
    pub fn num_boxes(&self) -> usize {
        self.views.iter().flatten().map(Vec::len).sum()
    }
}

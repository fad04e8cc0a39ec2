//! Transport-neutral request and result types of the service. Their serde form is the HTTP JSON
//! API; `grpc.rs` converts them to and from the protobuf messages.
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use crossview_core::capture::CaptureTime;
use crossview_core::{CameraSpec, Detection};

/// One camera's detections in a unary association request.
///
/// Unknown JSON fields are ignored, here as in batches (and as protobuf ignores unknown
/// fields): one rule for every request body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CameraView {
    /// The camera's name in the scene.
    pub camera: String,
    /// Its boxes (none: it saw nobody).
    #[serde(default)]
    pub detections: Vec<Detection>,
}

/// A whole, already synchronized frame (`POST /v1/scenes/{scene}/associate`). Cameras of the
/// scene absent from `views` count as missing. Unknown fields are ignored (see [`CameraView`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AssociateRequest {
    /// The frame id echoed in the result (default 0): a whole number within `0..=2^64 − 1`.
    #[serde(default, deserialize_with = "crossview_core::integral::u64")]
    #[schema(minimum = 0, maximum = 18446744073709551615_u64)]
    pub frame_id: u64,
    /// One entry per reporting camera.
    pub views: Vec<CameraView>,
    /// The frame's capture time (RFC 3339, or seconds since the Unix epoch): the result's
    /// frame id is then its tick (the scene must declare its frame rate), and a `frame_id`
    /// given too must be that tick.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<String>, format = DateTime)]
    pub time: Option<CaptureTime>,
}

/// One box of an identity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Member {
    /// Camera name.
    pub camera: String,
    /// Camera index in the scene.
    pub camera_index: usize,
    /// Index into that camera's batch.
    pub index: usize,
}

/// A person seen by one or more cameras in one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct IdentityOut {
    /// Dense, 0-based within the frame.
    pub id: usize,
    /// The person's track id: the same across frames and cameras while the scene's tracker
    /// follows them (`crossview_core::tracking`); absent on unary results (not tracked).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub track_id: Option<u64>,
    /// How sure the association is of this identity, in `[0, 1]`.
    pub confidence: f32,
    /// The boxes of this person, at most one per camera.
    pub members: Vec<Member>,
}

/// The association of one frame, as published to subscribers and returned by `associate`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct FrameResult {
    /// The scene.
    pub scene: String,
    /// The frame.
    pub frame_id: u64,
    /// The frame's tick time, for a scene fed capture times (`frame_id / fps` seconds after
    /// the Unix epoch, RFC 3339); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<String>, format = DateTime)]
    pub time: Option<CaptureTime>,
    /// True when every camera reported.
    pub complete: bool,
    /// Cameras that did not report.
    pub missing_cameras: Vec<String>,
    /// Cameras left out of association because they no longer fit the model (they moved:
    /// docs/camera-fit.md): each of their boxes is an identity of its own.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fenced_cameras: Vec<String>,
    /// The people of the frame.
    pub identities: Vec<IdentityOut>,
    /// Server-side latency: first batch (or request) to result, in milliseconds.
    pub latency_ms: f64,
    /// Set when association itself failed (the frame is still published, without identities).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The error's kind (`deadline_exceeded`, `unavailable`, `encoder`, ...: the labels of
    /// `crossview_errors_total`), set with `error`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error_kind: Option<String>,
    /// What became of the frame: associated, not associated because the scene has no model
    /// yet, or failed (see `error`).
    #[serde(default)]
    pub status: ResultStatus,
    /// The version of the model that associated the frame (its `crossview.version` and the
    /// file's content hash, `VERSION@HASH`); absent while the scene has no model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_version: Option<String>,
}

/// What became of a published frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ResultStatus {
    /// Associated by the scene's model: `identities` holds the result.
    #[default]
    Associated,
    /// Accepted and published, not associated: the scene was declared by its cameras and has
    /// no model yet (see `crossview serve --scene`).
    NoModel,
    /// Association failed; `error` says why.
    Failed,
    /// Shed whole under overload (`crossview serve --max-queue-delay`): never associated, no
    /// identities; `error` says why. Its batches were either refused (429 /
    /// `RESOURCE_EXHAUSTED`, shed at intake) or accepted and then waited past the budget.
    Shed,
}

/// What a reload (`SIGHUP`, `POST /v1/admin/reload`, gRPC `Reload`) did to one scene's model
/// file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct ReloadOutcome {
    /// The scene.
    pub scene: String,
    /// `swapped`, `unchanged` (the same file), `missing` (no file yet: a scene declared by
    /// its cameras keeps waiting for one) or `refused` (see `error`).
    pub outcome: String,
    /// The version serving the scene after the reload (`None`: no model).
    pub version: Option<String>,
    /// Why a file was refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// The acknowledgement of an accepted batch.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct BatchAck {
    /// The scene.
    pub scene: String,
    /// The batch's camera.
    pub camera: String,
    /// The batch's frame id: the camera's own id (for a batch with a capture time, the tick
    /// of its time less the camera's clock offset in milliseconds).
    pub frame_id: u64,
    /// Always true (a refused batch gets an error instead).
    pub accepted: bool,
}

/// What a client may know about a loaded scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SceneDescription {
    /// The scene's name.
    pub name: String,
    /// Its cameras, in camera-index order.
    pub cameras: Vec<CameraSpec>,
    /// The association threshold of the serving model.
    pub threshold: f32,
    /// The model's appearance weight.
    pub alpha: f32,
    /// The serving model's version (`VERSION@HASH`); absent while the scene has no model.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_version: Option<String>,
    /// Appearance vector length fixed by the first accepted batch with vectors; `None` while
    /// unknown.
    pub appearance_length: Option<usize>,
    /// How long a frame waits for its missing cameras, in milliseconds.
    pub sync_timeout_ms: u64,
    /// The live clock watch's latest estimate of each camera's clock offset; absent while the
    /// watch is off or has not yet seen enough frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock: Option<ClockEstimate>,
    /// The live watch's latest look at whether each camera still fits the model (a camera
    /// that was bumped, re-aimed or zoomed stops fitting); absent while the watch is off or
    /// has not yet seen enough frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fit: Option<FitEstimate>,
    /// What `serve --auto-retrain` is doing for the scene; absent when it is off.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retrain: Option<RetrainStatus>,
}

/// Healing (`serve --auto-retrain`, `docs/serve.md`): when a camera has not fitted for a while,
/// a model retrained on what was recorded since, gated without labels and swapped in live.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct RetrainStatus {
    /// `idle`, `waiting` (a camera does not fit: recording its new view), `training` or
    /// `gating`.
    pub state: String,
    /// The cameras that do not fit (the reason for the coming or running retrain).
    pub cameras: Vec<String>,
    /// Retrains started since the server started.
    pub attempts: u64,
    /// Of them, those that swapped a model in.
    pub swapped: u64,
    /// The last finished retrain: `swapped`, `refused`, `failed`, `timed_out` or
    /// `superseded`; absent before the first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_outcome: Option<String>,
    /// Why, in words (the gate's verdict, the error).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_reason: Option<String>,
    /// The model file the last swap put in service.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_model: Option<String>,
}

/// Whether each camera still fits the serving model, from the detections alone: how sharply
/// its boxes match the other cameras' at the same moment rather than at others, against how
/// sharply they did when the model was loaded (`docs/camera-fit.md`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct FitEstimate {
    /// Newest frames the look read (the most recent ones).
    pub frames: usize,
    /// Newest frame id among them.
    pub as_of_frame: u64,
    /// One entry per camera, in scene order.
    pub cameras: Vec<CameraFitState>,
}

/// One camera's live fit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CameraFitState {
    /// Camera name.
    pub camera: String,
    /// 1: fits as when the model was loaded; toward 0: it no longer fits. `None` while
    /// unknown or silent.
    pub score: Option<f32>,
    /// `fits`, `drifting` (falling), `does_not_fit` (fallen and stayed down: it moved),
    /// `silent` (no boxes lately) or `unknown` (linked to no other camera yet).
    pub state: String,
}

/// The server's live estimate of each camera's clock offset (`crossview serve
/// --clock-watch-window`), measured on the frames as the server groups them: after the
/// offsets declared in the scene (`@±N`), so a camera in sync, or one whose declared offset
/// is right, shows 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct ClockEstimate {
    /// Frames the estimate was computed from (the most recent ones).
    pub frames: usize,
    /// Newest frame id among them.
    pub as_of_frame: u64,
    /// Frame step of their ids (offsets in ids are multiples of it).
    pub step: i64,
    /// Camera the offsets are relative to (the one at the median offset).
    pub reference: String,
    /// One entry per camera, in scene order.
    pub cameras: Vec<CameraClock>,
}

/// One camera's live clock offset.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CameraClock {
    /// Camera name.
    pub camera: String,
    /// Offset in frame intervals (sub-frame: `+1.0` is one frame late), `None` when unknown:
    /// no confident overlap with another camera, or nobody moved.
    pub offset_frames: Option<f32>,
    /// Offset in frame ids, rounded to the frame step: what `@±N` would correct.
    pub offset_ids: Option<i64>,
    /// Confidence in `[0, 1]` (0 when unknown).
    pub confidence: f32,
    /// A camera that sends capture times: its clock offset in milliseconds (the whole frames
    /// the watch found, times the period, plus where within the period its captures fall);
    /// absent for cameras that send frame ids, or before enough captures.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset_ms: Option<f64>,
    /// How fast that offset moves, in ms per minute (a camera clock that gains: positive).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drift_ms_per_min: Option<f64>,
    /// How much single captures scatter about it (standard deviation, ms).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jitter_ms: Option<f64>,
}

/// The query of `GET /v1/scenes/{scene}/events`. Unknown parameters are ignored.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, IntoParams)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// `?boxes=true`: every event is a [`FrameWithBoxes`] (the result plus each reporting
    /// camera's boxes) instead of a bare [`FrameResult`]. Off by default.
    #[serde(default)]
    pub boxes: bool,
}

/// One camera's boxes in a published frame, as the server associated them (after clipping to
/// the image): `boxes[i]` is the box that a [`Member`] with this camera and `index == i`
/// points at.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct CameraBoxes {
    /// Camera name.
    pub camera: String,
    /// Camera index in the scene.
    pub camera_index: usize,
    /// `[x1, y1, x2, y2]` in pixels of the camera's image, in batch order.
    pub boxes: Vec<[f32; 4]>,
}

/// A published frame result together with the boxes it was computed from: the SSE event
/// data of `GET /v1/scenes/{scene}/events?boxes=true` (what a live viewer draws). Its JSON is
/// every [`FrameResult`] field unchanged plus `views`: one entry per camera that reported the
/// frame, in scene order (a camera in `missing_cameras` has none).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct FrameWithBoxes {
    /// The result, exactly as published without `?boxes`.
    #[serde(flatten)]
    pub result: FrameResult,
    /// Each reporting camera's boxes.
    #[serde(default)]
    pub views: Vec<CameraBoxes>,
}

/// The body of every HTTP error response: `{"error": {"kind", "message", "field"}}`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct ErrorBody {
    /// What went wrong.
    pub error: ErrorDetail,
}

/// One error: a stable kind, a message for people and the offending field, if any.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct ErrorDetail {
    /// A short, stable label (`invalid_argument`, `unknown_scene`, `unauthenticated`, ...: the
    /// labels of `crossview_errors_total`).
    pub kind: String,
    /// What went wrong, phrased for a person (long echoes of the input are truncated).
    pub message: String,
    /// The request field at fault (`body`, `views[0].detections[2].bbox`, `content-type`, ...),
    /// or null.
    pub field: Option<String>,
}

/// `GET /v1/scenes`: every loaded scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct SceneList {
    /// The scenes, by name.
    pub scenes: Vec<SceneDescription>,
}

/// `POST /v1/admin/reload`: what the reload did to each scene's model file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct ReloadReport {
    /// One outcome per model file (none when the server has no files to reload).
    pub reloads: Vec<ReloadOutcome>,
}

/// The answer to a JSON Lines body of `POST /v1/scenes/{scene}/batches`, streamed as the
/// lines are pushed: one result per batch line, then the totals.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct LinesReport {
    /// One entry per batch line (blank lines and a recording's scene header are skipped).
    pub results: Vec<LineResult>,
    /// Lines accepted.
    pub accepted: usize,
    /// Lines rejected.
    pub rejected: usize,
    /// Set when the server stopped early (too many rejected lines): the first line not read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped_at_line: Option<usize>,
    /// Set with `stopped_at_line`: why the rest of the body was not read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stopped: Option<String>,
}

/// What became of one line of a JSON Lines body.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct LineResult {
    /// 1-based line number in the body.
    pub line: usize,
    /// Whether the batch was accepted.
    pub accepted: bool,
    /// The accepted batch's camera.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
    /// The accepted batch's frame id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_id: Option<u64>,
    /// Why the line was rejected.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<LineError>,
}

/// Why one line of a JSON Lines body was rejected.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct LineError {
    /// The error's kind (as in [`ErrorDetail::kind`]).
    pub kind: String,
    /// What went wrong.
    pub message: String,
}

import datetime

from google.protobuf import timestamp_pb2 as _timestamp_pb2
from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ResultStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RESULT_STATUS_UNSPECIFIED: _ClassVar[ResultStatus]
    RESULT_STATUS_ASSOCIATED: _ClassVar[ResultStatus]
    RESULT_STATUS_NO_MODEL: _ClassVar[ResultStatus]
    RESULT_STATUS_FAILED: _ClassVar[ResultStatus]
    RESULT_STATUS_SHED: _ClassVar[ResultStatus]
RESULT_STATUS_UNSPECIFIED: ResultStatus
RESULT_STATUS_ASSOCIATED: ResultStatus
RESULT_STATUS_NO_MODEL: ResultStatus
RESULT_STATUS_FAILED: ResultStatus
RESULT_STATUS_SHED: ResultStatus

class BoundingBox(_message.Message):
    __slots__ = ("x1", "y1", "x2", "y2")
    X1_FIELD_NUMBER: _ClassVar[int]
    Y1_FIELD_NUMBER: _ClassVar[int]
    X2_FIELD_NUMBER: _ClassVar[int]
    Y2_FIELD_NUMBER: _ClassVar[int]
    x1: float
    y1: float
    x2: float
    y2: float
    def __init__(self, x1: _Optional[float] = ..., y1: _Optional[float] = ..., x2: _Optional[float] = ..., y2: _Optional[float] = ...) -> None: ...

class Detection(_message.Message):
    __slots__ = ("bbox", "score", "appearance")
    BBOX_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    APPEARANCE_FIELD_NUMBER: _ClassVar[int]
    bbox: BoundingBox
    score: float
    appearance: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, bbox: _Optional[_Union[BoundingBox, _Mapping]] = ..., score: _Optional[float] = ..., appearance: _Optional[_Iterable[float]] = ...) -> None: ...

class Batch(_message.Message):
    __slots__ = ("scene", "camera", "frame_id", "detections", "time")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    DETECTIONS_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    scene: str
    camera: str
    frame_id: int
    detections: _containers.RepeatedCompositeFieldContainer[Detection]
    time: _timestamp_pb2.Timestamp
    def __init__(self, scene: _Optional[str] = ..., camera: _Optional[str] = ..., frame_id: _Optional[int] = ..., detections: _Optional[_Iterable[_Union[Detection, _Mapping]]] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class BatchAck(_message.Message):
    __slots__ = ("scene", "camera", "frame_id", "code", "message", "kind", "retry_after_ms")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    RETRY_AFTER_MS_FIELD_NUMBER: _ClassVar[int]
    scene: str
    camera: str
    frame_id: int
    code: int
    message: str
    kind: str
    retry_after_ms: int
    def __init__(self, scene: _Optional[str] = ..., camera: _Optional[str] = ..., frame_id: _Optional[int] = ..., code: _Optional[int] = ..., message: _Optional[str] = ..., kind: _Optional[str] = ..., retry_after_ms: _Optional[int] = ...) -> None: ...

class CameraView(_message.Message):
    __slots__ = ("camera", "detections")
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    DETECTIONS_FIELD_NUMBER: _ClassVar[int]
    camera: str
    detections: _containers.RepeatedCompositeFieldContainer[Detection]
    def __init__(self, camera: _Optional[str] = ..., detections: _Optional[_Iterable[_Union[Detection, _Mapping]]] = ...) -> None: ...

class AssociateRequest(_message.Message):
    __slots__ = ("scene", "frame_id", "views", "time")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    VIEWS_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    scene: str
    frame_id: int
    views: _containers.RepeatedCompositeFieldContainer[CameraView]
    time: _timestamp_pb2.Timestamp
    def __init__(self, scene: _Optional[str] = ..., frame_id: _Optional[int] = ..., views: _Optional[_Iterable[_Union[CameraView, _Mapping]]] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class Member(_message.Message):
    __slots__ = ("camera", "camera_index", "index")
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    CAMERA_INDEX_FIELD_NUMBER: _ClassVar[int]
    INDEX_FIELD_NUMBER: _ClassVar[int]
    camera: str
    camera_index: int
    index: int
    def __init__(self, camera: _Optional[str] = ..., camera_index: _Optional[int] = ..., index: _Optional[int] = ...) -> None: ...

class Identity(_message.Message):
    __slots__ = ("id", "confidence", "members", "track_id")
    ID_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    MEMBERS_FIELD_NUMBER: _ClassVar[int]
    TRACK_ID_FIELD_NUMBER: _ClassVar[int]
    id: int
    confidence: float
    members: _containers.RepeatedCompositeFieldContainer[Member]
    track_id: int
    def __init__(self, id: _Optional[int] = ..., confidence: _Optional[float] = ..., members: _Optional[_Iterable[_Union[Member, _Mapping]]] = ..., track_id: _Optional[int] = ...) -> None: ...

class FrameResult(_message.Message):
    __slots__ = ("scene", "frame_id", "complete", "missing_cameras", "identities", "latency_ms", "error", "error_kind", "status", "model_version", "fenced_cameras", "time")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    COMPLETE_FIELD_NUMBER: _ClassVar[int]
    MISSING_CAMERAS_FIELD_NUMBER: _ClassVar[int]
    IDENTITIES_FIELD_NUMBER: _ClassVar[int]
    LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    ERROR_KIND_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    MODEL_VERSION_FIELD_NUMBER: _ClassVar[int]
    FENCED_CAMERAS_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    scene: str
    frame_id: int
    complete: bool
    missing_cameras: _containers.RepeatedScalarFieldContainer[str]
    identities: _containers.RepeatedCompositeFieldContainer[Identity]
    latency_ms: float
    error: str
    error_kind: str
    status: ResultStatus
    model_version: str
    fenced_cameras: _containers.RepeatedScalarFieldContainer[str]
    time: _timestamp_pb2.Timestamp
    def __init__(self, scene: _Optional[str] = ..., frame_id: _Optional[int] = ..., complete: _Optional[bool] = ..., missing_cameras: _Optional[_Iterable[str]] = ..., identities: _Optional[_Iterable[_Union[Identity, _Mapping]]] = ..., latency_ms: _Optional[float] = ..., error: _Optional[str] = ..., error_kind: _Optional[str] = ..., status: _Optional[_Union[ResultStatus, str]] = ..., model_version: _Optional[str] = ..., fenced_cameras: _Optional[_Iterable[str]] = ..., time: _Optional[_Union[datetime.datetime, _timestamp_pb2.Timestamp, _Mapping]] = ...) -> None: ...

class StreamResponse(_message.Message):
    __slots__ = ("ack", "result")
    ACK_FIELD_NUMBER: _ClassVar[int]
    RESULT_FIELD_NUMBER: _ClassVar[int]
    ack: BatchAck
    result: FrameResult
    def __init__(self, ack: _Optional[_Union[BatchAck, _Mapping]] = ..., result: _Optional[_Union[FrameResult, _Mapping]] = ...) -> None: ...

class SubscribeRequest(_message.Message):
    __slots__ = ("scene",)
    SCENE_FIELD_NUMBER: _ClassVar[int]
    scene: str
    def __init__(self, scene: _Optional[str] = ...) -> None: ...

class ListScenesRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListScenesResponse(_message.Message):
    __slots__ = ("scenes",)
    SCENES_FIELD_NUMBER: _ClassVar[int]
    scenes: _containers.RepeatedCompositeFieldContainer[Scene]
    def __init__(self, scenes: _Optional[_Iterable[_Union[Scene, _Mapping]]] = ...) -> None: ...

class ReloadRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ReloadResponse(_message.Message):
    __slots__ = ("reloads",)
    RELOADS_FIELD_NUMBER: _ClassVar[int]
    reloads: _containers.RepeatedCompositeFieldContainer[ReloadOutcome]
    def __init__(self, reloads: _Optional[_Iterable[_Union[ReloadOutcome, _Mapping]]] = ...) -> None: ...

class ReloadOutcome(_message.Message):
    __slots__ = ("scene", "outcome", "version", "error")
    SCENE_FIELD_NUMBER: _ClassVar[int]
    OUTCOME_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    scene: str
    outcome: str
    version: str
    error: str
    def __init__(self, scene: _Optional[str] = ..., outcome: _Optional[str] = ..., version: _Optional[str] = ..., error: _Optional[str] = ...) -> None: ...

class GetSceneRequest(_message.Message):
    __slots__ = ("scene",)
    SCENE_FIELD_NUMBER: _ClassVar[int]
    scene: str
    def __init__(self, scene: _Optional[str] = ...) -> None: ...

class Camera(_message.Message):
    __slots__ = ("name", "width", "height", "offset")
    NAME_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    name: str
    width: int
    height: int
    offset: int
    def __init__(self, name: _Optional[str] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., offset: _Optional[int] = ...) -> None: ...

class Scene(_message.Message):
    __slots__ = ("name", "cameras", "threshold", "alpha", "model_version", "appearance_length", "sync_timeout_ms", "clock", "fit", "retrain")
    NAME_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    ALPHA_FIELD_NUMBER: _ClassVar[int]
    MODEL_VERSION_FIELD_NUMBER: _ClassVar[int]
    APPEARANCE_LENGTH_FIELD_NUMBER: _ClassVar[int]
    SYNC_TIMEOUT_MS_FIELD_NUMBER: _ClassVar[int]
    CLOCK_FIELD_NUMBER: _ClassVar[int]
    FIT_FIELD_NUMBER: _ClassVar[int]
    RETRAIN_FIELD_NUMBER: _ClassVar[int]
    name: str
    cameras: _containers.RepeatedCompositeFieldContainer[Camera]
    threshold: float
    alpha: float
    model_version: str
    appearance_length: int
    sync_timeout_ms: int
    clock: ClockEstimate
    fit: FitEstimate
    retrain: RetrainStatus
    def __init__(self, name: _Optional[str] = ..., cameras: _Optional[_Iterable[_Union[Camera, _Mapping]]] = ..., threshold: _Optional[float] = ..., alpha: _Optional[float] = ..., model_version: _Optional[str] = ..., appearance_length: _Optional[int] = ..., sync_timeout_ms: _Optional[int] = ..., clock: _Optional[_Union[ClockEstimate, _Mapping]] = ..., fit: _Optional[_Union[FitEstimate, _Mapping]] = ..., retrain: _Optional[_Union[RetrainStatus, _Mapping]] = ...) -> None: ...

class RetrainStatus(_message.Message):
    __slots__ = ("state", "cameras", "attempts", "swapped", "last_outcome", "last_reason", "last_model")
    STATE_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    ATTEMPTS_FIELD_NUMBER: _ClassVar[int]
    SWAPPED_FIELD_NUMBER: _ClassVar[int]
    LAST_OUTCOME_FIELD_NUMBER: _ClassVar[int]
    LAST_REASON_FIELD_NUMBER: _ClassVar[int]
    LAST_MODEL_FIELD_NUMBER: _ClassVar[int]
    state: str
    cameras: _containers.RepeatedScalarFieldContainer[str]
    attempts: int
    swapped: int
    last_outcome: str
    last_reason: str
    last_model: str
    def __init__(self, state: _Optional[str] = ..., cameras: _Optional[_Iterable[str]] = ..., attempts: _Optional[int] = ..., swapped: _Optional[int] = ..., last_outcome: _Optional[str] = ..., last_reason: _Optional[str] = ..., last_model: _Optional[str] = ...) -> None: ...

class FitEstimate(_message.Message):
    __slots__ = ("frames", "as_of_frame", "cameras")
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    AS_OF_FRAME_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    frames: int
    as_of_frame: int
    cameras: _containers.RepeatedCompositeFieldContainer[CameraFit]
    def __init__(self, frames: _Optional[int] = ..., as_of_frame: _Optional[int] = ..., cameras: _Optional[_Iterable[_Union[CameraFit, _Mapping]]] = ...) -> None: ...

class CameraFit(_message.Message):
    __slots__ = ("camera", "known", "score", "state")
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    KNOWN_FIELD_NUMBER: _ClassVar[int]
    SCORE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    camera: str
    known: bool
    score: float
    state: str
    def __init__(self, camera: _Optional[str] = ..., known: _Optional[bool] = ..., score: _Optional[float] = ..., state: _Optional[str] = ...) -> None: ...

class ClockEstimate(_message.Message):
    __slots__ = ("frames", "as_of_frame", "step", "reference", "cameras")
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    AS_OF_FRAME_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    REFERENCE_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    frames: int
    as_of_frame: int
    step: int
    reference: str
    cameras: _containers.RepeatedCompositeFieldContainer[CameraClock]
    def __init__(self, frames: _Optional[int] = ..., as_of_frame: _Optional[int] = ..., step: _Optional[int] = ..., reference: _Optional[str] = ..., cameras: _Optional[_Iterable[_Union[CameraClock, _Mapping]]] = ...) -> None: ...

class CameraClock(_message.Message):
    __slots__ = ("camera", "known", "offset_frames", "offset_ids", "confidence", "offset_ms", "drift_ms_per_min", "jitter_ms")
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    KNOWN_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FRAMES_FIELD_NUMBER: _ClassVar[int]
    OFFSET_IDS_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_MS_FIELD_NUMBER: _ClassVar[int]
    DRIFT_MS_PER_MIN_FIELD_NUMBER: _ClassVar[int]
    JITTER_MS_FIELD_NUMBER: _ClassVar[int]
    camera: str
    known: bool
    offset_frames: float
    offset_ids: int
    confidence: float
    offset_ms: float
    drift_ms_per_min: float
    jitter_ms: float
    def __init__(self, camera: _Optional[str] = ..., known: _Optional[bool] = ..., offset_frames: _Optional[float] = ..., offset_ids: _Optional[int] = ..., confidence: _Optional[float] = ..., offset_ms: _Optional[float] = ..., drift_ms_per_min: _Optional[float] = ..., jitter_ms: _Optional[float] = ...) -> None: ...

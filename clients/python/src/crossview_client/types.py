"""Typed values of the API: what goes in (detections) and what comes out (frame results,
scenes, acks, reload outcomes), as plain dataclasses independent of the transport."""

from __future__ import annotations

import enum
from datetime import datetime
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeAlias, Union

import numpy as np
import numpy.typing as npt

__all__ = [
    "Boxes",
    "Detection",
    "Member",
    "Identity",
    "ResultStatus",
    "FrameResult",
    "Camera",
    "Scene",
    "PushAck",
    "ReloadOutcome",
    "Batch",
    "to_detections",
]


@dataclass(frozen=True, slots=True)
class Detection:
    """One detected box in pixels of its camera's image (``x1 < x2``, ``y1 < y2``)."""

    x1: float
    y1: float
    x2: float
    y2: float
    score: float | None = None
    appearance: tuple[float, ...] | None = None

    def to_json(self) -> dict[str, Any]:
        """The SPEC §7 detection object."""
        out: dict[str, Any] = {"bbox": [self.x1, self.y1, self.x2, self.y2]}
        if self.score is not None:
            out["score"] = self.score
        if self.appearance is not None:
            out["appearance"] = list(self.appearance)
        return out


# What push() takes as a camera's boxes: Detection objects, SPEC §7 dicts
# ({"bbox": [x1, y1, x2, y2], "score"?, "appearance"?}), or an N×4 / N×5 (x1, y1, x2, y2[,
# score]) NumPy array (or the same as nested lists of numbers).
Boxes: TypeAlias = Union[
    Sequence[Detection],
    Sequence[Mapping[str, Any]],
    Sequence[Sequence[float]],
    "npt.NDArray[Any]",
]


def to_detections(
    boxes: Boxes,
    appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
) -> list[Detection]:
    """Normalizes any accepted form of boxes (see :data:`Boxes`) to a list of detections.

    ``appearance``, when given, is one vector per box (an N×D array or N sequences) and
    overrides any vector in the boxes. Shapes are checked here; values (finite, inside the
    image, scores in [0, 1]) are the server's to judge, so its error names the field.
    """
    dets: list[Detection]
    if not isinstance(boxes, np.ndarray) and len(boxes) > 0 and all(
        not isinstance(b, (Mapping, Detection, str, bytes)) for b in boxes
    ):
        boxes = np.asarray(boxes, dtype=np.float64)  # rows of numbers
    if isinstance(boxes, np.ndarray):
        arr = np.asarray(boxes, dtype=np.float64)
        if arr.size == 0:
            arr = arr.reshape(0, 4)
        if arr.ndim != 2 or arr.shape[1] not in (4, 5):
            raise ValueError(f"boxes array must be N×4 or N×5 (x1, y1, x2, y2[, score]), got shape {arr.shape}")
        dets = [
            Detection(
                float(r[0]), float(r[1]), float(r[2]), float(r[3]),
                float(r[4]) if arr.shape[1] == 5 else None,
            )
            for r in arr
        ]
    else:
        dets = []
        for i, b in enumerate(boxes):
            if isinstance(b, Detection):
                dets.append(b)
                continue
            if not isinstance(b, Mapping):
                raise TypeError(f"boxes[{i}] must be a Detection or a mapping, not {type(b).__name__}")
            bbox = b.get("bbox")
            if bbox is None or len(bbox) != 4:
                raise ValueError(f"boxes[{i}] needs 'bbox': [x1, y1, x2, y2]")
            score = b.get("score")
            app = b.get("appearance")
            dets.append(
                Detection(
                    float(bbox[0]), float(bbox[1]), float(bbox[2]), float(bbox[3]),
                    float(score) if score is not None else None,
                    tuple(float(v) for v in app) if app is not None else None,
                )
            )
    if appearance is not None:
        app_arr = np.asarray(appearance, dtype=np.float64)
        if app_arr.ndim != 2 or app_arr.shape[0] != len(dets):
            raise ValueError(
                f"appearance must hold one vector per box ({len(dets)}×D), got shape {app_arr.shape}"
            )
        dets = [
            Detection(d.x1, d.y1, d.x2, d.y2, d.score, tuple(float(v) for v in row))
            for d, row in zip(dets, app_arr)
        ]
    return dets


@dataclass(frozen=True, slots=True)
class Batch:
    """One camera's detections for one frame: a SPEC §7 batch line plus its scene."""

    scene: str
    camera: str
    #: The camera's frame id; ``None`` when the batch carries a capture time instead.
    frame_id: int | None
    detections: tuple[Detection, ...]
    #: When the camera captured the frame, in seconds since the Unix epoch (``None``: the
    #: frame id says which frame it is). The scene must declare its frame rate.
    timestamp: float | None = None

    def to_json(self) -> dict[str, Any]:
        """The SPEC §7 batch line (without the scene, which is in the URL)."""
        line: dict[str, Any] = {"camera": self.camera}
        if self.frame_id is not None:
            line["frame_id"] = self.frame_id
        if self.timestamp is not None:
            line["time"] = self.timestamp
        line["detections"] = [d.to_json() for d in self.detections]
        return line


@dataclass(frozen=True, slots=True)
class Member:
    """One box of an identity: its camera, the camera's index in the scene, the box's index."""

    camera: str
    camera_index: int
    index: int


@dataclass(frozen=True, slots=True)
class Identity:
    """One person in one frame: at most one box per camera.

    ``id`` is dense within the frame; ``track_id`` follows the person across frames (None on
    unary ``associate`` results and with the server's ``--no-tracking``).
    """

    id: int
    confidence: float
    members: tuple[Member, ...]
    track_id: int | None = None


class ResultStatus(str, enum.Enum):
    """What became of a frame."""

    ASSOCIATED = "associated"
    NO_MODEL = "no_model"
    FAILED = "failed"
    SHED = "shed"  # dropped whole under overload (serve --max-queue-delay); ``error`` says why
    UNSPECIFIED = "unspecified"


@dataclass(frozen=True, slots=True)
class FrameResult:
    """The association of one frame, as published to subscribers (or answered by associate)."""

    scene: str
    frame_id: int
    complete: bool
    missing_cameras: tuple[str, ...]
    identities: tuple[Identity, ...]
    latency_ms: float
    status: ResultStatus
    model_version: str | None = None
    error: str | None = None
    error_kind: str | None = None
    #: Cameras left out of association because they no longer fit the model (they moved).
    fenced_cameras: tuple[str, ...] = ()
    #: The frame's tick time (UTC), for a scene fed capture times; ``None`` otherwise.
    time: datetime | None = None


@dataclass(frozen=True, slots=True)
class Camera:
    """One camera of a scene; ``offset`` is its declared clock offset in frame ids."""

    name: str
    width: int
    height: int
    offset: int = 0


@dataclass(frozen=True, slots=True)
class Scene:
    """A served scene as the server describes it."""

    name: str
    cameras: tuple[Camera, ...]
    threshold: float
    alpha: float
    model_version: str | None
    appearance_length: int
    sync_timeout_ms: int
    clock: Mapping[str, Any] | None = field(default=None, compare=False)
    #: Whether each camera still fits the model (``docs/camera-fit.md``): ``as_of_frame``,
    #: ``frames`` and per camera ``score`` and ``state``; ``None`` while unknown.
    fit: Mapping[str, Any] | None = field(default=None, compare=False)
    #: Healing (``serve --auto-retrain``, ``docs/camera-fit.md``): ``state`` (idle, waiting,
    #: training, gating), ``cameras``, ``attempts``, ``swapped`` and the last retrain's
    #: ``last_outcome``, ``last_reason``, ``last_model``; ``None`` when healing is off.
    retrain: Mapping[str, Any] | None = field(default=None, compare=False)


@dataclass(frozen=True, slots=True)
class PushAck:
    """The server's answer to one pushed batch; ``error`` is set when it was refused."""

    scene: str
    camera: str
    #: The frame id the batch was placed at (a timestamped batch's tick); ``None`` when a
    #: timestamped batch was refused.
    frame_id: int | None
    error: Exception | None = None

    @property
    def accepted(self) -> bool:
        """True when the server accepted the batch."""
        return self.error is None


@dataclass(frozen=True, slots=True)
class ReloadOutcome:
    """What a reload did to one scene's model file (swapped, unchanged, missing, refused)."""

    scene: str
    outcome: str
    version: str | None
    error: str | None

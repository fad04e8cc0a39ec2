"""Conversions between the typed values (types.py) and the two wire formats: protobuf messages
(the generated stubs in _pb/) and the HTTP JSON bodies."""

from __future__ import annotations

from collections.abc import Mapping
from datetime import datetime, timezone
from typing import Any

from google.protobuf.timestamp_pb2 import Timestamp

from ._pb import crossview_pb2 as pb
from .errors import GRPC_CODE_NAMES, Overloaded, ServerError, error_from_grpc
from .types import (
    Batch,
    Camera,
    Detection,
    FrameResult,
    Identity,
    Member,
    PushAck,
    ReloadOutcome,
    ResultStatus,
    Scene,
)

_STATUS_FROM_PB = {
    pb.RESULT_STATUS_ASSOCIATED: ResultStatus.ASSOCIATED,
    pb.RESULT_STATUS_NO_MODEL: ResultStatus.NO_MODEL,
    pb.RESULT_STATUS_FAILED: ResultStatus.FAILED,
    pb.RESULT_STATUS_SHED: ResultStatus.SHED,
}


def detection_to_pb(d: Detection) -> pb.Detection:
    """One detection as its protobuf message."""
    msg = pb.Detection(bbox=pb.BoundingBox(x1=d.x1, y1=d.y1, x2=d.x2, y2=d.y2))
    if d.score is not None:
        msg.score = d.score
    if d.appearance is not None:
        msg.appearance.extend(d.appearance)
    return msg


def batch_to_pb(b: Batch) -> pb.Batch:
    """One batch as its protobuf message."""
    msg = pb.Batch(
        scene=b.scene,
        camera=b.camera,
        frame_id=b.frame_id or 0,
        detections=[detection_to_pb(d) for d in b.detections],
    )
    if b.timestamp is not None:
        msg.time.CopyFrom(timestamp_to_pb(b.timestamp))
    return msg


def timestamp_to_pb(seconds: float) -> Timestamp:
    """Seconds since the Unix epoch as a protobuf Timestamp (nanoseconds kept to ~0.2 µs)."""
    whole = int(seconds // 1)
    nanos = round((seconds - whole) * 1e9)
    if nanos >= 1_000_000_000:
        whole, nanos = whole + 1, nanos - 1_000_000_000
    return Timestamp(seconds=whole, nanos=nanos)


def time_from_json(value: object) -> datetime | None:
    """A result's RFC 3339 ``time`` (nanoseconds: cut to microseconds) as an aware datetime."""
    if not isinstance(value, str) or not value:
        return None
    text = value.replace("Z", "+00:00")
    head, dot, rest = text.partition(".")
    if dot:
        digits = rest[: len(rest) - len(rest.lstrip("0123456789"))]
        text = f"{head}.{digits[:6].ljust(6, '0')}{rest[len(digits):]}"
    return datetime.fromisoformat(text)


def ack_from_pb(a: pb.BatchAck) -> PushAck:
    """A protobuf ack, its refusal (if any) as the exception the server's code maps to."""
    error = None
    if a.code != 0:
        error = error_from_grpc(GRPC_CODE_NAMES.get(a.code, "UNKNOWN"), a.message, a.kind)
        if isinstance(error, Overloaded) and a.retry_after_ms:
            error.retry_after = a.retry_after_ms / 1000.0
    return PushAck(scene=a.scene, camera=a.camera, frame_id=a.frame_id, error=error)


def result_from_pb(r: pb.FrameResult) -> FrameResult:
    """A protobuf frame result."""
    return FrameResult(
        scene=r.scene,
        frame_id=r.frame_id,
        complete=r.complete,
        missing_cameras=tuple(r.missing_cameras),
        fenced_cameras=tuple(r.fenced_cameras),
        identities=tuple(
            Identity(
                id=i.id,
                confidence=i.confidence,
                members=tuple(Member(m.camera, m.camera_index, m.index) for m in i.members),
                track_id=i.track_id if i.HasField("track_id") else None,
            )
            for i in r.identities
        ),
        latency_ms=r.latency_ms,
        status=_STATUS_FROM_PB.get(r.status, ResultStatus.UNSPECIFIED),
        time=r.time.ToDatetime(tzinfo=timezone.utc) if r.HasField("time") else None,
        model_version=r.model_version or None,
        error=r.error or None,
        error_kind=r.error_kind or None,
    )


def scene_from_pb(s: pb.Scene) -> Scene:
    """A protobuf scene description."""
    clock: dict[str, Any] | None = None
    if s.HasField("clock"):
        clock = {
            "frames": s.clock.frames,
            "as_of_frame": s.clock.as_of_frame,
            "step": s.clock.step,
            "reference": s.clock.reference,
            "cameras": [
                {
                    "camera": c.camera,
                    "known": c.known,
                    "offset_frames": c.offset_frames,
                    "offset_ids": c.offset_ids,
                    "confidence": c.confidence,
                }
                for c in s.clock.cameras
            ],
        }
    fit: dict[str, Any] | None = None
    if s.HasField("fit"):
        fit = {
            "frames": s.fit.frames,
            "as_of_frame": s.fit.as_of_frame,
            "cameras": [
                {
                    "camera": c.camera,
                    "score": c.score if c.known else None,
                    "state": c.state,
                }
                for c in s.fit.cameras
            ],
        }
    retrain: dict[str, Any] | None = None
    if s.HasField("retrain"):
        r = s.retrain
        retrain = {
            "state": r.state,
            "cameras": list(r.cameras),
            "attempts": r.attempts,
            "swapped": r.swapped,
            "last_outcome": r.last_outcome or None,
            "last_reason": r.last_reason or None,
            "last_model": r.last_model or None,
        }
    return Scene(
        name=s.name,
        cameras=tuple(Camera(c.name, c.width, c.height, c.offset) for c in s.cameras),
        threshold=s.threshold,
        alpha=s.alpha,
        model_version=s.model_version or None,
        appearance_length=s.appearance_length,
        sync_timeout_ms=s.sync_timeout_ms,
        clock=clock,
        fit=fit,
        retrain=retrain,
    )


def reload_from_pb(r: pb.ReloadResponse) -> list[ReloadOutcome]:
    """A protobuf reload answer."""
    return [
        ReloadOutcome(o.scene, o.outcome, o.version or None, o.error or None) for o in r.reloads
    ]


def _expect(obj: object, what: str) -> Mapping[str, Any]:
    if not isinstance(obj, Mapping):
        raise ServerError(f"unexpected answer: {what} is not a JSON object")
    return obj


def result_from_json(obj: object) -> FrameResult:
    """A frame result from its JSON object (HTTP answer or SSE event data)."""
    r = _expect(obj, "frame result")
    try:
        status = ResultStatus(r.get("status") or "unspecified")
    except ValueError:
        status = ResultStatus.UNSPECIFIED
    return FrameResult(
        scene=str(r["scene"]),
        frame_id=int(r["frame_id"]),
        complete=bool(r["complete"]),
        missing_cameras=tuple(str(c) for c in r.get("missing_cameras") or ()),
        fenced_cameras=tuple(str(c) for c in r.get("fenced_cameras") or ()),
        identities=tuple(
            Identity(
                id=int(i["id"]),
                confidence=float(i["confidence"]),
                members=tuple(
                    Member(str(m["camera"]), int(m["camera_index"]), int(m["index"]))
                    for m in i.get("members") or ()
                ),
                track_id=int(i["track_id"]) if i.get("track_id") is not None else None,
            )
            for i in r.get("identities") or ()
        ),
        latency_ms=float(r.get("latency_ms") or 0.0),
        status=status,
        time=time_from_json(r.get("time")),
        model_version=r.get("model_version") or None,
        error=r.get("error") or None,
        error_kind=r.get("error_kind") or None,
    )


def scene_from_json(obj: object) -> Scene:
    """A scene description from its JSON object."""
    s = _expect(obj, "scene")
    clock = s.get("clock")
    fit = s.get("fit")
    retrain = s.get("retrain")
    return Scene(
        name=str(s["name"]),
        cameras=tuple(
            Camera(str(c["name"]), int(c["width"]), int(c["height"]), int(c.get("offset") or 0))
            for c in s.get("cameras") or ()
        ),
        threshold=float(s.get("threshold") or 0.0),
        alpha=float(s.get("alpha") or 0.0),
        model_version=s.get("model_version") or None,
        appearance_length=int(s.get("appearance_length") or 0),
        sync_timeout_ms=int(s.get("sync_timeout_ms") or 0),
        clock=clock if isinstance(clock, Mapping) else None,
        fit=fit if isinstance(fit, Mapping) else None,
        retrain=retrain if isinstance(retrain, Mapping) else None,
    )


def reload_from_json(obj: object) -> list[ReloadOutcome]:
    """A reload answer from its JSON object."""
    body = _expect(obj, "reload answer")
    return [
        ReloadOutcome(
            str(o["scene"]), str(o["outcome"]), o.get("version") or None, o.get("error") or None
        )
        for o in body.get("reloads") or ()
    ]

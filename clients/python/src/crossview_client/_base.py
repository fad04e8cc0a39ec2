"""What every client does the same way, whatever its transport: turning user input into
batches, raising on refused pushes, replaying recordings."""

from __future__ import annotations

import asyncio
import math
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Mapping, Sequence
from datetime import datetime
from typing import Any, Union

import numpy.typing as npt

from .recording import ReplaySummary, open_recording
from .types import Batch, Boxes, FrameResult, PushAck, ReloadOutcome, Scene, to_detections

#: A capture time: an aware ``datetime`` or seconds since the Unix epoch.
Timestamp = Union[datetime, float, int]


def to_seconds(timestamp: Timestamp) -> float:
    """A capture time as seconds since the Unix epoch; a naive datetime is refused (its zone
    would be a guess)."""
    if isinstance(timestamp, datetime):
        if timestamp.tzinfo is None:
            raise ValueError("timestamp must be timezone-aware (e.g. datetime.now(timezone.utc))")
        return timestamp.timestamp()
    seconds = float(timestamp)
    if not math.isfinite(seconds) or seconds < 0:
        raise ValueError(f"timestamp must be seconds since the Unix epoch, got {timestamp!r}")
    return seconds


def make_batch(
    scene: str,
    camera: str,
    frame_id: int | None,
    boxes: Boxes,
    appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
    timestamp: Timestamp | None = None,
) -> Batch:
    """One batch from a camera's boxes in any accepted form (see ``types.Boxes``), stamped
    with a frame id, a capture time or both."""
    if frame_id is None and timestamp is None:
        raise ValueError("a batch needs a frame_id or a timestamp")
    if frame_id is not None and frame_id < 0:
        raise ValueError("frame_id must be >= 0")
    seconds = None if timestamp is None else to_seconds(timestamp)
    dets = tuple(to_detections(boxes, appearance))
    return Batch(scene, camera, None if frame_id is None else int(frame_id), dets, seconds)


def push_args(
    frame_id: Any, boxes: Boxes | None, timestamp: Timestamp | None
) -> tuple[int | None, Boxes]:
    """``push(scene, camera, frame_id, boxes)`` or, with capture times,
    ``push(scene, camera, boxes, timestamp=t)``: the frame id (if any) and the boxes."""
    if boxes is None:
        if timestamp is None:
            raise TypeError("push() needs boxes: push(scene, camera, frame_id, boxes)")
        return None, frame_id
    return frame_id, boxes


def frame_batches(scene: str, frame_id: int, views: Mapping[str, Boxes]) -> list[Batch]:
    """One batch per camera of a frame, ``views`` mapping camera name → boxes."""
    return [make_batch(scene, cam, frame_id, boxes) for cam, boxes in views.items()]


def summarize(summary: ReplaySummary, acks: Iterable[PushAck]) -> None:
    """Adds acks to a replay summary."""
    for ack in acks:
        if ack.error is None:
            summary.accepted += 1
        else:
            kind = getattr(ack.error, "kind", type(ack.error).__name__)
            summary.rejected[kind] = summary.rejected.get(kind, 0) + 1


def count_frames(batches: Iterable[Batch], summary: ReplaySummary) -> Iterator[Batch]:
    """The batches, counting their frames (consecutive frame ids) in ``summary``."""
    last: int | None = None
    for b in batches:
        if b.frame_id != last:
            last = b.frame_id
            summary.frames += 1
        yield b


def by_frame(batches: Iterable[Batch]) -> Iterator[list[Batch]]:
    """Consecutive batches grouped by frame id."""
    frame: list[Batch] = []
    for b in batches:
        if frame and b.frame_id != frame[-1].frame_id:
            yield frame
            frame = []
        frame.append(b)
    if frame:
        yield frame


class SyncClient(ABC):
    """The synchronous API, implemented by ``GrpcClient`` and ``HttpClient``."""

    @abstractmethod
    def scenes(self, *, timeout: float | None = None) -> list[Scene]:
        """Every served scene."""

    @abstractmethod
    def scene(self, name: str, *, timeout: float | None = None) -> Scene:
        """One scene; ``NotFound`` when the server has none of that name."""

    @abstractmethod
    def reload(self, *, timeout: float | None = None) -> list[ReloadOutcome]:
        """Re-reads every model file on the server (as SIGHUP): one outcome per scene."""

    @abstractmethod
    def push_many(self, batches: Iterable[Batch], *, timeout: float | None = None) -> list[PushAck]:
        """Pushes many batches, pipelined, in order; one ack each, refusals in ``ack.error``
        (nothing raised for them). Raises only when the transport fails."""

    @abstractmethod
    def associate(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timestamp: Timestamp | None = None,
        timeout: float | None = None,
    ) -> FrameResult:
        """Associates one already synchronized frame (``views``: camera → boxes); not
        published to subscribers and not tracked (no track ids). With ``timestamp`` (the
        frame's capture time; the scene must declare its rate) the result's ``frame_id`` is
        its tick (``frame_id`` may then be 0) and ``time`` the tick's time."""

    @abstractmethod
    def wait_ready(self, timeout: float = 30.0) -> None:
        """Waits until the server answers, at most ``timeout`` seconds (else ``Unavailable``)."""

    @abstractmethod
    def close(self) -> None:
        """Closes the connection(s)."""

    def push(
        self,
        scene: str,
        camera: str,
        frame_id: Any,
        boxes: Boxes | None = None,
        *,
        timestamp: Timestamp | None = None,
        appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
        timeout: float | None = None,
    ) -> PushAck:
        """Pushes one camera's boxes for one frame and waits for the server's ack.

        ``push(scene, camera, frame_id, boxes)``, or with the camera's capture time instead of
        a frame id, ``push(scene, camera, boxes, timestamp=t)`` (``t`` an aware ``datetime``
        or seconds since the Unix epoch; the scene must declare its frame rate, and the ack's
        ``frame_id`` is the frame the batch went to).

        ``boxes``: a list of ``{"bbox": [x1, y1, x2, y2], "score"?: s, "appearance"?: [...]}``
        dicts or ``Detection`` objects, or an N×4 / N×5 (with scores) NumPy array in pixels;
        ``appearance`` optionally one vector per box. An empty list tells the server the camera
        saw nobody. A refused batch raises its exception (``DuplicateBatch``, ``LateBatch``,
        ``InvalidArgument`` naming the field, ``NotFound``, ...). Not retried automatically.
        """
        frame_id, boxes = push_args(frame_id, boxes, timestamp)
        (ack,) = self.push_many(
            [make_batch(scene, camera, frame_id, boxes, appearance, timestamp)], timeout=timeout
        )
        if ack.error is not None:
            raise ack.error
        return ack

    def push_frame(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timeout: float | None = None,
    ) -> list[PushAck]:
        """Pushes every camera's boxes of one frame (``views``: camera → boxes), pipelined;
        returns the acks (refusals in ``ack.error``)."""
        return self.push_many(frame_batches(scene, frame_id, views), timeout=timeout)

    def stream_recording(
        self,
        path: "os.PathLike[str] | str",
        *,
        scene: str | None = None,
        fps: float | None = None,
        timeout: float | None = None,
    ) -> ReplaySummary:
        """Replays a SPEC §7 recording line by line — camera by camera, in file order — into
        ``scene`` (default: the recording header's name), at ``fps`` frames per second or as
        fast as the server acks. Refused batches are counted by kind, not raised."""
        rec = open_recording(path)
        summary = ReplaySummary()
        batches = count_frames(rec.batches(scene), summary)
        if fps:
            # Paced: frame n goes out n/fps seconds after the first, its batches acked at once.
            start = time.monotonic()
            for n, frame in enumerate(by_frame(batches)):
                time.sleep(max(0.0, start + n / fps - time.monotonic()))
                summarize(summary, self.push_many(frame, timeout=timeout))
        else:
            summarize(summary, self.push_many(batches, timeout=timeout))
        summary.torn_lines = rec.torn_lines
        return summary

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class AsyncClient(ABC):
    """The asyncio API, implemented by ``AsyncGrpcClient`` and ``AsyncHttpClient``: the same
    methods as :class:`SyncClient`, as coroutines."""

    @abstractmethod
    async def push_many(
        self, batches: Iterable[Batch], *, timeout: float | None = None
    ) -> list[PushAck]:
        """Pushes many batches, pipelined, in order; one ack each (see SyncClient.push_many)."""

    @abstractmethod
    async def close(self) -> None:
        """Closes the connection(s)."""

    async def push(
        self,
        scene: str,
        camera: str,
        frame_id: Any,
        boxes: Boxes | None = None,
        *,
        timestamp: Timestamp | None = None,
        appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
        timeout: float | None = None,
    ) -> PushAck:
        """Pushes one camera's boxes for one frame (or, with ``timestamp=``, its capture
        time); a refused batch raises (see SyncClient.push)."""
        frame_id, boxes = push_args(frame_id, boxes, timestamp)
        (ack,) = await self.push_many(
            [make_batch(scene, camera, frame_id, boxes, appearance, timestamp)], timeout=timeout
        )
        if ack.error is not None:
            raise ack.error
        return ack

    async def push_frame(
        self,
        scene: str,
        frame_id: int,
        views: Mapping[str, Boxes],
        *,
        timeout: float | None = None,
    ) -> list[PushAck]:
        """Pushes every camera's boxes of one frame, pipelined; returns the acks."""
        return await self.push_many(frame_batches(scene, frame_id, views), timeout=timeout)

    async def stream_recording(
        self,
        path: "os.PathLike[str] | str",
        *,
        scene: str | None = None,
        fps: float | None = None,
        timeout: float | None = None,
    ) -> ReplaySummary:
        """Replays a SPEC §7 recording camera by camera (see SyncClient.stream_recording), one
        frame's batches at a time, so memory stays bounded whatever the recording's length."""
        rec = open_recording(path)
        summary = ReplaySummary()
        loop = asyncio.get_running_loop()
        start = loop.time()
        for n, frame in enumerate(by_frame(count_frames(rec.batches(scene), summary))):
            if fps:
                await asyncio.sleep(max(0.0, start + n / fps - loop.time()))
            summarize(summary, await self.push_many(frame, timeout=timeout))
        summary.torn_lines = rec.torn_lines
        return summary

    async def __aenter__(self) -> Any:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

"""What every client does the same way, whatever its transport: turning user input into
batches, raising on refused pushes, replaying recordings."""

from __future__ import annotations

import asyncio
import os
import time
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy.typing as npt

from .recording import ReplaySummary, open_recording
from .types import Batch, Boxes, FrameResult, PushAck, ReloadOutcome, Scene, to_detections

def make_batch(
    scene: str,
    camera: str,
    frame_id: int,
    boxes: Boxes,
    appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
) -> Batch:
    """One batch from a camera's boxes in any accepted form (see ``types.Boxes``)."""
    if frame_id < 0:
        raise ValueError("frame_id must be >= 0")
    return Batch(scene, camera, int(frame_id), tuple(to_detections(boxes, appearance)))


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
        self, scene: str, frame_id: int, views: Mapping[str, Boxes], *, timeout: float | None = None
    ) -> FrameResult:
        """Associates one already synchronized frame (``views``: camera → boxes); not
        published to subscribers and not tracked (no track ids)."""

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
        frame_id: int,
        boxes: Boxes,
        *,
        appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
        timeout: float | None = None,
    ) -> PushAck:
        """Pushes one camera's boxes for one frame and waits for the server's ack.

        ``boxes``: a list of ``{"bbox": [x1, y1, x2, y2], "score"?: s, "appearance"?: [...]}``
        dicts or ``Detection`` objects, or an N×4 / N×5 (with scores) NumPy array in pixels;
        ``appearance`` optionally one vector per box. An empty list tells the server the camera
        saw nobody. A refused batch raises its exception (``DuplicateBatch``, ``LateBatch``,
        ``InvalidArgument`` naming the field, ``NotFound``, ...). Not retried automatically.
        """
        (ack,) = self.push_many(
            [make_batch(scene, camera, frame_id, boxes, appearance)], timeout=timeout
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
        frame_id: int,
        boxes: Boxes,
        *,
        appearance: npt.ArrayLike | Sequence[Sequence[float]] | None = None,
        timeout: float | None = None,
    ) -> PushAck:
        """Pushes one camera's boxes for one frame; a refused batch raises (see SyncClient.push)."""
        (ack,) = await self.push_many(
            [make_batch(scene, camera, frame_id, boxes, appearance)], timeout=timeout
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

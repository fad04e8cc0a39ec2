"""Reading SPEC §7 recordings (JSON Lines: a scene header, then one camera batch per line)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

from ._convert import time_from_json
from .types import Batch, Camera, to_detections

__all__ = ["Recording", "open_recording", "ReplaySummary"]


@dataclass
class Recording:
    """An open recording: its scene header and an iterator over its batch lines, in file order.

    ``torn_lines`` counts a last line cut short by a crash (no newline and not complete JSON),
    which is dropped as the server's own readers drop it; any other broken line raises
    ``ValueError`` naming the file and line.
    """

    path: str
    scene: str
    cameras: tuple[Camera, ...]
    _lines: Iterator[tuple[int, str, bool]] = field(repr=False)
    torn_lines: int = 0
    #: The frame rate the header declares (``"fps"``, frames per second), ``None`` if none:
    #: e.g. ``client.stream_recording(path, fps=rec.fps)`` replays it at its own pace.
    fps: float | None = None

    def batches(self, scene: str | None = None) -> Iterator[Batch]:
        """The batch lines as :class:`Batch` values for ``scene`` (default: the header's)."""
        target = scene or self.scene
        for lineno, line, ended in self._lines:
            if not line.strip():
                continue
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as e:
                if not ended:
                    self.torn_lines += 1
                    return
                raise ValueError(f"{self.path}:{lineno}: not JSON: {e}") from e
            try:
                frame_id, stamp = obj.get("frame_id"), obj.get("time")
                if frame_id is None and stamp is None:
                    raise KeyError("frame_id")
                yield Batch(
                    scene=target,
                    camera=str(obj["camera"]),
                    frame_id=None if frame_id is None else int(frame_id),
                    detections=tuple(to_detections(obj.get("detections") or [])),
                    timestamp=None if stamp is None else _seconds(stamp),
                )
            except (KeyError, TypeError, ValueError) as e:
                raise ValueError(f"{self.path}:{lineno}: not a batch line: {e!r}") from e


def _seconds(stamp: object) -> float:
    """A line's ``time`` (seconds since the Unix epoch, or RFC 3339) as seconds."""
    if isinstance(stamp, (int, float)) and not isinstance(stamp, bool):
        return float(stamp)
    parsed = time_from_json(stamp)
    if parsed is None:
        raise ValueError(f"time {stamp!r} is neither seconds nor an RFC 3339 date-time")
    return parsed.timestamp()


def _lines(f: "os.PathLike[str] | str") -> Iterator[tuple[int, str, bool]]:
    with open(f, encoding="utf-8") as fh:
        for n, line in enumerate(fh, start=1):
            yield n, line, line.endswith("\n")


def open_recording(path: "os.PathLike[str] | str") -> Recording:
    """Opens a SPEC §7 recording and reads its header line ``{"scene": {...}}`` (with its
    optional ``"fps"``)."""
    lines = _lines(path)
    try:
        _, first, _ = next(lines)
    except StopIteration:
        raise ValueError(f"{path}: empty recording (no scene header)") from None
    try:
        top = json.loads(first)
        header = top["scene"]
        cameras = tuple(
            Camera(str(c["name"]), int(c["width"]), int(c["height"])) for c in header["cameras"]
        )
        name = str(header["name"])
        fps = top.get("fps")
        if fps is not None and not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
            raise ValueError(f"fps must be a frame rate in (0, 1000], got {fps!r}")
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{path}:1: not a scene header: {e!r}") from e
    return Recording(
        path=os.fspath(path),
        scene=name,
        cameras=cameras,
        _lines=lines,
        fps=None if fps is None else float(fps),
    )


@dataclass
class ReplaySummary:
    """What a replay pushed: batches accepted, refusals by error kind, torn lines dropped."""

    accepted: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    torn_lines: int = 0
    frames: int = 0

    @property
    def rejected_total(self) -> int:
        """All refused batches."""
        return sum(self.rejected.values())

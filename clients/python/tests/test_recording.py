"""Reading recordings without a server: the header's declared frame rate, torn last lines."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from crossview_client import open_recording

SCENE = {"name": "lab", "cameras": [{"name": "a", "width": 640, "height": 480}]}
BATCH = {"camera": "a", "frame_id": 0, "detections": [{"bbox": [1, 2, 30, 80]}]}


def write(path: Path, header: dict[str, object], tail: str = "") -> Path:
    path.write_text(json.dumps(header) + "\n" + json.dumps(BATCH) + "\n" + tail)
    return path


def test_the_declared_frame_rate_is_read(tmp_path: Path) -> None:
    rec = open_recording(write(tmp_path / "r.jsonl", {"scene": SCENE, "fps": 10}))
    assert rec.fps == 10.0
    assert [b.frame_id for b in rec.batches()] == [0]
    assert open_recording(write(tmp_path / "n.jsonl", {"scene": SCENE})).fps is None


@pytest.mark.parametrize("bad", [0, -2, 1e9, "ten", [10]])
def test_a_rate_that_is_no_frame_rate_is_refused_on_line_one(tmp_path: Path, bad: object) -> None:
    with pytest.raises(ValueError, match=":1: not a scene header"):
        open_recording(write(tmp_path / "b.jsonl", {"scene": SCENE, "fps": bad}))


def test_a_torn_last_line_is_dropped_and_counted(tmp_path: Path) -> None:
    rec = open_recording(write(tmp_path / "t.jsonl", {"scene": SCENE}, tail='{"camera": "a", "fr'))
    assert len(list(rec.batches())) == 1
    assert rec.torn_lines == 1

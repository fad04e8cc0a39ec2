"""Capture times instead of frame ids, over gRPC and HTTP alike: ``push(scene, camera, boxes,
timestamp=t)`` with an aware ``datetime`` or Unix seconds, cameras with their own jitter; the
ack names the frame the batch went to, and results carry their tick time."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import datetime, timedelta, timezone

import pytest
from conftest import DEMO_CAMERAS, DEMO_TIMED_SCENE, Server, person_boxes, start_server

import crossview_client as cv

#: 2026-12-06T00:00:00Z; the scene runs at 10 frames/s: tick k is k / 10 s after the epoch.
T0 = datetime(2026, 12, 6, tzinfo=timezone.utc)
TICK0 = 17_965_152_000


@pytest.fixture(scope="module")
def timed_server() -> Iterator[Server]:
    s = start_server("--sync-timeout", "60s", "--scene", DEMO_TIMED_SCENE)
    yield s
    s.stop()


@pytest.mark.parametrize("transport,first", [("grpc", 0), ("http", 20)])
def test_timestamped_pushes_group_by_capture_time(
    timed_server: Server, transport: str, first: int
) -> None:
    client = cv.connect(timed_server.addr, transport, timeout=20.0)
    client.wait_ready(30)
    try:
        with client.subscribe("demo") as sub:
            for k in range(first, first + 3):
                for c, cam in enumerate(DEMO_CAMERAS):
                    # Each camera ±30 ms off the frame's time; half as aware datetimes, half as
                    # Unix seconds.
                    t = T0 + timedelta(seconds=k / 10, milliseconds=(-30, 10, 25, -5)[c])
                    stamp = t if c % 2 == 0 else t.timestamp()
                    ack = client.push("demo", cam, person_boxes(2), timestamp=stamp)
                    assert ack.accepted and ack.frame_id == TICK0 + k, ack
            for k in range(first, first + 3):
                r = next(iter(sub))
                assert (r.frame_id, r.complete) == (TICK0 + k, True), r
                assert r.time == T0 + timedelta(seconds=k / 10), r.time
        # Unary: the frame's tick and its time.
        views = {cam: person_boxes(2) for cam in DEMO_CAMERAS}
        r = client.associate("demo", 0, views, timestamp=T0 + timedelta(seconds=first / 10 + 0.02))
        assert (r.frame_id, r.time) == (TICK0 + first, T0 + timedelta(seconds=first / 10)), r
        # A naive datetime is refused before anything is sent (its zone would be a guess).
        with pytest.raises(ValueError):
            client.push("demo", "cam0", [], timestamp=datetime(2026, 12, 6))
        with pytest.raises(ValueError):
            client.push("demo", "cam0", [], timestamp=float("nan"))
    finally:
        client.close()


def test_a_scene_without_a_rate_refuses_times(server: Server) -> None:
    # The shared server's scene declares no rate (and other tests feed it frame ids).
    with cv.connect(server.addr, "http", timeout=20.0) as client:
        with pytest.raises(cv.InvalidArgument) as e:
            client.push("demo", "cam0", [], timestamp=T0)
        assert "frame rate" in str(e.value) or "fed frame ids" in str(e.value), e.value

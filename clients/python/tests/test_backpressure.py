"""A slow subscriber: what the server does to it and how the client says so.

The subscriber stops reading while 1500 frames are published. The results fill the
transport's buffers, then the server's ring: with a small ``--subscriber-buffer`` the server
drops the subscriber (``RESOURCE_EXHAUSTED`` / an SSE ``error`` event) and the iterator raises
``SubscriberLagged`` once the results that did reach it are read; with a short
``--subscriber-stall-timeout`` the server closes the connection and the iterator raises
``Unavailable`` saying a stall is one cause (with ``reconnect=False``; otherwise it would
resubscribe). Nothing here measures time."""

from __future__ import annotations

import socket
import threading
import time
from typing import Any

import httpx
import pytest
from conftest import DEMO_CAMERAS, Server, start_server

import crossview_client as cv

FRAMES = 1500
# 36 boxes per camera: results of about 8.9 kB, 13 MB for the flood, which the socket buffers
# (up to 4 MB for the server's send buffer on Linux) cannot absorb, so the server's ring always
# overflows. With 12 boxes (about 4.4 MB) they sometimes did, nothing was dropped, and the
# HTTP case waited out its bound (seen once in a CI run).
BOXES = [
    [100.0 + 60 * (i % 18), 80.0 + 300 * (i // 18), 140.0 + 60 * (i % 18), 360.0 + 300 * (i // 18), 0.9]
    for i in range(36)
]


def flood(server: Server) -> int:
    """Pushes FRAMES complete frames as fast as the server takes them; returns those accepted."""
    with cv.HttpClient(server.addr, timeout=60.0) as pusher:
        dets = tuple(cv.types.to_detections(BOXES))
        acks = pusher.push_many(cv.Batch("demo", c, f, dets) for f in range(FRAMES) for c in DEMO_CAMERAS)
    return sum(a.accepted for a in acks)


def slow_reader(transport: str) -> dict[str, Any]:
    """Client options that keep the client's receive buffers small, so a subscriber that does
    not read blocks the server after a few dozen results whatever the machine's speed
    (grpcio's flow-control window otherwise grows to hold them all, and so do loopback
    socket buffers)."""
    if transport == "grpc":
        return {"channel_options": [("grpc.http2.bdp_probe", 0)]}
    opts = [(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)]
    return {"http_transport": httpx.HTTPTransport(socket_options=opts)}


def drain(sub: cv.Subscription, timeout: float = 60.0) -> tuple[int, BaseException | None]:
    """Reads the subscription to its end (at most ``timeout`` s): results read, error raised."""
    out: list[tuple[int, BaseException | None]] = []

    def run() -> None:
        n = 0
        try:
            for _ in sub:
                n += 1
        except cv.CrossviewError as e:
            out.append((n, e))
            return
        out.append((n, None))

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout)
    if not out:
        sub.close()
        raise AssertionError(f"the subscription neither ended nor failed within {timeout} s")
    return out[0]


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_a_lagging_subscriber_is_dropped_and_told(transport: str) -> None:
    server = start_server("--subscriber-buffer", "16", "--subscriber-stall-timeout", "120s")
    try:
        with cv.connect(server.addr, transport, timeout=20.0, **slow_reader(transport)) as client:  # type: ignore[arg-type]
            sub = client.subscribe("demo", reconnect=False)
            assert flood(server) > 100
            n, err = drain(sub)
            assert isinstance(err, cv.SubscriberLagged), (n, err)
            assert isinstance(err, cv.ResourceExhausted) and "behind" in err.message
            # The SSE error event's data is the JSON error body; the message is read out of it.
            assert not err.message.lstrip().startswith("{"), err.message
            assert n < FRAMES
    finally:
        server.stop()


# gRPC only: over HTTP/1.1 the results the server had written before it closed the stalled
# connection still sit in the loopback socket buffers (megabytes), so reading them to the
# end through a small receive buffer takes a minute; the SSE side of back-pressure is
# covered by the lagging test above.
@pytest.mark.parametrize("transport", ["grpc"])
def test_a_stalled_subscriber_is_disconnected_and_told(transport: str) -> None:
    server = start_server("--subscriber-buffer", "100000", "--subscriber-stall-timeout", "1s")
    try:
        with cv.connect(server.addr, transport, timeout=20.0, **slow_reader(transport)) as client:  # type: ignore[arg-type]
            sub = client.subscribe("demo", reconnect=False)
            assert flood(server) > 100
            # Wait (bounded) until the server has given up on the subscriber.
            deadline = time.monotonic() + 60
            while server.metric('crossview_errors_total{kind="subscriber_stalled"}') < 1:
                assert time.monotonic() < deadline, "the server never dropped the stalled subscriber"
                time.sleep(0.2)
            n, err = drain(sub)
            assert isinstance(err, cv.Unavailable), (n, err)
            assert "stall" in err.message
            assert n < FRAMES
    finally:
        server.stop()

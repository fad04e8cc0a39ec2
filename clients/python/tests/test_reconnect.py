"""A server restart on the same port: the subscription resubscribes by itself (reconnect=True)
or raises Unavailable (reconnect=False); the next push reconnects, waiting for the server."""

from __future__ import annotations

import queue
import threading
import time

import pytest
from conftest import DEMO_CAMERAS, person_boxes, start_server

import crossview_client as cv


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_client_survives_a_server_restart(transport: str) -> None:
    server = start_server("--sync-timeout", "60s")
    try:
        with cv.connect(server.addr, transport, timeout=20.0) as client:  # type: ignore[arg-type]
            sub = client.subscribe("demo", reconnect=True, reconnect_timeout=60)
            results: queue.Queue[cv.FrameResult | BaseException] = queue.Queue()

            def consume() -> None:
                try:
                    for r in sub:
                        results.put(r)
                except BaseException as e:  # handed to the test thread
                    results.put(e)

            threading.Thread(target=consume, daemon=True).start()
            client.push_frame("demo", 1, {c: person_boxes(2) for c in DEMO_CAMERAS})
            first = results.get(timeout=30)
            assert isinstance(first, cv.FrameResult) and first.frame_id == 1

            server.restart()  # SIGTERM, then the same port again
            deadline = time.monotonic() + 60
            while sub.reconnects < 1:  # the iterator resubscribes by itself
                assert time.monotonic() < deadline, "the subscription never came back"
                time.sleep(0.05)
            # The next push reconnects too (a fresh server: frame ids may start anew).
            acks = client.push_frame("demo", 1, {c: person_boxes(2) for c in DEMO_CAMERAS})
            assert all(a.accepted for a in acks), acks
            second = results.get(timeout=30)
            assert isinstance(second, cv.FrameResult) and second.frame_id == 1 and second.complete
            sub.close()
    finally:
        server.stop()


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_without_reconnect_a_restart_raises_unavailable(transport: str) -> None:
    server = start_server()
    try:
        with cv.connect(server.addr, transport, timeout=20.0) as client:  # type: ignore[arg-type]
            sub = client.subscribe("demo", reconnect=False)
            server.stop()
            with pytest.raises(cv.Unavailable):
                next(sub)
            # With the server gone, calls fail within their timeout, as Unavailable.
            with pytest.raises(cv.Unavailable):
                client.push("demo", "cam0", 1, [], timeout=1.0)
    finally:
        server.stop()

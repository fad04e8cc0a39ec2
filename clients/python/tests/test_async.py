"""The asyncio clients (gRPC on grpc.aio, HTTP on httpx.AsyncClient) against the real server:
the same calls and the same exceptions as the synchronous ones."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from conftest import DEMO_CAMERAS, Server, person_boxes

import crossview_client as cv


@pytest.mark.parametrize("transport", ["grpc", "http"])
def test_async_client_pushes_subscribes_and_maps_errors(
    transport: str, server: Server, frame_id: int
) -> None:
    async def main() -> None:
        async with cv.connect_async(server.addr, transport, timeout=20.0) as client:  # type: ignore[arg-type]
            await client.wait_ready(30)
            (scene,) = await client.scenes()
            assert scene.name == "demo" and (await client.scene("demo")).name == "demo"
            sub = await client.subscribe("demo")
            await client.push("demo", "cam0", frame_id, np.array(person_boxes(3)))
            with pytest.raises(cv.DuplicateBatch):
                await client.push("demo", "cam0", frame_id, [])
            # Concurrent pushes of the other cameras, on one connection.
            acks = await asyncio.gather(*(
                client.push("demo", c, frame_id, [{"bbox": b[:4]} for b in person_boxes(3)])
                for c in DEMO_CAMERAS[1:]
            ))
            assert all(a.accepted for a in acks)
            async with sub:
                async for r in sub:
                    if r.frame_id == frame_id:
                        break
            assert r.complete and r.identities and all(i.track_id is not None for i in r.identities)
            with pytest.raises(cv.LateBatch):
                await client.push("demo", "cam1", frame_id, [])
            with pytest.raises(cv.NotFound):
                await client.push("nowhere", "cam0", frame_id, [])
            with pytest.raises(cv.NotFound):
                await client.subscribe("nowhere")
            with pytest.raises(cv.InvalidArgument) as e:
                await client.push("demo", "cam0", frame_id + 1, [{"bbox": [9, 9, 1, 1]}])
            assert e.value.field == "detections[0].bbox"
            u = await client.associate("demo", 3, {c: person_boxes(2) for c in DEMO_CAMERAS})
            assert u.complete and all(i.track_id is None for i in u.identities)
            (outcome,) = await client.reload()
            assert outcome.outcome == "unchanged"

    asyncio.run(asyncio.wait_for(main(), 60))

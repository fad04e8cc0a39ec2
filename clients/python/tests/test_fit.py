"""A camera that no longer fits the model, as the client reads it: the scene description's
``fit`` and a frame result's ``fenced_cameras``, the same over gRPC and HTTP JSON (the
server's own behaviour is tested end to end in tests/serve/camera_fit.rs)."""

from __future__ import annotations

from crossview_client import _convert
from crossview_client._pb import crossview_pb2 as pb

FIT_JSON = {
    "frames": 60,
    "as_of_frame": 519,
    "cameras": [
        {"camera": "cam0", "score": 1.02, "state": "fits"},
        {"camera": "cam1", "score": 0.12, "state": "does_not_fit"},
        {"camera": "cam2", "score": None, "state": "silent"},
    ],
}


def scene_json(fit: object) -> dict[str, object]:
    return {
        "name": "demo",
        "cameras": [{"name": "cam0", "width": 1280, "height": 720}],
        "threshold": 0.4,
        "alpha": 0.0,
        "sync_timeout_ms": 200,
        **({"fit": fit} if fit is not None else {}),
    }


def test_the_fit_reads_the_same_over_both_transports() -> None:
    from_json = _convert.scene_from_json(scene_json(FIT_JSON))
    scene = pb.Scene(name="demo", threshold=0.4, sync_timeout_ms=200)
    scene.cameras.add(name="cam0", width=1280, height=720)
    scene.fit.frames = 60
    scene.fit.as_of_frame = 519
    scene.fit.cameras.add(camera="cam0", known=True, score=1.02, state="fits")
    scene.fit.cameras.add(camera="cam1", known=True, score=0.12, state="does_not_fit")
    scene.fit.cameras.add(camera="cam2", known=False, state="silent")
    from_pb = _convert.scene_from_pb(scene)
    for s in (from_json, from_pb):
        assert s.fit is not None
        assert s.fit["as_of_frame"] == 519
        states = {c["camera"]: c["state"] for c in s.fit["cameras"]}
        assert states == {"cam0": "fits", "cam1": "does_not_fit", "cam2": "silent"}
        silent = next(c for c in s.fit["cameras"] if c["camera"] == "cam2")
        assert silent["score"] is None
    # No look yet: no fit, on either transport.
    assert _convert.scene_from_json(scene_json(None)).fit is None
    assert _convert.scene_from_pb(pb.Scene(name="demo")).fit is None


def test_a_fenced_camera_is_named_in_the_result() -> None:
    body = {
        "scene": "demo",
        "frame_id": 7,
        "complete": True,
        "missing_cameras": [],
        "fenced_cameras": ["cam1"],
        "identities": [],
        "latency_ms": 1.0,
        "status": "associated",
    }
    assert _convert.result_from_json(body).fenced_cameras == ("cam1",)
    r = pb.FrameResult(scene="demo", frame_id=7, complete=True, fenced_cameras=["cam1"])
    assert _convert.result_from_pb(r).fenced_cameras == ("cam1",)
    del body["fenced_cameras"]
    assert _convert.result_from_json(body).fenced_cameras == ()

"""The synchronous clients against the real server, over gRPC and HTTP alike: scenes, push
(NumPy and dict boxes, appearance vectors), subscribe, associate, reload, and the mapping of
the server's refusals onto the one exception hierarchy."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from conftest import DEMO_CAMERAS, Server, person_boxes

import crossview_client as cv
from crossview_client import errors


@pytest.fixture(params=["grpc", "http"])
def client(request: pytest.FixtureRequest, server: Server) -> Iterator[cv.SyncClient]:
    c = cv.connect(server.addr, request.param, timeout=20.0)
    c.wait_ready(30)
    yield c
    c.close()


def result_for(sub: cv.Subscription, frame_id: int) -> cv.FrameResult:
    """The subscription's result for ``frame_id`` (results of other frames are skipped)."""
    for r in sub:
        if r.frame_id == frame_id:
            return r
        assert r.frame_id < frame_id, f"frame {frame_id} never came, got {r.frame_id}"
    raise AssertionError("subscription ended")


def test_scenes_describe_the_demo_scene(client: cv.SyncClient) -> None:
    (scene,) = client.scenes()
    assert scene.name == "demo"
    assert [c.name for c in scene.cameras] == list(DEMO_CAMERAS)
    assert (scene.cameras[0].width, scene.cameras[0].height) == (1280, 720)
    assert scene.model_version is not None and scene.model_version.startswith("0.1.0@")
    assert scene.sync_timeout_ms == 60_000
    one = client.scene("demo")
    assert (one.name, one.cameras, one.model_version) == (scene.name, scene.cameras, scene.model_version)
    # float32 on the server: GET /v1/scenes widens it to 0.6000000238418579, GET
    # /v1/scenes/demo prints 0.6 (an inconsistency of the server's JSON).
    assert one.threshold == pytest.approx(scene.threshold, abs=1e-6)
    with pytest.raises(cv.NotFound) as e:
        client.scene("nowhere")
    assert e.value.kind == "unknown_scene"


def test_push_numpy_and_dict_boxes_then_subscribe(client: cv.SyncClient, frame_id: int) -> None:
    with client.subscribe("demo") as sub:
        arr = np.array(person_boxes(3))
        client.push("demo", "cam0", frame_id, arr)  # N×5: scores in the last column
        client.push("demo", "cam1", frame_id, arr[:, :4])  # N×4: no scores
        dicts = [{"bbox": b[:4], "score": b[4]} for b in person_boxes(3, shift=5)]
        client.push("demo", "cam2", frame_id, dicts)
        ack = client.push("demo", "cam3", frame_id, [])  # saw nobody: still completes the frame
        assert ack.accepted and (ack.scene, ack.camera, ack.frame_id) == ("demo", "cam3", frame_id)
        r = result_for(sub, frame_id)
    assert r.scene == "demo" and r.complete and r.missing_cameras == ()
    assert r.status is cv.ResultStatus.ASSOCIATED
    assert r.model_version is not None and r.model_version.startswith("0.1.0@")
    assert r.identities, "three people in three cameras give identities"
    for ident in r.identities:
        assert ident.track_id is not None
        assert 0.0 <= ident.confidence <= 1.0
        for m in ident.members:
            assert m.camera in DEMO_CAMERAS[:3] and m.index < 3
            assert DEMO_CAMERAS[m.camera_index] == m.camera
    boxes = sum(len(i.members) for i in r.identities)
    assert boxes == 9, "every box belongs to exactly one identity"


def test_push_frame_and_appearance_vectors(client: cv.SyncClient, frame_id: int) -> None:
    with client.subscribe("demo") as sub:
        app = np.linspace(0.0, 1.0, 3 * 4).reshape(3, 4)
        client.push("demo", "cam0", frame_id, np.array(person_boxes(3)), appearance=app)
        acks = client.push_frame(
            "demo", frame_id, {c: np.array(person_boxes(3)) for c in DEMO_CAMERAS[1:]}
        )
        assert [a.accepted for a in acks] == [True, True, True]
        r = result_for(sub, frame_id)
    assert r.complete and len(r.identities) >= 1
    assert client.scene("demo").appearance_length == 4
    with pytest.raises(cv.InvalidArgument) as e:  # every vector of a scene has one length
        client.push("demo", "cam0", frame_id + 1, [{"bbox": [1, 2, 30, 40], "appearance": [1.0]}])
    assert e.value.kind == "invalid_argument"


def test_duplicate_and_late_batches(client: cv.SyncClient, frame_id: int) -> None:
    client.push("demo", "cam0", frame_id, person_boxes(2))
    with pytest.raises(cv.DuplicateBatch) as dup:
        client.push("demo", "cam0", frame_id, [])
    assert dup.value.kind == "duplicate" and isinstance(dup.value, cv.Conflict)
    for cam in DEMO_CAMERAS[1:]:
        client.push("demo", cam, frame_id, person_boxes(2))
    # The frame is complete, so it was published: the same camera again is now late.
    with pytest.raises(cv.LateBatch) as late:
        client.push("demo", "cam0", frame_id, [])
    assert late.value.kind == "late" and isinstance(late.value, cv.Conflict)


def test_refusals_map_to_one_hierarchy(client: cv.SyncClient, frame_id: int) -> None:
    with pytest.raises(cv.NotFound) as e:
        client.push("nowhere", "cam0", frame_id, [])
    assert e.value.kind == "unknown_scene"
    with pytest.raises(cv.NotFound) as e:
        client.push("demo", "cam9", frame_id, [])
    assert e.value.kind == "unknown_camera"
    with pytest.raises(cv.InvalidArgument) as inv:
        client.push("demo", "cam0", frame_id, [{"bbox": [50, 60, 40, 70]}])  # inverted
    assert inv.value.field == "detections[0].bbox"
    with pytest.raises(cv.InvalidArgument) as inv:
        client.push("demo", "cam0", frame_id, np.array([[10, 10, 50, 90, 1.5]]))  # score > 1
    assert inv.value.field is not None and "score" in inv.value.field
    with pytest.raises(cv.InvalidArgument):
        client.push("demo", "cam0", frame_id, [{"bbox": [5000, 10, 6000, 90]}])  # outside
    with pytest.raises(cv.OutOfRange) as oor:
        client.push("demo", "cam0", frame_id + 10**9, [])
    assert oor.value.kind == "out_of_range"
    # Shapes are checked before anything is sent.
    with pytest.raises(ValueError):
        client.push("demo", "cam0", frame_id, np.zeros((2, 3)))
    # None of this changed the scene: the frame can still be pushed whole.
    acks = client.push_frame("demo", frame_id, {c: person_boxes(1) for c in DEMO_CAMERAS})
    assert all(a.accepted for a in acks)


def test_push_many_reports_each_batch(client: cv.SyncClient, frame_id: int) -> None:
    b = cv.Batch
    d = (cv.Detection(10, 20, 60, 200, 0.8),)
    acks = client.push_many([
        b("demo", "cam0", frame_id, d),
        b("demo", "cam0", frame_id, ()),  # duplicate
        b("demo", "cam1", frame_id, (cv.Detection(10, 20, 5, 200),)),  # inverted
        b("demo", "cam9", frame_id, ()),  # unknown camera
        b("demo", "cam1", frame_id, d),
        b("demo", "cam2", frame_id, d),
        b("demo", "cam3", frame_id, d),
    ])
    kinds = [a.error.kind if isinstance(a.error, cv.CrossviewError) else None for a in acks]
    assert kinds == [None, "duplicate", "invalid_argument", "unknown_camera", None, None, None]
    assert isinstance(acks[1].error, cv.DuplicateBatch)


def test_associate_is_unary_and_untracked(client: cv.SyncClient) -> None:
    views = {c: np.array(person_boxes(2)) for c in DEMO_CAMERAS}
    r = client.associate("demo", 7, views)
    assert r.scene == "demo" and r.frame_id == 7 and r.complete
    assert r.identities and all(i.track_id is None for i in r.identities)
    partial = client.associate("demo", 8, {"cam0": person_boxes(1)})
    assert not partial.complete and set(partial.missing_cameras) == set(DEMO_CAMERAS[1:])
    with pytest.raises(cv.NotFound):
        client.associate("nowhere", 7, views)
    with pytest.raises(cv.InvalidArgument):
        client.associate("demo", 7, {"cam0": [{"bbox": [1, 1, 1, 1]}]})


def test_reload_reports_each_model(client: cv.SyncClient) -> None:
    (outcome,) = client.reload()
    assert outcome.scene == "demo" and outcome.outcome == "unchanged"
    assert outcome.version == client.scene("demo").model_version


def test_errors_are_the_same_classes_for_both_transports() -> None:
    http = errors.error_from_http(409, {"error": {"kind": "duplicate", "message": "m", "field": None}})
    grpc = errors.error_from_grpc("ALREADY_EXISTS", "duplicate batch: ...")
    assert type(http) is type(grpc) is cv.DuplicateBatch
    assert type(errors.error_from_grpc("FAILED_PRECONDITION", "scene 'x' has no model yet")) is cv.NoModel
    assert type(errors.error_from_http(409, {"error": {"kind": "no_model", "message": "m"}})) is cv.NoModel
    assert type(errors.error_from_http(429, None, "busy")) is cv.ResourceExhausted
    assert type(errors.error_from_http(503, None)) is cv.Unavailable


def test_an_overloaded_scene_says_when_to_retry_on_both_transports() -> None:
    body = {"error": {"kind": "overloaded", "message": "overloaded: scene 'x' is over its queue budget"}}
    http = errors.error_from_http(429, body, "", "2")
    assert type(http) is cv.Overloaded and isinstance(http, cv.ResourceExhausted)
    assert http.retry_after == 2.0
    from crossview_client._convert import ack_from_pb
    from crossview_client._pb import crossview_pb2 as pb

    ack = ack_from_pb(pb.BatchAck(scene="x", camera="a", frame_id=7, code=8, kind="overloaded",
                                  message="overloaded: ...", retry_after_ms=250))
    assert type(ack.error) is cv.Overloaded and ack.error.retry_after == 0.25
    # A status without the server's kind metadata: the message's prefix tells.
    assert type(errors.error_from_grpc("RESOURCE_EXHAUSTED", "overloaded: frame 7 was shed")) is cv.Overloaded

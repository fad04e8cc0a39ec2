"""Push a detector's per-camera output to crossview, stamped with each camera's capture time,
and print the identities it returns.

The detector is yours: any function ``detect(camera, frame) -> N×5 array`` (x1, y1, x2, y2,
score in pixels), and the time the camera captured that frame (an RTSP reader, GStreamer or
OpenCV gives it per frame). The server groups the cameras' batches by those times (the scene
declares its rate: ``crossview serve --scene demo=cam0:1280x720,...@10fps``), so the cameras
need no shared frame counter. So that this script runs as it is, the stand-in below reads the
boxes of a SPEC §7 recording (e.g. one made by ``crossview simulate``) and stamps frame ``k``
of it ``k / fps`` after now.

    python push_from_detector.py --server 127.0.0.1:8080 --scene demo demo.jsonl
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

import crossview_client as cv

Detector = Callable[[str, int], "npt.NDArray[np.float64]"]


def recording_detector(path: str) -> tuple[list[str], list[int], float, Detector]:
    """A stand-in detector: the boxes a recording holds for each camera and frame, and the
    recording's frame rate (10 when it declares none)."""
    rec = cv.open_recording(path)
    boxes: dict[tuple[str, int], npt.NDArray[np.float64]] = {}
    frames: dict[int, None] = {}
    for b in rec.batches():
        assert b.frame_id is not None, "the stand-in reads a recording with frame ids"
        frames[b.frame_id] = None
        boxes[(b.camera, b.frame_id)] = np.array(
            [[d.x1, d.y1, d.x2, d.y2, 1.0 if d.score is None else d.score] for d in b.detections]
        ).reshape(-1, 5)

    def detect(camera: str, frame_id: int) -> npt.NDArray[np.float64]:
        return boxes.get((camera, frame_id), np.zeros((0, 5)))

    return [c.name for c in rec.cameras], list(frames), rec.fps or 10.0, detect


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording", help="SPEC §7 recording the stand-in detector reads")
    ap.add_argument("--server", default="127.0.0.1:8080")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--transport", choices=["grpc", "http"], default="grpc")
    ap.add_argument("--api-key")
    ap.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: all)")
    args = ap.parse_args()

    cameras, frame_ids, fps, detect = recording_detector(args.recording)
    if args.frames:
        frame_ids = frame_ids[: args.frames]
    with cv.connect(args.server, args.transport, api_key=args.api_key) as client:
        client.wait_ready(timeout=60)
        served = [c.name for c in client.scene(args.scene).cameras]
        if served != cameras:
            raise SystemExit(f"scene {args.scene!r} has cameras {served}, the recording {cameras}")
        tracks: dict[int, int] = defaultdict(int)
        start = time.time()
        with client.subscribe(args.scene) as results:
            for k, frame_id in enumerate(frame_ids):
                # One batch per camera, stamped with its capture time; a camera that saw
                # nobody sends an empty array. The ack names the frame the batch went to.
                captured = start + k / fps
                placed = 0
                for cam in cameras:
                    try:
                        ack = client.push(args.scene, cam, detect(cam, frame_id), timestamp=captured)
                        placed = max(placed, ack.frame_id or 0)
                    except cv.CrossviewError as e:
                        print(f"frame {k} camera {cam}: refused: {e}")
                for r in results:  # every camera reported: the frame's result is next
                    if r.frame_id >= placed:
                        break
                ids = " ".join(
                    f"{i.track_id}:{'+'.join(m.camera for m in i.members)}" for i in r.identities
                )
                for i in r.identities:
                    if i.track_id is not None:
                        tracks[i.track_id] += 1
                when = r.time.isoformat(timespec="milliseconds") if r.time else "-"
                print(f"frame {r.frame_id} at {when}: {len(r.identities)} identities  {ids}", flush=True)
        print(f"{len(frame_ids)} frames, {len(tracks)} tracks")


if __name__ == "__main__":
    main()

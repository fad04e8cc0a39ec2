"""Push a detector's per-camera output to crossview and print the identities it returns.

The detector is yours: any function ``detect(camera, frame_id) -> N×5 array`` (x1, y1, x2,
y2, score in pixels). So that this script runs as it is, the stand-in below reads the boxes
of a SPEC §7 recording (e.g. one made by ``crossview simulate``).

    python push_from_detector.py --server 127.0.0.1:8080 --scene demo demo.jsonl
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

import crossview_client as cv

Detector = Callable[[str, int], "npt.NDArray[np.float64]"]


def recording_detector(path: str) -> tuple[list[str], list[int], Detector]:
    """A stand-in detector: the boxes a recording holds for each camera and frame."""
    rec = cv.open_recording(path)
    boxes: dict[tuple[str, int], npt.NDArray[np.float64]] = {}
    frames: dict[int, None] = {}
    for b in rec.batches():
        frames[b.frame_id] = None
        boxes[(b.camera, b.frame_id)] = np.array(
            [[d.x1, d.y1, d.x2, d.y2, 1.0 if d.score is None else d.score] for d in b.detections]
        ).reshape(-1, 5)

    def detect(camera: str, frame_id: int) -> npt.NDArray[np.float64]:
        return boxes.get((camera, frame_id), np.zeros((0, 5)))

    return [c.name for c in rec.cameras], list(frames), detect


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording", help="SPEC §7 recording the stand-in detector reads")
    ap.add_argument("--server", default="127.0.0.1:8080")
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--transport", choices=["grpc", "http"], default="grpc")
    ap.add_argument("--api-key")
    ap.add_argument("--frames", type=int, default=0, help="stop after this many frames (0: all)")
    args = ap.parse_args()

    cameras, frame_ids, detect = recording_detector(args.recording)
    if args.frames:
        frame_ids = frame_ids[: args.frames]
    with cv.connect(args.server, args.transport, api_key=args.api_key) as client:
        client.wait_ready(timeout=60)
        served = [c.name for c in client.scene(args.scene).cameras]
        if served != cameras:
            raise SystemExit(f"scene {args.scene!r} has cameras {served}, the recording {cameras}")
        tracks: dict[int, int] = defaultdict(int)
        with client.subscribe(args.scene) as results:
            for frame_id in frame_ids:
                # One batch per camera; a camera that saw nobody sends an empty array.
                for ack in client.push_frame(args.scene, frame_id, {c: detect(c, frame_id) for c in cameras}):
                    if ack.error is not None:
                        print(f"frame {frame_id} camera {ack.camera}: refused: {ack.error}")
                for r in results:  # every camera reported: the frame's result is next
                    if r.frame_id >= frame_id:
                        break
                ids = " ".join(
                    f"{i.track_id}:{'+'.join(m.camera for m in i.members)}" for i in r.identities
                )
                for i in r.identities:
                    if i.track_id is not None:
                        tracks[i.track_id] += 1
                print(f"frame {r.frame_id}: {len(r.identities)} identities  {ids}", flush=True)
        print(f"{len(frame_ids)} frames, {len(tracks)} tracks")


if __name__ == "__main__":
    main()

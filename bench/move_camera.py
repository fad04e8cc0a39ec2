"""A camera that moves mid-stream, scripted on a SPEC §7 recording: the recording played
`--before` times as recorded, then `--after` times with one camera's boxes moved in its image
as a pan or a zoom would move them (boxes clipped to the image, dropped once outside), frame ids
renumbered so that the loops follow each other in time. `--before 2 --after 0` only loops.

Usage: python bench/move_camera.py IN.jsonl OUT.jsonl CAMERA [--pan F] [--tilt F] [--zoom Z]
           [--before N] [--after N] [--lag K]
  --pan F   every box moves by F x the image width (F > 0: to the right)
  --tilt F  every box moves by F x the image height
  --zoom Z  every box scales by Z about the image centre
  --lag K   the camera's frame ids also run K frame steps late after the move (a clock
            offset, not a move: what the fit must not report)
Prints the first moved frame id.
"""
import argparse
import json

p = argparse.ArgumentParser()
p.add_argument("src")
p.add_argument("dst")
p.add_argument("camera")
p.add_argument("--pan", type=float, default=0.0)
p.add_argument("--tilt", type=float, default=0.0)
p.add_argument("--zoom", type=float, default=1.0)
p.add_argument("--before", type=int, default=1)
p.add_argument("--after", type=int, default=1)
p.add_argument("--lag", type=int, default=0)
a = p.parse_args()

with open(a.src) as f:
    lines = [l for l in f.read().splitlines() if l.strip()]
header = json.loads(lines[0])
cams = {c["name"]: c for c in header["scene"]["cameras"]}
if a.camera not in cams:
    raise SystemExit(f"unknown camera {a.camera}; the scene has {sorted(cams)}")
W, H = cams[a.camera]["width"], cams[a.camera]["height"]
batches = [json.loads(l) for l in lines[1:]]
ids = sorted({b["frame_id"] for b in batches})
step = min((y - x for x, y in zip(ids, ids[1:])), default=1)
span = ids[-1] - ids[0] + step


def moved(det):
    x1, y1, x2, y2 = det["bbox"]
    cx, cy = W / 2, H / 2
    x1, x2 = cx + a.zoom * (x1 - cx) + a.pan * W, cx + a.zoom * (x2 - cx) + a.pan * W
    y1, y2 = cy + a.zoom * (y1 - cy) + a.tilt * H, cy + a.zoom * (y2 - cy) + a.tilt * H
    x1, x2 = max(0.0, x1), min(float(W), x2)
    y1, y2 = max(0.0, y1), min(float(H), y2)
    if x2 - x1 < 1 or y2 - y1 < 1:
        return None
    d = dict(det)
    d["bbox"] = [round(x1, 1), round(y1, 1), round(x2, 1), round(y2, 1)]
    return d


out = [json.dumps(header)]
first_moved = None
for loop in range(a.before + a.after):
    after = loop >= a.before
    for b in batches:
        b = dict(b)
        b["frame_id"] = b["frame_id"] - ids[0] + loop * span
        if after and b["camera"] == a.camera:
            b["detections"] = [d for d in map(moved, b["detections"]) if d is not None]
            b["frame_id"] += a.lag * step
            if first_moved is None:
                first_moved = loop * span
        out.append(json.dumps(b))
with open(a.dst, "w") as f:
    f.write("\n".join(out) + "\n")
print(first_moved if first_moved is not None else -1)

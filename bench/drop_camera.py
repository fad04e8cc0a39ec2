"""Scripted camera drop-out for the tracking figures: copies a SPEC §7 recording without one
camera's batches over a range of frames (by position in the recording's frame order).

Usage: python bench/drop_camera.py IN.jsonl OUT.jsonl CAMERA FIRST_FRAME_INDEX COUNT
e.g. `python bench/drop_camera.py sq3.jsonl sq3_drop.jsonl cam0 100 50` (5 s at 10 frames/s).
"""
import json
import sys

src, dst, camera, first, count = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
with open(src) as f:
    lines = [l for l in f.read().splitlines() if l.strip()]
frames = sorted({json.loads(l)["frame_id"] for l in lines[1:]})
lo, hi = frames[first], frames[min(first + count, len(frames)) - 1]
kept = [lines[0]]
dropped = 0
for l in lines[1:]:
    b = json.loads(l)
    if b["camera"] == camera and lo <= b["frame_id"] <= hi:
        dropped += 1
        continue
    kept.append(l)
with open(dst, "w") as f:
    f.write("\n".join(kept) + "\n")
print(f"dropped {dropped} batches of {camera}, frames {lo}..{hi}")

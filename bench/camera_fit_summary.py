"""One line per `crossview fit-check --json` run (bench/camera_fit.sh): when the moved camera
was first named `does_not_fit` after the move, and the false alarms of the others.

Usage: python bench/camera_fit_summary.py LOOKS.json CAMERA|- MOVE_FRAME_ID STEP FPS
"""
import json
import sys

path, moved, t0, step, fps = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), float(sys.argv[5])
alarms = drifting = 0
named = None
lowest = None
for line in open(path):
    look = json.loads(line)
    for c in look["cameras"]:
        if c["name"] == moved and look["as_of_frame"] >= t0:
            if named is None and c["state"] == "does_not_fit":
                named = (look["as_of_frame"] - t0) / step / fps
            continue
        alarms += c["state"] == "does_not_fit"
        drifting += c["state"] == "drifting"
        if c["score"] is not None:
            lowest = c["score"] if lowest is None else min(lowest, c["score"])
when = f"named after {named:.1f} s" if named is not None else "not named"
who = f"moved {moved}: {when}; " if moved != "-" else ""
low = f"{lowest:.2f}" if lowest is not None else "-"
print(f"{path}: {who}others: {alarms} false alarms, {drifting} drifting looks, lowest score {low}")

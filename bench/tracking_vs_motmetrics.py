"""Independent check of `crossview eval --tracking` with py-motmetrics (PyPI `motmetrics`).

Reads a labelled recording (SPEC §7, ids consistent over time) and the output of
`crossview associate --tracking` on it, and computes IDF1 with motmetrics: multi-camera (every
(frame, camera) one motmetrics frame of one sequence, as the MOTChallenge multi-camera devkit
concatenates cameras) and per camera, plus per-camera ID switches. Boxes are matched to
themselves (the tracker ran on the ground-truth boxes): distance 0 for a box and its own
output, no other pairs.

Usage: python bench/tracking_vs_motmetrics.py RECORDING.jsonl ASSOCIATE_OUTPUT.jsonl
Prints one JSON object: {"multi_camera": {"idf1": ...}, "per_camera": {name: {"idf1", "switches"}}}
"""
import json
import sys

import motmetrics as mm
import numpy as np


def read(recording, associated):
    with open(recording) as f:
        scene = json.loads(f.readline())["scene"]
        cams = [c["name"] for c in scene["cameras"]]
        truth = {}
        for line in f:
            if not line.strip():
                continue
            b = json.loads(line)
            truth[(b["frame_id"], b["camera"])] = [d["id"] for d in b["detections"]]
    tracks = {}
    with open(associated) as f:
        for line in f:
            r = json.loads(line)
            for ident in r["identities"]:
                for m in ident["members"]:
                    tracks[(r["frame_id"], m["camera"], m["detection"])] = ident["track_id"]
    return cams, truth, tracks


def accumulate(keys, truth, tracks):
    acc = mm.MOTAccumulator(auto_id=True)
    for key in keys:
        gts = truth.get(key, [])
        hyps = [tracks[(key[0], key[1], i)] for i in range(len(gts))]
        dist = np.full((len(gts), len(hyps)), np.nan)
        np.fill_diagonal(dist, 0.0)
        acc.update(gts, hyps, dist)
    return acc


def main():
    cams, truth, tracks = read(sys.argv[1], sys.argv[2])
    frames = sorted({f for f, _ in truth})
    mh = mm.metrics.create()
    multi = accumulate([(f, c) for f in frames for c in cams], truth, tracks)
    out = {"multi_camera": {"idf1": float(mh.compute(multi, metrics=["idf1"])["idf1"].iloc[0])}}
    out["per_camera"] = {}
    for c in cams:
        acc = accumulate([(f, c) for f in frames], truth, tracks)
        s = mh.compute(acc, metrics=["idf1", "num_switches", "mota"])
        out["per_camera"][c] = {
            "idf1": float(s["idf1"].iloc[0]),
            "switches": int(s["num_switches"].iloc[0]),
            "mota": float(s["mota"].iloc[0]),
        }
    print(json.dumps(out))


if __name__ == "__main__":
    main()

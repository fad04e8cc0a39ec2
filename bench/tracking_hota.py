"""HOTA of `crossview associate --tracking` output, computed by TrackEval (PyPI `trackeval`,
the MOTChallenge / HOTA authors' evaluator), which crossview itself does not implement.

Reads a labelled recording (SPEC §7, ids consistent over time) and the output of
`crossview associate --tracking` on it. The tracker ran on the recording's own boxes, so every
ground-truth box has its predicted box at IoU 1; the similarity of a ground-truth and a
predicted box is their IoU. Multi-camera: one sequence whose timesteps are the (frame, camera)
pairs, cameras concatenated as the MOTChallenge multi-camera devkit does (TrackEval needs an
id at most once per timestep; a person keeps one id across cameras); per camera: that
camera's frames alone. With the tracker on the ground-truth boxes DetA is ~1 (below 1 only
where overlapping boxes of one camera let HOTA's matching prefer another box) and HOTA is
about the square root of AssA: it scores the track ids.

Usage: python bench/tracking_hota.py RECORDING.jsonl ASSOCIATE_OUTPUT.jsonl
Prints one JSON object: {"multi_camera": {"hota", "deta", "assa"}, "per_camera": {name: {...}}}
"""
import json
import sys

import numpy as np
from trackeval.metrics import HOTA


def iou(a, b):
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def read(recording, associated):
    with open(recording) as f:
        scene = json.loads(f.readline())["scene"]
        cams = [c["name"] for c in scene["cameras"]]
        truth = {}
        for line in f:
            if line.strip():
                b = json.loads(line)
                truth[(b["frame_id"], b["camera"])] = b["detections"]
    tracks = {}
    with open(associated) as f:
        for line in f:
            r = json.loads(line)
            for ident in r["identities"]:
                for m in ident["members"]:
                    tracks[(r["frame_id"], m["camera"], m["detection"])] = ident["track_id"]
    return cams, truth, tracks


def sequence(frames, cams, truth, tracks):
    """TrackEval's per-sequence data: one timestep per (frame, camera of `cams`)."""
    gt_index, tr_index = {}, {}
    data = {"gt_ids": [], "tracker_ids": [], "similarity_scores": []}
    n_gt = n_tr = 0
    steps = [(f, c) for f in frames for c in cams if (f, c) in truth]
    for f, c in steps:
        gts, trs = [], []  # (box, id)
        for i, d in enumerate(truth[(f, c)]):
            gts.append((d["bbox"], gt_index.setdefault(d["id"], len(gt_index))))
            t = tracks.get((f, c, i))
            if t is not None:
                trs.append((d["bbox"], tr_index.setdefault(t, len(tr_index))))
        sim = np.zeros((len(gts), len(trs)))
        for a, (bg, _) in enumerate(gts):
            for b, (bt, _) in enumerate(trs):
                sim[a, b] = iou(bg, bt)
        data["gt_ids"].append(np.array([g[1] for g in gts], dtype=int))
        data["tracker_ids"].append(np.array([t[1] for t in trs], dtype=int))
        data["similarity_scores"].append(sim)
        n_gt += len(gts)
        n_tr += len(trs)
    data.update(
        num_timesteps=len(steps),
        num_gt_ids=len(gt_index),
        num_tracker_ids=len(tr_index),
        num_gt_dets=n_gt,
        num_tracker_dets=n_tr,
    )
    return data


def scores(data):
    r = HOTA().eval_sequence(data)
    return {
        "hota": float(np.mean(r["HOTA"])),
        "deta": float(np.mean(r["DetA"])),
        "assa": float(np.mean(r["AssA"])),
    }


def main():
    cams, truth, tracks = read(sys.argv[1], sys.argv[2])
    frames = sorted({f for f, _ in truth})
    out = {
        "multi_camera": scores(sequence(frames, cams, truth, tracks)),
        "per_camera": {c: scores(sequence(frames, [c], truth, tracks)) for c in cams},
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Python reference of the crossview inference pipeline (SPEC §3), for throughput comparison.

Per frame: ONE ONNX Runtime call embeds every box of every camera (boxes normalised by their
camera's image size, SPEC §2/§8); then for every camera pair i < j with boxes on both sides:
Euclidean distances of the embeddings, divided by their maximum (+1e-6), Hungarian assignment
(scipy.optimize.linear_sum_assignment), confidence S = 1 - D, pairs with S < threshold dropped.
No appearance term (the benchmark recordings carry none). Reading the recording is not timed,
unless --include-reading: then every timed pass reads and parses the file again (json + numpy)
before associating its frames, as an offline tool would.

Prints one JSON object: frames timed, frames/s (all passes together and the best pass), kept
matches over one pass (to cross-check the Rust run on the same model and frames).

    python bench/python_reference.py --model M.onnx --data REC.jsonl [--threads 1] [--include-reading]
"""
import argparse
import json
import sys
import time

import numpy as np
import onnxruntime as ort
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist


def read_recording(path):
    """Scene cameras and frames: a list of (frame_id, [per-camera float32 [n,4] pixel boxes])."""
    with open(path) as f:
        header = json.loads(f.readline())
        cameras = header["scene"]["cameras"]
        index = {c["name"]: k for k, c in enumerate(cameras)}
        frames = {}
        for line in f:
            line = line.strip()
            if not line:
                continue
            b = json.loads(line)
            views = frames.setdefault(b["frame_id"], [None] * len(cameras))
            views[index[b["camera"]]] = np.asarray(
                [d["bbox"] for d in b["detections"]], dtype=np.float32
            ).reshape(-1, 4)
    return cameras, [(fid, frames[fid]) for fid in sorted(frames)]


def associate(session, scale, views, threshold):
    """One frame: normalise the boxes, one encoder call, Hungarian matching per camera pair."""
    sizes = [0 if v is None else len(v) for v in views]
    present = [c for c, n in enumerate(sizes) if n]
    if not present:
        return 0
    boxes = np.concatenate([views[c] / scale[c] for c in present])
    cams = np.concatenate([np.full(sizes[c], c, dtype=np.int64) for c in present])
    emb = session.run(["embedding"], {"boxes": boxes, "camera": cams})[0]
    starts = np.cumsum([0] + [sizes[c] for c in present])
    per_view = [emb[starts[k] : starts[k + 1]] for k in range(len(present))]
    kept = 0
    for a in range(len(per_view)):
        for b in range(a + 1, len(per_view)):
            dg = cdist(per_view[a], per_view[b])
            d = dg / (dg.max() + 1e-6)
            rows, cols = linear_sum_assignment(d)
            s = 1.0 - d[rows, cols]
            kept += int(np.count_nonzero(s >= threshold))
    return kept


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--model", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads")
    p.add_argument("--warmup", type=int, default=20)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threshold", type=float, default=None, help="default: the model's")
    p.add_argument(
        "--include-reading",
        action="store_true",
        help="time reading and parsing the recording too (once per timed pass)",
    )
    args = p.parse_args()

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = args.threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    session = ort.InferenceSession(args.model, opts, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    threshold = args.threshold
    if threshold is None:
        threshold = float(meta.get("crossview.threshold", "0.4"))

    cameras, frames = read_recording(args.data)
    if not frames:
        sys.exit("no frames in " + args.data)
    scale = np.asarray(
        [[c["width"], c["height"], c["width"], c["height"]] for c in cameras], dtype=np.float32
    )
    work = [views for _, views in frames]
    for k in range(args.warmup):
        associate(session, scale, work[k % len(work)], threshold)

    kept = 0
    timed = 0
    passes = []
    for rep in range(args.repeat):
        start = time.perf_counter()
        if args.include_reading:
            _, frames = read_recording(args.data)
            work = [views for _, views in frames]
        for views in work:
            n = associate(session, scale, views, threshold)
            if rep == 0:
                kept += n
            timed += 1
        passes.append(time.perf_counter() - start)
    seconds = sum(passes)
    print(
        json.dumps(
            {
                "frames": timed,
                "seconds": seconds,
                "frames_per_second": timed / seconds,
                "best_pass_frames_per_second": len(work) / min(passes),
                "pass_seconds": passes,
                "include_reading": args.include_reading,
                "kept_matches": kept,
                "threads": args.threads,
                "onnxruntime": ort.__version__,
                "numpy": np.__version__,
            }
        )
    )


if __name__ == "__main__":
    main()

"""Throughput of the Python client (crossview_client.GrpcClient) pushing one 7-camera scene
as fast as the server acks, one process, against the release server — the Python
counterpart of the load tester's "as fast as it goes (gRPC)" row (bench/service_throughput.sh:
same simulated WILDTRACK layout, seed 11, width-64 random encoder, a fresh server per run).

frames/s = frames whose results came back / seconds from the first push to the last result.
Bounded: every wait has a timeout; the run stops after --frames frames.

Usage: .cache/venv/bin/python bench/python_client_throughput.py [--runs 3] [--frames 3000]
Env: CROSSVIEW_BIN (target/release/crossview), ORT_DYLIB_PATH, OUT (/var/tmp/cv-pyclient)
"""

from __future__ import annotations

import argparse
import datetime
import os
import re
import statistics
import subprocess
import threading
import time
from pathlib import Path

import crossview_client as cv

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=3000)
    ap.add_argument("--transport", choices=["grpc", "http"], default="grpc")
    args = ap.parse_args()
    b = os.environ.get("CROSSVIEW_BIN", str(ROOT / "target/release/crossview"))
    out = Path(os.environ.get("OUT", "/var/tmp/cv-pyclient"))
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("ORT_DYLIB_PATH", str(ROOT / ".cache/onnxruntime/libonnxruntime.so.1.31.1"))
    rec, model = out / "rec.jsonl", out / "model.onnx"
    subprocess.run([b, "simulate", "--preset", "wildtrack", "--frames", "600", "--seed", "11",
                    "--out", str(rec)], check=True, env=env, capture_output=True, timeout=120)
    subprocess.run([b, "model", "init", "--scene-from", str(rec), "--out", str(model), "--width", "64"],
                   check=True, env=env, capture_output=True, timeout=120)
    recording = cv.open_recording(rec)
    scene = recording.scene
    base = list(recording.batches())
    n_cams = len(recording.cameras)
    loops = -(-args.frames // 600)
    batches = [cv.Batch(scene, x.camera, x.frame_id + 600 * k, x.detections)
               for k in range(loops) for x in base][: args.frames * n_cams]
    frames = len(batches) // n_cams
    print(f"machine: {os.cpu_count()} cores, load {open('/proc/loadavg').read().split()[:3]}, "
          f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; {frames} frames x {n_cams} cameras, "
          f"{sum(len(x.detections) for x in batches) / len(batches):.1f} boxes per camera, {args.transport}")
    rates = []
    for run in range(args.runs):
        env["RUST_LOG"] = "info"
        srv = subprocess.Popen([b, "serve", "--listen", "127.0.0.1:0", "--model", f"{scene}={model}"],
                               stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
        assert srv.stderr is not None
        addr = ""
        for line in srv.stderr:
            m = re.search(r"(\d+\.\d+\.\d+\.\d+:\d+)", re.sub(r"\x1b\[[0-9;]*m", "", line))
            if "serving" in line and m:
                addr = m.group(1)
                break
        threading.Thread(target=lambda: [None for _ in srv.stderr], daemon=True).start()  # type: ignore[union-attr]
        try:
            with cv.connect(addr, args.transport, timeout=60) as client:  # type: ignore[arg-type]
                client.wait_ready(60)
                sub = client.subscribe(scene, reconnect=False)
                last = [0.0]
                got = [0]
                done = threading.Event()

                def consume() -> None:
                    for r in sub:
                        got[0] += 1
                        last[0] = time.perf_counter()
                        if r.frame_id == frames - 1:
                            break
                    done.set()

                threading.Thread(target=consume, daemon=True).start()
                t0 = time.perf_counter()
                acks = client.push_many(batches)
                rejected = sum(not a.accepted for a in acks)
                done.wait(120)
                sub.close()
            rate = got[0] / (last[0] - t0)
            rates.append(rate)
            print(f"run {run + 1}: {got[0]} results in {last[0] - t0:.2f} s = {rate:.0f} frames/s "
                  f"({rejected} batches refused)", flush=True)
        finally:
            srv.terminate()
            srv.wait(30)
    print(f"frames/s min / median / max: {min(rates):.0f} / {statistics.median(rates):.0f} / {max(rates):.0f}")


if __name__ == "__main__":
    main()

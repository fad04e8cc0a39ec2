#!/usr/bin/env bash
# Serve throughput smoke benchmark: a WILDTRACK-shaped synthetic recording (7 cameras
# 1920x1080, 200 frames, 20 random boxes per camera), a random width-768 encoder
# (`crossview model init`), `crossview serve`, one HTTP JSON Lines push of the whole recording,
# then the server's own metrics: time until all 200 frames are associated and the mean
# encoder+association time per frame. Usage: bench/serve_bench.sh [path/to/crossview]
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${1:-target/release/crossview}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
PORT=${PORT:-18499}
WORK=$(mktemp -d)
trap 'kill -TERM $PID 2>/dev/null || true; rm -rf "$WORK"' EXIT
python3 - "$WORK/rec.jsonl" <<'PY'
import json, random, sys
random.seed(1)
cams = [{"name": f"C{i+1}", "width": 1920, "height": 1080} for i in range(7)]
with open(sys.argv[1], "w") as f:
    f.write(json.dumps({"scene": {"name": "wt", "cameras": cams}}) + "\n")
    for fr in range(200):
        for c in cams:
            dets = []
            for _ in range(20):
                x, y = random.uniform(0, 1800), random.uniform(0, 700)
                dets.append({"bbox": [round(x, 1), round(y, 1), round(x + random.uniform(30, 120), 1),
                                      round(y + random.uniform(100, 350), 1)]})
            f.write(json.dumps({"camera": c["name"], "frame_id": fr * 5, "detections": dets}) + "\n")
PY
"$BIN" model init --scene-from "$WORK/rec.jsonl" --out "$WORK/wt.onnx" >/dev/null 2>&1
"$BIN" serve --model "$WORK/wt.onnx" --listen "127.0.0.1:$PORT" --queue-capacity 1000 2>"$WORK/log" &
PID=$!
until curl -sf "localhost:$PORT/readyz" >/dev/null; do sleep 0.1; done
start=$(date +%s.%N)
curl -sf -o "$WORK/push.json" -H 'content-type: application/x-ndjson' \
  --data-binary @"$WORK/rec.jsonl" "localhost:$PORT/v1/scenes/wt/batches"
until [ "$(curl -s "localhost:$PORT/metrics" | awk '/^crossview_inference_seconds_count/ {print $2}')" = 200 ]; do
  sleep 0.02
done
end=$(date +%s.%N)
curl -s "localhost:$PORT/metrics" | awk -v s="$start" -v e="$end" '
  /^crossview_inference_seconds_sum/ { inf = $2 }
  END { printf "200 frames (7 cameras x 20 boxes) in %.2f s = %.0f frames/s; encoder+association %.1f ms/frame\n", e - s, 200 / (e - s), inf * 1000 / 200 }'

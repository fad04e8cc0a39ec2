#!/usr/bin/env bash
# The capture-time accuracy rows of BENCHMARKS.md ("Capture times"): through the real server
# (bench/src/bin/capture_times.rs), what a client receives when cameras send capture times
# instead of frame ids, against the frame-id path.
#   - WILDTRACK validation frames (ground-truth boxes, ids hidden), 2 frames/s, models/wildtrack.onnx:
#     frame ids; times with each camera's own offset (up to ±1.5 periods) and jitter ±20 % of
#     a period, the offsets declared; the same, offsets found by the watch (--auto-align, the
#     recording looped 10 times, scored on the whole loops after the last misplaced batch);
#   - simulator square4, 10 frames/s, 10 minutes, models/demo.onnx: frame ids; times with
#     offsets up to ±500 ms, jitter ±40 ms, one camera drifting 20 ms/min, --auto-align.
# Usage: bash bench/capture_times.sh    Env: OUT (/var/tmp/cv-capture-times), PART (val),
#   WILDTRACK (../shared/data/wildtrack), SEEDS (3)
set -euo pipefail
cd "$(dirname "$0")/.."
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
OUT=${OUT:-/var/tmp/cv-capture-times}; mkdir -p "$OUT"
PART=${PART:-val}; WILDTRACK=${WILDTRACK:-../shared/data/wildtrack}
B=target/release/crossview; T=target/release/capture_times
$B import wildtrack-gt --dir "$WILDTRACK/annotations_positions" --split "$PART" --out "$OUT/gt.jsonl" 2>/dev/null
OFF=CVLab2:620,CVLab3:-740,CVLab4:380,IDIAP1:-250,IDIAP2:710,IDIAP3:-130
show() { python3 - "$1" "$2" <<'PY'
import json, sys
d = json.load(open(sys.argv[1])); r = d["report"]; a = r["after"]
print(f"| {sys.argv[2]} | {d['frames']} | {r['misplaced']} of {r['batches_placed']} (last capture frame {r['last_misplaced_capture_frame']}) | {100*r['acc']:.2f} / {100*r['ipaa_100']:.2f} | from frame {r['settled_from_capture_frame']}: {100*a['acc']:.2f} / {100*a['ipaa_100']:.2f} | {d['refused']} {d['refusals']} |")
PY
}
echo "| run | frames | batches misplaced | ACC / IPAA-100, all | after the last misplaced | refused |"
echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u '+%Y-%m-%d %H:%M') UTC"
$T --model models/wildtrack.onnx --data "$OUT/gt.jsonl" --ids > "$OUT/w_ids.json"
show "$OUT/w_ids.json" "WILDTRACK $PART, frame ids"
$T --model models/wildtrack.onnx --data "$OUT/gt.jsonl" --offsets-ms $OFF --jitter 0.2 --declare > "$OUT/w_declared.json"
show "$OUT/w_declared.json" "WILDTRACK $PART, times, offsets declared"
$T --model models/wildtrack.onnx --data "$OUT/gt.jsonl" --offsets-ms $OFF --jitter 0.2 --auto-align --loops 10 --rate 20 > "$OUT/w_auto.json"
show "$OUT/w_auto.json" "WILDTRACK $PART ×10, times, --auto-align"
for seed in ${SEEDS:-3}; do
  $B simulate --preset square4 --frames 6000 --seed "$seed" --out "$OUT/sim$seed.jsonl" 2>/dev/null
  $T --model models/demo.onnx --data "$OUT/sim$seed.jsonl" --ids --rate 100 > "$OUT/s${seed}_ids.json"
  show "$OUT/s${seed}_ids.json" "square4 seed $seed, frame ids"
  $T --model models/demo.onnx --data "$OUT/sim$seed.jsonl" --offsets-ms cam1:230,cam2:-470,cam3:500 --drift cam3:20 --jitter 0.4 --auto-align --rate 100 > "$OUT/s${seed}_auto.json"
  show "$OUT/s${seed}_auto.json" "square4 seed $seed, times, --auto-align"
done

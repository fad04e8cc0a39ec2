#!/usr/bin/env bash
# Push-to-result latency with capture times against frame ids (BENCHMARKS.md, "Capture
# times"): one 7-camera scene at 100 frames/s over gRPC and HTTP, the WILDTRACK validation
# frames (real density) served with models/wildtrack.onnx, the scene declared at 100 frames/s;
# each run 20 s on a fresh server, ROUNDS rounds alternating the two paths (paired).
# Usage: bash bench/capture_times_latency.sh   Env: OUT (/var/tmp/cv-times), PORT (18393),
#   ROUNDS (3), WILDTRACK (../shared/data/wildtrack)
set -u
cd "$(dirname "$0")/.." || exit 1
export ORT_DYLIB_PATH=$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1
OUT=${OUT:-/var/tmp/cv-times}; mkdir -p "$OUT"; PORT=${PORT:-18393}; TARGET=http://127.0.0.1:$PORT
B=target/release/crossview; L=target/release/crossview-loadtest
WILDTRACK=${WILDTRACK:-../shared/data/wildtrack}
$B import wildtrack-gt --dir "$WILDTRACK/annotations_positions" --split val --out "$OUT/rec.jsonl" 2>/dev/null
# The scene header at 100 frames/s (what capture times are grouped by).
head -1 "$OUT/rec.jsonl" | python3 -c 'import json,sys; h=json.load(sys.stdin); h["fps"]=100.0; print(json.dumps(h))' > "$OUT/scene.jsonl"
row() { python3 - "$1" "$2" <<'PY'
import json, sys
r = json.load(open(sys.argv[1])); l = r["latency_complete"]
print(f"| {sys.argv[2]} | {r['results_per_s']:.1f} | {l['p50_ms']:.2f} | {l['p99_ms']:.2f} | {l['p999_ms']:.2f} | {r['frames_lost']} | {sum(r['batches_rejected'].values())} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}
run() { local name=$1; shift
  $B serve --listen 127.0.0.1:$PORT --scene "$OUT/scene.jsonl" --model "wildtrack=models/wildtrack.onnx" >>"$OUT/server.log" 2>&1 & local S=$!
  $L --target $TARGET --recording "$OUT/rec.jsonl" --wait-ready 60s --json --rate 100 --duration 20s --loop "$@" > "$OUT/$name.json" 2>"$OUT/$name.err" || true
  kill $S; wait $S 2>/dev/null
  row "$OUT/$name.json" "$name" || tail -3 "$OUT/$name.err"
}
echo "| run | results/s | p50 ms | p99 ms | p99.9 ms | lost | rejected | verdict |"
echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u '+%Y-%m-%d %H:%M') UTC"
for r in $(seq 1 "${ROUNDS:-3}"); do
  for t in grpc http; do
    run "$t-ids-$r" --transport $t --frame-ids fresh
    run "$t-times-$r" --transport $t --frame-ids times
  done
done

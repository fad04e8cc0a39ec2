#!/usr/bin/env bash
# Tracking's effect on service latency (BENCHMARKS.md, "Tracking"): one 7-camera scene
# (simulator preset wildtrack, ~20 people per camera) at 100 frames/s over gRPC, width-64
# random encoder, a fresh server per run, alternating tracking on and off (three runs each,
# so the spread between runs of the same setting shows the noise). Bounded: --duration.
# Usage: bash bench/tracking_latency.sh     Env: OUT (/var/tmp/cv-track), PORT (18392), DURATION (20s)
set -u
cd "$(dirname "$0")/.." || exit 1
export ORT_DYLIB_PATH=$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1
OUT=${OUT:-/var/tmp/cv-track}; mkdir -p $OUT; PORT=${PORT:-18392}; TARGET=http://127.0.0.1:$PORT
DURATION=${DURATION:-20s}
B=target/release/crossview; L=target/release/crossview-loadtest
$B simulate --preset wildtrack --frames 600 --seed 11 --out $OUT/rec.jsonl 2>/dev/null
$B model init --scene-from $OUT/rec.jsonl --out $OUT/model.onnx --width 64 >/dev/null 2>&1
SCENE=$(head -1 $OUT/rec.jsonl | python3 -c 'import json,sys; print(json.load(sys.stdin)["scene"]["name"])')
row() { python3 - "$1" "$2" <<'PY'
import json, sys
r = json.load(open(sys.argv[1])); l = r["latency_complete"]
print(f"| {sys.argv[2]} | {r['results_per_s']:.1f} | {l['p50_ms']:.2f} | {l['p90_ms']:.2f} | {l['p99_ms']:.2f} | {l['p999_ms']:.2f} | {r['frames_lost']} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}
run() { local name=$1; shift
  $B serve --listen 127.0.0.1:$PORT --model "$SCENE=$OUT/model.onnx" "$@" >>$OUT/server.log 2>&1 & local S=$!
  $L --target $TARGET --recording $OUT/rec.jsonl --wait-ready 60s --json --server-pid $S \
    --transport grpc --rate 100 --duration $DURATION --loop > $OUT/$name.json 2>$OUT/$name.err || true
  kill $S; wait $S 2>/dev/null
  row $OUT/$name.json $name || tail -3 $OUT/$name.err
}
echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%Y-%m-%d\ %H:%M) UTC"
echo "| run | results/s | p50 ms | p90 ms | p99 ms | p99.9 ms | lost | verdict |"
echo "|---|---|---|---|---|---|---|---|"
for i in 1 2 3; do
  run tracking-on-$i
  run tracking-off-$i --no-tracking
done

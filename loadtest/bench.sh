#!/usr/bin/env bash
# Throughput/latency matrix of `crossview serve` measured with crossview-loadtest, for
# BENCHMARKS.md. Starts its own server on a loopback port, simulates the workload, writes one
# JSON report per run into $OUT and prints a table. Bounded: every run has --duration.
#
# Usage: bash loadtest/bench.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  LOADTEST_BIN (target/release/crossview-loadtest)
#        OUT (/var/tmp/crossview-bench)  PORT (18383)  PRESET (wildtrack)  WIDTH (768)
#        RATES ("10 20 40")  DURATION (20s)  SOAK_DURATION (0 = no soak run)
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
LOADTEST_BIN=${LOADTEST_BIN:-target/release/crossview-loadtest}
OUT=${OUT:-/var/tmp/crossview-bench}
PORT=${PORT:-18383}
PRESET=${PRESET:-wildtrack}
WIDTH=${WIDTH:-768}
RATES=${RATES:-10 20 40}
DURATION=${DURATION:-20s}
SOAK_DURATION=${SOAK_DURATION:-0}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
TARGET=http://127.0.0.1:$PORT

mkdir -p "$OUT"
"$CROSSVIEW_BIN" simulate --preset "$PRESET" --frames 600 --seed 11 --out "$OUT/rec.jsonl" 2>/dev/null
"$CROSSVIEW_BIN" model init --scene-from "$OUT/rec.jsonl" --out "$OUT/model.onnx" --width "$WIDTH" >/dev/null 2>&1
SCENE=$(head -1 "$OUT/rec.jsonl" | python3 -c 'import json,sys; print(json.load(sys.stdin)["scene"]["name"])')
MODELS="$SCENE=$OUT/model.onnx,$SCENE-1=$OUT/model.onnx,$SCENE-2=$OUT/model.onnx"

"$CROSSVIEW_BIN" serve --listen "127.0.0.1:$PORT" --model "$MODELS" >"$OUT/server.log" 2>&1 &
SERVER=$!
trap 'kill $SERVER 2>/dev/null || true; wait $SERVER 2>/dev/null || true' EXIT

run() { # run NAME loadtest-args...
  local name=$1; shift
  "$LOADTEST_BIN" --target "$TARGET" --recording "$OUT/rec.jsonl" --wait-ready 30s --json "$@" \
    >"$OUT/$name.json" 2>"$OUT/$name.err" || true
  python3 - "$OUT/$name.json" "$name" <<'PY'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except Exception as e:
    print(f"| {sys.argv[2]} | failed: {e} |"); sys.exit(0)
l = r["latency_complete"]
rate = r["rate_fps_per_scene"] or "max"
print(f"| {sys.argv[2]} | {r['transport']} | {len(r['scenes'])} | {rate} | {r['offered_batches_per_s']:.0f} "
      f"| {r['results_per_s']:.1f} | {l['p50_ms']:.1f} | {l['p90_ms']:.1f} | {l['p99_ms']:.1f} | {l['p999_ms']:.1f} "
      f"| {r['frames_lost']} | {sum(r['batches_rejected'].values())} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}

echo "| run | transport | scenes | fps/scene | batches/s offered | results/s | p50 ms | p90 ms | p99 ms | p99.9 ms | lost | rejected | verdict |"
echo "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
for t in grpc http; do
  for r in $RATES; do
    run "$t-1x$r" --transport "$t" --rate "$r" --duration "$DURATION" --loop
  done
  run "$t-1xmax" --transport "$t" --rate 0 --duration "$DURATION" --loop
  run "$t-3xmax" --transport "$t" --rate 0 --duration "$DURATION" --loop \
    --scene-names "$SCENE,$SCENE-1,$SCENE-2" --connections 3
done
if [[ $SOAK_DURATION != 0 ]]; then
  run "soak" --transport grpc --soak --rate 10 --duration "$SOAK_DURATION" \
    --scene-names "$SCENE,$SCENE-1,$SCENE-2" --server-pid "$SERVER"
  python3 -c 'import json,sys; r=json.load(open(sys.argv[1])); print("soak:", r["soak_counts"], r["server_rss"] and {k: r["server_rss"][k] for k in ("first_kib","max_kib","last_kib","samples")}, r["server_comparison"])' "$OUT/soak.json"
fi

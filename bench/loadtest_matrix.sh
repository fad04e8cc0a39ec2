#!/usr/bin/env bash
# Throughput/latency matrix of `crossview serve` measured with crossview-loadtest, for
# BENCHMARKS.md. Starts its own server on a loopback port, simulates the workload, writes one
# JSON report per run into $OUT and prints a table. Bounded: every run has --duration.
#
# Usage: bash bench/loadtest_matrix.sh
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

# Every run gets a fresh server: `--ids fresh` moves each run's frame ids far beyond the
# previous run's (Unix time based), which a running server treats as a camera restart (its
# first batches refused until most cameras agree, docs/serve.md "Frame ids") — real behaviour,
# but not what a latency row should measure.
SERVER=
stop_server() {
  if [[ -n $SERVER ]]; then kill "$SERVER" 2>/dev/null || true; wait "$SERVER" 2>/dev/null || true; fi
  SERVER=
}
start_server() {
  stop_server
  "$CROSSVIEW_BIN" serve --listen "127.0.0.1:$PORT" --model "$MODELS" >>"$OUT/server.log" 2>&1 &
  SERVER=$!
}
trap stop_server EXIT

run() { # run NAME loadtest-args...   (an argument @SERVER@ becomes the fresh server's pid)
  local name=$1; shift
  start_server
  local args=() a
  for a in "$@"; do [[ $a == @SERVER@ ]] && a=$SERVER; args+=("$a"); done
  "$LOADTEST_BIN" --target "$TARGET" --recording "$OUT/rec.jsonl" --wait-ready 30s --json "${args[@]}" \
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
    --scene-names "$SCENE,$SCENE-1,$SCENE-2" --server-pid @SERVER@
  python3 -c 'import json,sys; r=json.load(open(sys.argv[1])); print("soak:", r["soak_counts"], r["server_rss"] and {k: r["server_rss"][k] for k in ("first_kib","max_kib","last_kib","samples")}, r["server_comparison"])' "$OUT/soak.json"
fi

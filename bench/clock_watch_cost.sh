#!/usr/bin/env bash
# Cost of the live clock watch (issue #30): the same open-loop load — one 7-camera scene
# ($MODEL, default models/wildtrack.onnx; a simulated WILDTRACK-shaped recording, ~30 people) at 100 frames/s
# over gRPC — against a fresh server with the watch off (--clock-watch-window 0) and on (the
# defaults: 300 frames, one estimate per 10 s, ±10 frames), alternated twice. Per run: the
# push-to-result latency percentiles, the estimates made and their CPU share (the summed
# time of crossview_clock_estimate_seconds over the run's length: the watch thread's share of
# one core). Bounded: every run has --duration. Figures only on an idle machine.
#
# Usage: bash bench/clock_watch_cost.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  LOADTEST_BIN (target/release/crossview-loadtest)
#        OUT (/var/tmp/cv-clock)  PORT (18396)  RATE (100)  DURATION (40s)  ON_ARGS (extra flags for "on")
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
LOADTEST_BIN=${LOADTEST_BIN:-target/release/crossview-loadtest}
OUT=${OUT:-/var/tmp/cv-clock}
PORT=${PORT:-18396}
RATE=${RATE:-100}
DURATION=${DURATION:-40s}
TRANSPORT=grpc
ON_ARGS=${ON_ARGS:-}
MODEL=${MODEL:-models/wildtrack.onnx}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
TARGET=http://127.0.0.1:$PORT

# shellcheck source=bench/wildtrack_load.sh
source bench/wildtrack_load.sh

# run NAME [serve flags...]: a fresh server, one load run, its row.
run() {
  local name=$1; shift
  load_run "$name" "$@"
  python3 - "$OUT/$name.json" "$OUT/$name.metrics" "$name" "$DURATION" <<'PY'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except Exception as e:
    print(f"| {sys.argv[3]} | run failed ({e}); see {sys.argv[1][:-5]}.err |"); sys.exit(0)
m = {}
for line in open(sys.argv[2]):
    if line.startswith("crossview_clock_estimate_seconds_"):
        key, _, v = line.rpartition(" ")
        m[key.split("{")[0]] = float(v)
seconds = float(sys.argv[4].rstrip("s"))
n = int(m.get("crossview_clock_estimate_seconds_count", 0))
total = m.get("crossview_clock_estimate_seconds_sum", 0.0)
per = f"{total / n * 1e3:.0f}" if n else "-"
l = r["latency_complete"]
print(f"| {sys.argv[3]} | {r['rate_fps_per_scene'] or 'max'} | {r['results_per_s']:.1f} | {l['p50_ms']:.2f} | {l['p99_ms']:.2f} | {l['max_ms']:.2f} "
      f"| {r['frames_lost']} | {n} | {per} | {100 * total / seconds:.1f} % | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}

echo "| watch | rate (fps) | results/s | p50 ms | p99 ms | max ms | lost | estimates | ms per estimate | watch CPU (of one core) | load test |"
echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
for _ in 1 2; do
  run off --clock-watch-window 0
  # shellcheck disable=SC2086
  run on $ON_ARGS
done

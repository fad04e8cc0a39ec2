#!/usr/bin/env bash
# Recording overhead of `crossview serve --record` (issue #16): the same open-loop load — one
# 7-camera scene ($MODEL, default models/wildtrack.onnx) at 100 frames/s over gRPC — against a fresh server
# without and with --record, and the push-to-result latency percentiles of each, plus what the
# recorder wrote and dropped. Bounded: every run has --duration. Figures only on an idle
# machine (BENCHMARKS.md).
#
# Usage: bash bench/record_overhead.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  LOADTEST_BIN (target/release/crossview-loadtest)
#        OUT (/var/tmp/cv-record)  PORT (18395)  RATE (100)  DURATION (30s)  TRANSPORT (grpc)
#        RECORD_ARGS (extra serve flags for the recording run, e.g. "--record-max-file-bytes 8388608")
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
LOADTEST_BIN=${LOADTEST_BIN:-target/release/crossview-loadtest}
OUT=${OUT:-/var/tmp/cv-record}
PORT=${PORT:-18395}
RATE=${RATE:-100}
DURATION=${DURATION:-30s}
TRANSPORT=${TRANSPORT:-grpc}
RECORD_ARGS=${RECORD_ARGS:-}
MODEL=${MODEL:-models/wildtrack.onnx}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
TARGET=http://127.0.0.1:$PORT

# shellcheck source=bench/wildtrack_load.sh
source bench/wildtrack_load.sh

# run NAME [serve flags...]: a fresh server, one load run, its row.
run() {
  local name=$1; shift
  load_run "$name" "$@"
  python3 - "$OUT/$name.json" "$OUT/$name.metrics" "$name" <<'PY'
import json, sys
try:
    r = json.load(open(sys.argv[1]))
except Exception as e:
    print(f"| {sys.argv[3]} | run failed ({e}); see {sys.argv[1][:-5]}.err |"); sys.exit(0)
m = {}
for line in open(sys.argv[2]):
    if line.startswith("crossview_record_"):
        key, _, v = line.rpartition(" ")
        name = key.split("{")[0]
        m[name] = m.get(name, 0) + float(v)
l = r["latency_complete"]
rss = (r.get("server_rss") or {}).get("max_kib", "-")
print(f"| {sys.argv[3]} | {r['rate_fps_per_scene'] or 'max'} | {r['results_per_s']:.1f} | {l['p50_ms']:.2f} | {l['p90_ms']:.2f} | {l['p99_ms']:.2f} | {l['p999_ms']:.2f} | {l['max_ms']:.2f} | {r['frames_lost']} "
      f"| {int(m.get('crossview_record_batches_total', 0))} | {int(m.get('crossview_record_bytes_total', 0))} | {int(m.get('crossview_record_dropped_total', 0))} | {rss} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}

echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%Y-%m-%dT%H:%MZ); $TRANSPORT, $RATE frames/s, $DURATION"
echo "| run | fps | results/s | p50 ms | p90 ms | p99 ms | p99.9 ms | max ms | lost | recorded batches | recorded bytes | dropped | peak RSS KiB | verdict |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
run no-record
rm -rf "$OUT/recording"
# shellcheck disable=SC2086
run record --record "$OUT/recording" $RECORD_ARGS
echo "recording: $(du -sh "$OUT/recording" | cut -f1) in $(find "$OUT/recording" -name '*.jsonl' | wc -l) files under $OUT/recording"

#!/usr/bin/env bash
# Overload rows of BENCHMARKS.md ("Overload"): 64 scenes of the default model over gRPC, fed
# with WILDTRACK validation frames looped (real density), first as fast as the server takes them
# (capacity: associated frames/s), then open loop at 0.8x, 1.25x and 2x that capacity, RUNS runs
# each, a fresh server per run. After each run over capacity, the same server takes 5 s at 0.8x
# whose latency counts from 2 s on: whether it is back on time within 2 s. Release build,
# bounded (every run has --duration).
# Usage: bash bench/overload.sh
# Env: OUT (/var/tmp/cv-overload), PORT (18591), RUNS (3), DURATION (30s), SCENES (64),
#   REC (a recording to replay instead; e.g. the training frames, to choose settings),
#   SERVE_ARGS (extra `crossview serve` flags, e.g. "--max-queue-delay 250ms"),
#   FACTORS ("0.8 1.25 2"), CAPACITY (frames/s per scene: skip measuring it), MODEL
#   (models/wildtrack.onnx; e.g. models/wildtrack-w64.onnx)
set -u
cd "$(dirname "$0")/.." || exit 1
export ORT_DYLIB_PATH=$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1
OUT=${OUT:-/var/tmp/cv-overload}; mkdir -p "$OUT"; PORT=${PORT:-18591}
RUNS=${RUNS:-3}; DURATION=${DURATION:-30s}; SCENES=${SCENES:-64}; FACTORS=${FACTORS:-0.8 1.25 2}
B=target/release/crossview; L=target/release/crossview-loadtest; T=http://127.0.0.1:$PORT
if [[ -z ${REC:-} ]]; then
  REC=$OUT/val.jsonl
  $B import wildtrack-gt --dir ../shared/data/wildtrack/annotations_positions --split val \
    --out "$REC" 2>/dev/null || { echo "no WILDTRACK data in ../shared"; exit 1; }
fi
SCENE=$(head -1 "$REC" | python3 -c 'import json,sys; print(json.load(sys.stdin)["scene"]["name"])')
MODEL=${MODEL:-models/wildtrack.onnx}
MODELS=$(python3 -c "print(','.join(f'$SCENE-{i}=$MODEL' for i in range($SCENES)))")
# Every run sends fresh frame ids (the Unix time in ms x 1000): a wide window lets a second
# run on the same server follow the first without a restart of the ids.
SERVER=
serve() {
  # shellcheck disable=SC2086
  $B serve --listen 127.0.0.1:$PORT --model "$MODELS" --frame-window 100000000000 \
    ${SERVE_ARGS:-} >>"$OUT/server.log" 2>&1 &
  SERVER=$!
}
stop() { [[ -n $SERVER ]] && { kill "$SERVER"; wait "$SERVER" 2>/dev/null; }; SERVER=; }
trap stop EXIT
load() { # NAME RATE DURATION [LOAD-TESTER FLAGS]: one run against the running server
  $L --target "$T" --recording "$REC" --wait-ready 120s --json --server-pid "$SERVER" \
    --transport grpc --rate "$2" --duration "$3" --loop --scenes "$SCENES" --connections 8 \
    --max-in-flight 1000000 "${@:4}" >"$OUT/$1.json" 2>"$OUT/$1.err" || true
}
echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%Y-%m-%dT%H:%MZ)"
if [[ -z ${CAPACITY:-} ]]; then
  for r in $(seq 1 "$RUNS"); do serve; load "capacity-$r" 0 "$DURATION"; stop; done
  CAPACITY=$(python3 bench/overload_summary.py capacity "$OUT" "$SCENES")
fi
echo "capacity: $CAPACITY frames/s per scene ($SCENES scenes)"
for f in $FACTORS; do
  rate=$(python3 -c "print(round($f * $CAPACITY, 2))")
  for r in $(seq 1 "$RUNS"); do
    serve; load "x$f-$r" "$rate" "$DURATION"
    if python3 -c "import sys; sys.exit(0 if $f > 1 else 1)"; then
      load "x$f-$r-after" "$(python3 -c "print(round(0.8 * $CAPACITY, 2))")" 5s \
        --latency-after 2s
    fi
    stop
  done
done
python3 bench/overload_summary.py table "$OUT" "$SCENES" "$CAPACITY" $FACTORS

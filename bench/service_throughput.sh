#!/usr/bin/env bash
# Service throughput rows of BENCHMARKS.md ("Throughput"): one 7-camera scene at 100 frames/s
# and as fast as it goes, and 64 scenes x 10 frames/s, gRPC, width-64 random encoder, a fresh
# server per run (peak RSS sampled by the load tester). Bounded: every run has --duration.
# Usage: bash bench/service_throughput.sh     Env: OUT (/var/tmp/cv-svc), PORT (18391),
#   MODEL (a WILDTRACK model file to serve instead of the random encoder), REC (with MODEL: a
#   WILDTRACK recording to replay instead of the simulated one, e.g. the validation frames from
#   `crossview import wildtrack-gt --split val`: real density)
set -u
cd "$(dirname "$0")/.." || exit 1
export ORT_DYLIB_PATH=$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1
OUT=${OUT:-/var/tmp/cv-svc}; mkdir -p $OUT; PORT=${PORT:-18391}; TARGET=http://127.0.0.1:$PORT
B=target/release/crossview; L=target/release/crossview-loadtest
if [[ -n ${MODEL:-} ]]; then
  # A WILDTRACK model file (MODEL=models/wildtrack.onnx): the same simulated recording with its
  # cameras renamed to the model's (bench/wildtrack_load.sh), served with that file.
  CROSSVIEW_BIN=$B; source bench/wildtrack_load.sh; cp "$MODEL" $OUT/model.onnx
  if [[ -n ${REC:-} ]]; then cp "$REC" $OUT/rec.jsonl; fi
else
  $B simulate --preset wildtrack --frames 600 --seed 11 --out $OUT/rec.jsonl 2>/dev/null
  $B model init --scene-from $OUT/rec.jsonl --out $OUT/model.onnx --width 64 >/dev/null 2>&1
fi
SCENE=$(head -1 $OUT/rec.jsonl | python3 -c 'import json,sys; print(json.load(sys.stdin)["scene"]["name"])')
row() { python3 - "$1" "$2" <<'PY'
import json, sys
r = json.load(open(sys.argv[1])); l = r["latency_complete"]; rss = r.get("server_rss") or {}
print(f"| {sys.argv[2]} | {len(r['scenes'])} | {r['rate_fps_per_scene'] or 'max'} | {r['results_per_s']:.1f} | {l['p50_ms']:.1f} | {l['p99_ms']:.1f} | {l['p999_ms']:.1f} | {r['frames_lost']} | {sum(r['batches_rejected'].values())} | {rss.get('max_kib','-')} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}
run() { local name=$1 models=$2; shift 2
  $B serve --listen 127.0.0.1:$PORT --model "$models" >>$OUT/server.log 2>&1 & local S=$!
  $L --target $TARGET --recording $OUT/rec.jsonl --wait-ready 60s --json --server-pid $S "$@" > $OUT/$name.json 2>$OUT/$name.err || true
  kill $S; wait $S 2>/dev/null
  row $OUT/$name.json $name || tail -3 $OUT/$name.err
}
echo "| run | scenes | fps/scene | results/s | p50 ms | p99 ms | p99.9 ms | lost | rejected | peak RSS KiB | verdict |"
echo "machine: $(nproc) cores, load $(cut -d' ' -f1-3 /proc/loadavg), $(date -u +%H:%M) UTC"
run grpc-1x100 "$SCENE=$OUT/model.onnx" --transport grpc --rate 100 --duration 15s --loop
run grpc-1xmax "$SCENE=$OUT/model.onnx" --transport grpc --rate 0 --duration 15s --loop
M=$(python3 -c "print(','.join(f'$SCENE-{i}=$OUT/model.onnx' for i in range(64)))")
run grpc-64x10 "$M" --transport grpc --rate 10 --duration 20s --loop --scenes 64 --connections 8

#!/usr/bin/env bash
# The identity step's selection and report runs (BENCHMARKS.md, "Identities"): WILDTRACK
# training frames (the selection set) and validation frames (report only) with
# models/wildtrack.onnx, the parameter spread (±50 %), camera subsets, and the simulator's
# square4 presets with models/demo.onnx. Writes markdown tables to $OUT (default /tmp/identity_sweep).
set -euo pipefail
cd "$(dirname "$0")/.."
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
OUT=${OUT:-/tmp/identity_sweep}
mkdir -p "$OUT"
cargo build --release -p crossview -p crossview-bench --bin crossview --bin identity_sweep
B=target/release/crossview
S=target/release/identity_sweep
GT=${WILDTRACK_GT:-../shared/data/wildtrack/annotations_positions}
METHODS="clustering:0.35:0.125 union-find:0.5:0.3"
for split in train val; do
  $B import wildtrack-gt --dir "$GT" --split $split --out "$OUT/$split.jsonl"
  $S models/wildtrack.onnx "$OUT/$split.jsonl" --spread $METHODS > "$OUT/wildtrack_$split.md"
  for cams in 0,1 3,5 0,1,2 2,4,6 0,1,2,3 3,4,5,6; do
    $S models/wildtrack.onnx "$OUT/$split.jsonl" --cameras $cams $METHODS
  done > "$OUT/subsets_$split.md"
done
for people in 1 2 3 default; do
  extra=(); [ "$people" = default ] || extra=(--people "$people")
  $B simulate --preset square4 --frames 300 --seed 3 --clean "${extra[@]}" --out "$OUT/square4_$people.jsonl"
  $S models/demo.onnx "$OUT/square4_$people.jsonl" $METHODS
done > "$OUT/square4.md"
echo "tables in $OUT"

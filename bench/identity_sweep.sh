#!/usr/bin/env bash
# shellcheck disable=SC2086 # METHODS and GRID are lists of settings, split on purpose
# The identity step's selection and report runs (BENCHMARKS.md, "Identities"): the grid over
# t × b × veto share on the WILDTRACK training frames (the selection set) under
# $WILDTRACK_MODEL (default models/wildtrack-w64.onnx, the file the recorded selection used)
# and every model in $ENSEMBLES (the default trainer's outputs, e.g.
# "runs/s1.onnx runs/s2.onnx"), and on the simulator's square4 presets with models/demo.onnx,
# ranked by bench/identity_pick.py; then validation frames (report only) with the parameter
# spread (±50 %) and camera subsets. Writes markdown tables to $OUT (default /tmp/identity_sweep).
set -euo pipefail
cd "$(dirname "$0")/.."
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
OUT=${OUT:-/tmp/identity_sweep}
mkdir -p "$OUT"
cargo build --release -p crossview -p crossview-bench --bin crossview --bin identity_sweep
B=target/release/crossview
S=target/release/identity_sweep
WT=${WILDTRACK_MODEL:-models/wildtrack-w64.onnx}
GT=${WILDTRACK_GT:-../shared/data/wildtrack/annotations_positions}
METHODS="clustering:0.4:0.125:0.5 union-find:0.5:0.3"
GRID=""
for t in 0.25 0.3 0.35 0.4 0.45 0.5 0.55 0.6; do for b in 0 0.0625 0.125 0.25; do
  for v in 0 0.25 0.5 inf; do GRID="$GRID clustering:$t:$b:$v"; done
done; done
for split in train val; do
  $B import wildtrack-gt --dir "$GT" --split $split --out "$OUT/$split.jsonl"
done
names=(wt)
$S "$WT" "$OUT/train.jsonl" $GRID > "$OUT/grid_wt.md"
for m in ${ENSEMBLES:-}; do
  name=$(basename "$m" .onnx); names+=("$name")
  $S "$m" "$OUT/train.jsonl" $GRID > "$OUT/grid_$name.md"
done
for split in train val; do
  $S "$WT" "$OUT/$split.jsonl" --spread $METHODS > "$OUT/wildtrack_$split.md"
  for cams in 0,1 3,5 0,1,2 2,4,6 0,1,2,3 3,4,5,6; do
    $S "$WT" "$OUT/$split.jsonl" --cameras $cams $METHODS
  done > "$OUT/subsets_$split.md"
done
for people in 1 2 3 default; do
  extra=(); [ "$people" = default ] || extra=(--people "$people")
  $B simulate --preset square4 --frames 300 --seed 3 --clean "${extra[@]}" --out "$OUT/square4_$people.jsonl"
  $S models/demo.onnx "$OUT/square4_$people.jsonl" $METHODS
  [ "$people" = default ] || $S models/demo.onnx "$OUT/square4_$people.jsonl" $GRID > "$OUT/grid_sq$people.md"
done > "$OUT/square4.md"
python3 bench/identity_pick.py "$OUT" "${names[@]}" > "$OUT/selection.md"
echo "tables in $OUT (the choice: $OUT/selection.md)"

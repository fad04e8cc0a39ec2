#!/usr/bin/env bash
# shellcheck disable=SC2086 # GRID is a list of settings, split on purpose
# Identities with memory (BENCHMARKS.md, "Identities with memory"): the selection grid over
# λ × hold × link weight × link gate on the WILDTRACK training frames (the selection set) under
# models/wildtrack.onnx and models/wildtrack-w64.onnx, and on the simulator's square4 scenes
# with models/demo.onnx (1, 2, 3 and 12 people at 10 frames/s; groups that form and split at
# 10 and at 2 frames/s), ranked by bench/memory_pick.py; then the chosen setting with each
# parameter at ±50 % on the training and the validation frames (report only). Writes markdown
# tables to $OUT (default /tmp/memory_sweep).
set -euo pipefail
cd "$(dirname "$0")/.."
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
OUT=${OUT:-/tmp/memory_sweep}
mkdir -p "$OUT"
cargo build --release -p crossview -p crossview-bench --bin crossview --bin memory_sweep
B=target/release/crossview
S=target/release/memory_sweep
GT=${WILDTRACK_GT:-../shared/data/wildtrack/annotations_positions}
GRID="0"
for l in 0.6 0.7 0.75 0.8 0.9; do for h in 0.9 inf; do for w in 2 4 8; do for g in 2 3; do
  GRID="$GRID $l:$h:$w:$g:1"
done; done; done; done
for split in train val; do
  $B import wildtrack-gt --dir "$GT" --split $split --out "$OUT/$split.jsonl"
done
for people in 1 2 3 default; do
  extra=(); [ "$people" = default ] || extra=(--people "$people")
  $B simulate --preset square4 --frames 300 --seed 3 --clean "${extra[@]}" --out "$OUT/sq_$people.jsonl"
done
$B simulate --preset square4 --frames 600 --seed 3 --clean --groups 0.6 --out "$OUT/sq_groups.jsonl"
$B simulate --preset square4 --frames 600 --seed 4 --clean --groups 0.6 --fps 2 --out "$OUT/sq_groups2.jsonl"
for s in sq_1 sq_2 sq_3 sq_default sq_groups sq_groups2; do
  $S models/demo.onnx "$OUT/$s.jsonl" $GRID > "$OUT/g_$s.md"
done
$S models/wildtrack.onnx "$OUT/train.jsonl" $GRID > "$OUT/g_wt.md"
$S models/wildtrack-w64.onnx "$OUT/train.jsonl" $GRID > "$OUT/g_w64.md"
python3 bench/memory_pick.py "$OUT" > "$OUT/selection.md"
for m in wildtrack wildtrack-w64; do for split in train val; do
  $S models/$m.onnx "$OUT/$split.jsonl" --spread 0 default > "$OUT/final_${m}_$split.md"
done; done
for s in sq_1 sq_2 sq_3 sq_default sq_groups sq_groups2; do
  $S models/demo.onnx "$OUT/$s.jsonl" 0 default | tail -2
done > "$OUT/final_sim.md"
echo "tables in $OUT (the choice: $OUT/selection.md)"

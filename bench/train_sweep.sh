#!/bin/bash
# Runs several `crossview train` configurations side by side, one core each, with a time
# budget, and keeps their logs and histories (the exploration rows of BENCHMARKS.md).
# usage: BUDGET=450 OUT=sweep/ bench/train_sweep.sh TRAIN.jsonl VAL.jsonl CONFIGS.txt
# CONFIGS.txt lines: name width triplets_per_step max_edges lr fourier_features camera_dim val_every [extra flags...]
# e.g. `h86ns_w64 64 8 16 1e-3 32 32 10 --min-box-height 0.08 --drop-static-iou 0.8 --seed 1`
set -euo pipefail
B=${CROSSVIEW:-target/release/crossview}
BUDGET=${BUDGET:-450}
OUT=${OUT:-sweep}
mkdir -p "$OUT"
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296
i=0
while read -r name w t e lr f c ve extra; do
  [ -z "${name:-}" ] && continue
  taskset -c "$i" "$B" train --data "$1" --val "$2" --out "$OUT/$name.onnx" \
    --epochs 100000 --max-train-seconds "$BUDGET" --val-every "$ve" --triplets-per-step "$t" \
    --max-edges "$e" --width "$w" --lr "$lr" --fourier-features "$f" --camera-dim "$c" \
    --threads 1 --quiet ${extra:-} > "$OUT/$name.log" 2>&1 &
  i=$((i + 1))
done < "$3"
wait

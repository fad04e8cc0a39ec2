#!/usr/bin/env bash
# The unseen-scene figures of BENCHMARKS.md ("One student", MVOR): the default command trained
# on a scene none of our settings were chosen on — MVOR's three operating-room cameras, from
# Self-MVA's detector boxes, no labels — and, from the same seed's population, its student
# (`--export student`); both scored on MVOR's validation frames (SPEC §6's split of its 732
# multi-view frames: train 0-525, val 526-657, test 658-731) at MVOR's reference threshold 0.1
# (SPEC §3). One line per seed and model: pairwise ACC / IPAA-100, then the identities with
# each frame alone and as served (memory on; MVOR's frames are a minute apart, not a video);
# then what `--export auto` would have written (the student run's log compares the two on the
# held-out frames without labels).
#
# Data (not in ../shared; CC BY-NC-SA 4.0): `camma_mvor_2018_v2.json` from MVOR
# (github.com/CAMMA-public/MVOR) and Self-MVA's `data/MVOR/sequence1/output/detections_train.json`
# (github.com/CAMMA-public/Self-MVA, which also carries the annotation file).
#
# Usage: MVOR_DIR=<Self-MVA checkout>/data/MVOR bash bench/unseen_mvor.sh
# Env:   MVOR_DIR (the folder holding camma_mvor_2018_v2.json and sequence1/)  SEEDS (1 2 3 4 5)
#        CROSSVIEW_BIN (target/release/crossview)  OUT (/var/tmp/cv-unseen-mvor)  PART (val)
set -euo pipefail
cd "$(dirname "$0")/.."
B=${CROSSVIEW_BIN:-target/release/crossview}
OUT=${OUT:-/var/tmp/cv-unseen-mvor}
PART=${PART:-val}
: "${MVOR_DIR:?set MVOR_DIR to the folder holding camma_mvor_2018_v2.json and sequence1/}"
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
mkdir -p "$OUT"

"$B" import mvor-gt --file "$MVOR_DIR/camma_mvor_2018_v2.json" --out "$OUT/gt_all.jsonl" 2>/dev/null
"$B" import mvor-detections --file "$MVOR_DIR/sequence1/output/detections_train.json" \
  --out "$OUT/det_all.jsonl" 2>/dev/null
"$B" split --data "$OUT/det_all.jsonl" --part train --out "$OUT/det_train.jsonl"
"$B" split --data "$OUT/gt_all.jsonl" --part "$PART" --out "$OUT/gt_$PART.jsonl"

# ACC / IPAA-100 of the pairwise decision and of the identities (memory 0, then served).
score() {
  local m=$1 line=""
  for memory in 0 0.75; do
    line+=$("$B" eval --model "$m" --data "$OUT/gt_$PART.jsonl" --memory "$memory" 2>/dev/null |
      awk -v mem="$memory" '/^pairwise/ && mem == 0 {printf "pairwise %s / %s  ", $7, $8}
                            /^identities t=/ {printf "identities(memory %s) %s / %s  ", mem, $7, $8}')
  done
  echo "$line"
}

for seed in ${SEEDS:-1 2 3 4 5}; do
  for export in ensemble student; do
    m="$OUT/${export}_s$seed.onnx"
    if [[ ! -f $m ]]; then
      /usr/bin/time -f "%e s wall, %P CPU" "$B" train --data "$OUT/det_train.jsonl" --out "$m" \
        --seed "$seed" --threshold 0.1 --export "$export" > "${m%.onnx}.log" 2>&1
    fi
    echo "seed $seed $export: $(score "$m") [$(tail -1 "${m%.onnx}.log")]"
  done
  # The student run's verdict line compares both on the held-out frames without labels.
  grep -o 'key [0-9.]* % and expected accuracy [0-9.]* % against the ensemble.s [0-9.]* % and [0-9.]* %' \
    "$OUT/student_s$seed.log" | head -1 | sed "s/^/seed $seed held-out, student: /"
done

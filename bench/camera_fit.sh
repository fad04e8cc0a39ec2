#!/usr/bin/env bash
# The camera-fit figures of BENCHMARKS.md ("Camera fit"): `crossview fit-check` (the server's
# looks, offline) on
#   - WILDTRACK validation frames (ground-truth boxes, ids ignored) played 4 times as recorded,
#     then 3 times with one camera panned ±5 % of the width or zoomed 1.1× (bench/move_camera.py),
#     each of the 7 cameras in turn; unmoved 10 times; with a camera 2 frames late;
#   - simulator `square4` scenes, 10 seeds: the seed's camera panned ±5 % or zoomed 1.1× at 60 s
#     (`simulate --move`), and 6 min unmoved (seeds 0-4: a camera 3 frames late from 3 min;
#     5-9: a camera silent for 30 s from 3 min).
# One line per run (bench/camera_fit_summary.py). PART=train uses the training frames instead
# of the validation frames (what the settings were chosen on).
#
# Usage: bash bench/camera_fit.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  OUT (/var/tmp/cv-camera-fit)  PART (val)
#        WILDTRACK (../shared/data/wildtrack)  FIT_ARGS (extra fit-check flags: '--recent 30')
# Then:  python3 bench/camera_fit_replay.py OUT: each setting ±50 % on these looks.
set -euo pipefail
cd "$(dirname "$0")/.."
B=${CROSSVIEW_BIN:-target/release/crossview}
OUT=${OUT:-/var/tmp/cv-camera-fit}
PART=${PART:-val}
WILDTRACK=${WILDTRACK:-../shared/data/wildtrack}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
mkdir -p "$OUT"
S="python3 bench/camera_fit_summary.py"

"$B" import wildtrack-gt --dir "$WILDTRACK/annotations_positions" --split "$PART" --out "$OUT/gt.jsonl" 2>/dev/null
# shellcheck disable=SC2086  # FIT_ARGS: extra fit-check flags, e.g. '--recent 30'
check() { "$B" fit-check --model "$1" --data "$2" --json "${@:3}" ${FIT_ARGS:-} 2>/dev/null > "${2%.jsonl}.json"; }

echo "== WILDTRACK $PART frames, models/wildtrack.onnx (one look per 20 frames = 10 s)"
for cam in CVLab1 CVLab2 CVLab3 CVLab4 IDIAP1 IDIAP2 IDIAP3; do
  for mv in "pan:--pan 0.05" "panl:--pan -0.05" "zoom:--zoom 1.1"; do
    name=${mv%%:*}; args=${mv#*:}
    rec="$OUT/w_${cam}_$name.jsonl"
    # shellcheck disable=SC2086
    t0=$(python3 bench/move_camera.py "$OUT/gt.jsonl" "$rec" "$cam" $args --before 4 --after 3)
    check models/wildtrack.onnx "$rec"
    $S "${rec%.jsonl}.json" "$cam" "$t0" 5 2
  done
done
python3 bench/move_camera.py "$OUT/gt.jsonl" "$OUT/w_still.jsonl" CVLab1 --before 10 --after 0 >/dev/null
check models/wildtrack.onnx "$OUT/w_still.jsonl"; $S "$OUT/w_still.json" - 0 5 2
for cam in CVLab1 IDIAP3; do
  python3 bench/move_camera.py "$OUT/gt.jsonl" "$OUT/w_lag_$cam.jsonl" "$cam" --lag 2 --before 4 --after 3 >/dev/null
  check models/wildtrack.onnx "$OUT/w_lag_$cam.jsonl"; $S "$OUT/w_lag_$cam.json" - 0 5 2
done

echo "== simulator square4, models/demo.onnx (one look per 100 frames = 10 s)"
for seed in 0 1 2 3 4 5 6 7 8 9; do
  cam=cam$((seed % 4))
  for mv in "pan:pan=5%" "panl:pan=-5%" "zoom:zoom=1.1"; do
    name=${mv%%:*}; ch=${mv#*:}
    rec="$OUT/s_${seed}_$name.jsonl"
    "$B" simulate --preset square4 --frames 1200 --seed $((100 + seed)) --move "$cam@60:$ch" --out "$rec" 2>/dev/null
    check models/demo.onnx "$rec" --every 100
    $S "${rec%.jsonl}.json" "$cam" 600 1 10
  done
  rec="$OUT/n_$seed.jsonl"
  "$B" simulate --preset square4 --frames 3600 --seed $((200 + seed)) --out "$rec" 2>/dev/null
  if (( seed < 5 )); then
    python3 - "$rec" "$cam" <<'PY'
import json, sys
path, cam = sys.argv[1], sys.argv[2]
lines = open(path).read().splitlines()
out = [lines[0]]
for l in lines[1:]:
    b = json.loads(l)
    if b["camera"] == cam and b["frame_id"] >= 1800:
        b["frame_id"] += 3
    out.append(json.dumps(b))
open(path, "w").write("\n".join(out) + "\n")
PY
  else
    python3 bench/drop_camera.py "$rec" "$rec.tmp" "$cam" 1800 300 >/dev/null && mv "$rec.tmp" "$rec"
  fi
  check models/demo.onnx "$rec" --every 100
  $S "${rec%.jsonl}.json" - 0 1 10
done

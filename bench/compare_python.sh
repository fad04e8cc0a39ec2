#!/usr/bin/env bash
# Rust pipeline vs the Python reference (bench/python_reference.py) on the same model and the
# same WILDTRACK-sized frames, in one run: frames/s of each and the ratio.
#
# Work per frame, both sides: one ONNX Runtime encoder call over every box (1 intra-op thread,
# 1 inter-op thread by default), then SPEC §3 matching of every camera pair (21 for 7 cameras):
# distances, max-normalisation, Hungarian, threshold. Rust deals the frames to WORKERS threads
# (one encoder session each); IDENTITIES=1 makes it also build the global identities (work the
# reference does not do). The Python reference is one process (its ONNX Runtime session uses
# PY_THREADS intra-op threads). Reading the recording is not timed.
#
# Usage: bench/compare_python.sh [WIDTH ...]      (default widths: 64 768)
# Environment: PEOPLE (95 → ~35 boxes per camera), FRAMES (200), THREADS (1, ORT threads per Rust
#              worker), WORKERS (2), PY_THREADS (1), IDENTITIES (0), REPEAT (3), SEED (11),
#              PYTHON (python3).
set -euo pipefail
cd "$(dirname "$0")/.."

PEOPLE=${PEOPLE:-95}
FRAMES=${FRAMES:-200}
THREADS=${THREADS:-1}
WORKERS=${WORKERS:-2}
PY_THREADS=${PY_THREADS:-1}
IDENTITIES=${IDENTITIES:-0}
REPEAT=${REPEAT:-3}
SEED=${SEED:-11}
PYTHON=${PYTHON:-python3}
WIDTHS=("$@")
[ ${#WIDTHS[@]} -gt 0 ] || WIDTHS=(64 768)

source bench/python_env.sh

cargo build --release --quiet -p crossview -p crossview-bench --bin crossview --bin pipeline
BIN=./target/release/crossview
WORK=.cache/bench-compare
mkdir -p "$WORK"
DATA="$WORK/wildtrack_p${PEOPLE}_f${FRAMES}_s${SEED}.jsonl"
[ -f "$DATA" ] || RUST_LOG=warn "$BIN" simulate --preset wildtrack --people "$PEOPLE" \
  --frames "$FRAMES" --seed "$SEED" --clean --no-ids --out "$DATA"

echo "machine: $(lscpu | sed -n 's/^Model name: *//p') | $(nproc) cores | load $(cut -d' ' -f1-3 /proc/loadavg)"
echo "data: $DATA (wildtrack preset, 7 cameras, $PEOPLE people, $FRAMES frames); rust $WORKERS worker(s) x $THREADS ORT thread(s), identities $IDENTITIES; python $PY_THREADS ORT thread(s); $REPEAT timed passes"
for W in "${WIDTHS[@]}"; do
  MODEL="$WORK/wildtrack_w${W}.onnx"
  if [ ! -f "$MODEL" ]; then
    if [ "$W" = 768 ]; then
      # Random 768-wide embeddings are nearly equidistant: a low stored threshold keeps some
      # matches, so the kept-match cross-check below means something.
      RUST_LOG=warn "$BIN" model init --scene-from "$DATA" --out "$MODEL" --seed 3 --threshold 0.05
    else
      RUST_LOG=warn "$BIN" model init --scene-from "$DATA" --out "$MODEL" --seed 3 \
        --width "$W" --fourier 32 --camera-dim 32
    fi
  fi
  ident=(); [ "$IDENTITIES" = 1 ] && ident=(--identities)
  RUST=$(RUST_LOG=warn ./target/release/pipeline --model "$MODEL" --data "$DATA" \
    --threads "$THREADS" --workers "$WORKERS" "${ident[@]}" \
    --repeat "$REPEAT" --json)
  PY=$("$VENV/bin/python" bench/python_reference.py --model "$MODEL" --data "$DATA" \
    --threads "$PY_THREADS" --repeat "$REPEAT")
  "$VENV/bin/python" - "$W" "$RUST" "$PY" <<'PY'
import json, sys
w, rust, py = sys.argv[1], json.loads(sys.argv[2]), json.loads(sys.argv[3])
r, p = rust["frames_per_second"], py["frames_per_second"]
print(f"width {w:>4}: rust {r:8.1f} frames/s (encoder {100 * rust['encoder_seconds'] / rust['worker_seconds']:.0f}% of busy time, "
      f"{rust['boxes_per_frame']:.1f} boxes, {rust['pairs_per_frame']:.1f} pairs/frame) | "
      f"python {p:8.1f} frames/s | ratio {r / p:5.2f}x | kept matches rust {rust['kept_matches']} python {py['kept_matches']}")
PY
done

#!/usr/bin/env bash
# Offline association end to end vs the Python reference, in one run on one machine (issue 18):
# frames/s of `crossview associate` (whole process: load the model, read the recording, embed,
# match every camera pair, build the identities, write one JSON line per frame) and of
# bench/python_reference.py with --include-reading (every timed pass reads and parses the
# recording, then embeds and matches every camera pair; no identities, nothing written), and
# the ratio.
#
# Data: `crossview simulate --preset wildtrack --people 95 --frames 400 --seed 11 --clean`
# (7 cameras, ~250 boxes per frame); model: a random width-64 encoder (`crossview model init
# --width 64 --fourier 32 --camera-dim 32 --seed 3`, the demo model's architecture).
# Rust: best of REPEAT runs of the process with --workers WORKERS (and, for reference,
# --workers 1; both outputs must be byte-identical). Python: one process, best pass of REPEAT,
# for each ORT intra-op thread count in PY_THREADS; the best of those is the reference.
#
# Usage: bench/associate_vs_python.sh
# Environment: WORKERS (2), REPEAT (5), PY_THREADS ("1 2"), PEOPLE (95), FRAMES (400), SEED (11),
#              PYTHON (python3).
set -euo pipefail
cd "$(dirname "$0")/.."

WORKERS=${WORKERS:-2}
REPEAT=${REPEAT:-5}
PY_THREADS=${PY_THREADS:-"1 2"}
PEOPLE=${PEOPLE:-95}
FRAMES=${FRAMES:-400}
SEED=${SEED:-11}
PYTHON=${PYTHON:-python3}

source bench/python_env.sh

cargo build --release --quiet
BIN=./target/release/crossview
WORK=.cache/bench-associate
mkdir -p "$WORK"
DATA="$WORK/wildtrack_p${PEOPLE}_f${FRAMES}_s${SEED}_clean.jsonl"
MODEL="$WORK/wildtrack_w64.onnx"
[ -f "$DATA" ] || RUST_LOG=warn "$BIN" simulate --preset wildtrack --people "$PEOPLE" \
  --frames "$FRAMES" --seed "$SEED" --clean --out "$DATA"
[ -f "$MODEL" ] || RUST_LOG=warn "$BIN" model init --scene-from "$DATA" --out "$MODEL" \
  --seed 3 --width 64 --fourier 32 --camera-dim 32

# Best wall-clock seconds of REPEAT runs of `crossview associate --workers $1`, and that run's
# own split (loading + reading, then associating + writing) from its log line.
rust_best() {
  local w=$1 best="" best_log="" t0 t1 secs log
  for _ in $(seq "$REPEAT"); do
    t0=$(date +%s%N)
    log=$(RUST_LOG=info "$BIN" --log-format json associate --model "$MODEL" --data "$DATA" \
      --out "$WORK/out_w$w.jsonl" --workers "$w" 2>&1 >/dev/null | grep '"associated"')
    t1=$(date +%s%N)
    secs=$((t1 - t0))
    if [ -z "$best" ] || [ "$secs" -lt "$best" ]; then
      best=$secs
      best_log=$log
    fi
  done
  echo "$("$VENV/bin/python" -c "print($best / 1e9)") $best_log"
}

echo "machine: $(lscpu | sed -n 's/^Model name: *//p') | $(nproc) cores | load $(cut -d' ' -f1-3 /proc/loadavg)"
echo "data: $DATA (7 cameras, $PEOPLE people, $FRAMES frames); model: $MODEL (random, width 64)"
read -r R1 LOG1 <<<"$(rust_best 1)"
read -r RW LOGW <<<"$(rust_best "$WORKERS")"
cmp -s "$WORK/out_w1.jsonl" "$WORK/out_w$WORKERS.jsonl" ||
  { echo "bench: --workers 1 and --workers $WORKERS outputs differ" >&2; exit 1; }
PY_BEST=""
for T in $PY_THREADS; do
  PY=$("$VENV/bin/python" bench/python_reference.py --model "$MODEL" --data "$DATA" \
    --threads "$T" --repeat "$REPEAT" --include-reading)
  PY_BEST="$PY_BEST$PY"$'\n'
done
"$VENV/bin/python" - "$WORKERS" "$R1" "$RW" "$LOG1" "$LOGW" "$PY_BEST" "$WORK/out_w$WORKERS.jsonl" <<'PY'
import json, sys
workers = int(sys.argv[1])
r1, rw = float(sys.argv[2]), float(sys.argv[3])
logs = [json.loads(sys.argv[4])["fields"], json.loads(sys.argv[5])["fields"]]
pys = [json.loads(l) for l in sys.argv[6].splitlines() if l.strip()]
frames = logs[0]["frames"]
for w, secs, log in [(1, r1, logs[0]), (workers, rw, logs[1])]:
    print(f"rust associate --workers {w}: {frames / secs:8.1f} frames/s end to end ({secs:.3f} s; "
          f"in-process: load+read {log['load_read_seconds']:.3f} s, associate+write "
          f"{log['associate_write_seconds']:.3f} s = {frames / log['associate_write_seconds']:.1f} frames/s)")
for p in pys:
    print(f"python reference, {p['threads']} ORT thread(s), reading included: "
          f"{p['best_pass_frames_per_second']:8.1f} frames/s (best of {len(p['pass_seconds'])} passes); "
          f"kept matches {p['kept_matches']}")
with open(sys.argv[7]) as f:
    kept = sum(len(p["matches"]) for line in f for p in json.loads(line)["pairs"])
print(f"kept pairwise matches: rust {kept}, python {pys[0]['kept_matches']}")
best = max(pys, key=lambda p: p["best_pass_frames_per_second"])
ratio = (frames / rw) / best["best_pass_frames_per_second"]
print(f"ratio: rust --workers {workers} / best python ({best['threads']} thread(s)) = {ratio:.2f}x "
      f"(target >= 10x: {'met' if ratio >= 10 else 'not met'})")
PY

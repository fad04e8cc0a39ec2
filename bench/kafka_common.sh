# shellcheck shell=bash
# Shared by bench/kafka_cpu.sh and bench/kafka_scaling.sh (sourced, not run): after the caller
# has set CROSSVIEW_BIN, TANSU, OUT, PRESET, WIDTH and SCENES, it checks for the broker,
# simulates the scene and makes a random-weight model of WIDTH, and defines MODELS (SCENES
# copies of the scene under names SCENE-0, SCENE-1, ...), NAMES, and the process helpers:
# free_port, stop_all (the EXIT trap: every PID in PIDS), cpu_s PID (CPU seconds so far).
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
[[ -x $TANSU ]] || { echo "no tansu at $TANSU (run make setup)" >&2; exit 2; }

mkdir -p "$OUT"
"$CROSSVIEW_BIN" simulate --preset "$PRESET" --frames 600 --seed 11 --out "$OUT/rec.jsonl" 2>/dev/null
"$CROSSVIEW_BIN" model init --scene-from "$OUT/rec.jsonl" --out "$OUT/model.onnx" --width "$WIDTH" >/dev/null 2>&1
SCENE=$(head -1 "$OUT/rec.jsonl" | python3 -c 'import json,sys; print(json.load(sys.stdin)["scene"]["name"])')
# shellcheck disable=SC2153 # SCENES is set by the caller
MODELS=$(for i in $(seq 0 $((SCENES - 1))); do printf '%s-%d=%s,' "$SCENE" "$i" "$OUT/model.onnx"; done)
MODELS=${MODELS%,}
NAMES=$(for i in $(seq 0 $((SCENES - 1))); do printf '%s-%d,' "$SCENE" "$i"; done)
NAMES=${NAMES%,}

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
PIDS=()
stop_all() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  for p in "${PIDS[@]}"; do wait "$p" 2>/dev/null || true; done
  PIDS=()
}
trap stop_all EXIT
# CPU seconds (user + system) a process has used so far.
cpu_s() { awk -v hz="$(getconf CLK_TCK)" '{printf "%.2f", ($14 + $15) / hz}' "/proc/$1/stat" 2>/dev/null || echo 0; }

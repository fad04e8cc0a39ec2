#!/usr/bin/env bash
# Kafka mode takeover figures for BENCHMARKS.md ("Kafka mode"): RUNS runs of
# bench/kafka_takeover.py (8 scenes x 7 cameras at 10 frames/s, each frame's cameras spread
# over 50 ms, two replicas with the shipped settings, one killed with SIGKILL and restarted),
# each against a fresh tansu broker and fresh replicas. Prints one JSON line per run (also in
# $OUT/runN.json): camera batches lost, frames lost, takeover time, survivor max stall,
# duplicates (with producer id / epoch).
#
# Usage: bash bench/kafka_takeover.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  TANSU (.cache/tansu/tansu)
#        OUT (/var/tmp/crossview-kafka-takeover)  RUNS (5)  SECONDS_ (45)  KILL_AT (10)
#        RESTART_AT (25)  REPLICA_ARGS (extra `crossview serve` flags, e.g. "--sync-timeout 1s")
# Needs python3; installs confluent-kafka==2.16.1 (PyPI) into .cache/kafka-venv.
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
TANSU=${TANSU:-.cache/tansu/tansu}
OUT=${OUT:-/var/tmp/crossview-kafka-takeover}
RUNS=${RUNS:-5}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
[[ -x $TANSU ]] || { echo "no tansu at $TANSU (run make setup)" >&2; exit 2; }
VENV=.cache/kafka-venv
if ! "$VENV/bin/python" -c 'import confluent_kafka' 2>/dev/null; then
  "${PYTHON:-python3}" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "confluent-kafka==2.16.1"
fi
for run in $(seq "$RUNS"); do
  "$VENV/bin/python" bench/kafka_takeover.py --crossview "$CROSSVIEW_BIN" --tansu "$TANSU" \
    --out "$OUT" --run "$run" --seconds "${SECONDS_:-45}" --kill-at "${KILL_AT:-10}" \
    --restart-at "${RESTART_AT:-25}" --replica-args "${REPLICA_ARGS:-}"
done

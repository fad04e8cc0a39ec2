#!/usr/bin/env bash
# Kafka mode takeover figures for BENCHMARKS.md ("Kafka mode"): RUNS runs of
# bench/kafka_takeover.py (8 scenes x 7 cameras at 10 frames/s, each frame's cameras spread
# over 50 ms, two replicas with the shipped settings), each against a fresh Apache Kafka broker
# (one node, scripts/kafka/broker.sh, in a temporary folder) and fresh replicas. CASE=kill: one
# replica killed with SIGKILL at KILL_AT and restarted at RESTART_AT; CASE=rolling: a rolling
# restart from KILL_AT on (SIGTERM a replica, start it again once it has exited, wait for its
# /readyz, then the other); CASE=scale: one replica, two more start at KILL_AT and stop
# (SIGTERM) at RESTART_AT; CASE=camera: every scene's last camera stops sending at KILL_AT
# (time to the first partial frame). Prints one JSON line per run (also in $OUT/runN.json): camera
# batches lost, frames lost, takeover time, stalls, duplicates (with producer id / epoch),
# and for CASE=rolling each step's stop, ready and handover times.
#
# Usage: bash bench/kafka_takeover.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  OUT (/var/tmp/crossview-kafka-takeover)
#        RUNS (5)  CASE (kill|rolling|scale|camera)  SECONDS_ (45; rolling: 60)  KILL_AT (10)  RESTART_AT (25)
#        GROUP_PROTOCOL (classic|consumer: the replicas' --kafka-group-protocol; consumer)
#        STATIC=1 (static membership: --kafka-instance-id per replica, kept by its restart)
#        REPLICA_ARGS (extra `crossview serve` flags, e.g. "--sync-timeout 1s")
#        KAFKA_HEAP (the broker's heap, 384m)
# Needs python3 and Java 17+ (the broker: the jars `make setup` puts in .cache/kafka/);
# installs confluent-kafka==2.16.1 (PyPI) into .cache/kafka-venv.
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
OUT=${OUT:-/var/tmp/crossview-kafka-takeover}
RUNS=${RUNS:-5}
CASE=${CASE:-kill}
GROUP_PROTOCOL=${GROUP_PROTOCOL:-consumer}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
case $CASE in
  kill) seconds=${SECONDS_:-45} ;;
  rolling) seconds=${SECONDS_:-60} ;;
  scale|camera) seconds=${SECONDS_:-45} ;;
  *) echo "CASE must be kill, rolling, scale or camera, got '$CASE'" >&2; exit 2 ;;
esac
case $GROUP_PROTOCOL in
  classic|consumer) ;;
  *) echo "GROUP_PROTOCOL must be classic or consumer, got '$GROUP_PROTOCOL'" >&2; exit 2 ;;
esac
kafka_version=$(sed -n 's:.*<kafka.version>\(.*\)</kafka.version>.*:\1:p' scripts/kafka/pom.xml)
[[ -d ${CROSSVIEW_KAFKA_HOME:-.cache/kafka/$kafka_version}/libs ]] \
  || { echo "no Apache Kafka $kafka_version jars in .cache/kafka (run make setup)" >&2; exit 2; }
VENV=.cache/kafka-venv
if ! "$VENV/bin/python" -c 'import confluent_kafka' 2>/dev/null; then
  "${PYTHON:-python3}" -m venv "$VENV"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check "confluent-kafka==2.16.1"
fi
extra=(--case "$CASE" --group-protocol "$GROUP_PROTOCOL")
[[ ${STATIC:-0} == 1 ]] && extra+=(--static-membership)
for run in $(seq "$RUNS"); do
  "$VENV/bin/python" bench/kafka_takeover.py --crossview "$CROSSVIEW_BIN" \
    --broker-sh scripts/kafka/broker.sh "${extra[@]}" \
    --out "$OUT" --run "$run" --seconds "$seconds" --kill-at "${KILL_AT:-10}" \
    --restart-at "${RESTART_AT:-25}" --replica-args "${REPLICA_ARGS:-}"
done

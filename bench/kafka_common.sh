# shellcheck shell=bash
# Shared by bench/kafka_cpu.sh and bench/kafka_scaling.sh (sourced, not run): after the caller
# has set CROSSVIEW_BIN, OUT, PRESET, WIDTH and SCENES, it checks for the broker's jars,
# simulates the scene and makes a random-weight model of WIDTH, and defines MODELS (SCENES
# copies of the scene under names SCENE-0, SCENE-1, ...), NAMES, the broker helpers
# broker_start NAME (a fresh Apache Kafka broker, scripts/kafka/broker.sh, in a temporary
# folder: sets BROKER, its host:port, and BROKER_PID, its JVM) and create_topic NAME PARTITIONS
# (Kafka's TopicCommand), and the process helpers: free_port, stop_all (the EXIT trap: every
# PID in PIDS, then every broker started, whose log is kept as $OUT/NAME.broker.log), cpu_s PID
# (CPU seconds so far).
# Env: KAFKA_HEAP (the broker's heap, 384m) and KAFKA_SET_* pass through to broker.sh.
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
KAFKA_BROKER_SH=scripts/kafka/broker.sh
KAFKA_VERSION=$(sed -n 's:.*<kafka.version>\(.*\)</kafka.version>.*:\1:p' scripts/kafka/pom.xml)
[[ -d ${CROSSVIEW_KAFKA_HOME:-.cache/kafka/$KAFKA_VERSION}/libs ]] \
  || { echo "no Apache Kafka $KAFKA_VERSION jars in .cache/kafka (run make setup)" >&2; exit 2; }

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
BROKER_DIRS=()
BROKER_NAMES=()
broker_start() { # broker_start NAME
  local dir
  dir=$(mktemp -d "${TMPDIR:-/tmp}/crossview-kafka.XXXXXX")
  BROKER_DIRS+=("$dir")
  BROKER_NAMES+=("$1")
  BROKER=$(bash "$KAFKA_BROKER_SH" start "$dir")
  # shellcheck disable=SC2034 # read by the callers
  BROKER_PID=$(cat "$dir/pid")
}
create_topic() { # create_topic NAME PARTITIONS
  bash "$KAFKA_BROKER_SH" tool org.apache.kafka.tools.TopicCommand --bootstrap-server "$BROKER" \
    --create --topic "$1" --partitions "$2" --replication-factor 1 >/dev/null
}
# The replicas first (they commit and leave their group), then the brokers.
stop_all() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null || true; done
  for p in "${PIDS[@]}"; do wait "$p" 2>/dev/null || true; done
  PIDS=()
  local i
  for i in "${!BROKER_DIRS[@]}"; do
    bash "$KAFKA_BROKER_SH" stop "${BROKER_DIRS[$i]}" || true
    cp "${BROKER_DIRS[$i]}/broker.log" "$OUT/${BROKER_NAMES[$i]}.broker.log" 2>/dev/null || true
    rm -rf "${BROKER_DIRS[$i]}"
  done
  BROKER_DIRS=()
  BROKER_NAMES=()
}
trap stop_all EXIT
# CPU seconds (user + system) a process has used so far.
cpu_s() { awk -v hz="$(getconf CLK_TCK)" '{printf "%.2f", ($14 + $15) / hz}' "/proc/$1/stat" 2>/dev/null || echo 0; }

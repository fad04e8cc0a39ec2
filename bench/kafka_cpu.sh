#!/usr/bin/env bash
# CPU per frame of one `crossview serve` replica in Kafka mode beside the gRPC path's, on the
# same scenes at the same rate (BENCHMARKS.md, "Kafka mode"): SCENES scenes of the simulator's
# PRESET at RATE frames/s each for DURATION, driven by `crossview-loadtest` (gRPC pushes and a
# gRPC subscription; or batches produced to a fresh Apache Kafka broker, scripts/kafka/broker.sh,
# and results read from the output topic). The server's CPU time (user + system, /proc/PID/stat) is read just before the
# load starts and just after it ends, so start-up and model loading are left out; CPU per
# frame = that difference / the results the load tester received. The broker's CPU is
# reported apart. Each mode runs ROUNDS times, alternating (kafka, grpc, kafka, grpc, ...).
# The live clock watch is off in both (`--clock-watch-window 0`): it is the same in every
# transport, but its one estimate per scene per 10 s (~0.6 s of CPU each for 7 cameras) falls
# inside a 20 s load window or not by chance (measured: 5.0 of a Kafka run's 9.1 CPU seconds).
#
# Usage: bash bench/kafka_cpu.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  LOADTEST_BIN (target/release/crossview-loadtest)
#        OUT (/var/tmp/crossview-kafka-cpu)  PRESET (wildtrack)
#        WIDTH (64)  SCENES (8)  PARTITIONS (8)  RATE (10)  DURATION (20s)  ROUNDS (3)
#        FORMAT (json|protobuf)  REPLICA_ARGS (extra `crossview serve` flags)
#        KAFKA_HEAP (the broker's heap, 384m)
# The broker: Apache Kafka from the jars `make setup` puts in .cache/kafka/ (needs Java 17+).
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
LOADTEST_BIN=${LOADTEST_BIN:-target/release/crossview-loadtest}
OUT=${OUT:-/var/tmp/crossview-kafka-cpu}
PRESET=${PRESET:-wildtrack}
WIDTH=${WIDTH:-64}
SCENES=${SCENES:-8}
PARTITIONS=${PARTITIONS:-8}
RATE=${RATE:-10}
DURATION=${DURATION:-20s}
ROUNDS=${ROUNDS:-3}
FORMAT=${FORMAT:-json}
# shellcheck source=bench/kafka_common.sh
source bench/kafka_common.sh

run() { # run MODE ROUND
  local mode=$1 name="$1-$2" port; port=$(free_port)
  local extra=() load=() bpid=
  if [[ $mode == kafka ]]; then
    broker_start "$name"
    local broker=$BROKER
    bpid=$BROKER_PID
    create_topic batches "$PARTITIONS"
    create_topic results 4
    extra=(--kafka-brokers "$broker" --kafka-input-topic batches --kafka-output-topic results
           --kafka-group cpu --kafka-input-format "$FORMAT" --kafka-output-format "$FORMAT")
    load=(--transport kafka --kafka-brokers "$broker" --kafka-format "$FORMAT")
  else
    load=(--transport grpc --target "http://127.0.0.1:$port")
  fi
  # shellcheck disable=SC2086
  "$CROSSVIEW_BIN" serve --listen "127.0.0.1:$port" --model "$MODELS" "${extra[@]}" \
    --clock-watch-window 0 ${REPLICA_ARGS:-} \
    >"$OUT/$name.server.log" 2>&1 &
  local spid=$!; PIDS+=("$spid")
  for _ in $(seq 600); do curl -sf "http://127.0.0.1:$port/readyz" >/dev/null && break; sleep 0.1; done
  if [[ $mode == kafka ]]; then # every partition owned
    for _ in $(seq 600); do
      (( $(curl -sf "http://127.0.0.1:$port/metrics" | grep -c '^crossview_kafka_assigned{.* 1$' || true) == PARTITIONS )) && break
      sleep 0.1
    done
  fi
  local c0 b0=0; c0=$(cpu_s "$spid"); [[ -n $bpid ]] && b0=$(cpu_s "$bpid")
  "$LOADTEST_BIN" "${load[@]}" --recording "$OUT/rec.jsonl" --scene-names "$NAMES" \
    --rate "$RATE" --duration "$DURATION" --loop --drain-timeout 10s --json \
    >"$OUT/$name.json" 2>"$OUT/$name.err" || true
  local c1 b1=0; c1=$(cpu_s "$spid"); [[ -n $bpid ]] && b1=$(cpu_s "$bpid")
  stop_all
  python3 - "$OUT/$name.json" "$mode" "$c0" "$c1" "$b0" "$b1" <<'PY'
import json, sys
path, mode, c0, c1, b0, b1 = sys.argv[1], sys.argv[2], *map(float, sys.argv[3:])
r = json.load(open(path))
n = r["results"]
cpu = c1 - c0
broker = f"{(b1 - b0) / n * 1000:.2f}" if mode == "kafka" and n else "–"
print(f"| {mode} | {len(r['scenes'])} | {r['rate_fps_per_scene']} | {n} | {r['frames_lost']} "
      f"| {cpu:.2f} | **{cpu / max(n, 1) * 1000:.2f}** | {broker} | {r['latency_complete']['p50_ms']:.1f} |")
PY
}

echo "| path | scenes | fps/scene | results | lost | server CPU s | server CPU ms/frame | broker CPU ms/frame | p50 ms |"
echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
for round in $(seq "$ROUNDS"); do
  run kafka "$round"
  run grpc "$round"
done

#!/usr/bin/env bash
# Kafka mode scaling figure for BENCHMARKS.md: 16 scenes of 7 cameras through an Apache Kafka
# broker (one node, scripts/kafka/broker.sh) with 1 and 2 `crossview serve` replicas in one
# consumer group, driven by `crossview-loadtest --transport kafka`. Every run gets a fresh
# broker and fresh replicas; it waits until the group has assigned every input partition,
# then runs the load tester and reads the peak RSS (VmHWM) and the CPU time used (user +
# system, from start-up to the end of the run) of the broker and each replica (the broker's
# includes its JVM's start and the topics' creation).
# "skipped by live read": results the load tester's live consumer never got although they are
# in the output topic (it re-reads the topic after the run); the earlier test broker (tansu
# 0.6.0) did this now and then with two producers on one partition (BENCHMARKS.md, "Kafka
# mode"); Apache Kafka should show 0.
# Writes one JSON report per run into $OUT and prints a markdown table. Bounded: every run
# has --duration.
#
# Usage: bash bench/kafka_scaling.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  LOADTEST_BIN (target/release/crossview-loadtest)
#        OUT (/var/tmp/crossview-kafka-bench)  PRESET (wildtrack)
#        WIDTH (64)  SCENES (16)  PARTITIONS (8)  REPLICAS ("1 2")  RATES ("10 0": 0 = as fast
#        as the load tester's window allows)  DURATION (20s)  FORMAT (json|protobuf)
#        REPLICA_ARGS (extra `crossview serve` flags, e.g. "--kafka-property fetch.wait.max.ms=50")
#        KAFKA_HEAP (the broker's heap, 384m)
# The broker: Apache Kafka from the jars `make setup` puts in .cache/kafka/ (needs Java 17+).
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
LOADTEST_BIN=${LOADTEST_BIN:-target/release/crossview-loadtest}
OUT=${OUT:-/var/tmp/crossview-kafka-bench}
PRESET=${PRESET:-wildtrack}
WIDTH=${WIDTH:-64}
SCENES=${SCENES:-16}
PARTITIONS=${PARTITIONS:-8}
REPLICAS=${REPLICAS:-1 2}
RATES=${RATES:-10 0}
DURATION=${DURATION:-20s}
FORMAT=${FORMAT:-json}
# shellcheck source=bench/kafka_common.sh
source bench/kafka_common.sh
peak_kib() { awk '/VmHWM/ {print $2}' "/proc/$1/status" 2>/dev/null || echo 0; }

run() { # run REPLICAS RATE
  local n=$1 rate=$2
  local name="kafka-${n}r-$2"
  broker_start "$name"
  local broker=$BROKER bpid=$BROKER_PID
  create_topic batches "$PARTITIONS"
  create_topic results 4
  local rpids=() ports=() i
  for i in $(seq "$n"); do
    local port; port=$(free_port); ports+=("$port")
    "$CROSSVIEW_BIN" serve --listen "127.0.0.1:$port" --model "$MODELS" \
      --kafka-brokers "$broker" --kafka-input-topic batches --kafka-output-topic results \
      --kafka-group bench --kafka-producer-id "r$i" --kafka-input-format "$FORMAT" ${REPLICA_ARGS:-} \
      >"$OUT/$name.replica$i.log" 2>&1 &
    rpids+=($!); PIDS+=($!)
  done
  # Ready, and every input partition owned by some replica.
  local t0=$SECONDS owned=0
  while (( SECONDS - t0 < 60 )); do
    owned=0
    for port in "${ports[@]}"; do
      local m; m=$(curl -sf "http://127.0.0.1:$port/metrics" || true)
      owned=$(( owned + $(grep -c '^crossview_kafka_assigned{.* 1$' <<<"$m" || true) ))
    done
    (( owned == PARTITIONS )) && break
    sleep 0.5
  done
  (( owned == PARTITIONS )) || { echo "| $name | group did not settle ($owned of $PARTITIONS partitions owned) |"; stop_all; return; }
  "$LOADTEST_BIN" --transport kafka --kafka-brokers "$broker" --kafka-format "$FORMAT" \
    --recording "$OUT/rec.jsonl" --scene-names "$NAMES" --rate "$rate" --duration "$DURATION" --loop \
    --window 4 --drain-timeout 15s --json >"$OUT/$name.json" 2>"$OUT/$name.err" || true
  local rss
  rss="broker $(( $(peak_kib "$bpid") / 1024 )) MB / $(cpu_s "$bpid") s"
  for i in "${!rpids[@]}"; do rss+=", r$((i + 1)) $(( $(peak_kib "${rpids[$i]}") / 1024 )) MB / $(cpu_s "${rpids[$i]}") s"; done
  stop_all
  python3 - "$OUT/$name.json" "$n" "$rss" <<'PY'
import json, sys
path, n, rss = sys.argv[1], sys.argv[2], sys.argv[3]
try:
    r = json.load(open(path))
except Exception as e:
    print(f"| {n} | failed: {e} |"); sys.exit(0)
l = r["latency_complete"]
rate = r["rate_fps_per_scene"] or "max"
print(f"| {n} | {len(r['scenes'])} | {rate} | {r['offered_batches_per_s']:.0f} | {r['results_per_s']:.1f} "
      f"| {l['p50_ms']:.1f} | {l['p90_ms']:.1f} | {l['p99_ms']:.1f} | {l['p999_ms']:.1f} "
      f"| {r['frames_lost']} | {r.get('results_missed_live', 0)} | {r['duplicate_results']} | {rss} | {'PASS' if r['passed'] else 'FAIL'} |")
PY
}

echo "| replicas | scenes | fps/scene | batches/s offered | results/s | p50 ms | p90 ms | p99 ms | p99.9 ms | lost | skipped by live read | duplicates | peak RSS / CPU time | verdict |"
echo "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"
for rate in $RATES; do
  for n in $REPLICAS; do
    run "$n" "$rate"
  done
done

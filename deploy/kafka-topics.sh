#!/bin/bash
# The compose kafka profile's one-shot topic job: waits for the tansu broker, then creates each
# NAME:PARTITIONS topic that does not exist yet (an existing topic is kept as it is, whatever its
# partition count), and exits 0. Idempotent. Runs in the tansu image (deploy/Dockerfile.tansu).
#   Usage: crossview-kafka-topics NAME:PARTITIONS...
#   Env:   KAFKA_BROKER_URL [tcp://broker:9092]  KAFKA_WAIT_S [120] (how long to wait for it)
set -euo pipefail
broker=${KAFKA_BROKER_URL:-tcp://broker:9092}
wait_s=${KAFKA_WAIT_S:-120}
(( $# > 0 )) || { echo "usage: crossview-kafka-topics NAME:PARTITIONS..." >&2; exit 2; }
deadline=$((SECONDS + wait_s))
# `tansu topic list` prints the topics as one line of JSON once the broker answers.
until existing=$(tansu topic list --broker "$broker" 2>/dev/null); do
  if (( SECONDS >= deadline )); then
    echo "kafka-topics: no broker answered at $broker within ${wait_s}s" >&2
    exit 1
  fi
  sleep 1
done
for spec in "$@"; do
  name=${spec%%:*}
  partitions=${spec#*:}
  if [[ -z $name || ! $partitions =~ ^[1-9][0-9]*$ ]]; then
    echo "kafka-topics: bad topic spec '$spec' (want NAME:PARTITIONS)" >&2
    exit 2
  fi
  if grep -qF "\"name\":\"$name\"" <<<"$existing"; then
    echo "kafka-topics: $name exists, kept"
  else
    tansu topic create "$name" --partitions "$partitions" --broker "$broker"
    echo "kafka-topics: created $name, partitions=$partitions"
  fi
done

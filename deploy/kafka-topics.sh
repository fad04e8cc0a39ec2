#!/bin/bash
# The compose kafka profile's one-shot topic job: waits for the broker, then creates each
# NAME:PARTITIONS topic that does not exist yet (an existing topic is kept as it is, whatever its
# partition count), and exits 0. Idempotent. Runs in the broker's image (deploy/Dockerfile.kafka)
# with Apache Kafka's own TopicCommand (what kafka-topics.sh runs).
#   Usage: crossview-kafka-topics NAME:PARTITIONS...
#   Env:   KAFKA_BOOTSTRAP_SERVERS [broker:9092]  KAFKA_WAIT_S [120] (how long to wait for it)
#          KAFKA_REPLICATION_FACTOR [1]  KAFKA_HOME [/opt/kafka] (libs/, config/log4j2.properties)
set -euo pipefail
bootstrap=${KAFKA_BOOTSTRAP_SERVERS:-broker:9092}
wait_s=${KAFKA_WAIT_S:-120}
replication=${KAFKA_REPLICATION_FACTOR:-1}
home=${KAFKA_HOME:-/opt/kafka}
java=${JAVA_HOME:+$JAVA_HOME/bin/}java
(( $# > 0 )) || { echo "usage: crossview-kafka-topics NAME:PARTITIONS..." >&2; exit 2; }
for spec in "$@"; do
  name=${spec%%:*}
  partitions=${spec#*:}
  if [[ -z $name || ! $partitions =~ ^[1-9][0-9]*$ ]]; then
    echo "kafka-topics: bad topic spec '$spec' (want NAME:PARTITIONS)" >&2
    exit 2
  fi
done

# Each admin call gives up after 10 s (the client's default is a minute), so the wait below
# tries again soon after the broker appears.
config=$(mktemp)
trap 'rm -f "$config"' EXIT
printf 'request.timeout.ms=5000\ndefault.api.timeout.ms=10000\n' >"$config"
topic_command() {
  timeout 60 "$java" -Xmx256m -XX:+UseSerialGC -XX:TieredStopAtLevel=1 \
    -Dlog4j2.configurationFile="$home/config/log4j2.properties" -cp "$home/libs/*" \
    org.apache.kafka.tools.TopicCommand --bootstrap-server "$bootstrap" \
    --command-config "$config" "$@"
}

deadline=$((SECONDS + wait_s))
until existing=$(topic_command --list 2>/dev/null); do
  if (( SECONDS >= deadline )); then
    echo "kafka-topics: no broker answered at $bootstrap within ${wait_s}s" >&2
    exit 1
  fi
  sleep 2
done
for spec in "$@"; do
  name=${spec%%:*}
  partitions=${spec#*:}
  if grep -qxF -- "$name" <<<"$existing"; then
    echo "kafka-topics: $name exists, kept"
  else
    topic_command --create --if-not-exists --topic "$name" --partitions "$partitions" \
      --replication-factor "$replication" >/dev/null
    echo "kafka-topics: created $name, partitions=$partitions, replication factor $replication"
  fi
done

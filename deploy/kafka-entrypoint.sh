#!/bin/bash
# The entrypoint of deploy/Dockerfile.kafka (the compose `kafka` profile's broker): a
# single-node Apache Kafka broker in KRaft mode, broker and controller in one process, as
# scripts/kafka/broker.sh runs it for the tests, but listening on every interface and
# advertising the service's name. Formats the storage on the first start (a container restart
# keeps it), writes server.properties anew on every start, then execs the JVM (PID 1: SIGTERM
# is a controlled shutdown).
#
# Env (defaults in brackets):
#   KAFKA_ADVERTISED_HOST [broker]  the name clients reach it by (they connect to whatever the
#                                   metadata says: change it with the service's name)
#   KAFKA_PORT [9092]               client listener (PLAINTEXT, every interface)
#   KAFKA_CONTROLLER_PORT [9093]    controller listener (loopback only: one node)
#   KAFKA_DATA_DIR [/var/lib/kafka/data]  KAFKA_CLUSTER_ID [random, at format time]
#   KAFKA_HEAP_OPTS [-Xmx512m -Xms512m]  KAFKA_JVM_OPTS [G1, as Kafka's start script]
#   KAFKA_HOME [/opt/kafka]         libs/ (the jars) and config/log4j2.properties
#   KAFKA_SET_<name, dots as __>    any further broker setting, e.g.
#                                   KAFKA_SET_log__retention__hours=24
set -euo pipefail
home=${KAFKA_HOME:-/opt/kafka}
data=${KAFKA_DATA_DIR:-/var/lib/kafka/data}
conf=$(dirname "$data")/server.properties
host=${KAFKA_ADVERTISED_HOST:-broker}
port=${KAFKA_PORT:-9092}
cport=${KAFKA_CONTROLLER_PORT:-9093}
java=${JAVA_HOME:+$JAVA_HOME/bin/}java
cp="$home/libs/*"
log4j=-Dlog4j2.configurationFile=$home/config/log4j2.properties
read -ra heap <<<"${KAFKA_HEAP_OPTS:--Xmx512m -Xms512m}"
read -ra jvm <<<"${KAFKA_JVM_OPTS:--XX:+UseG1GC -XX:MaxGCPauseMillis=20 -XX:InitiatingHeapOccupancyPercent=35 -XX:+ExplicitGCInvokesConcurrent -Djava.awt.headless=true}"

mkdir -p "$data"
cat >"$conf" <<PROPS
process.roles=broker,controller
node.id=1
controller.quorum.voters=1@127.0.0.1:$cport
listeners=PLAINTEXT://0.0.0.0:$port,CONTROLLER://127.0.0.1:$cport
advertised.listeners=PLAINTEXT://$host:$port
controller.listener.names=CONTROLLER
inter.broker.listener.name=PLAINTEXT
listener.security.protocol.map=PLAINTEXT:PLAINTEXT,CONTROLLER:PLAINTEXT
log.dirs=$data
num.partitions=1
# One node: every internal topic at replication 1.
offsets.topic.replication.factor=1
transaction.state.log.replication.factor=1
transaction.state.log.min.isr=1
share.coordinator.state.topic.replication.factor=1
share.coordinator.state.topic.min.isr=1
# The first assignment at once rather than 3 s after the first member joins.
group.initial.rebalance.delay.ms=0
# The KIP-848 (consumer) group protocol with crossview's classic-protocol settings: a dead
# replica noticed after 6 s, heartbeats every 500 ms (Kafka's defaults: 45 s and 5 s).
group.consumer.min.session.timeout.ms=6000
group.consumer.session.timeout.ms=6000
group.consumer.min.heartbeat.interval.ms=500
group.consumer.heartbeat.interval.ms=500
# Topics are made by the topic job (crossview-kafka-topics), with their partition counts.
auto.create.topics.enable=false
PROPS
for var in $(compgen -e | grep '^KAFKA_SET_' || true); do
  name=${var#KAFKA_SET_}
  echo "${name//__/.}=${!var}" >>"$conf"
done

if [[ ! -f $data/meta.properties ]]; then
  id=${KAFKA_CLUSTER_ID:-$("$java" -Xmx128m "$log4j" -cp "$cp" kafka.tools.StorageTool random-uuid)}
  echo "kafka: formatting $data (cluster id $id)"
  "$java" -Xmx128m "$log4j" -cp "$cp" kafka.tools.StorageTool format --ignore-formatted \
    -t "$id" -c "$conf"
fi
echo "kafka: node 1 (broker + controller) on 0.0.0.0:$port, advertised as $host:$port"
exec "$java" "${heap[@]}" "${jvm[@]}" "$log4j" -cp "$cp" kafka.Kafka "$conf"

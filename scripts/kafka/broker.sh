#!/usr/bin/env bash
# A single-node Apache Kafka broker (KRaft, combined broker + controller) for the project's tests,
# benchmarks and load tests, from the jars `make setup` resolved into .cache/kafka/ (pom.xml
# beside this script). Internal topics at replication 1; group timeouts lowered so that tests
# may use short sessions with both group protocols (classic and KIP-848 `consumer`).
#
#   broker.sh run DIR [PORT] [--parent PID]  format DIR if new, run the broker in the foreground on
#                                            127.0.0.1:PORT (0 or none: a free port; DIR run
#                                            before keeps its data and controller port); with
#                                            --parent, stop when process PID is gone
#   broker.sh start DIR [PORT]               the same in the background; waits until it is ready
#                                            and prints its bootstrap address (host:port)
#   broker.sh stop DIR                       stops a broker started on DIR (SIGTERM, then SIGKILL)
#   broker.sh tool CLASS ARGS...             a Kafka tool (e.g. org.apache.kafka.tools.TopicCommand)
#
# DIR holds server.properties, data/, broker.log, the address (addr) and the pid (pid).
# Env: CROSSVIEW_KAFKA_HOME (the libs/ folder's parent; default .cache/kafka/<version>),
# KAFKA_HEAP (default 384m), KAFKA_READY_S (default 90), and every broker setting as
# KAFKA_SET_<name with dots as __> (e.g. KAFKA_SET_group__consumer__session__timeout__ms=6000).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
version=$(sed -n 's:.*<kafka.version>\(.*\)</kafka.version>.*:\1:p' "$here/pom.xml")
home=${CROSSVIEW_KAFKA_HOME:-$root/.cache/kafka/$version}
java=${JAVA_HOME:+$JAVA_HOME/bin/}java

die() { echo "kafka broker: $*" >&2; exit 1; }
[[ -d $home/libs ]] || die "no jars in $home/libs (run \`make setup\`)"
cp="$home/libs/*"

free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

# Writes DIR/server.properties for PORT (and a controller port of its own), formats DIR/data once.
configure() {
  local dir=$1 port=$2 cport
  # A restart on the same folder keeps its controller port (the quorum's address).
  cport=$(sed -n 's/^controller.quorum.voters=1@127.0.0.1:\([0-9]*\)$/\1/p' "$dir/server.properties" 2>/dev/null || true)
  [[ -n $cport ]] || cport=$(free_port)
  mkdir -p "$dir/data"
  cat > "$dir/server.properties" <<PROPS
process.roles=broker,controller
node.id=1
controller.quorum.voters=1@127.0.0.1:$cport
listeners=PLAINTEXT://127.0.0.1:$port,CONTROLLER://127.0.0.1:$cport
advertised.listeners=PLAINTEXT://127.0.0.1:$port
controller.listener.names=CONTROLLER
inter.broker.listener.name=PLAINTEXT
listener.security.protocol.map=PLAINTEXT:PLAINTEXT,CONTROLLER:PLAINTEXT
log.dirs=$dir/data
num.partitions=1
offsets.topic.replication.factor=1
offsets.topic.num.partitions=4
transaction.state.log.replication.factor=1
transaction.state.log.min.isr=1
transaction.state.log.num.partitions=4
share.coordinator.state.topic.replication.factor=1
share.coordinator.state.topic.min.isr=1
group.initial.rebalance.delay.ms=0
# Short sessions allowed for tests, with both protocols (a user's cluster keeps its own).
group.min.session.timeout.ms=500
group.consumer.min.session.timeout.ms=1000
group.consumer.min.heartbeat.interval.ms=100
group.consumer.session.timeout.ms=6000
group.consumer.heartbeat.interval.ms=500
log.flush.interval.messages=9223372036854775807
auto.create.topics.enable=false
PROPS
  local var name
  for var in $(compgen -e | grep '^KAFKA_SET_' || true); do
    name=${var#KAFKA_SET_}; name=${name//__/.}
    echo "$name=${!var}" >> "$dir/server.properties"
  done
  if [[ ! -f $dir/data/meta.properties ]]; then
    "$java" -Xmx128m -cp "$cp" -Dlog4j2.configurationFile="$here/log4j2.properties" \
      kafka.tools.StorageTool format --ignore-formatted \
      -t "$(uuid)" -c "$dir/server.properties" > "$dir/format.log" 2>&1 \
      || { cat "$dir/format.log" >&2; die "formatting $dir/data failed"; }
  fi
}

# A cluster id: a base64url UUID, never one starting with "-" (the tool would take it for a flag).
uuid() {
  python3 -c '
import base64, uuid
while True:
    s = base64.urlsafe_b64encode(uuid.uuid4().bytes).decode().rstrip("=")
    if not s.startswith("-"):
        print(s)
        break'
}

run() {
  local dir=$1 port=${2:-0} parent=
  shift $(( $# >= 2 ? 2 : 1 ))
  [[ ${1:-} == --parent ]] && parent=$2
  [[ $port == 0 ]] && port=$(free_port)
  dir=$(mkdir -p "$dir" && cd "$dir" && pwd)
  configure "$dir" "$port"
  echo "127.0.0.1:$port" > "$dir/addr"
  "$java" -Xmx"${KAFKA_HEAP:-384m}" -Xms64m -XX:+UseSerialGC -XX:TieredStopAtLevel=1 \
    -Djava.awt.headless=true -Dlog4j2.configurationFile="$here/log4j2.properties" \
    -Dkafka.logs.dir="$dir" -cp "$cp" kafka.Kafka "$dir/server.properties" \
    > "$dir/broker.log" 2>&1 &
  jpid=$!
  echo "$jpid" > "$dir/pid"
  trap 'kill "$jpid" 2>/dev/null; wait "$jpid" 2>/dev/null; exit 0' TERM INT
  trap 'kill -9 "$jpid" 2>/dev/null || true' EXIT
  if [[ -n $parent ]]; then
    while kill -0 "$jpid" 2>/dev/null && kill -0 "$parent" 2>/dev/null; do sleep 0.5; done
    kill "$jpid" 2>/dev/null || true
  fi
  wait "$jpid"
}

# Ready: the broker says it started and the port accepts connections.
ready() {
  local dir=$1 deadline=$((SECONDS + ${KAFKA_READY_S:-90}))
  until grep -q 'Kafka Server started' "$dir/broker.log" 2>/dev/null; do
    kill -0 "$(cat "$dir/pid" 2>/dev/null || echo 0)" 2>/dev/null \
      || { tail -20 "$dir/broker.log" >&2 || true; die "broker on $dir exited"; }
    (( SECONDS < deadline )) || die "broker on $dir not ready in ${KAFKA_READY_S:-90}s"
    sleep 0.2
  done
}

cmd=${1:-}; shift || true
case $cmd in
  run) run "$@" ;;
  start)
    dir=$(mkdir -p "$1" && cd "$1" && pwd)
    rm -f "$dir/pid" "$dir/broker.log"
    setsid "$0" run "$dir" "${2:-0}" < /dev/null > "$dir/run.log" 2>&1 &
    echo $! > "$dir/runner.pid"
    until [[ -s $dir/pid ]]; do
      kill -0 "$(cat "$dir/runner.pid")" 2>/dev/null || { cat "$dir/run.log" >&2; die "broker on $dir did not start"; }
      sleep 0.1
    done
    ready "$dir"
    cat "$dir/addr" ;;
  stop)
    dir=$1
    [[ -f $dir/pid ]] || exit 0
    pid=$(cat "$dir/pid")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
    rm -f "$dir/pid" ;;
  tool)
    class=$1; shift
    exec "$java" -Xmx256m -XX:+UseSerialGC -XX:TieredStopAtLevel=1 \
      -Dlog4j2.configurationFile="$here/log4j2.properties" -cp "$cp" "$class" "$@" ;;
  *) sed -n '2,20p' "$0" >&2; exit 2 ;;
esac

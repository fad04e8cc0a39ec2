# shellcheck shell=bash
# Sourced by deploy/smoke.sh (step 6 there): the compose `kafka` profile run for real. Uses
# smoke.sh's COMPOSE, PROJECT, IMAGE, WORK, log/pass/fail/build and the KAFKA_* settings.

# The sum of a metric's series on a replica's published port (0 when absent or unreachable).
kafka_metric_sum() { # kafka_metric_sum PORT NAME
  { curl -fsS -m 5 "http://127.0.0.1:$1/metrics" 2>/dev/null || true; } \
    | awk -v n="$2" 'index($0, n "{") == 1 || index($0, n " ") == 1 { v += $NF } END { printf "%d\n", v + 0 }'
}

# Input partitions owned by the two replicas together.
kafka_owned() {
  local a b
  a=$(kafka_metric_sum "$CROSSVIEW_REPLICA_A_PORT" crossview_kafka_assigned)
  b=$(kafka_metric_sum "$CROSSVIEW_REPLICA_B_PORT" crossview_kafka_assigned)
  echo "$((a + b)) $a $b"
}


# The input partitions a replica owns now (from its /metrics), space-separated.
kafka_partitions() { # kafka_partitions PORT
  { curl -fsS -m 5 "http://127.0.0.1:$1/metrics" 2>/dev/null || true; } \
    | sed -n 's/^crossview_kafka_assigned{.*partition="\([0-9]*\)".*} 1$/\1/p' | tr '\n' ' '
}

# Scenes of SCENES (comma-separated) that replica-b started on a partition outside OWNED (what
# it owned before the kill), from its JSON log LOG: the killed replica's scenes it took over.
kafka_taken_over() { # kafka_taken_over LOG SCENES OWNED
  python3 - "$@" <<'PY'
import json, sys
log, scenes, owned = sys.argv[1], set(sys.argv[2].split(",")), set(sys.argv[3].split())
taken = set()
for line in open(log, errors="replace"):
    try:
        r = json.loads(line[line.index("{"):])
    except ValueError:
        continue
    f = r.get("fields", r)
    if (f.get("message") == "kafka: scene (re)starts here" and f.get("scene") in scenes
            and str(f.get("partition")) not in owned):
        taken.add(f["scene"])
print(",".join(sorted(taken)))
PY
}

# Waits until the replicas own every input partition between them; echoes "total a b".
kafka_wait_owned() {
  local owned
  for _ in $(seq 1 90); do
    owned=$(kafka_owned)
    [[ ${owned%% *} -eq $KAFKA_PARTITIONS ]] && break
    sleep 1
  done
  echo "$owned"
}


# podman-compose --profile kafka up -d ARGS, its output added to compose-up-kafka.log.
kafka_up() {
  "${COMPOSE[@]}" --profile kafka up -d "$@" >>"$WORK/logs/compose-up-kafka.log" 2>&1 \
    || { tail -n 30 "$WORK/logs/compose-up-kafka.log" >&2; fail "podman-compose --profile kafka up -d $*"; }
}

kafka_profile() {
  log "kafka profile: Apache Kafka broker, topic job, two replicas in one group, the replay client"
  # The broker's jars (.cache/kafka/VERSION/libs, the version pinned in scripts/kafka/pom.xml
  # and in Dockerfile.kafka's KAFKA_VERSION) come from `make setup`.
  local version
  version=$(sed -n 's:.*<kafka.version>\(.*\)</kafka.version>.*:\1:p' scripts/kafka/pom.xml)
  [[ -d .cache/kafka/$version/libs ]] || bash scripts/setup.sh
  [[ -d .cache/kafka/$version/libs ]] || fail "no Apache Kafka $version jars in .cache/kafka (scripts/setup.sh)"
  build kafka -f deploy/Dockerfile.kafka --build-arg "KAFKA_VERSION=$version" -t localhost/crossview-kafka:local .
  "${COMPOSE[@]}" down -t 5 >/dev/null 2>&1 || true # the default profile's services
  # In stages, each with --no-deps: podman 4.3 turns depends_on into --requires and then
  # cannot start a container whose requirement is the exited one-shot topic job ("depends on
  # container ... not found in input list"), and it has no healthy/completed conditions.
: >"$WORK/logs/compose-up-kafka.log"
  kafka_up broker kafka-topics
  wait_job "${PROJECT}_kafka-topics_1" kafka-topics 180
  pass "broker up, topic job created the topics (exit code 0)"
  kafka_up --no-deps replica-a replica-b
  wait_readyz "$CROSSVIEW_REPLICA_A_PORT" replica-a
  wait_readyz "$CROSSVIEW_REPLICA_B_PORT" replica-b
  pass "replica-a and replica-b ready (/readyz: consumer group joined)"
  CROSSVIEW_REPLAY_SCENES=$KAFKA_SCENES_BEFORE kafka_up --no-deps kafka-replay

  log "waiting for the profile's replay client (Kafka, $KAFKA_SCENES_BEFORE)"
  local owned net restarts
  wait_job "${PROJECT}_kafka-replay_1" kafka-replay 240
  check_report "$WORK/logs/kafka-replay.out" "kafka replay before the kill"
  pass "kafka-replay (compose service): every frame of $KAFKA_SCENES_BEFORE has a result on 'results'"
  owned=$(kafka_wait_owned)
  [[ ${owned%% *} -eq $KAFKA_PARTITIONS ]] || fail "the replicas own ${owned%% *} of $KAFKA_PARTITIONS input partitions"
  read -r _ a b <<<"$owned"
  pass "the replicas own all $KAFKA_PARTITIONS input partitions between them (replica-a $a, replica-b $b)"

  log "SIGKILL replica-a through the engine, replay new scenes during the takeover"
  local b_owned taken
  b_owned=$(kafka_partitions "$CROSSVIEW_REPLICA_B_PORT")
  podman kill -s KILL "${PROJECT}_replica-a_1" >/dev/null || fail "podman kill -s KILL replica-a"
  pass "replica-a SIGKILLed (podman kill -s KILL)"
  net=$(podman inspect -f '{{range $k, $v := .NetworkSettings.Networks}}{{$k}} {{end}}' "${PROJECT}_replica-b_1" | awk '{print $1}')
  [[ -n $net ]] || fail "no network of ${PROJECT}_replica-b_1"
  # Results of replica-a's partitions come once replica-b has taken them over (about 1.5 × the
  # 6 s session, docs/kafka.md) or replica-a is back: a drain timeout well above that.
  podman run --rm --network "$net" -v "$WORK/run/data:/data:ro" --entrypoint crossview-replay "$IMAGE" \
    --transport=kafka --kafka-brokers=broker:9092 --allow-host=broker,replica-b \
    --target=http://replica-b:8080 --wait-ready=90s --recording /data/replay.jsonl \
    --scene-names "$KAFKA_SCENES_AFTER" --rate "$CROSSVIEW_REPLAY_RATE" \
    --frames "$CROSSVIEW_REPLAY_FRAMES" --drain-timeout 60s --json \
    >"$WORK/logs/kafka-replay-after.json" 2>"$WORK/logs/kafka-replay-after.stderr" \
    || { tail -n 40 "$WORK/logs/kafka-replay-after.json" "$WORK/logs/kafka-replay-after.stderr" >&2; fail "kafka replay during the takeover"; }
  check_report "$WORK/logs/kafka-replay-after.json" "kafka replay during the takeover"
  pass "every frame of $KAFKA_SCENES_AFTER, replayed from a second container after the kill, has a result"
  podman logs "${PROJECT}_replica-b_1" >"$WORK/logs/replica-b.log" 2>&1 || true
  taken=$(kafka_taken_over "$WORK/logs/replica-b.log" "$KAFKA_SCENES_AFTER" "$b_owned")
  [[ -n $taken ]] || fail "none of $KAFKA_SCENES_AFTER was on replica-a's partitions (replica-b owned $b_owned): the takeover was not exercised"
  pass "replica-b took over replica-a's partitions (it owned $b_owned) and served $taken there"
  owned=$(kafka_wait_owned)
  [[ ${owned%% *} -eq $KAFKA_PARTITIONS ]] || fail "after the takeover the replicas own ${owned%% *} of $KAFKA_PARTITIONS partitions"
  read -r _ a b <<<"$owned"
  restarts=$(podman inspect -f '{{.RestartCount}}' "${PROJECT}_replica-a_1" 2>/dev/null || echo '?')
  pass "after the takeover all $KAFKA_PARTITIONS partitions are owned (replica-a $a, replica-b $b; replica-a restarted $restarts time(s) by its restart policy)"
  kafka_rolling_restart "$net"
}

# A rolling restart through the engine while new scenes are replayed: replica-a back first,
# then each replica stopped (SIGTERM, `podman stop`) and started again in turn, the next one
# only once the restarted one is ready. Every frame replayed meanwhile must have a result.
kafka_rolling_restart() { # kafka_rolling_restart NETWORK
  local net=$1 replay r port
  log "rolling restart: each replica stopped (SIGTERM) and started again in turn, $KAFKA_SCENES_ROLL replayed meanwhile"
  podman start "${PROJECT}_replica-a_1" >/dev/null 2>&1 || true
  wait_readyz "$CROSSVIEW_REPLICA_A_PORT" replica-a
  # 100 frames at 8 frames/s: about 12 s, over the whole roll.
  podman run --rm --network "$net" -v "$WORK/run/data:/data:ro" --entrypoint crossview-replay "$IMAGE" \
    --transport=kafka --kafka-brokers=broker:9092 --allow-host=broker,replica-b \
    --target=http://replica-b:8080 --wait-ready=90s --recording /data/replay.jsonl \
    --scene-names "$KAFKA_SCENES_ROLL" --rate 8 \
    --frames "$CROSSVIEW_REPLAY_FRAMES" --drain-timeout 60s --json \
    >"$WORK/logs/kafka-replay-roll.json" 2>"$WORK/logs/kafka-replay-roll.stderr" &
  replay=$!
  sleep 3
  for r in replica-a replica-b; do
    port=$CROSSVIEW_REPLICA_A_PORT
    [[ $r == replica-b ]] && port=$CROSSVIEW_REPLICA_B_PORT
    podman stop -t 30 "${PROJECT}_${r}_1" >/dev/null || fail "podman stop $r"
    podman start "${PROJECT}_${r}_1" >/dev/null || fail "podman start $r"
    wait_readyz "$port" "$r"
  done
  pass "replica-a and replica-b each stopped with SIGTERM, started again and ready, in turn"
  wait "$replay" \
    || { tail -n 40 "$WORK/logs/kafka-replay-roll.json" "$WORK/logs/kafka-replay-roll.stderr" >&2; fail "kafka replay during the rolling restart"; }
  check_report "$WORK/logs/kafka-replay-roll.json" "kafka replay during the rolling restart"
  pass "every frame of $KAFKA_SCENES_ROLL, replayed during the rolling restart, has a result"
}

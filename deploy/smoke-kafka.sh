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

kafka_wait_ready() { # kafka_wait_ready PORT NAME
  for _ in $(seq 1 120); do
    curl -fsS -m 2 "http://127.0.0.1:$1/readyz" >/dev/null 2>&1 && return
    sleep 1
  done
  fail "$2 not ready on 127.0.0.1:$1/readyz after 120 s"
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

kafka_check_report() { # kafka_check_report FILE LABEL
  python3 - "$1" "$2" <<'PY' || fail "kafka replay report ($2), see $1"
import json, sys
text = open(sys.argv[1]).read()
r = json.loads(text[text.index("{"):])
assert r["passed"], r["failures"]
assert r["frames_lost"] == 0 and r["results"] > 0, r
print(f"[smoke] kafka replay ({sys.argv[2]}): {r['batches_sent']} batches over "
      f"{len(r['scenes'])} scenes, {r['results']} results, lost {r['frames_lost']}, "
      f"p50 {r['latency_complete']['p50_ms']:.1f} ms, p99 {r['latency_complete']['p99_ms']:.1f} ms",
      file=sys.stderr)
PY
}

kafka_profile() {
  log "kafka profile: broker, topic job, two replicas in one group, the replay client"
  build tansu -f deploy/Dockerfile.tansu -t localhost/crossview-tansu:local .
  "${COMPOSE[@]}" down -t 5 >/dev/null 2>&1 || true # the default profile's services
  # In stages, each with --no-deps: podman 4.3 turns depends_on into --requires and then
  # cannot start a container whose requirement is the exited one-shot topic job ("depends on
  # container ... not found in input list"), and it has no healthy/completed conditions.
  local up=("${COMPOSE[@]}" --profile kafka up -d) c rc
  "${up[@]}" broker kafka-topics >"$WORK/logs/compose-up-kafka.log" 2>&1 \
    || { tail -n 30 "$WORK/logs/compose-up-kafka.log" >&2; fail "podman-compose --profile kafka up broker kafka-topics"; }
  rc=$(timeout 120 podman wait "${PROJECT}_kafka-topics_1") || fail "the topic job did not finish"
  [[ $rc -eq 0 ]] || { podman logs "${PROJECT}_kafka-topics_1" >&2; fail "the topic job exited with $rc"; }
  pass "broker up, topic job created the topics (exit code 0)"
  "${up[@]}" --no-deps replica-a replica-b >>"$WORK/logs/compose-up-kafka.log" 2>&1 \
    || { tail -n 30 "$WORK/logs/compose-up-kafka.log" >&2; fail "podman-compose --profile kafka up replica-a replica-b"; }
  kafka_wait_ready "$CROSSVIEW_REPLICA_A_PORT" replica-a
  kafka_wait_ready "$CROSSVIEW_REPLICA_B_PORT" replica-b
  pass "replica-a and replica-b ready (/readyz: consumer group joined)"
  CROSSVIEW_REPLAY_SCENES=$KAFKA_SCENES_BEFORE "${up[@]}" --no-deps kafka-replay \
    >>"$WORK/logs/compose-up-kafka.log" 2>&1 \
    || { tail -n 30 "$WORK/logs/compose-up-kafka.log" >&2; fail "podman-compose --profile kafka up kafka-replay"; }

  log "waiting for the profile's replay client (Kafka, $KAFKA_SCENES_BEFORE)"
  local owned net restarts
  c=${PROJECT}_kafka-replay_1
  rc=$(timeout 240 podman wait "$c") || fail "kafka replay client did not finish"
  podman logs "$c" >"$WORK/logs/kafka-replay.json" 2>"$WORK/logs/kafka-replay.stderr" || true
  [[ $rc -eq 0 ]] || { tail -n 40 "$WORK/logs/kafka-replay.json" "$WORK/logs/kafka-replay.stderr" >&2; fail "kafka replay client exit code $rc"; }
  kafka_check_report "$WORK/logs/kafka-replay.json" "before the kill"
  pass "kafka-replay (compose service): every frame of $KAFKA_SCENES_BEFORE has a result on 'results'"
  owned=$(kafka_wait_owned)
  [[ ${owned%% *} -eq $KAFKA_PARTITIONS ]] || fail "the replicas own ${owned%% *} of $KAFKA_PARTITIONS input partitions"
  read -r _ a b <<<"$owned"
  pass "the replicas own all $KAFKA_PARTITIONS input partitions between them (replica-a $a, replica-b $b)"

  log "SIGKILL replica-a through the engine, replay new scenes during the takeover"
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
  kafka_check_report "$WORK/logs/kafka-replay-after.json" "during the takeover"
  pass "every frame of $KAFKA_SCENES_AFTER, replayed from a second container after the kill, has a result"
  owned=$(kafka_wait_owned)
  [[ ${owned%% *} -eq $KAFKA_PARTITIONS ]] || fail "after the takeover the replicas own ${owned%% *} of $KAFKA_PARTITIONS partitions"
  read -r _ a b <<<"$owned"
  restarts=$(podman inspect -f '{{.RestartCount}}' "${PROJECT}_replica-a_1" 2>/dev/null || echo '?')
  pass "after the takeover all $KAFKA_PARTITIONS partitions are owned (replica-a $a, replica-b $b; replica-a restarted $restarts time(s) by its restart policy)"
}

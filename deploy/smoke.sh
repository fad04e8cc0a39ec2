#!/usr/bin/env bash
# End-to-end smoke test of the container deployment, run with podman + podman-compose:
#   1. installs/configures podman when missing and builds a local debian:bookworm-slim base
#      image with debootstrap (no registry needed);
#   2. builds the images: deploy/Dockerfile (multi-stage, with a local stand-in for
#      rust:1-bookworm made from this machine's toolchain) or, with SMOKE_BUILD=prebuilt,
#      deploy/Dockerfile.prebuilt from `cargo build --release`; plus deploy/Dockerfile.prometheus;
#   3. simulates a recording and writes a random-weight model with the image's own binary;
#   4. `podman-compose up -d` (server, prometheus, replay client) on published loopback ports;
#   5. sends real traffic: HTTP batches for every camera of a few frames with results read back
#      from the SSE stream, the replay client's gRPC report, a HTTP load-test run from a second
#      container; checks /healthz, /readyz, the container health check, resource limits,
#      /metrics counters and that Prometheus scraped the server; stops the server with SIGTERM
#      and expects a clean exit;
#   6. the `kafka` profile (SMOKE_KAFKA=0 skips it): broker, topic job, two replicas in one
#      consumer group and the profile's replay client; checks that every replayed frame has a
#      result, SIGKILLs one replica through the engine (`podman kill -s KILL`; its restart
#      policy brings it back), replays new scenes from a second container while the group
#      rebalances, and checks again that every frame has a result and that the replicas own
#      every input partition between them afterwards;
#   7. tears everything down. Exits non-zero on any failure.
#
# Usage: bash deploy/smoke.sh            (as root; `make smoke`)
# Env:   SMOKE_BUILD=source|prebuilt     SMOKE_PORT (18080)  SMOKE_PROM_PORT (19090)
#        SMOKE_KEEP=1 (leave the stack running)   SMOKE_WORK (/var/tmp/crossview-smoke)
#        SMOKE_NO_CARGO=1 (prebuilt: package target/release as it is)
#        SMOKE_KAFKA=0 (skip the kafka profile)  SMOKE_REPLICA_A_PORT (18081)  SMOKE_REPLICA_B_PORT (18082)
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD

BUILD=${SMOKE_BUILD:-source}
PORT=${SMOKE_PORT:-18080}
PROM_PORT=${SMOKE_PROM_PORT:-19090}
WORK=${SMOKE_WORK:-/var/tmp/crossview-smoke}
PROJECT=crossview-smoke
BASE_IMAGE=docker.io/library/debian:bookworm-slim
RUST_IMAGE=${SMOKE_RUST_IMAGE:-docker.io/library/rust:1-bookworm}
IMAGE=localhost/crossview:local
PROM_IMAGE=localhost/crossview-prometheus:local
ORT_LIB=.cache/onnxruntime/libonnxruntime.so.1.31.1
# The replay service drives REPLAY_SCENES; the HTTP checks use HTTP_SCENE meanwhile.
REPLAY_SCENES=square4-0,square4-1
# The kafka profile: scenes replayed before the kill, then new ones during the takeover (new
# scenes, so their frame ids never meet the first replay's). Eight of them, so that some land
# on the killed replica's partitions whichever half it owned (one run with four had none).
KAFKA=${SMOKE_KAFKA:-1}
KAFKA_SCENES_BEFORE=square4-0,square4-1,square4-2,square4-3
KAFKA_SCENES_AFTER=$(seq -s, -f 'square4-%g' 4 11)
KAFKA_SCENES_ROLL=$(seq -s, -f 'square4-%g' 12 19)
KAFKA_PARTITIONS=8
HTTP_SCENE=square4-2
HTTP_FRAMES=5
# The HTTP load test's scenes: not used before in the run. (Its fresh frame ids jump far above
# an earlier client's on the same scene, and the server refuses a jump beyond its frame-id
# window until the cameras agree on it: the first batches would be rejected as out of range.)
LOADTEST_SCENES=square4-6,square4-7

log() { printf '\n[smoke %s] %s\n' "$(date +%H:%M:%S)" "$*" >&2; }
fail() { printf '\n[smoke] FAIL: %s\n' "$*" >&2; exit 1; }
PASSED=()
pass() { PASSED+=("$1"); printf '[smoke] ok: %s\n' "$1" >&2; }

mkdir -p "$WORK/logs"

# ---------------------------------------------------------------- 1. podman and base image
setup_podman() {
  if ! command -v podman >/dev/null || ! command -v runc >/dev/null \
     || ! command -v debootstrap >/dev/null; then
    log "installing podman, runc, debootstrap"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq podman runc debootstrap >/dev/null
  fi
  if ! grep -qs 'cgroup_manager *= *"cgroupfs"' /etc/containers/containers.conf; then
    log "writing /etc/containers/containers.conf"
    mkdir -p /etc/containers
    cat >/etc/containers/containers.conf <<'EOF'
[containers]
default_ulimits = []

[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
EOF
  fi
  if ! podman image exists "$BASE_IMAGE"; then
    log "building $BASE_IMAGE with debootstrap (minbase)"
    rm -rf "$WORK/rootfs"
    debootstrap --variant=minbase bookworm "$WORK/rootfs" http://deb.debian.org/debian \
      >"$WORK/logs/debootstrap.log" 2>&1 || fail "debootstrap (see $WORK/logs/debootstrap.log)"
    tar -C "$WORK/rootfs" -c . | podman import - "$BASE_IMAGE" >/dev/null
    rm -rf "$WORK/rootfs"
  fi
  COMPOSE_VENV=$REPO/.cache/podman-compose-venv
  if [[ ! -x $COMPOSE_VENV/bin/podman-compose ]]; then
    log "installing podman-compose into $COMPOSE_VENV"
    python3 -m venv "$COMPOSE_VENV"
    "$COMPOSE_VENV/bin/pip" install -q podman-compose
  fi
  COMPOSE=("$COMPOSE_VENV/bin/podman-compose" -p "$PROJECT" -f deploy/docker-compose.yml)
}

# ---------------------------------------------------------------- 2. images
build() { # build LOGNAME podman-build-args...
  local name=$1; shift
  log "podman build $name"
  # docker format keeps the images' HEALTHCHECK (OCI has no such field).
  if ! podman build --pull=never --network=host --format docker "$@" >"$WORK/logs/build-$name.log" 2>&1; then
    tail -n 40 "$WORK/logs/build-$name.log" >&2
    fail "image build $name (see $WORK/logs/build-$name.log)"
  fi
}

build_rust_standin() {
  if podman image exists "$RUST_IMAGE"; then return; fi
  log "making a local stand-in for $RUST_IMAGE from this machine's toolchain"
  local ctx=$WORK/rust-standin toolchain
  toolchain=$(rustup show active-toolchain | awk '{print $1}')
  [[ -d $HOME/.rustup/toolchains/$toolchain ]] || fail "no rustup toolchain $toolchain"
  rm -rf "$ctx" && mkdir -p "$ctx"
  cp deploy/rust-standin/Containerfile "$ctx/"
  cp /etc/ssl/certs/ca-certificates.crt "$ctx/" || fail "no /etc/ssl/certs/ca-certificates.crt"
  printf 'version = "12"\ndefault_toolchain = "%s"\nprofile = "minimal"\nauto_self_update = "disable"\n' \
    "$toolchain" >"$ctx/settings.toml"
  # Docs are not needed to build; rustup proxies (cargo, rustc, ...) come from ~/.cargo/bin.
  tar -C "$HOME" --exclude="toolchains/$toolchain/share/doc" \
      --transform 's,^\.rustup,rustup,;s,^\.cargo,cargo,' \
      -cf "$ctx/toolchain.tar" ".rustup/toolchains/$toolchain" .cargo/bin
  tar -C "$ctx" --transform 's,^,rustup/,' -rf "$ctx/toolchain.tar" settings.toml
  build rust-standin -f "$ctx/Containerfile" -t "$RUST_IMAGE" "$ctx"
  rm -f "$ctx/toolchain.tar"
}

build_images() {
  [[ -f $ORT_LIB ]] || bash scripts/setup.sh
  build prometheus -f deploy/Dockerfile.prometheus -t "$PROM_IMAGE" .
  case $BUILD in
    source)
      build_rust_standin
      build crossview -f deploy/Dockerfile --build-arg "RUST_IMAGE=$RUST_IMAGE" -t "$IMAGE" .
      ;;
    prebuilt)
      if [[ -z ${SMOKE_NO_CARGO:-} ]]; then
        log "cargo build --release (host)"
        cargo build --release --locked -p crossview -p crossview-loadtest --bins \
          >"$WORK/logs/cargo-release.log" 2>&1 || fail "cargo build (see $WORK/logs/cargo-release.log)"
      fi
      build crossview -f deploy/Dockerfile.prebuilt -t "$IMAGE" .
      ;;
    *) fail "SMOKE_BUILD must be source or prebuilt, got '$BUILD'" ;;
  esac
  pass "images built ($BUILD): $IMAGE, $PROM_IMAGE"
}

# ---------------------------------------------------------------- 3. data
make_data() {
  log "simulating a recording and writing a model with the image's binary"
  rm -rf "$WORK/run" && mkdir -p "$WORK/run/models" "$WORK/run/data"
  chmod -R 0777 "$WORK/run"
  podman run --rm --network=none -v "$WORK/run:/work" "$IMAGE" \
    simulate --preset square4 --frames 120 --seed 3 --out /work/data/replay.jsonl \
    >"$WORK/logs/simulate.log" 2>&1 || { cat "$WORK/logs/simulate.log" >&2; fail "crossview simulate"; }
  podman run --rm --network=none -v "$WORK/run:/work" "$IMAGE" \
    model init --scene-from /work/data/replay.jsonl --out /work/models/square4.onnx --width 128 \
    >"$WORK/logs/model-init.log" 2>&1 || { cat "$WORK/logs/model-init.log" >&2; fail "crossview model init"; }
  [[ -s $WORK/run/models/square4.onnx && -s $WORK/run/data/replay.jsonl ]] || fail "no model/recording"
  pass "simulate + model init ran in the image ($(($(wc -l <"$WORK/run/data/replay.jsonl") - 1)) batches)"
}

# ---------------------------------------------------------------- 4. compose
export CROSSVIEW_PORT=$PORT CROSSVIEW_PROMETHEUS_PORT=$PROM_PORT
export CROSSVIEW_MODELS_DIR=$WORK/run/models CROSSVIEW_REPLAY_DIR=$WORK/run/data
CROSSVIEW_MODELS=$(for i in $(seq 0 19); do printf 'square4-%d=/models/square4.onnx,' "$i"; done)
export CROSSVIEW_MODELS=${CROSSVIEW_MODELS%,}
export CROSSVIEW_REPLICA_A_PORT=${SMOKE_REPLICA_A_PORT:-18081} CROSSVIEW_REPLICA_B_PORT=${SMOKE_REPLICA_B_PORT:-18082}
export CROSSVIEW_KAFKA_PARTITIONS=$KAFKA_PARTITIONS
export CROSSVIEW_REPLAY_SCENES=$REPLAY_SCENES CROSSVIEW_REPLAY_FRAMES=100 CROSSVIEW_REPLAY_RATE=20
export CROSSVIEW_REPLAY_TRANSPORT=grpc

teardown() {
  local rc=$?
  if [[ $rc -ne 0 ]]; then
    for c in server prometheus replay broker kafka-topics replica-a replica-b kafka-replay; do
      podman logs --tail 40 "${PROJECT}_${c}_1" >"$WORK/logs/container-$c.log" 2>&1 || true
      echo "--- last log lines of $c" >&2; tail -n 15 "$WORK/logs/container-$c.log" >&2 || true
    done
  fi
  if [[ -z ${SMOKE_KEEP:-} && -n ${COMPOSE+x} ]]; then
    log "podman-compose down"
    "${COMPOSE[@]}" --profile kafka down -t 5 >"$WORK/logs/compose-down.log" 2>&1 || true
  fi
  if [[ -n ${SSE_PID:-} ]]; then kill "$SSE_PID" 2>/dev/null || true; fi
  if [[ $rc -eq 0 ]]; then
    printf '\n[smoke] PASS (%d checks)\n' "${#PASSED[@]}" >&2
  else
    printf '\n[smoke] FAILED after %d passing checks; logs in %s/logs\n' "${#PASSED[@]}" "$WORK" >&2
  fi
  exit $rc
}

compose_up() {
  log "podman-compose up -d"
  "${COMPOSE[@]}" --profile kafka down -t 5 >/dev/null 2>&1 || true
  "${COMPOSE[@]}" up -d >"$WORK/logs/compose-up.log" 2>&1 \
    || { tail -n 30 "$WORK/logs/compose-up.log" >&2; fail "podman-compose up"; }
  pass "podman-compose up -d"
}

# Polls 127.0.0.1:PORT/readyz until it answers 200 (at most 120 s).
wait_readyz() { # wait_readyz PORT NAME
  for _ in $(seq 1 120); do
    curl -fsS -m 2 "http://127.0.0.1:$1/readyz" >/dev/null 2>&1 && return
    sleep 1
  done
  fail "$2 not ready on 127.0.0.1:$1/readyz after 120 s"
}

wait_ready() {
  wait_readyz "$PORT" server
  curl -fsS -m 2 "http://127.0.0.1:$PORT/healthz" >/dev/null || fail "/healthz not 200"
  pass "/readyz and /healthz answer 200 on the published port $PORT"
}

check_container() {
  local c=${PROJECT}_server_1 mem cpus
  podman healthcheck run "$c" >/dev/null 2>&1 || fail "container health check of $c"
  pass "container HEALTHCHECK (crossview-healthcheck /readyz) passes"
  mem=$(podman inspect -f '{{.HostConfig.Memory}}' "$c")
  cpus=$(podman inspect -f '{{.HostConfig.NanoCpus}}' "$c")
  [[ $mem -gt 0 ]] || fail "no memory limit on $c"
  pass "resource limits applied: memory=$mem bytes, nano_cpus=$cpus"
}

metric() { # metric NAME SCENE -> value (0 when absent)
  curl -fsS -m 5 "http://127.0.0.1:$PORT/metrics" | awk -v n="$1" -v s="scene=\"$2\"" '
    index($0, n "{") == 1 && index($0, s) { v += $NF } END { printf "%d\n", v + 0 }'
}

http_traffic() {
  log "HTTP: SSE subscription + batches of every camera for $HTTP_FRAMES frames"
  local before sse=$WORK/logs/sse.log frames posted=0 code
  before=$(metric crossview_batches_total "$HTTP_SCENE")
  curl -sN -m 60 "http://127.0.0.1:$PORT/v1/scenes/$HTTP_SCENE/events" >"$sse" 2>/dev/null &
  SSE_PID=$!
  sleep 1
  # Frame ids far above the replay client's, so the two never collide.
  mkdir -p "$WORK/run/http"
  frames=$(python3 - "$WORK/run/data/replay.jsonl" "$WORK/run/http" "$HTTP_FRAMES" <<'PY'
import json, sys, os
src, out, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
lines = open(src).read().splitlines()[1:]
batches = [json.loads(l) for l in lines if l.strip()]
ids = sorted({b["frame_id"] for b in batches})[:n]
k = 0
for b in batches:
    if b["frame_id"] in ids:
        b["frame_id"] += 1_000_000
        k += 1
        with open(os.path.join(out, f"{k:04d}.json"), "w") as f:
            json.dump(b, f)
print(" ".join(str(i + 1_000_000) for i in ids))
PY
)
  for f in "$WORK"/run/http/*.json; do
    code=$(curl -s -o "$WORK/logs/post.out" -w '%{http_code}' -m 10 -H 'content-type: application/json' \
      --data-binary "@$f" "http://127.0.0.1:$PORT/v1/scenes/$HTTP_SCENE/batches")
    [[ $code == 202 || $code == 200 ]] || { cat "$WORK/logs/post.out" >&2; fail "POST batch -> HTTP $code"; }
    posted=$((posted + 1))
  done
  pass "POSTed $posted batches (all cameras of frames $frames) -> 202"
  for _ in $(seq 1 50); do
    local missing=0
    for id in $frames; do grep -q "\"frame_id\":${id}[,}]" "$sse" || missing=$((missing + 1)); done
    [[ $missing -eq 0 ]] && break
    sleep 0.2
  done
  for id in $frames; do
    grep -q "\"frame_id\":${id}[,}]" "$sse" || { head -c 2000 "$sse" >&2; fail "frame $id never came back on SSE"; }
  done
  grep -q '^event: frame' "$sse" || fail "SSE events are not named 'frame'"
  grep -q '"identities":\[{' "$sse" || fail "no SSE frame result carries an identity"
  kill "$SSE_PID" 2>/dev/null || true; SSE_PID=
  pass "every posted frame came back as an SSE 'frame' event with identities"
  local after; after=$(metric crossview_batches_total "$HTTP_SCENE")
  [[ $((after - before)) -ge $posted ]] || fail "crossview_batches_total moved by $((after - before)), posted $posted"
  pass "/metrics crossview_batches_total{scene=$HTTP_SCENE} moved $before -> $after"
}

# Waits (at most SECS) for the one-shot container C to exit and saves its output as
# $WORK/logs/NAME.out and NAME.stderr; fails unless it exited 0.
wait_job() { # wait_job CONTAINER NAME SECS
  local rc
  rc=$(timeout "$3" podman wait "$1") || fail "$2 did not finish"
  podman logs "$1" >"$WORK/logs/$2.out" 2>"$WORK/logs/$2.stderr" || true
  [[ $rc -eq 0 ]] || { tail -n 40 "$WORK/logs/$2.out" "$WORK/logs/$2.stderr" >&2; fail "$2 exit code $rc"; }
}

# Checks a load tester's JSON report (log lines before it are skipped): passed, no frame lost,
# results came back, every batch accepted; prints a summary (with the server's counters when
# the report compared them).
check_report() { # check_report FILE LABEL
  python3 - "$1" "$2" <<'PY' || fail "$2 report check (see $1)"
import json, sys
text = open(sys.argv[1]).read()
r = json.loads(text[text.index("{"):])
assert r["passed"], r["failures"]
assert r["frames_lost"] == 0 and r["results"] > 0 and r["batches_accepted"] == r["batches_sent"], r
counters = ", ".join(f"{c['metric']}={c['server']}({'ok' if c['matches'] else 'MISMATCH'})"
                     for c in r.get("server_comparison") or [])
print(f"[smoke] {sys.argv[2]}: {r['batches_sent']} batches over {len(r['scenes'])} scenes, "
      f"{r['results']} results, lost {r['frames_lost']}, p50 {r['latency_complete']['p50_ms']:.1f} ms, "
      f"p99 {r['latency_complete']['p99_ms']:.1f} ms" + (f", server counters {counters}" if counters else ""),
      file=sys.stderr)
PY
}

replay_report() {
  log "waiting for the replay client (gRPC, $REPLAY_SCENES) to finish"
  wait_job "${PROJECT}_replay_1" replay 180
  check_report "$WORK/logs/replay.out" replay
  pass "replay client (compose service, gRPC Push+Subscribe over the compose network) passed, 0 frames lost"
}

loadtest_http() {
  log "HTTP load test from a second container through the published port"
  podman run --rm --network=host -v "$WORK/run/data:/data:ro" --entrypoint crossview-loadtest "$IMAGE" \
    --target "http://127.0.0.1:$PORT" --recording /data/replay.jsonl --transport http \
    --scene-names "$LOADTEST_SCENES" --rate 20 --frames 60 --connections 2 --json \
    >"$WORK/logs/loadtest-http.json" 2>"$WORK/logs/loadtest-http.stderr" \
    || { cat "$WORK/logs/loadtest-http.json" "$WORK/logs/loadtest-http.stderr" >&2; fail "HTTP load test"; }
  check_report "$WORK/logs/loadtest-http.json" "http loadtest"
  pass "HTTP load test (POST + SSE, 2 fresh scenes) passed with 0 frames lost"
}

graceful_stop() {
  local c=${PROJECT}_server_1 code
  podman stop -t 20 "$c" >/dev/null || fail "podman stop $c"
  code=$(podman inspect -f '{{.State.ExitCode}}' "$c")
  [[ $code == 0 ]] || fail "server exited with $code on SIGTERM"
  pass "server shut down gracefully on SIGTERM (exit code 0)"
}

prometheus_check() {
  log "Prometheus: target up and the counter scraped"
  local url=http://127.0.0.1:$PROM_PORT ok=
  for _ in $(seq 1 60); do
    if curl -fsS -m 3 "$url/api/v1/query?query=sum(crossview_batches_total)" 2>/dev/null \
       | python3 -c 'import json,sys; r=json.load(sys.stdin)["data"]["result"]; sys.exit(0 if r and float(r[0]["value"][1]) > 0 else 1)'; then
      ok=1; break
    fi
    sleep 1
  done
  [[ -n $ok ]] || fail "Prometheus never scraped crossview_batches_total"
  curl -fsS -m 3 "$url/api/v1/targets" | grep -q '"health":"up"' || fail "Prometheus target not up"
  pass "Prometheus scraped server:8080/metrics (target up, sum(crossview_batches_total) > 0)"
}

# ---------------------------------------------------------------- 6. kafka profile
# shellcheck source=deploy/smoke-kafka.sh
source deploy/smoke-kafka.sh

setup_podman
trap teardown EXIT
build_images
make_data
compose_up
wait_ready
check_container
http_traffic
replay_report
loadtest_http
curl -fsS -m 3 "http://127.0.0.1:$PORT/readyz" >/dev/null || fail "/readyz after traffic"
pass "/readyz still ok after traffic"
prometheus_check
graceful_stop
[[ $KAFKA == 0 ]] || kafka_profile

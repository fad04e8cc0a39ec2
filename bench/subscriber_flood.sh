#!/usr/bin/env bash
# Subscribers that never read (issue #28, items 2 and 3): a release `crossview serve` with two
# scenes (lab: frames flow; idle: nothing pushed) and the default limits, then
# bench/src/bin/subscriber_flood.rs: 6,000 never-read HTTP/2 event streams (1 GiB windows,
# sockets not read), 10,000 HTTP/1.1 SSE subscriptions attempted on the idle scene, 200 frames
# pushed at 10 frames/s, /healthz probed on a new connection every 20 ms. Prints the driver's
# figures and the server's resident memory before and at its peak (VmHWM). Bounded: the
# driver ends after its frames. Figures only on an otherwise idle machine (BENCHMARKS.md).
#
# Usage: bash bench/subscriber_flood.sh
# Env:   CROSSVIEW_BIN (target/release/crossview)  FLOOD_BIN (target/release/subscriber_flood)
#        PORT (18396)  H2_STREAMS (6000)  SSE_ATTEMPTS (10000)  FRAMES (200)  SERVE_ARGS (extra flags)
set -euo pipefail
cd "$(dirname "$0")/.."
CROSSVIEW_BIN=${CROSSVIEW_BIN:-target/release/crossview}
FLOOD_BIN=${FLOOD_BIN:-target/release/subscriber_flood}
PORT=${PORT:-18396}
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$PWD/.cache/onnxruntime/libonnxruntime.so.1.31.1}
ulimit -n 65536 2>/dev/null || ulimit -n "$(ulimit -Hn)"
# shellcheck disable=SC2086
"$CROSSVIEW_BIN" serve --listen "127.0.0.1:$PORT" --model lab=models/demo.onnx \
  --scene "idle=a:640x480,b:640x480" ${SERVE_ARGS:-} 2>/dev/null &
SERVER=$!
trap 'kill $SERVER 2>/dev/null || true; wait $SERVER 2>/dev/null || true' EXIT
for _ in $(seq 1 200); do
  curl -sf "http://127.0.0.1:$PORT/readyz" >/dev/null && break
  sleep 0.05
done
rss() { awk -v k="$1:" '$1 == k { print int($2 / 1024) }' "/proc/$SERVER/status"; }
echo "server RSS before: $(rss VmRSS) MiB"
"$FLOOD_BIN" --addr "127.0.0.1:$PORT" --scene lab --idle-scene idle \
  --h2-streams "${H2_STREAMS:-6000}" --sse-attempts "${SSE_ATTEMPTS:-10000}" --frames "${FRAMES:-200}"
echo "server RSS after: $(rss VmRSS) MiB, peak (VmHWM): $(rss VmHWM) MiB"
curl -s "http://127.0.0.1:$PORT/metrics" | grep -E '^crossview_(subscribers_dropped_total|connections_(refused|evicted)_total|errors_total\{kind="(resource_exhausted|subscriber_stalled)"\})' || true

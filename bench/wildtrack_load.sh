# shellcheck shell=bash
# Shared by the load benchmarks of one 7-camera scene (record_overhead.sh, clock_watch_cost.sh),
# sourced after they set CROSSVIEW_BIN, LOADTEST_BIN, OUT, PORT, TARGET, MODEL, TRANSPORT,
# RATE and DURATION: the WILDTRACK-shaped recording, and one load run against a fresh server.
mkdir -p "$OUT"
# A simulated WILDTRACK-shaped recording (7 cameras of 1920x1080, 30 people, detector noise),
# its cameras renamed to the model's (C1..C7 -> CVLab1..4, IDIAP1..3, same image size).
"$CROSSVIEW_BIN" simulate --preset wildtrack --frames 600 --seed 11 --out "$OUT/sim.jsonl" 2>/dev/null
python3 - "$OUT/sim.jsonl" "$OUT/rec.jsonl" <<'PY'
import json, sys
names = ["CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3"]
src, dst = open(sys.argv[1]), open(sys.argv[2], "w")
header = json.loads(src.readline())
rename = {c["name"]: n for c, n in zip(header["scene"]["cameras"], names)}
for c in header["scene"]["cameras"]:
    c["name"] = rename[c["name"]]
dst.write(json.dumps(header) + "\n")
for line in src:
    b = json.loads(line)
    b["camera"] = rename[b["camera"]]
    dst.write(json.dumps(b) + "\n")
PY

SERVER=
stop_server() {
  if [[ -n $SERVER ]]; then kill "$SERVER" 2>/dev/null || true; wait "$SERVER" 2>/dev/null || true; fi
  SERVER=
}
trap stop_server EXIT

# load_run NAME [serve flags...]: a fresh server with those flags, one load run; leaves
# $OUT/NAME.json (the load tester's report) and $OUT/NAME.metrics (the server's /metrics).
load_run() {
  local name=$1; shift
  stop_server
  "$CROSSVIEW_BIN" serve --listen 127.0.0.1:$PORT --model "wildtrack=$MODEL" "$@" >>"$OUT/server-$name.log" 2>&1 &
  SERVER=$!
  "$LOADTEST_BIN" --target $TARGET --recording "$OUT/rec.jsonl" --scene-names wildtrack --wait-ready 60s \
    --transport "$TRANSPORT" --rate "$RATE" --duration "$DURATION" --loop --json --server-pid $SERVER \
    >"$OUT/$name.json" 2>"$OUT/$name.err" || true
  curl -s "$TARGET/metrics" >"$OUT/$name.metrics" || true
  stop_server
}

#!/bin/bash
# Replay client entrypoint: streams a recording into the server with crossview-loadtest.
# Uses $CROSSVIEW_LOADTEST_RECORDING when that file exists; otherwise, when
# $CROSSVIEW_REPLAY_PRESET is set, simulates one first (crossview simulate). Extra arguments
# go to crossview-loadtest.
set -euo pipefail
rec=${CROSSVIEW_LOADTEST_RECORDING:-/data/replay.jsonl}
if [[ ! -f "$rec" ]]; then
  if [[ -z "${CROSSVIEW_REPLAY_PRESET:-}" ]]; then
    echo "replay: no recording at $rec and no CROSSVIEW_REPLAY_PRESET to simulate one" >&2
    exit 2
  fi
  rec=/tmp/replay.jsonl
  crossview simulate --preset "$CROSSVIEW_REPLAY_PRESET" \
    --frames "${CROSSVIEW_REPLAY_SIM_FRAMES:-200}" --seed "${CROSSVIEW_REPLAY_SEED:-1}" --out "$rec"
fi
export CROSSVIEW_LOADTEST_RECORDING="$rec"
exec crossview-loadtest "$@"

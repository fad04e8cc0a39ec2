#!/usr/bin/env bash
# A population against the single run, paired by seed: member 0 of `--population K --seed S`
# is the single run `--seed S`, so each row compares the same starting point. For every seed:
# `crossview train` with `--population 1` and with `--population K`, wall time and CPU use
# (GNU time), then `crossview eval` of both exported files on the validation recording
# (pairwise and identity rows). Nothing here chooses a setting: it reports.
#
# usage: bench/train_population.sh TRAIN.jsonl VAL.jsonl "SEEDS" [extra train flags...]
# env:   K (members, default 4), THREADS (default: all cores), OUT (default train-pop/),
#        CROSSVIEW (default target/release/crossview)
# e.g.   B=target/release/crossview
#        $B simulate --preset square4 --people 3 --frames 300 --seed 1 --out sq-train.jsonl
#        $B simulate --preset square4 --people 3 --frames 100 --seed 2 --clean --out sq-val.jsonl
#        bench/train_population.sh sq-train.jsonl sq-val.jsonl "1 2 3"
set -euo pipefail
B=${CROSSVIEW:-target/release/crossview}
K=${K:-4}
THREADS=${THREADS:-$(nproc)}
OUT=${OUT:-train-pop}
TRAIN=$1 VAL=$2 SEEDS=$3
shift 3
mkdir -p "$OUT"
export MALLOC_MMAP_THRESHOLD_=4294967296 MALLOC_TRIM_THRESHOLD_=4294967296

for seed in $SEEDS; do
  for pop in 1 "$K"; do
    name="$OUT/s$seed-p$pop"
    /usr/bin/time -f "%e %P" -o "$name.time" \
      "$B" train --data "$TRAIN" --out "$name.onnx" --seed "$seed" --population "$pop" \
      --threads "$THREADS" --quiet --no-sync-check "$@" > "$name.log" 2>&1
    "$B" eval --model "$name.onnx" --data "$VAL" --report "$name.eval.json" > /dev/null
  done
done

python3 - "$OUT" "$K" $SEEDS <<'EOF'
import json, sys
out, k, seeds = sys.argv[1], sys.argv[2], sys.argv[3:]

def scores(path):
    runs = json.load(open(path))["runs"]
    row = {}
    for r in runs:
        m = r["metrics"]
        row.setdefault(r["mode"], (100 * m["acc"], 100 * m["ipaa_100"]))
    return row

def fmt(row, mode):
    return "%.2f / %.2f" % row[mode] if mode in row else "-"

print(f"| seed | --population 1: pairwise | identities | min (CPU) | --population {k}: pairwise | identities | min (CPU) | winner |")
print("|---:|---|---|---|---|---|---|---|")
sums = {}
for s in seeds:
    cells = [s]
    for p in ("1", k):
        base = f"{out}/s{s}-p{p}"
        row = scores(base + ".eval.json")
        wall, cpu = open(base + ".time").read().split()
        cells += [fmt(row, "pairwise"), fmt(row, "identities"), f"{float(wall) / 60:.1f} ({cpu})"]
        for mode in ("pairwise", "identities"):
            if mode in row:
                sums.setdefault((p, mode), []).append(row[mode])
    log = open(f"{out}/s{s}-p{k}.log").read()
    cells.append(log.split("population: ")[-1].split(";")[0].strip() if "population: " in log else "-")
    print("| " + " | ".join(cells) + " |")
mean = lambda xs: "%.2f / %.2f" % (sum(a for a, _ in xs) / len(xs), sum(b for _, b in xs) / len(xs))
print("| **mean** | " + " | ".join(
    [mean(sums.get(("1", "pairwise"), [(0, 0)])), mean(sums.get(("1", "identities"), [(0, 0)])), "",
     mean(sums.get((k, "pairwise"), [(0, 0)])), mean(sums.get((k, "identities"), [(0, 0)])), "", ""]) + " |")
EOF

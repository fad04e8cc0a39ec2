"""The memory's selection rule (BENCHMARKS.md, "Identities with memory"), fixed before the
validation frames were read: among the settings that keep every simulator scene within 0.2 ACC
of its frames alone and beat the frames alone on the WILDTRACK training frames under both
models, the highest mean of ACC + IPAA-100 over the two models on the training frames.

Usage: python3 bench/memory_pick.py DIR (the g_*.md tables of bench/memory_sweep.sh)."""
import re
import sys

SIMS = ["sq_1", "sq_2", "sq_3", "sq_default", "sq_groups", "sq_groups2"]
MODELS = ["wt", "w64"]


def load(path):
    rows = {}
    for line in open(path):
        c = [x.strip() for x in line.strip().strip("|").split("|")]
        if len(c) < 15 or not (c[0] == "0 (alone)" or re.match(r"[\d.]+$", c[0])):
            continue
        rows[tuple(c[:5])] = dict(acc=float(c[5]), ipaa=float(c[6]), extra=int(c[13]))
    return rows


def main():
    d = sys.argv[1]
    data = {n: load(f"{d}/g_{n}.md") for n in SIMS + MODELS}
    alone_key = ("0 (alone)", "", "", "", "")
    alone = {n: data[n][alone_key] for n in data}
    ranked = []
    for key in data["wt"]:
        if key == alone_key:
            continue
        worst = min(data[n][key]["acc"] - alone[n]["acc"] for n in SIMS)
        above = all(data[n][key]["acc"] > alone[n]["acc"] for n in MODELS)
        score = sum(data[n][key]["acc"] + data[n][key]["ipaa"] for n in MODELS) / len(MODELS)
        ranked.append((worst >= -0.2 and above, score, worst, key))
    ranked.sort(key=lambda r: (r[0], r[1]), reverse=True)
    print("| eligible | λ | hold | weight | gate | margin | train ACC + IPAA-100 (mean of 2 models) | worst simulator ΔACC |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for ok, score, worst, key in ranked[:12]:
        print(f"| {'yes' if ok else 'no'} | {' | '.join(key)} | {score:.2f} | {worst:+.2f} |")
    best = ranked[0]
    print(f"\nchosen: λ {best[3][0]}, hold {best[3][1]}, link weight {best[3][2]}, gate {best[3][3]}, margin {best[3][4]}")


main()

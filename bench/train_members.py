#!/usr/bin/env python3
"""What the default `crossview train` exported, against what each part and each other choice
would have: BENCHMARKS.md, "Training". For every seed S, DIR holds `sS.onnx` (the default
command's output), `mem-sS/member-i.onnx` (`--members-out`) and `sS.log` (its stderr: the
label-free score lines of every member). Scores
every member subset (built with `crossview model combine`, calibrated on TRAIN) and the
exported file on GT (the selection set, e.g. WILDTRACK training frames with ground truth) and
VAL (reports only), then prints per seed and as means: member 0 (= `--population 1`), the best
member by the label-free key, the best M together for M = 1..K, halving schedules (drop the
worse half by the mean of the last 3 keys at the given fractions of the 1100-epoch first
stage, never below 2 members), and two labelled choices: the subset with the best ACC on GT
(labels of the selection set: the one the project's rules allow) and on VAL (the frames that
report: optimistic, and more so the more subsets there are), each reported on VAL.

usage: bench/train_members.py DIR TRAIN.jsonl GT.jsonl VAL.jsonl SEED... (CROSSVIEW: the binary)
"""
import itertools, json, os, re, statistics as st, subprocess, sys

B = os.environ.get("CROSSVIEW", "target/release/crossview")


def run(*args):
    return subprocess.run([B, *args], check=True, capture_output=True, text=True).stdout


def scores(model, data, report):
    if not os.path.exists(report):
        run("eval", "--model", model, "--data", data, "--report", report)
    runs = json.load(open(report))["runs"]
    get = lambda mode: [x for x in runs if x["mode"] == mode][0]["metrics"]
    return [(100 * get(m)["acc"], 100 * get(m)["ipaa_100"]) for m in ("pairwise", "identities")]


def seed_rows(d, train, gt, val, s):
    out = os.path.join(d, f"res-s{s}")
    os.makedirs(out, exist_ok=True)
    pop = json.loads(re.search(r"crossview.population = (\{.*\})", run("model", "info", f"{d}/s{s}.onnx")).group(1))
    best = [m["best_key"] for m in pop["members"]]
    seeds = [str(m["seed"]) for m in pop["members"]]
    curves = {i: [] for i in range(len(seeds))}
    for line in open(f"{d}/s{s}.log"):
        g = re.search(r"label-free score epoch=(\d+) seed=(\d+) .*cycle=([0-9.]+)", re.sub(r"\x1b\[[0-9;]*m", "", line))
        if g and g.group(2) in seeds:
            curves[seeds.index(g.group(2))].append((int(g.group(1)), float(g.group(3))))
    def subset(sub):
        tag = "m" + "".join(map(str, sorted(sub)))
        path = f"{d}/mem-s{s}/member-{sub[0]}.onnx" if len(sub) == 1 else f"{out}/{tag}.onnx"
        if not os.path.exists(path):
            run("model", "combine", *[f"{d}/mem-s{s}/member-{i}.onnx" for i in sorted(sub)], "--out", path, "--data", train, "--seed", str(s))
        return {"gt": scores(path, gt, f"{out}/{tag}-gt.json"), "val": scores(path, val, f"{out}/{tag}-val.json")}
    members = range(len(best))
    subs = {sub: subset(sub) for r in range(1, len(best) + 1) for sub in itertools.combinations(members, r)}
    rows = {"member 0 (--population 1)": subs[(0,)]}
    by_key = sorted(members, key=lambda i: -best[i])
    for name, fractions in (("25,50", [0.25, 0.5]), ("50", [0.5]), ("75", [0.75]), ("none", [])):
        alive = list(members)
        for f in fractions:
            e = int(1100 * f)
            key = {i: st.mean(k for ep, k in curves[i] if e - 75 < ep <= e) for i in alive}
            alive = sorted(alive, key=lambda i: -key[i])[: max(2, len(alive) // 2)]
        alive.sort(key=lambda i: -best[i])
        for m in range(1, len(alive) + 1):
            rows[f"halving {name}, best {m}"] = subs[tuple(sorted(alive[:m]))]
    rows["exported"] = {"gt": scores(f"{d}/s{s}.onnx", gt, f"{out}/export-gt.json"), "val": scores(f"{d}/s{s}.onnx", val, f"{out}/export-val.json")}
    rows["best member by key"] = subs[(by_key[0],)]
    on_gt = max(subs, key=lambda sub: subs[sub]["gt"][0][0])
    rows["labelled choice (GT)"] = subs[on_gt]
    label = max(subs, key=lambda sub: subs[sub]["val"][0][0])
    rows["labelled choice (VAL)"] = subs[label]
    keys = ", ".join(f"{100 * best[i]:.2f} ({i})" for i in by_key)
    tag = lambda sub: "m" + "".join(map(str, sub))
    rows["_about"] = f"keys {keys}; labelled choice {tag(on_gt)} on GT, {tag(label)} on VAL"
    return rows


def main():
    d, train, gt, val, *seeds = sys.argv[1:]
    all_rows = {s: seed_rows(d, train, gt, val, s) for s in seeds}
    f = lambda x: f"{x[0]:.2f} / {x[1]:.2f}"
    print("| choice | GT pairwise | GT identities | VAL pairwise | VAL identities | VAL worst pairwise ACC |")
    print("|---|---|---|---|---|---|")
    for name in all_rows[seeds[0]]:
        if name.startswith("_"):
            continue
        v = [all_rows[s][name] for s in seeds if name in all_rows[s]]
        mean = lambda d_, i: (st.mean(x[d_][i][0] for x in v), st.mean(x[d_][i][1] for x in v))
        print(f"| {name} | {f(mean('gt', 0))} | {f(mean('gt', 1))} | {f(mean('val', 0))} | {f(mean('val', 1))} | {min(x['val'][0][0] for x in v):.2f} |")
    print()
    print("| seed | member 0: VAL pairwise / identities | best member by key | **exported: pairwise** | **identities** "
          "| labelled choice on GT: VAL pairwise | gap | labelled choice on VAL | gap | about |")
    print("|---:|---|---|---|---|---|---:|---|---:|---|")
    for s in seeds:
        r = all_rows[s]
        both = lambda x: f"{f(x['val'][0])} / {f(x['val'][1])}"
        gap = lambda name: r["exported"]["val"][0][0] - r[name]["val"][0][0]
        print(f"| {s} | {both(r['member 0 (--population 1)'])} | {both(r['best member by key'])} | "
              f"{f(r['exported']['val'][0])} | {f(r['exported']['val'][1])} | "
              f"{f(r['labelled choice (GT)']['val'][0])} | {gap('labelled choice (GT)'):+.2f} | "
              f"{f(r['labelled choice (VAL)']['val'][0])} | {gap('labelled choice (VAL)'):+.2f} | {r['_about']} |")


if __name__ == "__main__":
    main()

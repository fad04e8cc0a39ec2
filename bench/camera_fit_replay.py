"""The camera fit's settings moved, on the looks `bench/camera_fit.sh` leaves in its OUT folder:
replays each run's per-pair contrasts (`fit-check --json`) through a copy of
`crossview_core::fit::FitWatch` with one setting changed, and counts the moves named within
60 s and the false-alarm looks (BENCHMARKS.md, "Camera fit", the ±50 % table). With the
defaults it gives what `fit-check` itself gave (check it: the first line). The newest-frames
setting changes the contrasts themselves: for it, run `FIT_ARGS='--recent 30'
bash bench/camera_fit.sh` instead.

Usage: python bench/camera_fit_replay.py OUT [OUT_TRAIN]
  OUT        a camera_fit.sh folder (validation frames and the simulator)
  OUT_TRAIN  one made with PART=train (its WILDTRACK runs are used instead, with OUT's
             simulator runs: the choosing sets)
"""
import glob
import json
import os
import sys

DEFAULT = dict(min_baseline=0.15, drifting=0.8, misfit=0.7, confirm=2)


class Watch:
    """crossview_core::fit::FitWatch, setting for setting."""

    def __init__(self, n, min_baseline, drifting, misfit, confirm):
        self.n, self.mb, self.dr, self.mf, self.cf = n, min_baseline, drifting, misfit, confirm
        self.pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
        self.base = [None] * len(self.pairs)
        self.hist = [[] for _ in range(n)]
        self.state = ["unknown"] * n

    def look(self, contrast, silent):
        fits = lambda c: self.state[c] in ("fits", "unknown")
        for k, (a, b) in enumerate(self.pairs):
            if self.base[k] is None and contrast[k] is not None and fits(a) and fits(b) \
                    and not silent[a] and not silent[b]:
                self.base[k] = contrast[k]
        ratios = [(contrast[k] / self.base[k], self.base[k])
                  if self.base[k] is not None and contrast[k] is not None and self.base[k] >= self.mb
                  else None for k in range(len(self.pairs))]
        aside, scores = [False] * self.n, [None] * self.n
        for _ in range(self.n // 2 + 1):
            kept = sorted(r[0] for (a, b), r in zip(self.pairs, ratios)
                          if r and not aside[a] and not aside[b])
            g = kept[len(kept) // 2] if kept else None
            g = g if g is not None and g > 0 else None
            for c in range(self.n):
                if aside[c]:
                    continue
                s = w = 0.0
                for (a, b), r in zip(self.pairs, ratios):
                    if c in (a, b) and not aside[a] and not aside[b] and r:
                        s, w = s + r[0] * r[1], w + r[1]
                scores[c] = s / w / g if g is not None and w > 0 else None
            low = [(scores[c], c) for c in range(self.n)
                   if not aside[c] and scores[c] is not None and scores[c] < self.mf]
            if low and sum(aside) < self.n // 2:
                aside[min(low)[1]] = True
            else:
                break
        for c in range(self.n):
            self.state[c] = self.step(c, scores[c], silent[c])
        return self.state

    def step(self, c, score, silent):
        if silent:
            return "silent"
        if score is None:
            return "unknown"
        h = self.hist[c]
        h.append(score)
        if len(h) > max(self.cf, 1):
            h.pop(0)
        full = len(h) >= max(self.cf, 1)
        if self.state[c] == "does_not_fit" and not (full and all(x >= self.dr for x in h)):
            return "does_not_fit"
        if full and all(x < self.mf for x in h):
            return "does_not_fit"
        return "drifting" if score < self.dr else "fits"


def run(path, moved, t0, step, fps, settings):
    looks = [json.loads(l) for l in open(path)]
    names = [c["name"] for c in looks[0]["cameras"]]
    w, named, alarms = Watch(len(names), **settings), None, 0
    for look in looks:
        states = w.look([p.get("contrast") for p in look["pairs"]],
                        [c["state"] == "silent" for c in look["cameras"]])
        for c, s in enumerate(states):
            if names[c] == moved and look["as_of_frame"] >= t0:
                if named is None and s == "does_not_fit":
                    named = (look["as_of_frame"] - t0) / step / fps
            elif s == "does_not_fit":
                alarms += 1
    return named, alarms


def suite(wild, sim, settings):
    """Named within 60 s (WILDTRACK pans, WILDTRACK zooms, simulator pans, simulator zooms)
    and false-alarm looks over every run."""
    def moves(folder, kind):
        return sorted(f for f in glob.glob(os.path.join(folder, f"w_*_{kind}.json")))
    wild_cam = lambda f: os.path.basename(f).split("_")[1]
    pans = [run(f, wild_cam(f), 1440, 5, 2, settings) for k in ("pan", "panl") for f in moves(wild, k)]
    zooms = [run(f, wild_cam(f), 1440, 5, 2, settings) for f in moves(wild, "zoom")]
    sim_runs = sorted(glob.glob(os.path.join(sim, "s_*_*.json")))
    sim_cam = lambda f: "cam%d" % (int(os.path.basename(f).split("_")[1]) % 4)
    spans = [run(f, sim_cam(f), 600, 1, 10, settings) for f in sim_runs if "zoom" not in f]
    szooms = [run(f, sim_cam(f), 600, 1, 10, settings) for f in sim_runs if "zoom" in f]
    still = [run(f, "-", 0, 5, 2, settings) for f in glob.glob(os.path.join(wild, "w_still.json"))
             + glob.glob(os.path.join(wild, "w_lag_*.json"))]
    still += [run(f, "-", 0, 1, 10, settings) for f in sorted(glob.glob(os.path.join(sim, "n_*.json")))]
    within = lambda runs: f"{sum(1 for n, _ in runs if n is not None and n <= 60)}/{len(runs)}"
    alarms = sum(a for _, a in pans + zooms + spans + szooms + still)
    return (f"WILDTRACK pans {within(pans)}, zooms {within(zooms)}; simulator pans {within(spans)}, "
            f"zooms {within(szooms)}; false-alarm looks {alarms}")


def main():
    sim = sys.argv[1]
    wild = sys.argv[2] if len(sys.argv) > 2 else sim
    print("defaults:", suite(wild, sim, DEFAULT))
    for key in ("misfit", "drifting", "min_baseline", "confirm"):
        for factor in (0.5, 1.5):
            value = DEFAULT[key] * factor
            value = max(1, round(value)) if key == "confirm" else round(value, 4)
            print(f"{key} {value}:", suite(wild, sim, {**DEFAULT, key: value}))


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Summary of bench/overload.sh's load-tester reports.

  overload_summary.py capacity OUT SCENES    median associated frames/s per scene of the
                                             capacity-*.json runs (printed alone)
  overload_summary.py table OUT SCENES CAPACITY FACTOR...
                                             one Markdown row per run
"""
import glob
import json
import statistics
import sys


def load(path):
    with open(path) as f:
        return json.load(f)


def associated_per_s(r):
    """Frames associated (results not shed) per second of the run."""
    secs = max(r["send_seconds"], 1e-9)
    return (r["results"] - r.get("results_shed", 0)) / secs


def server(r, metric):
    for c in r.get("server_comparison") or []:
        if c["metric"] == metric:
            return c["server"]
    return None


def capacity(out, scenes):
    runs = [load(p) for p in sorted(glob.glob(f"{out}/capacity-*.json"))]
    per_scene = [associated_per_s(r) / scenes for r in runs]
    print(f"{statistics.median(per_scene):.2f}")


def rss(r):
    s = r.get("server_rss") or {}
    series = [kib for _, kib in s.get("series", [])]
    half = series[len(series) // 2:] or series
    return (f"{s.get('max_kib', 0) / 1024:.0f} MB (second half {min(half) / 1024:.0f}–"
            f"{max(half) / 1024:.0f})") if series else "-"


def table(out, scenes, cap, factors):
    print("| run | frames/s per scene | associated/s | shed (client / server) | refused late "
          "| partial though complete when sent | cut by overload | complete p50 / p99 / max ms "
          "| after: p99 ms (0.8×, frames sent 2–5 s after) | peak RSS | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for f in factors:
        for p in sorted(glob.glob(f"{out}/x{f}-[0-9].json")):
            r = load(p)
            l = r["latency_complete"]
            after = p.replace(".json", "-after.json")
            try:
                a = load(after)["latency_complete"]
                after_s = f"{a['p99_ms']:.0f}"
            except (OSError, ValueError, KeyError):
                after_s = "-"
            name = p.rsplit("/", 1)[1][:-5]
            print(f"| {name} | {r['rate_fps_per_scene']} ({float(f):.2f}×) "
                  f"| {associated_per_s(r):.0f} "
                  f"| {r.get('results_shed', 0)} / {server(r, 'crossview_frames_shed_total')} "
                  f"| {r['batches_rejected'].get('late', 0)} | {r.get('partial_all_accepted', 0)} "
                  f"| {r.get('frames_cut_by_overload', 0)} "
                  f"| {l['p50_ms']:.0f} / {l['p99_ms']:.0f} / {l['max_ms']:.0f} | {after_s} "
                  f"| {rss(r)} | {'PASS' if r['passed'] else 'FAIL: ' + '; '.join(r['failures'])} |")


if __name__ == "__main__":
    if sys.argv[1] == "capacity":
        capacity(sys.argv[2], int(sys.argv[3]))
    else:
        table(sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), sys.argv[5:])

#!/usr/bin/env python3
"""Accuracy of `crossview sync-check` on simulated scenes with injected camera lags.

For each seed: simulate a held-out scene (detector noise on), then run `sync-check
--simulate-lag` with lags of 0, ±1, ±3, ±10 frames on one camera and ±1, ±3, ±10 on two cameras
at once (opposite signs, so the two differ by twice the lag). A run is *exact* when every camera
has an offset and every camera pair's difference equals the injected one to the frame
(reference-free). Also checks that a static scene (people move ~1 mm a frame: --fps 1000) and a
camera that sees other people (its batches taken from another seed's scene: no overlap) answer
"unknown".

With --data REC instead (a recording known to be in sync, e.g. the WILDTRACK detections):
the recording as it is, then every camera in turn delayed by each of --delays frame steps.

Usage: bench/sync_offsets.py --bin target/release/crossview --model M --preset square4 [--seeds 20]
       bench/sync_offsets.py --bin target/release/crossview --model M --data REC [--delays 1,2,4]
Prints a Markdown table; --json FILE writes every run.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile


def simulate(binary, preset, frames, seed, out, extra=()):
    subprocess.run(
        [binary, "simulate", "--preset", preset, "--frames", str(frames), "--seed", str(seed),
         "--no-ids", "--out", out, *extra],
        check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def sync_check(binary, model, data, lags, max_offset):
    cmd = [binary, "sync-check", "--model", model, "--data", data, "--json",
           "--max-offset", str(max_offset)]
    for cam, lag in lags.items():
        cmd += ["--simulate-lag", f"{cam}:{lag}"]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out)


def exact(report, lags):
    """Every camera known and every pair's difference equal to the injected one."""
    return outcome(report, lags)[0] == "right", outcome(report, lags)[1]


def outcome(report, lags):
    """("right" | "unknown" | "wrong", largest refined error in steps over the known pairs):
    right when every camera is known and every pair's difference is the injected one; unknown
    when some camera is unknown and every known pair is right; wrong when any known pair is
    off (a wrong number, the failure that matters)."""
    cams = report["cameras"]
    step = report["step"]
    errs = []
    wrong = False
    for a in cams:
        for b in cams:
            if a["frames"] is None or b["frames"] is None:
                continue
            want = (lags.get(b["name"], 0) - lags.get(a["name"], 0)) * step
            if b["frames"] - a["frames"] != want:
                wrong = True
            errs.append(abs(b["refined"] - a["refined"] - want) / step)
    err = max(errs) if errs else None
    if wrong:
        return "wrong", err
    if any(c["frames"] is None for c in cams):
        return "unknown", err
    return "right", err


def swap_camera(base, other, camera, out):
    """`base` with `camera`'s batches replaced by those of `other` (another scene's people)."""
    with open(base) as f, open(other) as g, open(out, "w") as w:
        theirs = [l for l in g.readlines()[1:] if json.loads(l)["camera"] == camera]
        lines = f.readlines()
        w.write(lines[0])
        w.writelines(l for l in lines[1:] if json.loads(l)["camera"] != camera)
        w.writelines(theirs)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--bin", default="target/release/crossview")
    p.add_argument("--model", required=True)
    p.add_argument("--preset", default="square4")
    p.add_argument("--seeds", type=int, default=20)
    p.add_argument("--first-seed", type=int, default=100)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--max-offset", type=int, default=20)
    p.add_argument("--json")
    p.add_argument("--data", help="a recording in sync: delay every camera in turn")
    p.add_argument("--delays", default="1,2,4")
    args = p.parse_args()
    if args.data:
        return delays(args)

    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            data = os.path.join(tmp, f"s{seed}.jsonl")
            simulate(args.bin, args.preset, args.frames, seed, data)
            names = [c["name"] for c in json.loads(open(data).readline())["scene"]["cameras"]]
            n = len(names)
            one, two = names[seed % n], names[(seed + 1) % n]
            cases = [("1 camera", {one: l}) for l in (0, 1, -1, 3, -3, 10, -10)]
            cases += [("2 cameras", {one: l, two: -l}) for l in (1, -1, 3, -3, 10, -10)]
            for kind, lags in cases:
                r = sync_check(args.bin, args.model, data, lags, args.max_offset)
                got, err = outcome(r, lags)
                lag = max(abs(v) for v in lags.values())
                runs.append({"seed": seed, "kind": kind, "lag": lag, "lags": lags,
                             "exact": got == "right", "outcome": got,
                             "max_refined_error_frames": err})
            # A static scene and a camera with no overlap.
            static = os.path.join(tmp, f"static{seed}.jsonl")
            simulate(args.bin, args.preset, args.frames, seed, static, ["--fps", "1000"])
            r = sync_check(args.bin, args.model, static, {}, args.max_offset)
            quiet = all(c["frames"] is None for c in r["cameras"])
            runs.append({"seed": seed, "kind": "static scene", "lag": 0, "exact": quiet,
                         "outcome": "right" if quiet else "wrong"})
            other = os.path.join(tmp, f"o{seed}.jsonl")
            simulate(args.bin, args.preset, args.frames, seed + 10_000, other)
            swapped = os.path.join(tmp, f"x{seed}.jsonl")
            swap_camera(data, other, one, swapped)
            r = sync_check(args.bin, args.model, swapped, {}, args.max_offset)
            cams = {c["name"]: c for c in r["cameras"]}
            # Right: the swapped camera unknown, every other at 0; unknown: the swapped one
            # unknown and some other too (weak profiles), never a number; wrong otherwise.
            others = [c["frames"] for k, c in cams.items() if k != one]
            if cams[one]["frames"] is not None or any(f not in (None, 0) for f in others):
                got = "wrong"
            else:
                got = "right" if all(f == 0 for f in others) else "unknown"
            runs.append({"seed": seed, "kind": "no overlap", "lag": 0,
                         "exact": got == "right", "outcome": got})
            print(f"seed {seed}: {sum(r['exact'] for r in runs if r['seed'] == seed)}"
                  f"/{sum(1 for r in runs if r['seed'] == seed)} right", file=sys.stderr)

    print(f"| preset | frames | case | lag (frames) | right | unknown | wrong | of | max refined error (frames) |")
    print("|---|---:|---|---:|---:|---:|---:|---:|---:|")
    keys = []
    for r in runs:
        k = (r["kind"], r["lag"])
        if k not in keys:
            keys.append(k)
    for kind, lag in keys:
        sel = [r for r in runs if r["kind"] == kind and r["lag"] == lag]
        errs = [r["max_refined_error_frames"] for r in sel if r.get("max_refined_error_frames") is not None]
        err = f"{max(errs):.2f}" if errs else "-"
        shown = "±" + str(lag) if lag else "0"
        count = lambda o: sum(r["outcome"] == o for r in sel)
        print(f"| {args.preset} | {args.frames} | {kind} | {shown} | {count('right')} | "
              f"{count('unknown')} | {count('wrong')} | {len(sel)} | {err} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f, indent=1)


def delays(args):
    """Every camera of an in-sync recording delayed in turn by each of --delays steps."""
    names = [c["name"] for c in json.loads(open(args.data).readline())["scene"]["cameras"]]
    runs = []
    r = sync_check(args.bin, args.model, args.data, {}, args.max_offset)
    ok, err = exact(r, {})
    runs.append({"delay": 0, "camera": "-", "exact": ok, "max_refined_error_frames": err,
                 "report": r})
    for d in [int(x) for x in args.delays.split(",")]:
        for cam in names:
            r = sync_check(args.bin, args.model, args.data, {cam: d}, args.max_offset)
            ok, err = exact(r, {cam: d})
            runs.append({"delay": d, "camera": cam, "exact": ok,
                         "max_refined_error_frames": err, "report": r})
            print(f"{cam} +{d}: {'right' if ok else 'WRONG'}", file=sys.stderr)
    print("| delay (frame steps) | cameras delayed in turn | right | max refined error (steps) | weakest camera confidence |")
    print("|---:|---:|---:|---:|---:|")
    for d in sorted({r["delay"] for r in runs}):
        sel = [r for r in runs if r["delay"] == d]
        errs = [r["max_refined_error_frames"] for r in sel if r["max_refined_error_frames"] is not None]
        conf = min(c["confidence"] for r in sel for c in r["report"]["cameras"])
        err = f"{max(errs):.2f}" if errs else "-"
        print(f"| {d} | {len(sel) if d else 'none'} | {sum(r['exact'] for r in sel)}/{len(sel)} | {err} | {conf:.2f} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(runs, f, indent=1)


if __name__ == "__main__":
    main()

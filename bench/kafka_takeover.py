"""Kafka mode takeover benchmark (BENCHMARKS.md, "Kafka mode"; run by bench/kafka_takeover.sh).

A fresh Apache Kafka broker (one node, scripts/kafka/broker.sh, in a temporary folder; its log
is kept as runN.broker.log), an 8-partition input topic (Kafka's TopicCommand), two `crossview
serve` replicas in one group with the shipped settings, 8 scenes of 7 cameras at 10 frames/s,
each frame's camera batches spread evenly over 50 ms (keyed by scene, the default
partitioner), and one of two cases:

* `--case kill` (the default): replica A killed with SIGKILL at --kill-at and restarted (as
  `a2`) at --restart-at;
* `--case rolling`: a rolling restart from --kill-at on: replica A gets SIGTERM, once it has
  exited it is started again (as `a2`) and, once that one's /readyz says it joined the group,
  the same for B (as `b2`). --restart-at is not used.
* `--case scale`: replica A alone at first; B and C start at --kill-at (1 -> 3 replicas) and
  get SIGTERM at --restart-at (3 -> 1).
* `--case camera`: two replicas; the last camera of every scene stops sending at --kill-at
  (for good): reports, per scene, the time from that camera's last batch written to the first
  partial result (missing it) written.

`--group-protocol classic|consumer` (default consumer) is passed to every replica as
`--kafka-group-protocol`; `--static-membership` gives each replica slot a static member id
(`--kafka-instance-id replica-a`, `replica-b`) that its restarted process keeps.
Afterwards every topic is read from the beginning with an independent client, and the run
prints:

* camera batches lost: batches the broker acknowledged that are in no result of their frame
  (their camera reported), and the dead-letter records;
* frames lost: frames sent with no result at all;
* takeover: for the scenes A published before the kill, the longest time from the kill to the
  first result of that scene published by another replica (rolling: for each step, the scenes
  whose last result before the SIGTERM was the stopped replica's, the longest time from the
  SIGTERM to a result of another; the longest of the steps, each also under `rolling`);
* survivor stall: for the scenes B published before the kill, the longest gap between two
  consecutive results of one scene (broker timestamps) from the kill to the end of sending;
  also the longest gap of any scene around the restart (rolling: of any scene from the first
  SIGTERM to the end of sending);
* duplicates: frames published more than once, whether each copy carries producer id and
  epoch, distinct per copy, and how many copies are partial.

Usage: python bench/kafka_takeover.py --crossview target/release/crossview --out DIR
         [--case kill|rolling --seconds 45 --kill-at 10 --restart-at 25 --run N
          --group-protocol classic|consumer --static-membership --broker-sh scripts/kafka/broker.sh]
"""

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

from confluent_kafka import OFFSET_BEGINNING, Consumer, Producer, TopicPartition

SCENES = 8
FPS = 10
SPREAD_S = 0.050
BROKER_SH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "scripts", "kafka", "broker.sh")


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def start_broker(script, run):
    """A fresh broker in a temporary folder: (folder, bootstrap host:port)."""
    d = tempfile.mkdtemp(prefix=f"crossview-kafka-run{run}-")
    r = subprocess.run(["bash", script, "start", d], capture_output=True, text=True)
    if r.returncode != 0:
        shutil.rmtree(d, ignore_errors=True)
        raise SystemExit(f"the Kafka broker did not start: {r.stderr.strip()[-2000:]}")
    return d, r.stdout.strip().splitlines()[-1]


def stop_broker(script, d, keep_log):
    subprocess.run(["bash", script, "stop", d], check=False)
    try:
        shutil.copy(os.path.join(d, "broker.log"), keep_log)
    except OSError:
        pass
    shutil.rmtree(d, ignore_errors=True)


def create_topic(script, broker, topic, partitions):
    subprocess.run(["bash", script, "tool", "org.apache.kafka.tools.TopicCommand",
                    "--bootstrap-server", broker, "--create", "--topic", topic,
                    "--partitions", str(partitions), "--replication-factor", "1"],
                   check=True, capture_output=True)


def metrics(port):
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2) as r:
            return r.read().decode()
    except OSError:
        return ""


def ready(port):
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=2) as r:
            return r.status == 200
    except OSError:
        return False


def owned(port):
    return {
        line.split('partition="')[1].split('"')[0]
        for line in metrics(port).splitlines()
        if line.startswith("crossview_kafka_assigned{") and line.endswith(" 1")
    }


class Replica:
    """A replica process: NAME is its producer id, SLOT its place in the group (a restarted
    replica keeps its slot; with --static-membership the slot is its group.instance.id)."""

    def __init__(self, args, broker, models, name, slot):
        self.port = free_port()
        self.name = name
        self.slot = slot
        cmd = [
            args.crossview, "serve", "--listen", f"127.0.0.1:{self.port}", "--model", models,
            "--kafka-brokers", broker, "--kafka-input-topic", "batches",
            "--kafka-output-topic", "results", "--kafka-dead-letter-topic", "dead",
            "--kafka-group", "replicas", "--kafka-producer-id", name,
        ]
        cmd += ["--kafka-group-protocol", args.group_protocol]
        if args.static_membership:
            cmd += ["--kafka-instance-id", f"replica-{slot}"]
        cmd += args.replica_args.split()
        self.started = time.time()
        log = open(os.path.join(args.out, f"run{args.run}.{name}.log"), "w")
        self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)

    def wait_ready(self, timeout=60):
        t = time.time()
        while time.time() - t < timeout:
            if ready(self.port):
                return time.time() - self.started
            time.sleep(0.05)
        raise SystemExit(f"replica {self.name} not ready after {timeout} s")

    def stop(self, timeout=30):
        """SIGTERM, then waits for the exit: its exit code (SIGKILL after `timeout` s: None)."""
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return None


def rolling_restart(a, broker, models, replicas, procs, steps):
    """Each replica in turn: SIGTERM, wait for its exit, start it again (same slot, producer id
    NAME2), wait for the new one's /readyz. Appends one dict per step to `steps`."""
    for old in replicas:
        step = {"replica": old.name, "sigterm_at": time.time()}
        steps.append(step)
        step["exit_code"] = old.stop()
        step["exited_at"] = time.time()
        new = Replica(a, broker, models, f"{old.slot}2", old.slot)
        procs.append(new.proc)
        try:
            new.wait_ready()
        except SystemExit as e:
            step["error"] = str(e)
            return
        step["ready_at"] = time.time()


def read_all(broker, topic):
    """Every record of `topic`, from the beginning to its end (no consumer group). The end is
    asked for again once reached, until it stays put: the broker may report a high watermark
    that lags the records it has acknowledged."""
    c = Consumer({"bootstrap.servers": broker, "group.id": "unused", "enable.auto.commit": False})
    parts = c.list_topics(topic, timeout=10).topics[topic].partitions
    out, next_of = [], {}
    t = time.time()
    while time.time() - t < 60:
        ends = {}
        for p in parts:
            _, hi = c.get_watermark_offsets(TopicPartition(topic, p), timeout=10)
            if hi > next_of.get(p, 0):
                ends[p] = hi
        if not ends:
            break
        c.assign([TopicPartition(topic, p, next_of.get(p, OFFSET_BEGINNING)) for p in ends])
        while ends and time.time() - t < 60:
            m = c.poll(0.5)
            if m is None or m.error():
                continue
            out.append(m)
            next_of[m.partition()] = m.offset() + 1
            if m.offset() + 1 >= ends.get(m.partition(), 0):
                ends.pop(m.partition(), None)
        time.sleep(0.5)
    c.close()
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--crossview", required=True)
    ap.add_argument("--broker-sh", default=BROKER_SH, help="scripts/kafka/broker.sh")
    ap.add_argument("--case", choices=["kill", "rolling", "scale", "camera"], default="kill")
    ap.add_argument("--group-protocol", choices=["classic", "consumer"], default="consumer",
                    help="--kafka-group-protocol of the replicas")
    ap.add_argument("--static-membership", action="store_true",
                    help="--kafka-instance-id per replica slot (kept across its restart)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seconds", type=float, default=45)
    ap.add_argument("--kill-at", type=float, default=10)
    ap.add_argument("--restart-at", type=float, default=25)
    ap.add_argument("--run", default="1")
    ap.add_argument("--replica-args", default="", help="extra `crossview serve` flags")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    rec = os.path.join(a.out, "rec.jsonl")
    model = os.path.join(a.out, "model.onnx")
    if not os.path.exists(model):
        subprocess.run([a.crossview, "simulate", "--preset", "wildtrack", "--frames", "600",
                        "--seed", "11", "--out", rec], check=True, capture_output=True)
        subprocess.run([a.crossview, "model", "init", "--scene-from", rec, "--out", model,
                        "--width", "64"], check=True, capture_output=True)
    with open(rec) as f:
        header = json.loads(f.readline())
        lines = [json.loads(x) for x in f]
    scene = header["scene"]["name"]
    cameras = [c["name"] if isinstance(c, dict) else c for c in header["scene"]["cameras"]]
    by_frame = {}
    for b in lines:
        by_frame.setdefault(b["frame_id"], {})[b["camera"]] = b
    frame_ids = sorted(by_frame)
    names = [f"{scene}-{i}" for i in range(SCENES)]
    models = ",".join(f"{n}={model}" for n in names)

    broker_dir, broker = start_broker(a.broker_sh, a.run)
    procs = []
    steps, roller = [], None
    try:
        for t, n in (("batches", 8), ("results", 1), ("dead", 1)):
            create_topic(a.broker_sh, broker, t, n)
        ra = Replica(a, broker, models, "a", "a")
        procs.append(ra.proc)
        group = [ra]
        if a.case != "scale":
            rb = Replica(a, broker, models, "b", "b")
            procs.append(rb.proc)
            group.append(rb)
        ready_a = ra.wait_ready()
        ready_b = rb.wait_ready() if a.case != "scale" else 0.0
        t = time.time()
        while len(set().union(*(owned(r.port) for r in group))) < 8 and time.time() - t < 60:
            time.sleep(0.1)
        settle = time.time() - ra.started
        extra = []

        acked, failed = [], [0]

        created, ack_delay = {}, {}

        def on_delivery(err, msg):
            if err is None:
                key = (msg.key().decode(), json.loads(msg.value())["camera"],
                       json.loads(msg.value())["frame_id"])
                acked.append(key)
                created[key] = msg.timestamp()[1] / 1000.0
                ack_delay[key] = time.time() - created[key]
            else:
                failed[0] += 1

        p = Producer({"bootstrap.servers": broker, "linger.ms": 1, "enable.idempotence": True})
        # The schedule: frame k of every scene at k / FPS, camera c at c * SPREAD / (n - 1).
        events = []
        n_frames = int(a.seconds * FPS)
        for k in range(n_frames):
            # The recording's detections, looped; frame ids keep growing.
            fid = k + 1
            src = by_frame[frame_ids[k % len(frame_ids)]]
            for ci, cam in enumerate(cameras):
                if cam not in src:
                    continue
                at = k / FPS + ci * SPREAD_S / max(1, len(cameras) - 1)
                body = dict(src[cam])
                body["frame_id"] = fid
                events.append((at, json.dumps(body)))
        events.sort(key=lambda e: e[0])
        t0 = time.time()
        killed_at = restarted_at = None
        ra2 = None
        i = 0
        while i < len(events):
            now = time.time() - t0
            if killed_at is None and now >= a.kill_at:
                killed_at = time.time()
                if a.case == "kill":
                    ra.proc.send_signal(signal.SIGKILL)
                elif a.case == "rolling":
                    roller = threading.Thread(target=rolling_restart, daemon=True,
                                              args=(a, broker, models, [ra, rb], procs, steps))
                    roller.start()
                elif a.case == "scale":
                    extra = [Replica(a, broker, models, n, n) for n in ("b", "c")]
                    procs += [r.proc for r in extra]
            if a.case in ("kill", "scale") and restarted_at is None and now >= a.restart_at:
                if a.case == "kill":
                    ra2 = Replica(a, broker, models, "a2", "a")
                    procs.append(ra2.proc)
                else:
                    for r in extra:
                        r.proc.send_signal(signal.SIGTERM)
                restarted_at = time.time()
            at, body = events[i]
            if at > now:
                p.poll(min(at - now, 0.005))
                continue
            if a.case == "camera" and at >= a.kill_at and json.loads(body)["camera"] == cameras[-1]:
                i += 1
                continue
            for n in names:
                p.produce("batches", key=n, value=body, on_delivery=on_delivery)
            p.poll(0)
            i += 1
        sent_end = time.time()
        p.flush(30)
        del p  # closed before the broker stops
        if roller is not None:  # a rolling restart still under way when sending ended
            roller.join(120)
        # Drain: wait 5 s for the last results.
        time.sleep(5)
        res = read_all(broker, "results")
        dead = read_all(broker, "dead")
    finally:
        for pr in procs:
            if pr.poll() is None:
                pr.send_signal(signal.SIGTERM)
        for pr in procs:
            try:
                pr.wait(15)
            except subprocess.TimeoutExpired:
                pr.kill()
        stop_broker(a.broker_sh, broker_dir, os.path.join(a.out, f"run{a.run}.broker.log"))

    results = []
    for m in res:
        v = json.loads(m.value())
        results.append({
            "scene": v["scene"], "frame": v["frame_id"], "missing": v.get("missing_cameras") or [],
            "producer": (v.get("producer") or {}).get("id"),
            "epoch": (v.get("producer") or {}).get("epoch"), "ts": m.timestamp()[1] / 1000.0,
            "latency_ms": v.get("latency_ms"),
        })
    reported = {}
    copies = {}
    for r in results:
        key = (r["scene"], r["frame"])
        copies.setdefault(key, []).append(r)
        reported.setdefault(key, set()).update(c for c in cameras if c not in r["missing"])
    frames_sent = {(s, f) for s, _, f in acked}
    batches_lost = sum(1 for s, c, f in acked if c not in reported.get((s, f), set()))
    frames_lost = sum(1 for k in frames_sent if k not in copies)
    # How late the source itself sent each lost batch: its create time less the earliest of
    # its frame's batches (the producer here runs on the same loaded cores, so it can fall
    # behind its 50 ms schedule); beyond the sync timeout the batch was late at the source.
    first_sent = {}
    for (s_, c_, f_), t in created.items():
        first_sent[(s_, f_)] = min(t, first_sent.get((s_, f_), t))
    lost_spread = sorted(created[(s_, c_, f_)] - first_sent[(s_, f_)]
                         for s_, c_, f_ in acked if c_ not in reported.get((s_, f_), set()))
    # A run too short to reach the kill (or the restart) has no such phase. Rolling: from the
    # first SIGTERM (killed_at) until the last restarted replica is ready (restarted_at).
    killed_at = killed_at if killed_at is not None else float("inf")
    if a.case == "rolling":
        last_ready = steps[-1].get("ready_at") if len(steps) == 2 else None
        restarted_at = last_ready if last_ready is not None else float("inf")
        phases = ("before-roll", "rolling", "after-roll")
    else:
        restarted_at = restarted_at if restarted_at is not None else float("inf")
        phases = ("before-kill", "kill-restart", "after-restart")

    def phase_of(t):
        return phases[0] if t < killed_at else (phases[1] if t < restarted_at else phases[2])

    # A few of the lost batches and frames, to look up in the replicas' logs
    # (run N.<replica>.log): scene, frame, camera, seconds since sending began, phase, and how
    # long the broker took to acknowledge it to this producer (a late acknowledgement: the
    # batch reached the broker late, the source's doing).
    lost_examples = [
        (s_, f_, c_, round(created[(s_, c_, f_)] - t0, 3), phase_of(created[(s_, c_, f_)]),
         round(ack_delay[(s_, c_, f_)], 3))
        for s_, c_, f_ in acked if c_ not in reported.get((s_, f_), set())
    ][:20]
    dups = {k: v for k, v in copies.items() if len(v) > 1}
    dup_tagged = all(c["producer"] and c["epoch"] is not None for v in dups.values() for c in v)
    dup_distinct = all(len({(c["producer"], c["epoch"]) for c in v}) == len(v) for v in dups.values())
    partial_copies = sum(1 for v in dups.values() for c in v if c["missing"])
    partial = sum(1 for r in results if r["missing"])
    before = [r for r in results if r["ts"] < killed_at]
    a_scenes = {r["scene"] for r in before if r["producer"] == "a"}
    b_scenes = {r["scene"] for r in before if r["producer"] == "b"}
    takeover = 0.0
    for s in a_scenes:
        later = [r["ts"] for r in results if r["scene"] == s and r["ts"] >= killed_at and r["producer"] != "a"]
        takeover = max(takeover, (min(later) - killed_at) if later else float("inf"))

    def handover(victim, t_stop):
        """For the scenes whose last result before t_stop was victim's, the longest time from
        t_stop to a result of that scene by another replica."""
        last = {}
        for r in sorted(results, key=lambda r: r["ts"]):
            if r["ts"] >= t_stop:
                break
            last[r["scene"]] = r["producer"]
        worst = 0.0
        for s in (s for s, prod in last.items() if prod == victim):
            later = [r["ts"] for r in results if r["scene"] == s and r["ts"] >= t_stop and r["producer"] != victim]
            worst = max(worst, (min(later) - t_stop) if later else float("inf"))
        return worst

    rolling = []
    for st in steps:
        step = {"replica": st["replica"], "sigterm_at_s": round(st["sigterm_at"] - t0, 2),
                "exit_code": st.get("exit_code"),
                "stop_s": round(st["exited_at"] - st["sigterm_at"], 2) if "exited_at" in st else None,
                "ready_s": round(st["ready_at"] - st["exited_at"], 2) if "ready_at" in st else None,
                "handover_s": round(handover(st["replica"], st["sigterm_at"]), 2)}
        if "error" in st:
            step["error"] = st["error"]
        rolling.append(step)
    if a.case == "rolling":
        takeover = max((x["handover_s"] for x in rolling), default=0.0)
    if a.case in ("scale", "camera"):
        takeover = 0.0
    # Case camera: per scene, from the stopped camera's last batch written to the first result
    # missing it.
    stopped_to_partial = []
    if a.case == "camera":
        gone = cameras[-1]
        for s_ in names:
            last = max((t for (sc, c_, _), t in created.items() if sc == s_ and c_ == gone),
                       default=None)
            first = min((r["ts"] for r in results if r["scene"] == s_ and gone in r["missing"]),
                        default=None)
            if last is not None and first is not None:
                stopped_to_partial.append(round(first - last, 3))

    def max_gap(scenes, start, end):
        worst = 0.0
        for s in scenes:
            ts = sorted(r["ts"] for r in results if r["scene"] == s and start <= r["ts"] <= end)
            worst = max([worst] + [b - a_ for a_, b in zip(ts, ts[1:])])
        return worst

    reasons = {}
    for m in dead:
        why = dict(m.headers() or []).get("crossview-error", b"").decode()
        when = m.timestamp()[1] / 1000.0
        k = f"{phase_of(when)}: {why.split(':')[0][:40]}"
        reasons[k] = reasons.get(k, 0) + 1
    partial_when = {}
    for r in results:
        if r["missing"]:
            phase = phase_of(r["ts"])
            partial_when[phase] = partial_when.get(phase, 0) + 1
    # End to end: from the frame's last camera batch written (its create time) to the first
    # result of the frame written to the output topic (its create time), complete frames only.
    last_sent = {}
    for (s_, c_, f_), t in created.items():
        last_sent[(s_, f_)] = max(last_sent.get((s_, f_), t), t)
    first_result = {}
    for r in results:
        if not r["missing"]:
            k = (r["scene"], r["frame"])
            first_result[k] = min(first_result.get(k, r["ts"]), r["ts"])
    e2e = sorted(first_result[k] - last_sent[k] for k in first_result if k in last_sent)
    # The same before the first kill / stop / start (steady state, two replicas).
    e2e_steady = sorted(first_result[k] - last_sent[k] for k in first_result
                        if k in last_sent and first_result[k] < killed_at)

    def pct(xs, q):
        return round(xs[min(len(xs) - 1, int(q * len(xs)))] * 1000, 1) if xs else None
    report = {
        "run": a.run, "case": a.case, "group_protocol": a.group_protocol,
        "e2e_ms_p50_p99": [pct(e2e, 0.5), pct(e2e, 0.99)],
        "e2e_ms_p50_p99_before_the_event": [pct(e2e_steady, 0.5), pct(e2e_steady, 0.99)],
        "static_membership": a.static_membership,
        "frames_sent": len(frames_sent), "batches_sent": len(acked),
        "batches_not_acked": failed[0], "results": len(results), "partial_results": partial,
        "camera_batches_lost": batches_lost, "dead_letters": len(dead), "frames_lost": frames_lost,
        "takeover_s": round(takeover, 2),
    }
    if a.case == "kill":
        report["survivor_max_stall_s"] = round(max_gap(b_scenes, killed_at, sent_end), 2)
        report["max_stall_any_scene_after_restart_s"] = round(
            max_gap(a_scenes | b_scenes, restarted_at, sent_end), 2)
    elif a.case == "scale":
        report["max_stall_any_scene_scaling_s"] = round(
            max_gap(set(names), killed_at, sent_end), 2)
    elif a.case == "camera":
        report["stopped_camera_to_partial_s"] = sorted(stopped_to_partial)
        report["max_stall_any_scene_s"] = round(max_gap(set(names), t0 + 2, sent_end), 2)
    else:
        report["rolling"] = rolling
        report["max_stall_any_scene_rolling_s"] = round(
            max_gap({r["scene"] for r in results}, killed_at, sent_end), 2)
    report.update({
        "duplicates": len(dups), "duplicates_partial_copies": partial_copies,
        "duplicates_all_with_producer_epoch": dup_tagged, "duplicate_copies_distinct": dup_distinct,
        "first_readyz_s": [round(ready_a, 2), round(ready_b, 2)], "all_assigned_s": round(settle, 2),
        "scenes_a_b": [len(a_scenes), len(b_scenes)],
        "dead_letter_reasons": reasons, "partial_results_by_phase": partial_when,
        "lost_examples": lost_examples,
        "partial_examples": [
            (r["scene"], r["frame"], r["producer"], r["latency_ms"], len(r["missing"]),
             round(r["ts"] - t0, 3))
            for r in results if r["missing"]
        ][:10],
        "lost_batches_sent_late_s": {
            "within_0.2": sum(1 for x in lost_spread if x <= 0.2),
            "beyond_0.2": sum(1 for x in lost_spread if x > 0.2),
            "max": round(lost_spread[-1], 3) if lost_spread else None,
        },
    })
    with open(os.path.join(a.out, f"run{a.run}.json"), "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())

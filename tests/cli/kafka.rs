//! Kafka mode against a real Kafka-protocol broker (tansu, started by the test on a free
//! loopback port; `make setup` fetches it): replicas of the real binary consume simulated
//! recordings' batch lines keyed by scene and produce frame results keyed by scene.
//!
//! Asserted: every accepted batch appears in a published result (its camera reported in a
//! result of its scene and frame); a malformed record is counted and skipped without stalling
//! its partition; a replica restarted in the same group resumes from the committed offsets
//! (nothing already published is published again after a graceful stop); with two replicas
//! sharing 8 scenes, one killed with SIGKILL mid-stream, the other takes its scenes over and
//! every batch still appears in a result, duplicates only as documented (a frame published
//! again after the takeover, by another producer or epoch), and counted.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use crossview_testing::kafka::Broker;
use crossview_testing::*;
use rdkafka::config::ClientConfig;
use rdkafka::consumer::{Consumer, StreamConsumer};
use rdkafka::message::{Header, Headers, Message, OwnedHeaders};
use rdkafka::producer::{FutureProducer, FutureRecord};
use serde_json::Value;

/// One batch line of a simulated recording: (camera, frame id, the line).
type Line = (String, u64, String);

fn simulate(bin: &str, dir: &std::path::Path, frames: u32) -> Vec<Line> {
    let out = dir.join("sim.jsonl");
    run_crossview(
        bin,
        &[
            "simulate",
            "--preset",
            "square4",
            "--frames",
            &frames.to_string(),
            "--seed",
            "3",
            "--clean",
            "--out",
            out.to_str().unwrap(),
        ],
        &[],
    );
    std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let v: Value = serde_json::from_str(l).unwrap();
            (
                v["camera"].as_str().unwrap().to_string(),
                v["frame_id"].as_u64().unwrap(),
                l.to_string(),
            )
        })
        .collect()
}

/// What every test starts from: a broker with topics `batches` and `results`, the binary,
/// and a simulated recording's batch lines.
struct Setup {
    broker: Broker,
    bin: &'static str,
    lines: Vec<Line>,
}

/// A fresh broker (`batches` with `partitions` partitions, `results` with one) and `frames`
/// simulated frames; `None` when there is no broker binary (see [`Broker::start`]).
fn setup(partitions: u32, frames: u32) -> Option<Setup> {
    let broker = Broker::start()?;
    broker.create_topic("batches", partitions);
    broker.create_topic("results", 1);
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    let lines = simulate(bin, tmp.path(), frames);
    Some(Setup { broker, bin, lines })
}

fn producer(broker: &Broker) -> FutureProducer {
    ClientConfig::new()
        .set("bootstrap.servers", &broker.addr)
        .set("linger.ms", "1")
        .create()
        .unwrap()
}

async fn send(p: &FutureProducer, topic: &str, key: Option<&str>, value: &str) {
    send_with(p, topic, key, value.as_bytes(), None).await
}

/// Produces one record, with a `content-type` header when given.
async fn send_with(
    p: &FutureProducer,
    topic: &str,
    key: Option<&str>,
    value: &[u8],
    content_type: Option<&str>,
) {
    let mut r = FutureRecord::<str, [u8]>::to(topic).payload(value);
    if let Some(k) = key {
        r = r.key(k);
    }
    if let Some(ct) = content_type {
        r = r.headers(OwnedHeaders::new().insert(Header {
            key: "content-type",
            value: Some(ct),
        }));
    }
    guard("produce", p.send(r, Duration::from_secs(20)))
        .await
        .unwrap();
}

/// Reads the output topic from the beginning (its own group).
struct Results {
    consumer: StreamConsumer,
    seen: Vec<Value>,
}

impl Results {
    fn new(broker: &Broker, topic: &str) -> Self {
        let consumer: StreamConsumer = ClientConfig::new()
            .set("bootstrap.servers", &broker.addr)
            .set("group.id", format!("checker-{topic}"))
            .set("auto.offset.reset", "earliest")
            .set("enable.auto.commit", "false")
            .create()
            .unwrap();
        consumer.subscribe(&[topic]).unwrap();
        Results {
            consumer,
            seen: Vec::new(),
        }
    }

    /// (scene, frame) → the cameras some result of it reported.
    fn covered(&self) -> BTreeMap<(String, u64), BTreeSet<String>> {
        let mut out: BTreeMap<(String, u64), BTreeSet<String>> = BTreeMap::new();
        for r in &self.seen {
            let key = (
                r["scene"].as_str().unwrap().to_string(),
                r["frame_id"].as_u64().unwrap(),
            );
            let missing: BTreeSet<&str> = r["missing_cameras"]
                .as_array()
                .map(|a| a.iter().filter_map(Value::as_str).collect())
                .unwrap_or_default();
            let entry = out.entry(key).or_default();
            // The reported cameras are those of the scene not listed as missing.
            for c in &SQUARE4 {
                if !missing.contains(c) {
                    entry.insert(c.to_string());
                }
            }
        }
        out
    }

    /// The batches of `expected` not yet covered by a result.
    fn uncovered(&self, expected: &[(String, String, u64)]) -> Vec<(String, String, u64)> {
        let covered = self.covered();
        expected
            .iter()
            .filter(|(s, c, f)| {
                !covered
                    .get(&(s.clone(), *f))
                    .is_some_and(|cams| cams.contains(c))
            })
            .cloned()
            .collect()
    }

    /// Reads results until every batch of `expected` is covered (bounded by a hang guard).
    async fn wait_cover(&mut self, expected: &[(String, String, u64)]) {
        let guard_for = Duration::from_secs(90);
        let t = std::time::Instant::now();
        loop {
            let left = self.uncovered(expected);
            if left.is_empty() {
                return;
            }
            assert!(
                t.elapsed() < guard_for,
                "hang guard: {} batches never appeared in a result, e.g. {:?}",
                left.len(),
                &left[..left.len().min(5)]
            );
            self.read_for(Duration::from_millis(500)).await;
        }
    }

    /// Reads whatever results arrive within `d`.
    async fn read_for(&mut self, d: Duration) {
        let until = tokio::time::Instant::now() + d;
        while let Ok(m) = tokio::time::timeout_at(until, self.consumer.recv()).await {
            let m = m.unwrap();
            let v = match header(&m, "content-type").as_deref() {
                Some("application/x-protobuf") => protobuf_result(&m),
                ct => {
                    assert_eq!(ct, Some("application/json"));
                    serde_json::from_slice(m.payload().unwrap()).unwrap()
                }
            };
            assert_eq!(
                m.key().map(|k| String::from_utf8_lossy(k).to_string()),
                v["scene"].as_str().map(String::from),
                "results are keyed by scene"
            );
            let producer = v["producer"]["id"].as_str().expect("producer.id");
            assert!(!producer.is_empty());
            assert!(v["producer"]["epoch"].as_u64().is_some(), "producer.epoch");
            self.seen.push(v);
        }
    }

    /// (scene, frame) published more than once, with the (producer, epoch) of each copy.
    fn duplicates(&self) -> BTreeMap<(String, u64), Vec<(String, u64)>> {
        let mut all: BTreeMap<(String, u64), Vec<(String, u64)>> = BTreeMap::new();
        for r in &self.seen {
            all.entry((
                r["scene"].as_str().unwrap().to_string(),
                r["frame_id"].as_u64().unwrap(),
            ))
            .or_default()
            .push((
                r["producer"]["id"].as_str().unwrap().to_string(),
                r["producer"]["epoch"].as_u64().unwrap(),
            ));
        }
        all.retain(|_, v| v.len() > 1);
        all
    }
}

/// The value of header `key` of `m`, if any.
fn header<M: Message>(m: &M, key: &str) -> Option<String> {
    let h = m.headers()?;
    (0..h.count())
        .map(|i| h.get(i))
        .find(|h| h.key == key)
        .and_then(|h| h.value.map(|v| String::from_utf8_lossy(v).to_string()))
}

/// A protobuf `FrameResult` record as the JSON fields the checks read (producer from the
/// headers).
fn protobuf_result<M: Message>(m: &M) -> Value {
    use prost::Message as _;
    let r = crossview_api::pb::FrameResult::decode(m.payload().unwrap()).expect("a FrameResult");
    serde_json::json!({
        "scene": r.scene,
        "frame_id": r.frame_id,
        "missing_cameras": r.missing_cameras,
        "identities": r.identities.len(),
        "producer": {
            "id": header(m, "crossview-producer").expect("crossview-producer header"),
            "epoch": header(m, "crossview-epoch").and_then(|e| e.parse::<u64>().ok()).expect("crossview-epoch header"),
        },
    })
}

/// The cameras of the simulator's `square4` preset (`models/demo.onnx`'s scene).
const SQUARE4: [&str; 4] = ["cam0", "cam1", "cam2", "cam3"];

fn model_args(scenes: &[String]) -> Vec<String> {
    let demo = repo_root().join("models/demo.onnx");
    scenes
        .iter()
        .flat_map(|s| ["--model".to_string(), format!("{s}={}", demo.display())])
        .collect()
}

fn kafka_args(broker: &Broker, group: &str, id: &str) -> Vec<String> {
    [
        "--kafka-brokers",
        &broker.addr,
        "--kafka-input-topic",
        "batches",
        "--kafka-output-topic",
        "results",
        "--kafka-group",
        group,
        "--kafka-producer-id",
        id,
        "--kafka-property",
        "session.timeout.ms=6000",
        "--kafka-property",
        "heartbeat.interval.ms=500",
        "--sync-timeout",
        "5s",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

async fn serve(bin: &str, args: &[String]) -> (ChildGuard, String) {
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let (child, base) = spawn_serve(bin, &args).await;
    // Ready once the consumer has joined its group.
    let http = reqwest::Client::new();
    guard("readiness", async {
        loop {
            let r = http.get(format!("{base}/readyz")).send().await;
            if r.is_ok_and(|r| r.status().is_success()) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await;
    (child, base)
}

/// Waits until the replica at `base` counted `malformed` malformed records, checks it counted
/// `accepted` accepted ones, and returns its metrics.
async fn records_counted(base: &str, accepted: usize, malformed: u32) -> String {
    wait_for_metric(
        base,
        "crossview_kafka_records_total{outcome=\"malformed\"}",
        malformed.into(),
    )
    .await;
    let m = metrics_text(base).await;
    assert_eq!(
        metric(&m, "crossview_kafka_records_total{outcome=\"accepted\"}"),
        accepted as f64,
        "{m}"
    );
    m
}

async fn metrics_text(base: &str) -> String {
    reqwest::get(format!("{base}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_replica_publishes_every_batch_skips_malformed_and_resumes_after_restart() {
    let Some(Setup {
        broker, bin, lines, ..
    }) = setup(4, 20)
    else {
        return;
    };
    broker.create_topic("dead", 1);
    let scenes: Vec<String> = vec!["north".into(), "south".into()];
    let mut args = model_args(&scenes);
    args.extend(kafka_args(&broker, "replicas", "r1"));
    args.extend(["--kafka-dead-letter-topic".into(), "dead".into()]);
    let (child, base) = serve(bin, &args).await;
    let p = producer(&broker);
    let mut results = Results::new(&broker, "results");

    // The first 10 frames of both scenes, with malformed records in the middle of `north`'s
    // partition (not JSON, not a batch, no key) and a rejected one (a scene nobody serves).
    let mut expected = Vec::new();
    for (i, (cam, frame, line)) in lines.iter().enumerate() {
        if *frame >= 10 {
            continue;
        }
        for s in &scenes {
            send(&p, "batches", Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
        if i == 8 {
            send(&p, "batches", Some("north"), "{not json").await;
            send(&p, "batches", Some("north"), r#"{"scene":"north"}"#).await;
            send(&p, "batches", None, &lines[0].2).await;
            send(&p, "batches", Some("nowhere"), &lines[0].2).await;
        }
    }
    results.wait_cover(&expected).await;
    let m = records_counted(&base, expected.len(), 3).await;
    assert!(m.contains("crossview_kafka_assigned{"), "{m}");
    // Consumer lag is exported per owned partition that holds records (librdkafka
    // statistics, every 2 s) and falls to 0 once everything is consumed and committed.
    let mut lags = Vec::new();
    for _ in 0..150 {
        let m = metrics_text(&base).await;
        lags = m
            .lines()
            .filter(|l| l.starts_with("crossview_kafka_consumer_lag{topic=\"batches\""))
            .map(String::from)
            .collect();
        if !lags.is_empty() && lags.iter().all(|l| l.ends_with(" 0")) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(
        !lags.is_empty() && lags.iter().all(|l| l.ends_with(" 0")),
        "consumer lag never reached 0: {lags:?}"
    );
    assert_eq!(
        metric(&m, "crossview_kafka_records_total{outcome=\"rejected\"}"),
        1.0,
        "{m}"
    );
    // The refused records went to the dead-letter topic, each saying why.
    let dead: StreamConsumer = ClientConfig::new()
        .set("bootstrap.servers", &broker.addr)
        .set("group.id", "checker-dead")
        .set("auto.offset.reset", "earliest")
        .create()
        .unwrap();
    dead.subscribe(&["dead"]).unwrap();
    let mut reasons = Vec::new();
    while reasons.len() < 4 {
        let m = guard("dead letters", dead.recv()).await.unwrap();
        let why = header(&m, "crossview-error").expect("crossview-error header");
        reasons.push(why);
    }
    assert!(reasons.iter().any(|r| r.contains("nowhere")), "{reasons:?}");
    assert!(
        results.duplicates().is_empty(),
        "{:?}",
        results.duplicates()
    );
    // Everything published has its offsets committed: a graceful stop, then a new replica in
    // the same group resumes after them.
    signal(&child, "TERM");
    let mut child = child;
    guard("replica exit", async {
        while child.try_wait().unwrap().is_none() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let before = results.seen.len();
    let mut args = model_args(&scenes);
    args.extend(kafka_args(&broker, "replicas", "r2"));
    let (_child, _base) = serve(bin, &args).await;
    for (cam, frame, line) in &lines {
        if *frame < 10 {
            continue;
        }
        for s in &scenes {
            send(&p, "batches", Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
    }
    results.wait_cover(&expected).await;
    results.read_for(Duration::from_secs(1)).await;
    let after: Vec<&Value> = results.seen[before..].iter().collect();
    assert!(
        after
            .iter()
            .all(|r| r["frame_id"].as_u64().unwrap() >= 10 && r["producer"]["id"] == "r2"),
        "the restarted replica re-published a frame already committed"
    );
    assert!(
        results.duplicates().is_empty(),
        "{:?}",
        results.duplicates()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn two_replicas_share_scenes_and_one_killed_hands_them_over() {
    let Some(Setup {
        broker, bin, lines, ..
    }) = setup(4, 24)
    else {
        return;
    };
    let scenes: Vec<String> = (0..8).map(|i| format!("scene{i}")).collect();
    let mut a_args = model_args(&scenes);
    a_args.extend(kafka_args(&broker, "replicas", "a"));
    let mut b_args = model_args(&scenes);
    b_args.extend(kafka_args(&broker, "replicas", "b"));
    let (mut a, a_base) = serve(bin, &a_args).await;
    let (_b, b_base) = serve(bin, &b_args).await;
    // Both own partitions once the group has settled.
    for base in [&a_base, &b_base] {
        guard("assignment", async {
            loop {
                let m = metrics_text(base).await;
                if m.lines()
                    .any(|l| l.starts_with("crossview_kafka_assigned{") && l.ends_with(" 1"))
                {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        })
        .await;
    }
    let p = producer(&broker);
    let mut results = Results::new(&broker, "results");
    let mut expected = Vec::new();
    for (cam, frame, line) in &lines {
        if *frame >= 12 {
            continue;
        }
        for s in &scenes {
            send(&p, "batches", Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
    }
    results.wait_cover(&expected).await;
    let producers: BTreeSet<&str> = results
        .seen
        .iter()
        .filter_map(|r| r["producer"]["id"].as_str())
        .collect();
    assert_eq!(
        producers,
        BTreeSet::from(["a", "b"]),
        "both replicas own scenes"
    );
    // Mid-stream: half of the rest sent, A killed, the rest sent.
    let rest: Vec<&Line> = lines.iter().filter(|(_, f, _)| *f >= 12).collect();
    let (first, second) = rest.split_at(rest.len() / 2);
    for (cam, frame, line) in first {
        for s in &scenes {
            send(&p, "batches", Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
    }
    signal(&a, "KILL");
    let _ = a.wait();
    for (cam, frame, line) in second {
        for s in &scenes {
            send(&p, "batches", Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
    }
    results.wait_cover(&expected).await;
    results.read_for(Duration::from_secs(1)).await;
    let dups = results.duplicates();
    eprintln!(
        "{} results, {} frames published more than once after the SIGKILL",
        results.seen.len(),
        dups.len()
    );
    for (frame, copies) in &dups {
        let distinct: BTreeSet<&(String, u64)> = copies.iter().collect();
        assert_eq!(
            distinct.len(),
            copies.len(),
            "{frame:?} published twice by one producer and epoch: {copies:?}"
        );
    }
    // B took A's scenes over: after the kill every scene's last frame came from B.
    let last = lines.iter().map(|(_, f, _)| *f).max().unwrap();
    for s in &scenes {
        assert!(
            results.seen.iter().any(|r| r["scene"] == s.as_str()
                && r["frame_id"].as_u64() == Some(last)
                && r["producer"]["id"] == "b"),
            "{s}: its last frame was not published by the surviving replica"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn protobuf_batches_in_and_protobuf_results_out() {
    let Some(Setup {
        broker, bin, lines, ..
    }) = setup(2, 6)
    else {
        return;
    };
    let scenes: Vec<String> = vec!["east".into()];
    let mut args = model_args(&scenes);
    args.extend(kafka_args(&broker, "proto", "p1"));
    args.extend(["--kafka-output-format".into(), "protobuf".into()]);
    let (_child, base) = serve(bin, &args).await;
    let p = producer(&broker);
    let mut results = Results::new(&broker, "results");
    // Even frames as protobuf `Batch` (named by the header), odd ones as JSON lines without
    // a header (the default input format); one record with a content type nobody reads.
    let mut expected = Vec::new();
    for (cam, frame, line) in &lines {
        let batch: crossview_core::Batch = serde_json::from_str(line).unwrap();
        if frame % 2 == 0 {
            use prost::Message as _;
            let pb = crossview_api::convert::batch_to_pb("east", &batch).encode_to_vec();
            send_with(
                &p,
                "batches",
                Some("east"),
                &pb,
                Some("application/x-protobuf"),
            )
            .await;
        } else {
            send(&p, "batches", Some("east"), line).await;
        }
        expected.push(("east".to_string(), cam.clone(), *frame));
        if expected.len() == 3 {
            send_with(
                &p,
                "batches",
                Some("east"),
                line.as_bytes(),
                Some("text/csv"),
            )
            .await;
        }
    }
    results.wait_cover(&expected).await;
    assert!(
        results
            .seen
            .iter()
            .all(|r| r["identities"].as_u64() > Some(0)),
        "every frame of the clean simulation associates someone"
    );
    records_counted(&base, expected.len(), 1).await;
}

//! Kafka mode against a real Apache Kafka broker (one per test binary, on a free loopback
//! port, each test on topics of its own; `make setup` resolves it from Maven Central):
//! replicas of the real binary consume simulated recordings' batch lines keyed by scene and
//! produce frame results keyed by scene.
//!
//! One module per guarantee: [`basic`] (one replica: every batch published, malformed records
//! skipped, resume after a restart, protobuf), [`rebalance`] (replicas joining, dying and
//! coming back mid-stream and mid-frame lose no camera batch), [`outage`] (a broker down at
//! start or gone mid-stream: not ready meanwhile, nothing lost), [`stream_time`] (a frame waits
//! on the stream, not the wall clock: a paused replica cuts no frame, a camera that stops
//! still yields partial frames, producers' clocks that are off cut nothing), [`capture_times`]
//! (batches stamped with capture times, in the value or the record, go to their tick).

mod basic;
mod capture_times;
mod outage;
mod rebalance;
mod stream_time;

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use crossview_testing::kafka::{Broker, Topics};
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

/// The capture times the cameras stamp their records with: frame `f` of camera `camN` at
/// `start_ms + f × 100 + N × spread_ms` (10 frames/s, each frame's cameras `spread_ms` apart).
#[derive(Debug, Clone, Copy)]
struct Capture {
    start_ms: i64,
    spread_ms: i64,
}

impl Capture {
    /// Capture starting now.
    fn live(spread_ms: i64) -> Self {
        Capture::from_ms_ago(0, spread_ms)
    }

    /// Capture that started `ago_ms` ago (a backlog).
    fn from_ms_ago(ago_ms: i64, spread_ms: i64) -> Self {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_millis() as i64;
        Capture {
            start_ms: now - ago_ms,
            spread_ms,
        }
    }

    /// The stamp of `camera`'s batch of `frame`.
    fn stamp(&self, camera: &str, frame: u64) -> i64 {
        let n: i64 = camera.trim_start_matches("cam").parse().unwrap_or(0);
        self.start_ms + frame as i64 * 100 + n * self.spread_ms
    }
}

/// What every test starts from: a broker with topics `batches` and `results`, the binary,
/// and a simulated recording's batch lines.
struct Setup {
    broker: &'static Broker,
    topics: Topics,
    bin: &'static str,
    lines: Vec<Line>,
}

/// The shared broker with fresh topics (`batches` with `partitions` partitions, `results` and
/// `dead` with one) and `frames` simulated frames; `None` without a broker (see
/// [`Broker::shared`]).
fn setup(partitions: u32, frames: u32) -> Option<Setup> {
    let broker = Broker::shared()?;
    let topics = broker.topics(partitions);
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    let lines = simulate(bin, tmp.path(), frames);
    Some(Setup {
        broker,
        topics,
        bin,
        lines,
    })
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
            // A broker away for a while (tests/cli/kafka/outage.rs) is an error event here.
            let Ok(m) = m else {
                continue;
            };
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

    /// The results read so far that miss a camera.
    fn partial(&self) -> Vec<&Value> {
        self.seen
            .iter()
            .filter(|r| {
                r["missing_cameras"]
                    .as_array()
                    .is_some_and(|a| !a.is_empty())
            })
            .collect()
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

/// A replica's Kafka arguments: `topics`, group `group` (made unique to the topics), producer
/// id `id`, the dead-letter topic.
fn kafka_args(broker: &Broker, topics: &Topics, group: &str, id: &str) -> Vec<String> {
    let group = format!("{group}-{}", topics.batches);
    [
        "--kafka-brokers",
        &broker.addr,
        "--kafka-input-topic",
        &topics.batches,
        "--kafka-output-topic",
        &topics.results,
        "--kafka-dead-letter-topic",
        &topics.dead,
        "--kafka-group",
        &group,
        "--kafka-producer-id",
        id,
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

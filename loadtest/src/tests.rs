//! End-to-end tests of the driver against a small in-process stand-in of the server's HTTP
//! API (batches in, SSE results out, /metrics), which can be told to never publish some
//! frames: the load generator must then report exactly those as lost.
use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

use axum::Router;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use clap::Parser;
use crossview_core::Batch;
use futures::StreamExt;
use tokio::sync::broadcast;
use tokio_stream::wrappers::BroadcastStream;

use crate::args::Args;
use crate::driver;

/// Cameras seen per `(scene, frame id)`.
type Seen = Arc<Mutex<HashMap<(String, u64), HashSet<String>>>>;

#[derive(Clone)]
struct Fake {
    cameras: usize,
    /// Frames the fake server accepts but never publishes.
    swallow: HashSet<u64>,
    seen: Seen,
    batches: Arc<Mutex<HashMap<String, u64>>>,
    results: broadcast::Sender<(String, u64)>,
}

async fn push(State(f): State<Fake>, Path(scene): Path<String>, body: String) -> Response {
    let Ok(b) = serde_json::from_str::<Batch>(&body) else {
        return StatusCode::UNPROCESSABLE_ENTITY.into_response();
    };
    let complete = {
        let mut seen = f.seen.lock().unwrap();
        let cams = seen.entry((scene.clone(), b.frame_id)).or_default();
        if !cams.insert(b.camera.clone()) {
            let body = r#"{"error": {"kind": "duplicate", "message": "twice"}}"#;
            return (StatusCode::CONFLICT, body).into_response();
        }
        cams.len() == f.cameras
    };
    *f.batches.lock().unwrap().entry(scene.clone()).or_default() += 1;
    if complete && !f.swallow.contains(&b.frame_id) {
        let _ = f.results.send((scene, b.frame_id));
    }
    (StatusCode::ACCEPTED, "{}").into_response()
}

async fn events(State(f): State<Fake>, Path(scene): Path<String>) -> impl IntoResponse {
    let stream = BroadcastStream::new(f.results.subscribe()).filter_map(move |r| {
        let scene = scene.clone();
        async move {
            let (s, id) = r.ok()?;
            (s == scene).then(|| {
                let data = format!(
                    r#"{{"scene":"{s}","frame_id":{id},"complete":true,"missing_cameras":[],"identities":[],"latency_ms":0.1}}"#
                );
                Ok::<_, std::convert::Infallible>(Event::default().event("frame").data(data))
            })
        }
    });
    Sse::new(stream)
}

async fn describe(Path(scene): Path<String>) -> Response {
    if scene != "lab" {
        return StatusCode::NOT_FOUND.into_response();
    }
    let body = r#"{"name": "lab", "cameras": [{"name": "a", "width": 640, "height": 480}, {"name": "b", "width": 640, "height": 480}], "threshold": 0.4}"#;
    ([("content-type", "application/json")], body).into_response()
}

async fn metrics(State(f): State<Fake>) -> String {
    f.batches
        .lock()
        .unwrap()
        .iter()
        .map(|(s, n)| format!("crossview_batches_total{{scene=\"{s}\"}} {n}\n"))
        .collect()
}

/// Starts the fake server on a loopback port; returns its base URL.
async fn start(cameras: usize, swallow: &[u64]) -> String {
    let (results, _) = broadcast::channel(1024);
    let fake = Fake {
        cameras,
        swallow: swallow.iter().copied().collect(),
        seen: Arc::default(),
        batches: Arc::default(),
        results,
    };
    let app = Router::new()
        .route("/v1/scenes/{scene}/batches", post(push))
        .route("/v1/scenes/{scene}/events", get(events))
        .route("/metrics", get(metrics))
        .route("/readyz", get(|| async { "ready" }))
        .route("/v1/scenes/{scene}", get(describe))
        .with_state(fake);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await.unwrap() });
    format!("http://{addr}")
}

/// A two-camera recording of `frames` frames with one box per camera.
fn recording(frames: u64) -> tempfile::NamedTempFile {
    use std::io::Write;
    let mut f = tempfile::NamedTempFile::new().unwrap();
    writeln!(
        f,
        r#"{{"scene": {{"name": "lab", "cameras": [{{"name": "a", "width": 640, "height": 480}}, {{"name": "b", "width": 640, "height": 480}}]}}}}"#
    )
    .unwrap();
    for id in 0..frames {
        for cam in ["a", "b"] {
            writeln!(
                f,
                r#"{{"camera": "{cam}", "frame_id": {id}, "detections": [{{"bbox": [10, 20, 50, 120]}}]}}"#
            )
            .unwrap();
        }
    }
    f
}

fn args(base: &str, rec: &std::path::Path, extra: &[&str]) -> Args {
    let mut v = vec![
        "crossview-loadtest".to_string(),
        format!("--target={base}"),
        format!("--recording={}", rec.display()),
        "--transport=http".to_string(),
        "--frame-ids=original".to_string(),
        "--drain-timeout=2s".to_string(),
    ];
    v.extend(extra.iter().map(|s| s.to_string()));
    Args::parse_from(v)
}

#[tokio::test]
async fn open_loop_run_matches_every_frame() {
    let base = start(2, &[]).await;
    let rec = recording(12);
    let report = driver::run(&args(&base, rec.path(), &["--rate=200", "--wait-ready=5s"]))
        .await
        .unwrap();
    assert!(report.passed, "{}", report.to_text());
    assert_eq!(report.batches_sent, 24);
    assert_eq!(report.batches_accepted, 24);
    assert_eq!(report.results, 12);
    assert_eq!(report.frames_lost, 0);
    assert_eq!(report.latency_complete.count, 12);
    let batches = &report.server_comparison[0];
    assert_eq!(
        (batches.ours, batches.server),
        (24, Some(24)),
        "{batches:?}"
    );
    let frames = &report.server_comparison[1];
    assert_eq!(
        (frames.ours, frames.server),
        (12, None),
        "not exposed: {frames:?}"
    );
}

#[tokio::test]
async fn swallowed_frames_are_reported_lost_and_fail_the_run() {
    let base = start(2, &[3, 7]).await;
    let rec = recording(10);
    let mut a = args(&base, rec.path(), &["--rate=0", "--scene-names=lab"]);
    a.drain_timeout = std::time::Duration::from_millis(300);
    let report = driver::run(&a).await.unwrap();
    assert!(!report.passed);
    assert_eq!(report.frames_lost, 2);
    assert_eq!(
        report.lost_examples,
        vec![("lab".to_string(), 3), ("lab".to_string(), 7)]
    );
    assert_eq!(report.results, 8);
}

#[tokio::test]
async fn unknown_scene_fails_before_sending() {
    let base = start(2, &[]).await;
    let rec = recording(2);
    let err = driver::run(&args(&base, rec.path(), &["--scene-names=lab,nope"]))
        .await
        .unwrap_err();
    assert!(
        format!("{err:#}").contains("does not serve scene 'nope'"),
        "{err:#}"
    );
}

#[tokio::test]
async fn refuses_non_loopback_targets() {
    let rec = recording(1);
    let err = driver::run(&args("http://192.0.2.1:8080", rec.path(), &[]))
        .await
        .unwrap_err();
    assert!(format!("{err:#}").contains("not loopback"), "{err:#}");
}

/// A stand-in replica on a real broker: reads `batches` (JSON or protobuf by header), and once
/// both cameras of a frame arrived produces its JSON result to `results`, except for the
/// frames whose recording id is in `swallow`.
async fn fake_replica(broker: String, swallow: HashSet<u64>) {
    use prost::Message as _;
    use rdkafka::config::ClientConfig;
    use rdkafka::consumer::{Consumer, StreamConsumer};
    use rdkafka::message::{Headers, Message};
    use rdkafka::producer::{FutureProducer, FutureRecord};
    // Assigned, not subscribed: no group join to wait for.
    let consumer: StreamConsumer = ClientConfig::new()
        .set("bootstrap.servers", &broker)
        .set("group.id", "fake-replica")
        .set("fetch.wait.max.ms", "10")
        .create()
        .unwrap();
    let mut parts = rdkafka::TopicPartitionList::new();
    for p in 0..2 {
        parts
            .add_partition_offset("batches", p, rdkafka::Offset::Beginning)
            .unwrap();
    }
    consumer.assign(&parts).unwrap();
    let producer: FutureProducer = ClientConfig::new()
        .set("bootstrap.servers", &broker)
        .create()
        .unwrap();
    let mut seen: HashMap<(String, u64), HashSet<String>> = HashMap::new();
    loop {
        // Transient client errors (a connection being set up) are retried.
        let Ok(m) = consumer.recv().await else {
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
            continue;
        };
        let scene = String::from_utf8(m.key().unwrap().to_vec()).unwrap();
        let protobuf = m.headers().is_some_and(|h| {
            h.iter()
                .any(|h| h.key == "content-type" && h.value == Some(b"application/x-protobuf"))
        });
        let payload = m.payload().unwrap();
        let (camera, frame) = if protobuf {
            let b = crossview_api::pb::Batch::decode(payload).unwrap();
            assert_eq!(b.scene, scene, "protobuf batches name their scene");
            (b.camera, b.frame_id)
        } else {
            let b: Batch = serde_json::from_slice(payload).unwrap();
            (b.camera, b.frame_id)
        };
        let cams = seen.entry((scene.clone(), frame)).or_default();
        // Fresh frame ids are shifted by a multiple of 1000: swallow by the recording's id.
        if cams.insert(camera) && cams.len() == 2 && !swallow.contains(&(frame % 1000)) {
            let body = format!(
                r#"{{"scene":"{scene}","frame_id":{frame},"complete":true,"identities":[]}}"#
            );
            let r = FutureRecord::to("results").key(&scene).payload(&body);
            producer
                .send(r, std::time::Duration::from_secs(10))
                .await
                .unwrap();
        }
    }
}

/// Kafka transport through a real Apache Kafka broker (`make setup`): batches keyed
/// by scene in both encodings, results read back from the output topic; a frame the replica
/// never publishes is reported lost.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kafka_transport_through_a_real_broker() {
    let Some(broker) = crossview_testing::kafka::Broker::start() else {
        return;
    };
    broker.create_topic("batches", 2);
    broker.create_topic("results", 2);
    let fake = tokio::spawn(fake_replica(broker.addr.clone(), HashSet::from([4])));
    let rec = recording(8);
    for format in ["json", "protobuf"] {
        let a = Args::parse_from([
            "crossview-loadtest".to_string(),
            format!("--recording={}", rec.path().display()),
            "--transport=kafka".to_string(),
            format!("--kafka-brokers={}", broker.addr),
            format!("--kafka-format={format}"),
            "--rate=100".to_string(),
            "--drain-timeout=5s".to_string(),
        ]);
        let report = driver::run(&a).await.unwrap();
        assert_eq!(report.batches_sent, 16, "{format}: {}", report.to_text());
        assert_eq!(report.batches_accepted, 16, "{format}");
        assert_eq!(report.results, 7, "{format}: {}", report.to_text());
        assert_eq!(report.latency_complete.count, 7, "{format}");
        assert_eq!(report.frames_lost, 1, "{format}");
        let (scene, frame) = &report.lost_examples[0];
        assert_eq!(scene, "lab");
        assert_eq!(
            frame % 1000,
            4,
            "{format}: frame ids are shifted, the fourth is lost"
        );
        assert!(!report.passed);
        assert!(
            report.server_comparison.is_empty(),
            "no single server to compare with"
        );
    }
    // Its consumer closes while the broker still runs (a close against a dead broker waits
    // for librdkafka's timeouts).
    fake.abort();
    let _ = fake.await;
}

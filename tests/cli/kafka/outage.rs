//! A broker that is down when a replica starts, then goes away mid-stream and comes back while
//! the cameras keep sending: the replica says so (`/readyz` 503 while no broker answers, a
//! warning in its log), keeps serving HTTP, and once the broker is back reconnects, rejoins its
//! group and publishes every camera batch sent, none lost, none partial.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crossview_testing::kafka::{Broker, Topics};

use super::rebalance::{SYNC_TIMEOUT, Sent, stream};
use super::*;

/// `/readyz`'s status (0: no answer).
async fn readyz(base: &str) -> u16 {
    reqwest::get(format!("{base}/readyz"))
        .await
        .map_or(0, |r| r.status().as_u16())
}

/// Waits (bounded by `within`) until `/readyz` answers `status`.
async fn wait_readyz(base: &str, status: u16, within: Duration) {
    let t = Instant::now();
    while readyz(base).await != status {
        assert!(
            t.elapsed() < within,
            "/readyz never answered {status} in {within:?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_broker_down_at_start_and_gone_mid_stream_loses_nothing() {
    let Some(mut broker) = Broker::stopped() else {
        return;
    };
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    let lines = simulate(bin, tmp.path(), 60);
    let topics = Topics {
        batches: "batches".into(),
        results: "results".into(),
        dead: "dead".into(),
    };
    let scenes = vec!["north".to_string()];
    let mut args = model_args(&scenes);
    args.extend(kafka_args(&broker, &topics, "replicas", "r1"));
    args.extend(["--sync-timeout".into(), SYNC_TIMEOUT.into()]);
    // Topics that appear after the start are found within a second.
    args.extend([
        "--kafka-property".into(),
        "topic.metadata.refresh.interval.ms=1000".into(),
    ]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let (_replica, base) = spawn_serve(bin, &args).await;

    // Down at start: HTTP answers, the replica is not ready.
    for _ in 0..10 {
        assert_eq!(readyz(&base).await, 503, "ready without a broker");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    broker.restart();
    for (t, n) in [
        (&topics.batches, 1),
        (&topics.results, 1),
        (&topics.dead, 1),
    ] {
        broker.create_topic(t, n);
    }
    wait_readyz(&base, 200, Duration::from_secs(60)).await;
    let p = Arc::new(producer(&broker));
    let mut results = Results::new(&broker, &topics.results);
    let capture = Capture::live(25);
    let gap = Duration::from_millis(25);
    let mut sent: Vec<Sent> =
        stream(&p, &topics.batches, &lines, &scenes, 0..20, gap, capture).await;
    results.wait_cover(&sent).await;

    // Gone mid-stream: not ready while it is away; the cameras keep sending meanwhile (their
    // producer holds the batches until the broker is back).
    broker.kill();
    wait_readyz(&base, 503, Duration::from_secs(60)).await;
    let sending = {
        let (p, topic, lines, scenes) = (
            p.clone(),
            topics.batches.clone(),
            lines.clone(),
            scenes.clone(),
        );
        tokio::spawn(async move { stream(&p, &topic, &lines, &scenes, 20..60, gap, capture).await })
    };
    tokio::time::sleep(Duration::from_secs(2)).await;
    broker.restart();
    wait_readyz(&base, 200, Duration::from_secs(60)).await;
    sent.extend(sending.await.unwrap());
    results.wait_cover(&sent).await;
    results.read_for(Duration::from_secs(1)).await;
    let partial = results.partial();
    assert!(partial.is_empty(), "partial results: {partial:?}");
    let m = metrics_text(&base).await;
    assert_eq!(
        metric(&m, "crossview_kafka_records_total{outcome=\"rejected\"}"),
        0.0,
        "{m}"
    );
}

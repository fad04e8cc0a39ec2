//! Bounded cost per frame: the largest frame the limits allow is associated within its budget,
//! a frame over the cost limit is refused before it costs anything, a backlog of expensive
//! frames is shed once over the queue budget instead of delaying every later frame, and
//! shutdown ends within its grace (queued frames published with an error).

use std::time::{Duration, Instant};

use crossview_serve::cost::frame_cost;
use crossview_testing::*;
use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_largest_allowed_frame_answers_within_its_budget_and_a_larger_one_is_refused() {
    let server = start(|_| {}).await;
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/lab/associate");
    let n = largest_uniform();
    let t = Instant::now();
    let r = guard(
        "largest frame",
        http.post(&url).json(&associate_body(n)).send(),
    )
    .await
    .unwrap();
    let took = t.elapsed();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    let v: serde_json::Value = r.json().await.unwrap();
    assert!(v.get("error").is_none(), "{v}");
    eprintln!(
        "3 x {n} boxes ({} cost units) associated in {took:?} ({:.2} ns/unit, this build)",
        frame_cost(&[n; 3]),
        took.as_nanos() as f64 / frame_cost(&[n; 3]) as f64
    );
    assert!(took < Duration::from_secs(20), "{took:?}");

    // One box more per camera is over the cost limit: refused, nothing queued.
    let (status, v) = server
        .post_json("/v1/scenes/lab/associate", &associate_body(n + 1))
        .await;
    assert_eq!(status, 422);
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("--max-frame-cost"),
        "{v}"
    );
    // Batch by batch: the batch that would push the frame over the limit is the one refused.
    for c in 0..2 {
        let (status, _) = server
            .post_json("/v1/scenes/lab/batches", &batch_json(c, 7, n + 1))
            .await;
        assert_eq!(status, 202);
    }
    let (status, _) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(2, 7, n + 1))
        .await;
    assert_eq!(status, 422);
    server.shutdown().await.unwrap();
}

/// Pushes `frames` frames of 3 × `n` boxes and one small frame after them.
async fn push_backlog(server: &TestServer, frames: u64, n: usize) -> usize {
    let mut client = server.grpc().await;
    // Every frame begun before any is complete: none meets a queue at intake.
    let size = move |f| if f > frames { 2 } else { n };
    let batches: Vec<_> = (0..3)
        .flat_map(|c| (1..=frames + 1).map(move |f| batch(c, f, size(f))))
        .collect();
    let total = batches.len();
    let mut acks = client
        .push(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    while let Some(a) = guard("acks", acks.next()).await {
        assert_eq!(a.unwrap().code, 0);
    }
    total
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_backlog_of_expensive_frames_is_shed_past_the_queue_budget() {
    let server = start(|c| c.limits.max_queue_delay = Duration::from_millis(100)).await;
    let mut results = server.subscribe("lab").await;
    let frames = 12;
    push_backlog(&server, frames, largest_uniform() * 3 / 4).await;
    let (mut associated, mut cut) = (0, 0);
    for f in 1..=frames + 1 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, f);
        if r.error.is_empty() {
            associated += 1;
        } else {
            assert!(r.error.contains("--max-queue-delay"), "{}", r.error);
            assert_eq!(r.status, crossview_api::pb::ResultStatus::Shed as i32);
            assert!(r.identities.is_empty());
            cut += 1;
        }
    }
    assert!(associated >= 1, "the first frame is associated");
    assert!(cut >= 1, "a 12-frame backlog outlives a 100 ms budget");
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_frames_shed_total{scene=\"lab\",stage=\"queue\"}"
        ),
        cut as f64
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_respects_its_grace_with_expensive_frames_queued() {
    let server = start(|c| {
        c.limits.max_queue_delay = Duration::from_secs(600);
        c.shutdown_grace = Duration::from_millis(200);
    })
    .await;
    let mut results = server.subscribe("lab").await;
    let frames = 30;
    push_backlog(&server, frames, largest_uniform() * 3 / 4).await;
    server.shutdown().await.unwrap();
    // Every accepted frame is still published, those past the grace with an error.
    let mut got = 0;
    let mut unassociated = 0;
    while let Some(r) = guard("results", results.next()).await {
        let r = r.unwrap();
        got += 1;
        if r.error.contains("shutting down") {
            unassociated += 1;
        }
    }
    assert_eq!(got, frames + 1);
    assert!(
        unassociated >= 1,
        "a 30-frame backlog outlives a 200 ms grace"
    );
}

//! Overload costs whole frames, never cameras: while a scene's queue delay is over its budget
//! (`--max-queue-delay`), a new frame is shed whole — every batch of it refused with 429 /
//! `RESOURCE_EXHAUSTED`, kind `overloaded` and a retry-after, over HTTP and gRPC alike, and
//! the frame published with status `shed` — frames already queued past the budget are shed
//! too, no frame is published partial, and the scene serves on time once the backlog is gone.

use std::time::{Duration, Instant};

use crossview_api::pb;
use crossview_serve::Limits;
use crossview_serve::cost::frame_cost;
use crossview_testing::*;
use futures::StreamExt;

const BUDGET: Duration = Duration::from_millis(60);

/// The most boxes per camera (all three cameras alike) the default limits admit: the most
/// expensive frame a client can send.
fn heaviest() -> usize {
    let l = Limits::default();
    (1..=l.max_detections)
        .take_while(|&n| frame_cost(&[n; 3]) <= l.max_frame_cost)
        .last()
        .unwrap()
}

/// How long one frame of 3 × `n` boxes takes to associate here (unary call).
async fn time_one(server: &TestServer, n: usize) -> Duration {
    let views: Vec<_> = (0..3)
        .map(|c| {
            let mut b = batch_json(c, 1, n);
            b.as_object_mut().unwrap().remove("frame_id");
            b
        })
        .collect();
    let body = serde_json::json!({ "frame_id": 1, "views": views });
    let t = Instant::now();
    let (status, v) = server.post_json("/v1/scenes/lab/associate", &body).await;
    assert_eq!(status, 200, "{v}");
    t.elapsed()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_over_its_budget_sheds_new_frames_whole_and_says_when_to_retry() {
    let server = start(|c| c.limits.max_queue_delay = BUDGET).await;
    let n = heaviest();
    let one = time_one(&server, n).await;
    assert!(
        one > BUDGET * 3,
        "one frame of 3 x {n} boxes takes {one:?}: too fast to build a backlog over {BUDGET:?}"
    );
    let mut results = server.subscribe("lab").await;

    // Four heavy frames at once: the first is associated, the other three wait behind it.
    let mut grpc = server.grpc().await;
    let burst: Vec<_> = (1..=4)
        .flat_map(|f| (0..3).map(move |c| batch(c, f, n)))
        .collect();
    let acks: Vec<_> = grpc
        .push(futures::stream::iter(burst))
        .await
        .unwrap()
        .into_inner()
        .collect()
        .await;
    assert!(
        acks.iter().all(|a| a.as_ref().unwrap().code == 0),
        "{acks:?}"
    );
    // Past the budget, while the first frame still runs: frame 5 is shed at intake.
    tokio::time::sleep(BUDGET + Duration::from_millis(40)).await;
    let http = reqwest::Client::new();
    for c in 0..2 {
        let r = http
            .post(server.url("/v1/scenes/lab/batches"))
            .json(&batch_json(c, 5, 2))
            .send()
            .await
            .unwrap();
        assert_eq!(r.status(), 429);
        let retry: u64 = r.headers()["retry-after"]
            .to_str()
            .unwrap()
            .parse()
            .unwrap();
        assert!(retry >= 1, "{retry}");
        let v: serde_json::Value = r.json().await.unwrap();
        assert_eq!(v["error"]["kind"], "overloaded", "{v}");
        assert!(
            v["error"]["message"]
                .as_str()
                .unwrap()
                .contains("--max-queue-delay"),
            "{v}"
        );
    }
    let ack = grpc
        .push(futures::stream::iter([batch(2, 5, 2)]))
        .await
        .unwrap()
        .into_inner()
        .next()
        .await
        .unwrap()
        .unwrap();
    assert_eq!(ack.code, tonic::Code::ResourceExhausted as i32, "{ack:?}");
    assert_eq!(ack.kind, "overloaded");
    assert!(ack.retry_after_ms >= 1, "{ack:?}");

    // Every frame is published, in order: whole and associated, or shed — never partial.
    let mut shed = Vec::new();
    for f in 1..=5 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, f);
        if r.status == pb::ResultStatus::Shed as i32 {
            assert!(r.identities.is_empty());
            assert!(r.error.contains("--max-queue-delay"), "{}", r.error);
            shed.push(f);
        } else {
            assert_eq!(r.status, pb::ResultStatus::Associated as i32, "{r:?}");
            assert!(r.complete, "frame {f} published partial: {r:?}");
        }
    }
    assert_eq!(
        shed,
        vec![2, 3, 4, 5],
        "the first frame ran, the rest waited past the budget"
    );

    // The backlog gone, the scene serves on time again.
    for c in 0..3 {
        let (status, v) = server
            .post_json("/v1/scenes/lab/batches", &batch_json(c, 6, 2))
            .await;
        assert_eq!(status, 202, "{v}");
    }
    let r = guard("result", results.next()).await.unwrap().unwrap();
    assert_eq!((r.frame_id, r.complete), (6, true));
    assert_eq!(r.status, pb::ResultStatus::Associated as i32);

    let m = server.metrics().await;
    let shed_at = |stage: &str| {
        metric(
            &m,
            &format!("crossview_frames_shed_total{{scene=\"lab\",stage=\"{stage}\"}}"),
        )
    };
    assert_eq!(shed_at("intake"), 1.0);
    assert_eq!(shed_at("queue"), 3.0);
    assert_eq!(
        metric(&m, "crossview_errors_total{kind=\"overloaded\"}"),
        3.0
    );
    assert!(metric(&m, "crossview_queue_delay_seconds_count{scene=\"lab\"}") >= 6.0);
    server.shutdown().await.unwrap();
}

//! Overload costs whole frames, never cameras: while a scene's queue delay is over its budget
//! (`--max-queue-delay`), a new frame is shed whole — every batch of it refused with 429 /
//! `RESOURCE_EXHAUSTED`, kind `overloaded` and a retry-after, over HTTP and gRPC alike, and
//! the frame published with status `shed` — frames already queued past the budget are shed
//! too, no frame is published partial, and the scene serves on time once the backlog is gone.

use std::time::{Duration, Instant};

use crossview_api::pb;
use crossview_testing::*;
use futures::StreamExt;

const BUDGET: Duration = Duration::from_millis(30);

/// How long one frame of 3 × `n` boxes takes to associate here (unary call).
async fn time_one(server: &TestServer, n: usize) -> Duration {
    let t = Instant::now();
    let (status, v) = server
        .post_json("/v1/scenes/lab/associate", &associate_body(n))
        .await;
    assert_eq!(status, 200, "{v}");
    t.elapsed()
}

/// Pushes `batches` on one `Push` call and returns their acks.
async fn push(server: &TestServer, batches: Vec<pb::Batch>) -> Vec<pb::BatchAck> {
    let mut grpc = server.grpc().await;
    let acks = grpc
        .push(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    acks.map(Result::unwrap).collect().await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_over_its_budget_sheds_new_frames_whole_and_says_when_to_retry() {
    let server = start(|c| c.limits.max_queue_delay = BUDGET).await;
    let n = largest_uniform();
    let one = time_one(&server, n).await;
    assert!(
        one > BUDGET * 4,
        "one frame of 3 x {n} boxes takes {one:?}: too fast to build a backlog over {BUDGET:?}"
    );
    let mut results = server.subscribe("lab").await;

    // Heavy frames, one after the other, faster than they are associated: the queue grows
    // until a new frame meets it over the budget and is shed at intake. A frame whose first
    // batch was taken is taken whole, however long the queue meanwhile.
    let mut f = 0;
    let first = loop {
        f += 1;
        assert!(f < 40, "no frame was shed");
        let acks = push(&server, vec![batch(0, f, n)]).await;
        assert_eq!(acks.len(), 1, "one ack per batch");
        let ack = acks.into_iter().next().unwrap();
        if ack.code == 0 {
            let rest = push(&server, vec![batch(1, f, n), batch(2, f, n)]).await;
            assert!(rest.iter().all(|a| a.code == 0), "frame {f} cut: {rest:?}");
            continue;
        }
        assert_eq!(ack.code, tonic::Code::ResourceExhausted as i32, "{ack:?}");
        assert_eq!(ack.kind, "overloaded");
        assert!(ack.message.contains("--max-queue-delay"), "{ack:?}");
        assert!(ack.retry_after_ms >= 1, "{ack:?}");
        break ack;
    };
    let shed_frame = first.frame_id;
    // Its other cameras are refused too, whatever the queue does now (HTTP says when to retry).
    let http = reqwest::Client::new();
    for c in 1..3 {
        let r = http
            .post(server.url("/v1/scenes/lab/batches"))
            .json(&batch_json(c, shed_frame, 2))
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
    }

    // Every frame is published, in order: whole and associated, or shed — never partial.
    let mut shed = Vec::new();
    for f in 1..=shed_frame {
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
    assert_eq!(shed.last(), Some(&shed_frame), "{shed:?}");

    // The backlog gone, the scene associates again (a busy machine may still shed a few).
    let mut f = shed_frame + 1;
    loop {
        for c in 0..3 {
            let (status, v) = server
                .post_json("/v1/scenes/lab/batches", &batch_json(c, f, 2))
                .await;
            assert!(status == 202 || status == 429, "{status} {v}");
        }
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, f);
        if r.status == pb::ResultStatus::Associated as i32 {
            assert!(r.complete, "{r:?}");
            break;
        }
        assert_eq!(r.status, pb::ResultStatus::Shed as i32, "{r:?}");
        assert!(f < shed_frame + 40, "the scene never associates again");
        tokio::time::sleep(BUDGET).await;
        shed.push(f);
        f += 1;
    }

    let m = server.metrics().await;
    let shed_at = |stage: &str| {
        metric(
            &m,
            &format!("crossview_frames_shed_total{{scene=\"lab\",stage=\"{stage}\"}}"),
        )
    };
    assert!(shed_at("intake") >= 1.0);
    assert_eq!(shed_at("intake") + shed_at("queue"), shed.len() as f64);
    assert!(metric(&m, "crossview_errors_total{kind=\"overloaded\"}") >= 3.0);
    assert!(metric(&m, "crossview_queue_delay_seconds_count{scene=\"lab\"}") >= 3.0);
    server.shutdown().await.unwrap();
}

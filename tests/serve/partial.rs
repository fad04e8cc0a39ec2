//! A camera that never reports: after the sync timeout the frame leaves as partial, naming
//! the missing camera, over gRPC Subscribe and over the HTTP Server-Sent-Events stream.

use std::time::Duration;

use crossview_testing::*;
use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn missing_camera_gives_partial_frame_after_timeout() {
    let server = start(|c| c.sync_timeout = Duration::from_millis(150)).await;
    let mut sub = server.grpc().await;
    let mut results = sub
        .subscribe(crossview_api::pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let sse = reqwest::get(server.url("/v1/scenes/lab/events"))
        .await
        .unwrap();
    assert_eq!(sse.status(), 200);
    let mut sse = sse.bytes_stream();

    // Cameras c0 and c2 report frame 7 over HTTP; c1 never does.
    for cam in [0usize, 2] {
        let (status, _) = server
            .post_json("/v1/scenes/lab/batches", &batch_json(cam, 7, 2))
            .await;
        assert_eq!(status, 202);
    }

    let r = guard("partial frame", results.next())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(r.frame_id, 7);
    assert!(!r.complete);
    assert_eq!(r.missing_cameras, vec!["c1"]);
    check_identities(&r, &[2, 0, 2]);

    // The same result as an SSE `frame` event.
    let mut text = String::new();
    guard("SSE frame event", async {
        while !text.contains("\n\n") || !text.contains("event: frame") {
            let chunk = sse.next().await.unwrap().unwrap();
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    })
    .await;
    let data = text
        .lines()
        .find_map(|l| l.strip_prefix("data: "))
        .expect("data line");
    let v: serde_json::Value = serde_json::from_str(data).unwrap();
    assert_eq!(v["frame_id"], 7);
    assert_eq!(v["complete"], false);
    assert_eq!(v["missing_cameras"][0], "c1");

    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_frames_total{scene=\"lab\",state=\"partial\"}"
        ),
        1.0
    );
    server.shutdown().await.unwrap();
}

//! Careless (not hostile) clients, one guarantee per test: only accepted batches fix a scene's
//! appearance length; boxes overlapping the image edge are clipped and counted, boxes entirely
//! outside refused; unknown JSON fields are ignored by every body; echoed client input is
//! truncated; a half-closed `Stream` call ends and a cancelled one stops counting as a
//! subscriber; a subscriber that stops reading is dropped on a timer.

use std::time::Duration;

use crossview_api::pb;
use crossview_testing::*;
use futures::StreamExt;
use tonic::Code;

fn with_appearance(mut b: serde_json::Value, len: usize) -> serde_json::Value {
    for d in b["detections"].as_array_mut().unwrap() {
        d["appearance"] = serde_json::json!(vec![0.5f32; len]);
    }
    b
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_an_accepted_batch_fixes_the_appearance_length() {
    let server = start(|_| {}).await;
    let http = reqwest::Client::new();
    // Frame 5 complete, so frame 3 is late.
    for c in 0..3 {
        let (status, _) = server
            .post_json("/v1/scenes/lab/batches", &batch_json(c, 5, 1))
            .await;
        assert_eq!(status, 202);
    }
    let late = with_appearance(batch_json(0, 3, 1), 8);
    assert_eq!(
        server.post_json("/v1/scenes/lab/batches", &late).await.0,
        409
    );
    // A unary call with 8 values is answered but fixes nothing either.
    let mut view = with_appearance(batch_json(0, 9, 1), 8);
    view.as_object_mut().unwrap().remove("frame_id");
    let (status, _) = server
        .post_json(
            "/v1/scenes/lab/associate",
            &serde_json::json!({ "frame_id": 9, "views": [view] }),
        )
        .await;
    assert_eq!(status, 200);
    let scene: serde_json::Value = http
        .get(server.url("/v1/scenes/lab"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert!(scene["appearance_length"].is_null(), "{scene}");
    // The first accepted batch with vectors fixes it.
    let ok = with_appearance(batch_json(0, 6, 2), 16);
    assert_eq!(server.post_json("/v1/scenes/lab/batches", &ok).await.0, 202);
    let scene: serde_json::Value = http
        .get(server.url("/v1/scenes/lab"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(scene["appearance_length"], 16);
    let other = with_appearance(batch_json(1, 6, 1), 8);
    assert_eq!(
        server.post_json("/v1/scenes/lab/batches", &other).await.0,
        422
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn edge_boxes_are_clipped_and_counted_outside_boxes_refused() {
    let server = start(|_| {}).await;
    // c0 is 1920x1080: y1 = -1 (WILDTRACK's own boxes), x2 one pixel past the edge.
    let b = serde_json::json!({"camera": "c0", "frame_id": 1, "detections": [
        {"bbox": [10, -1, 50, 200]}, {"bbox": [1880, 10, 1921, 200]}, {"bbox": [100, 10, 150, 200]}]});
    assert_eq!(server.post_json("/v1/scenes/lab/batches", &b).await.0, 202);
    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_clipped_boxes_total{scene=\"lab\"}"),
        2.0
    );
    // Entirely outside the image: refused, naming the box.
    let b = serde_json::json!({"camera": "c0", "frame_id": 2, "detections": [{"bbox": [5000, 10, 6000, 90]}]});
    let (status, v) = server.post_json("/v1/scenes/lab/batches", &b).await;
    assert_eq!(status, 422);
    assert_eq!(v["error"]["field"], "detections[0].bbox");
    assert!(
        v["error"]["message"]
            .as_str()
            .unwrap()
            .contains("entirely outside"),
        "{v}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unknown_json_fields_are_ignored_by_every_body() {
    let server = start(|_| {}).await;
    let mut b = batch_json(0, 1, 1);
    b["note"] = "from a newer client".into();
    let (status, _) = server.post_json("/v1/scenes/lab/batches", &b).await;
    assert_eq!(status, 202);
    let frame = serde_json::json!({ "frame_id": 3, "views": [{"camera": "c1", "detections": [], "x": 1}], "y": 2 });
    let (status, _) = server.post_json("/v1/scenes/lab/associate", &frame).await;
    assert_eq!(status, 200);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn echoed_client_input_is_truncated() {
    let server = start(|_| {}).await;
    let huge = "x".repeat(1 << 20);
    let r = reqwest::Client::new()
        .post(server.url("/v1/scenes/lab/batches"))
        .json(&serde_json::json!({"camera": huge, "frame_id": 1, "detections": []}))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 404);
    assert!(r.bytes().await.unwrap().len() < 2048);
    let mut client = server.grpc().await;
    let e = client
        .get_scene(pb::GetSceneRequest {
            scene: "y".repeat(3 << 20),
        })
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::NotFound);
    assert!(e.message().len() < 1024, "{}", e.message().len());
    let mut b = batch(0, 1, 1);
    b.camera = "z".repeat(3 << 20);
    let mut acks = client
        .push(futures::stream::iter(vec![b]))
        .await
        .unwrap()
        .into_inner();
    let ack = guard("ack", acks.next()).await.unwrap().unwrap();
    assert_eq!(ack.code, Code::NotFound as i32);
    assert!(ack.message.len() < 1024 && ack.camera.len() < 1024);
    server.shutdown().await.unwrap();
}

/// Waits until the scene's subscriber gauge reads `n`.
async fn subscribers_become(server: &TestServer, n: f64) {
    guard(&format!("subscriber count {n}"), async {
        while metric(
            &server.metrics().await,
            "crossview_subscribers{scene=\"lab\"}",
        ) != n
        {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_half_closed_stream_call_ends_and_a_cancelled_one_is_no_subscriber() {
    let server = start(|c| c.sync_timeout = Duration::from_millis(50)).await;
    let mut client = server.grpc().await;
    // Frames 1..=3, all cameras, then the client half-closes.
    let batches: Vec<_> = (1..=3u64)
        .flat_map(|f| (0..3).map(move |c| batch(c, f, 1)))
        .collect();
    let mut out = client
        .stream(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    let mut frames = Vec::new();
    while let Some(m) = guard("the call ends after the half-close", out.next()).await {
        if let Some(pb::stream_response::Event::Result(r)) = m.unwrap().event {
            frames.push(r.frame_id);
        }
    }
    assert_eq!(frames, vec![1, 2, 3]);
    subscribers_become(&server, 0.0).await;

    // A call the client cancels stops counting at once, without another frame.
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(batch(0, 10, 1)).await.unwrap();
    let mut out = client
        .stream(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let _ack = guard("ack", out.next()).await;
    subscribers_become(&server, 1.0).await;
    drop(out);
    drop(tx);
    subscribers_become(&server, 0.0).await;
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_that_stops_reading_is_dropped_on_a_timer() {
    let server = start(|c| {
        c.connections.subscriber_stall_timeout = Duration::from_millis(300);
        c.limits.queue_capacity = 1 << 16;
        c.limits.subscriber_buffer = 1 << 16;
        c.limits.max_queue_delay = Duration::from_secs(600);
    })
    .await;
    // Subscribes on its own connection (a small HTTP/2 window, so it fills fast) and never
    // reads.
    let channel = tonic::transport::Channel::from_shared(server.url(""))
        .unwrap()
        .initial_stream_window_size(65_535)
        .initial_connection_window_size(65_535)
        .connect()
        .await
        .unwrap();
    let mut idle_client = pb::association_client::AssociationClient::new(channel);
    let _never_read = idle_client
        .subscribe(pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();
    subscribers_become(&server, 1.0).await;
    // Far more results (~2 KB each) than the subscriber's 64 KiB window holds.
    let mut client = server.grpc().await;
    let batches: Vec<_> = (1..=300u64)
        .flat_map(|f| (0..3).map(move |c| batch(c, f, 60)))
        .collect();
    let mut acks = client
        .push(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    while let Some(a) = guard("acks", acks.next()).await {
        assert_eq!(a.unwrap().code, 0);
    }
    let waited =
        tokio::time::timeout(Duration::from_secs(20), subscribers_become(&server, 0.0)).await;
    let m0 = server.metrics().await;
    assert!(waited.is_ok(), "{m0}");
    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_errors_total{kind=\"subscriber_stalled\"}"),
        1.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
}

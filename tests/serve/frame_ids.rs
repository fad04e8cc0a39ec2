//! Frame ids from careless cameras: one batch with a huge frame id (or a jump to 10^9) is
//! refused as out of range and cannot make a scene's later frames late; far-future junk cannot
//! fill the pending slots and break real frames up; a majority of cameras restarting their ids
//! moves the scene to the new ids.

use crossview_api::pb;
use crossview_testing::*;
use futures::StreamExt;
use tonic::Code;

/// Pushes `batches` over one gRPC Push stream and returns the ack codes.
async fn push_all(server: &TestServer, batches: Vec<pb::Batch>) -> Vec<i32> {
    let mut client = server.grpc().await;
    let mut acks = client
        .push(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    let mut codes = Vec::new();
    while let Some(a) = guard("acks", acks.next()).await {
        codes.push(a.unwrap().code);
    }
    codes
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_huge_frame_id_cannot_deny_the_scene() {
    let server = start(|c| c.sync_timeout = std::time::Duration::from_millis(20)).await;
    let mut results = server.subscribe("lab").await;
    // Frame 1 complete, then the hostile ids, alone and repeated.
    let mut batches: Vec<_> = (0..3).map(|c| batch(c, 1, 2)).collect();
    batches.push(batch(0, u64::MAX, 1));
    batches.push(batch(1, 1_000_000_000, 1));
    let codes = push_all(&server, batches).await;
    assert_eq!(&codes[..3], &[0, 0, 0]);
    assert_eq!(codes[3], Code::OutOfRange as i32);
    assert_eq!(codes[4], Code::OutOfRange as i32);
    // The same over HTTP: 422, kind out_of_range. (A different id: two cameras agreeing on
    // one out-of-range id are a majority of three, which restarts the ids, see below.)
    let (status, body) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(2, 1 << 63, 1))
        .await;
    assert_eq!(status, 422);
    assert_eq!(body["error"]["kind"], "out_of_range");
    // Normal frames after them are accepted and come out complete.
    let codes = push_all(
        &server,
        (2..6)
            .flat_map(|f| (0..3).map(move |c| batch(c, f, 2)))
            .collect(),
    )
    .await;
    assert!(codes.iter().all(|&c| c == 0), "{codes:?}");
    let mut got = Vec::new();
    while got.len() < 5 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert!(r.complete, "{r:?}");
        got.push(r.frame_id);
    }
    assert_eq!(got, vec![1, 2, 3, 4, 5]);
    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_out_of_range_batches_total{scene=\"lab\"}"),
        3.0
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn far_future_junk_does_not_break_up_real_frames() {
    let server = start(|c| c.sync_timeout = std::time::Duration::from_secs(30)).await;
    let mut results = server.subscribe("lab").await;
    // Anchor the scene at frame 0, then 64 single-camera junk batches far ahead.
    let codes = push_all(&server, (0..3).map(|c| batch(c, 0, 1)).collect()).await;
    assert_eq!(codes, vec![0, 0, 0]);
    let junk: Vec<_> = (0..64).map(|k| batch(0, 1_000_000 + k, 1)).collect();
    let codes = push_all(&server, junk).await;
    assert!(
        codes.iter().all(|&c| c == Code::OutOfRange as i32),
        "{codes:?}"
    );
    // 35 real batches (frames 1..=12 of 3 cameras, less one): all accepted, all complete.
    let real: Vec<_> = (1..=12u64)
        .flat_map(|f| (0..3).map(move |c| batch(c, f, 1)))
        .take(35)
        .collect();
    let codes = push_all(&server, real).await;
    assert!(codes.iter().all(|&c| c == 0), "{codes:?}");
    for f in 0..=11u64 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, f);
        assert!(r.complete, "frame {f} broken up: {r:?}");
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cameras_restarting_their_ids_move_the_scene() {
    let server = start(|c| c.sync_timeout = std::time::Duration::from_millis(20)).await;
    let mut results = server.subscribe("lab").await;
    let codes = push_all(&server, (0..3).map(|c| batch(c, 5_000_000, 1)).collect()).await;
    assert_eq!(codes, vec![0, 0, 0]);
    let first = guard("result", results.next()).await.unwrap().unwrap();
    assert_eq!(first.frame_id, 5_000_000);
    // The cameras restart at 0: the first is refused (one camera is no majority), the
    // second completes the majority and is accepted, then everything of the new ids is.
    let codes = push_all(
        &server,
        vec![
            batch(0, 0, 1),
            batch(1, 0, 1),
            batch(2, 0, 1),
            batch(0, 1, 1),
        ],
    )
    .await;
    assert_eq!(codes, vec![Code::OutOfRange as i32, 0, 0, 0]);
    let r = guard("result", results.next()).await.unwrap().unwrap();
    assert_eq!(r.frame_id, 0);
    assert_eq!(r.missing_cameras, vec!["c0".to_string()]);
    server.shutdown().await.unwrap();
}

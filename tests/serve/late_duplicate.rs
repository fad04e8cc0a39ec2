//! Late batches (frame already emitted) and duplicate batches (same camera and frame twice)
//! are rejected with their own status on both transports, counted, and change nothing.

use std::time::Duration;

use crossview_testing::*;
use futures::StreamExt;
use tonic::Code;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn late_and_duplicate_batches_are_rejected_and_counted() {
    let server = start(|c| c.sync_timeout = Duration::from_secs(120)).await;
    let mut client = server.grpc().await;
    let mut results = client
        .subscribe(crossview_api::pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();

    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut acks = client
        .push(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    let mut send = async |b| {
        tx.send(b).await.unwrap();
        guard("ack", acks.next()).await.unwrap().unwrap()
    };

    assert_eq!(send(batch(0, 5, 1)).await.code, 0);
    let dup = send(batch(0, 5, 2)).await;
    assert_eq!(dup.code, Code::AlreadyExists as i32, "{dup:?}");
    assert_eq!(dup.kind, "duplicate");
    assert_eq!(send(batch(1, 5, 1)).await.code, 0);
    assert_eq!(send(batch(2, 5, 1)).await.code, 0);
    // Frame 5 is complete and emitted now.
    let r = guard("frame 5", results.next()).await.unwrap().unwrap();
    assert_eq!((r.frame_id, r.complete), (5, true));
    // The kept c0 batch is the first one (1 box), not the duplicate (2 boxes).
    check_identities(&r, &[1, 1, 1]);

    let late = send(batch(1, 5, 1)).await;
    assert_eq!(late.code, Code::FailedPrecondition as i32, "{late:?}");
    assert_eq!(late.kind, "late");
    let older = send(batch(2, 3, 1)).await;
    assert_eq!(older.code, Code::FailedPrecondition as i32);

    // Over HTTP: 409 for both, with the kind in the body.
    let (status, body) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(0, 5, 1))
        .await;
    assert_eq!(status, 409);
    assert_eq!(body["error"]["kind"], "late");
    assert_eq!(
        server
            .post_json("/v1/scenes/lab/batches", &batch_json(0, 9, 1))
            .await
            .0,
        202
    );
    let (status, body) = server
        .post_json("/v1/scenes/lab/batches", &batch_json(0, 9, 1))
        .await;
    assert_eq!(status, 409);
    assert_eq!(body["error"]["kind"], "duplicate");

    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_late_batches_total{scene=\"lab\"}"),
        3.0,
        "{m}"
    );
    assert_eq!(
        metric(&m, "crossview_duplicate_batches_total{scene=\"lab\"}"),
        2.0,
        "{m}"
    );
    assert_eq!(metric(&m, "crossview_errors_total{kind=\"late\"}"), 3.0);
    assert_eq!(metric(&m, "crossview_batches_total{scene=\"lab\"}"), 4.0);
    server.shutdown().await.unwrap();
}

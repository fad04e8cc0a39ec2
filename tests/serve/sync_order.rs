//! Three cameras push from three separate gRPC connections, each in its own shuffled frame
//! order; a subscriber receives every frame exactly once, complete, in frame-id order.

use std::time::Duration;

use crossview_testing::*;
use futures::StreamExt;
use rand::SeedableRng;
use rand::seq::SliceRandom;

const FRAMES: u64 = 20;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shuffled_pushes_from_three_connections_come_out_in_order() {
    let server = start(|c| {
        // Long enough that no frame times out: completeness must come from the cameras.
        c.sync_timeout = Duration::from_secs(120);
        c.max_pending_frames = 1000;
    })
    .await;
    let mut sub = server.grpc().await;
    let mut results = sub
        .subscribe(crossview_api::pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();

    let mut pushers = Vec::new();
    for cam in 0..3usize {
        let mut client = server.grpc().await;
        pushers.push(tokio::spawn(async move {
            let mut order: Vec<u64> = (0..FRAMES).collect();
            order.shuffle(&mut rand_chacha::ChaCha8Rng::seed_from_u64(cam as u64 + 1));
            let batches: Vec<_> = order
                .iter()
                .map(|&f| batch(cam, f, 1 + (f as usize + cam) % 3))
                .collect();
            let mut acks = client
                .push(futures::stream::iter(batches))
                .await
                .unwrap()
                .into_inner();
            let mut n = 0;
            while let Some(ack) = acks.next().await {
                let ack = ack.unwrap();
                assert_eq!(ack.code, 0, "{ack:?}");
                n += 1;
            }
            assert_eq!(n, FRAMES);
        }));
    }
    for p in pushers {
        guard("pusher", p).await.unwrap();
    }

    let mut got = Vec::new();
    while got.len() < FRAMES as usize {
        let r = guard("subscriber", results.next())
            .await
            .expect("stream open")
            .expect("result");
        assert!(r.complete, "{r:?}");
        assert!(r.missing_cameras.is_empty());
        let f = r.frame_id as usize;
        check_identities(&r, &[1 + f % 3, 1 + (f + 1) % 3, 1 + (f + 2) % 3]);
        got.push(r.frame_id);
    }
    assert_eq!(got, (0..FRAMES).collect::<Vec<_>>());

    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_batches_total{scene=\"lab\"}"),
        (3 * FRAMES) as f64
    );
    assert_eq!(
        metric(
            &m,
            "crossview_frames_total{scene=\"lab\",state=\"complete\"}"
        ),
        FRAMES as f64
    );
    assert_eq!(metric(&m, "crossview_pending_frames{scene=\"lab\"}"), 0.0);
    server.shutdown().await.unwrap();
}

/// The one-client-has-all-cameras case: a single bidirectional `Stream` call sends every
/// camera's batches and receives the acknowledgements and the scene's results, in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_client_with_all_cameras_over_the_bidirectional_stream() {
    use crossview_api::pb::stream_response::Event;
    let server = start(|c| c.sync_timeout = Duration::from_secs(120)).await;
    let mut client = server.grpc().await;
    // Interleaved frames and cameras, as a client with several detectors would send them.
    let order = [
        (2, 0),
        (1, 2),
        (1, 0),
        (2, 1),
        (3, 2),
        (1, 1),
        (2, 2),
        (3, 0),
        (3, 1),
    ];
    let batches: Vec<_> = order.iter().map(|&(f, cam)| batch(cam, f, 2)).collect();
    let mut out = client
        .stream(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    let (mut acks, mut frames) = (0, Vec::new());
    while frames.len() < 3 {
        let msg = guard("stream", out.next()).await.unwrap().unwrap();
        match msg.event.unwrap() {
            Event::Ack(a) => {
                assert_eq!(a.code, 0, "{a:?}");
                acks += 1;
            }
            Event::Result(r) => {
                assert!(r.complete);
                check_identities(&r, &[2, 2, 2]);
                frames.push(r.frame_id);
            }
        }
    }
    assert_eq!(frames, vec![1, 2, 3]);
    assert!(acks >= 8, "the last ack may follow the last result");
    server.shutdown().await.unwrap();
}

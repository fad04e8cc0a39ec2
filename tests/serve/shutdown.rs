//! Graceful shutdown: intake stops, pending (incomplete) frames are flushed as partial results
//! to subscribers, every accepted batch appears in exactly one result, and `run` returns.

use std::collections::BTreeMap;
use std::time::Duration;

use crossview_testing::*;
use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_flushes_pending_frames_with_none_lost() {
    let server = start(|c| {
        // Nothing times out by itself: only shutdown can release the incomplete frames.
        c.sync_timeout = Duration::from_secs(600);
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
    let mut sse = reqwest::get(server.url("/v1/scenes/lab/events"))
        .await
        .unwrap()
        .bytes_stream();

    // Which cameras report which frame: some complete, most not.
    let mut pushed: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
    for f in 0..12u64 {
        let cams: Vec<usize> = (0..3)
            .filter(|c| !(f + *c as u64).is_multiple_of(4) || f.is_multiple_of(5))
            .collect();
        pushed.insert(f, cams);
    }
    let mut client = server.grpc().await;
    let batches: Vec<_> = pushed
        .iter()
        .flat_map(|(&f, cams)| cams.iter().map(move |&c| batch(c, f, 1)))
        .collect();
    let n_batches = batches.len();
    let mut acks = client
        .push(futures::stream::iter(batches))
        .await
        .unwrap()
        .into_inner();
    let mut accepted = 0;
    while let Some(a) = guard("acks", acks.next()).await {
        assert_eq!(a.unwrap().code, 0);
        accepted += 1;
    }
    assert_eq!(accepted, n_batches);

    let shutdown = tokio::spawn(server.shutdown());

    let mut got: BTreeMap<u64, Vec<usize>> = BTreeMap::new();
    let mut order = Vec::new();
    while let Some(r) = guard("subscriber", results.next()).await {
        let r = r.unwrap();
        let reported: Vec<usize> = (0..3)
            .filter(|c| !r.missing_cameras.contains(&CAMERAS[*c].to_string()))
            .collect();
        assert_eq!(r.complete, reported.len() == 3);
        assert!(
            got.insert(r.frame_id, reported).is_none(),
            "frame {} twice",
            r.frame_id
        );
        order.push(r.frame_id);
    }
    assert!(order.windows(2).all(|w| w[0] < w[1]), "{order:?}");
    assert_eq!(got, pushed, "every accepted batch in exactly one result");

    // The SSE stream got the same frames and then ended.
    let mut text = String::new();
    guard("SSE end", async {
        while let Some(chunk) = sse.next().await {
            match chunk {
                Ok(c) => text.push_str(&String::from_utf8_lossy(&c)),
                Err(_) => break,
            }
        }
    })
    .await;
    assert_eq!(text.matches("event: frame").count(), pushed.len(), "{text}");

    guard("server exit", shutdown).await.unwrap().unwrap();
}

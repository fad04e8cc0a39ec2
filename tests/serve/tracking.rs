//! Track ids in the stream: every identity of a synchronized frame carries a `track_id`, the
//! same people standing still keep theirs from frame to frame (over gRPC and in the JSON of
//! the SSE stream), a frame-id gap does not reset them, and unary results carry none, nor
//! does any result with tracking off.

use crossview_api::pb;
use crossview_testing::*;
use futures::StreamExt;

/// Every camera's batch of frame `frame_id` with the same boxes as frame 0 (nobody moves).
async fn push_still_frame(server: &TestServer, frame_id: u64) {
    for cam in 0..3 {
        let mut b = batch_json(cam, 0, 4);
        b["frame_id"] = frame_id.into();
        let (status, _) = server.post_json("/v1/scenes/lab/batches", &b).await;
        assert_eq!(status, 202);
    }
}

/// `(sorted members, track id)` of each identity of a result.
fn tracked(r: &pb::FrameResult) -> Vec<(Vec<(u32, u32)>, u64)> {
    let mut out: Vec<_> = r
        .identities
        .iter()
        .map(|i| {
            let m = i
                .members
                .iter()
                .map(|m| (m.camera_index, m.index))
                .collect();
            (m, i.track_id.expect("a streamed identity has a track id"))
        })
        .collect();
    out.sort();
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn people_standing_still_keep_their_track_ids() {
    let server = start(|_| {}).await;
    let mut results = server.subscribe("lab").await;
    let sse = reqwest::get(server.url("/v1/scenes/lab/events"))
        .await
        .unwrap();
    let mut sse = sse.bytes_stream();
    // Frames 1..=5, then a gap in the ids (frame 50): the same boxes every time.
    let ids = [1u64, 2, 3, 4, 5, 50];
    let mut first = None;
    for &f in &ids {
        push_still_frame(&server, f).await;
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, f);
        check_identities(&r, &[4, 4, 4]);
        let t = tracked(&r);
        let all: std::collections::HashSet<u64> = t.iter().map(|(_, id)| *id).collect();
        assert_eq!(
            all.len(),
            t.len(),
            "track ids are unique within a frame: {t:?}"
        );
        match &first {
            None => first = Some(t),
            Some(f0) => assert_eq!(&t, f0, "frame {f}: the same people keep their tracks"),
        }
    }
    // The SSE stream's JSON carries the same track ids.
    let mut text = String::new();
    guard("SSE frame events", async {
        while text.matches("event: frame").count() < ids.len() || !text.ends_with("\n\n") {
            let chunk = sse.next().await.unwrap().unwrap();
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    })
    .await;
    let data = text
        .lines()
        .filter_map(|l| l.strip_prefix("data: "))
        .next_back()
        .unwrap();
    let v: serde_json::Value = serde_json::from_str(data).unwrap();
    let mut sse_tracks: Vec<u64> = v["identities"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["track_id"].as_u64().expect("track_id in the JSON"))
        .collect();
    sse_tracks.sort();
    let mut grpc_tracks: Vec<u64> = first.unwrap().into_iter().map(|(_, t)| t).collect();
    grpc_tracks.sort();
    assert_eq!(sse_tracks, grpc_tracks);

    // A unary call is not part of the stream: no track ids.
    let mut client = server.grpc().await;
    let r = client
        .associate(pb::AssociateRequest {
            scene: "lab".into(),
            frame_id: 51,
            time: None,
            views: (0..3)
                .map(|c| pb::CameraView {
                    camera: CAMERAS[c].into(),
                    detections: dets(c, 0, 4),
                })
                .collect(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!r.identities.is_empty());
    assert!(r.identities.iter().all(|i| i.track_id.is_none()));
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tracking_off_streams_identities_without_track_ids() {
    let server = start(|c| c.tracker = None).await;
    let mut results = server.subscribe("lab").await;
    for f in 1..=2 {
        push_still_frame(&server, f).await;
        let r = guard("result", results.next()).await.unwrap().unwrap();
        check_identities(&r, &[4, 4, 4]);
        assert!(r.identities.iter().all(|i| i.track_id.is_none()), "{r:?}");
    }
    server.shutdown().await.unwrap();
}

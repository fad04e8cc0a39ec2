//! Capture times instead of frame ids: cameras that stamp their batches with when they captured
//! them, each with its own clock offset and jitter, the cameras of one frame pushed spread in
//! time and out of order, are grouped into the frames they were captured in; results carry the
//! frame's tick time; recordings keep the times; bad times are refused naming the field and
//! change nothing. Real server on 127.0.0.1:0, real ONNX model, HTTP, gRPC and SSE clients.
use std::time::Duration;

use crossview_api::pb;
use crossview_serve::RecordConfig;
use crossview_serve::config::SceneDecl;
use crossview_testing::*;
use futures::StreamExt;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use serde_json::json;

/// 2026-12-06T00:00:00Z in seconds: the test's first frame.
const T0: f64 = 1_796_515_200.0;
/// The scene's rate and period.
const FPS: f64 = 10.0;
const PERIOD: f64 = 1.0 / FPS;
/// The tick of frame 0 (ticks count periods from the Unix epoch).
const TICK0: u64 = 17_965_152_000;

/// The test scene `lab` at 10 frames/s: camera c1's clock declared 1,230 ms ahead; c2's clock
/// 45 ms ahead, not declared (followed from its times).
fn timed_scene(c: &mut crossview_serve::ServeConfig) {
    c.sync_timeout = Duration::from_secs(5);
    c.limits.subscriber_buffer = 10_000;
    c.scenes =
        vec![SceneDecl::parse("lab=c0:1920x1080,c1:1280x720@+1230ms,c2:640x480@10fps").unwrap()];
}

/// Camera `c`'s capture time of frame `k` (seconds), as its own clock stamps it: the true time
/// plus its clock offset plus `jitter` seconds.
fn stamp(c: usize, k: u64, jitter: f64) -> f64 {
    let clock = [0.0, 1.230, 0.045][c];
    T0 + k as f64 * PERIOD + clock + jitter
}

/// A camera batch stamped with a time only (Unix seconds, or RFC 3339 when `rfc`).
fn timed_batch(c: usize, k: u64, t: f64, rfc: bool) -> serde_json::Value {
    let mut b = batch_json(c, k, 2);
    b.as_object_mut().unwrap().remove("frame_id");
    b["time"] = if rfc { json!(rfc3339(t)) } else { json!(t) };
    b
}

fn rfc3339(t: f64) -> String {
    let ns = (t * 1e9).round() as i64;
    crossview_core::capture::CaptureTime::from_unix_nanos(ns)
        .unwrap()
        .to_rfc3339()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn timestamped_cameras_with_offsets_and_jitter_are_grouped_into_their_frames() {
    let server = start(timed_scene).await;
    let mut results = server.subscribe("lab").await;
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/lab/batches");
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    const FRAMES: u64 = 40;
    // Every batch of two frames at a time, shuffled: cameras of one frame spread in time and
    // out of order. Jitter up to ±30 ms (c2: ±15 ms about its 45 ms); the first frame's none,
    // so c2's first capture places its phase clear of the half period.
    let mut sends: Vec<(usize, u64)> = Vec::new();
    for pair in (0..FRAMES).collect::<Vec<_>>().chunks(2) {
        let mut both: Vec<(usize, u64)> = pair
            .iter()
            .flat_map(|&k| (0..3).map(move |c| (c, k)))
            .collect();
        both.shuffle(&mut rng);
        // A camera's own batches stay in capture order (a camera never sends backwards).
        for c in 0..3 {
            let slots: Vec<usize> = (0..both.len()).filter(|&i| both[i].0 == c).collect();
            for (slot, &k) in slots.iter().zip(pair) {
                both[*slot].1 = k;
            }
        }
        sends.extend(both);
    }
    for (n, &(c, k)) in sends.iter().enumerate() {
        let jitter = if k == 0 {
            0.0
        } else if c == 2 {
            rng.random_range(-0.015..0.015)
        } else {
            rng.random_range(-0.030..0.030)
        };
        let body = timed_batch(c, k, stamp(c, k, jitter), n % 2 == 0);
        let r = http.post(&url).json(&body).send().await.unwrap();
        let status = r.status();
        let ack: serde_json::Value = r.json().await.unwrap();
        assert_eq!(status, 202, "camera {c} frame {k}: {ack}");
    }
    for k in 0..FRAMES {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!(r.frame_id, TICK0 + k, "{r:?}");
        assert!(r.complete, "frame {k} cut: {r:?}");
        let t = r
            .time
            .expect("a timed scene's result carries its tick time");
        let expected = (T0 + k as f64 * PERIOD) * 1e9;
        let got = t.seconds as f64 * 1e9 + f64::from(t.nanos);
        assert!((got - expected).abs() < 1e3, "{t:?} for frame {k}");
        check_identities(&r, &[2, 2, 2]);
    }
    // The JSON form: SSE/HTTP results carry the time as RFC 3339.
    let d = server.get_json("/v1/scenes/lab").await;
    assert_eq!(d["cameras"][1]["offset_ms"], 1230, "{d}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_batches_and_unary_requests_take_timestamps() {
    let server = start(timed_scene).await;
    let mut results = server.subscribe("lab").await;
    let mut client = server.grpc().await;
    let ts = |t: f64| prost_types::Timestamp {
        seconds: t.floor() as i64,
        nanos: ((t - t.floor()) * 1e9).round() as i32,
    };
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut acks = client
        .push(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    for k in 0..3 {
        for c in [2, 0, 1] {
            let mut b = batch(c, 0, 2);
            b.time = Some(ts(stamp(c, k, 0.0)));
            tx.send(b).await.unwrap();
            let ack = guard("ack", acks.next()).await.unwrap().unwrap();
            assert_eq!(ack.code, 0, "{ack:?}");
            // The ack names the tick the batch went to (its time less the camera's offset).
            assert_eq!(ack.frame_id, TICK0 + k, "{ack:?}");
        }
    }
    for k in 0..3 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!((r.frame_id, r.complete), (TICK0 + k, true), "{r:?}");
    }
    // A bad timestamp in a stream: refused in its ack, the stream goes on.
    let mut b = batch(0, 0, 1);
    b.time = Some(prost_types::Timestamp {
        seconds: T0 as i64,
        nanos: -5,
    });
    tx.send(b).await.unwrap();
    let ack = guard("ack", acks.next()).await.unwrap().unwrap();
    assert_eq!(ack.code, tonic::Code::InvalidArgument as i32, "{ack:?}");
    assert!(ack.message.contains("time"), "{ack:?}");
    drop(tx);
    // Unary: the frame's id is its time's tick, and the result carries the tick time.
    let mut req = pb::AssociateRequest {
        scene: "lab".into(),
        views: (0..3)
            .map(|c| pb::CameraView {
                camera: CAMERAS[c].into(),
                detections: dets(c, 9, 2),
            })
            .collect(),
        ..Default::default()
    };
    req.time = Some(ts(T0 + 0.5 + 0.02));
    let r = client.associate(req.clone()).await.unwrap().into_inner();
    assert_eq!(r.frame_id, TICK0 + 5);
    assert_eq!(r.time, Some(ts(T0 + 0.5)));
    req.frame_id = TICK0 + 6;
    let e = client.associate(req).await.unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(e.message().contains("frame_id"), "{e:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_times_are_refused_naming_the_field_and_change_nothing() {
    // A scene without a frame rate takes no times.
    let plain = start(|_| {}).await;
    let (status, body) = plain
        .post_json("/v1/scenes/lab/batches", &timed_batch(0, 0, T0, false))
        .await;
    assert_eq!(status, 422, "{body}");
    assert!(body.to_string().contains("frame rate"), "{body}");
    plain.shutdown().await.unwrap();

    let server = start(|c| {
        timed_scene(c);
        c.time_tolerance = Some(Duration::from_millis(20));
    })
    .await;
    let post = |body: serde_json::Value| {
        let s = &server;
        async move { s.post_json("/v1/scenes/lab/batches", &body).await }
    };
    let refused = |(status, body): (reqwest::StatusCode, serde_json::Value), field: &str| {
        // 400: the body does not parse; 422: it parses, and is refused.
        assert!(status == 400 || status == 422, "{status} {body}");
        let text = body.to_string();
        assert!(text.contains(field), "{field}: {text}");
    };
    // Junk in the time field itself: refused by the body's parser, naming it.
    for junk in [
        json!(-5),
        json!(1e300),
        json!("yesterday"),
        json!("1969-12-31T23:59:59Z"),
    ] {
        let mut b = batch_json(0, 0, 1);
        b.as_object_mut().unwrap().remove("frame_id");
        b["time"] = junk;
        refused(post(b).await, "capture time");
    }
    // Neither a frame id nor a time.
    let mut b = batch_json(0, 0, 1);
    b.as_object_mut().unwrap().remove("frame_id");
    refused(post(b).await, "frame_id");
    // A frame id that is not the time's tick.
    let mut b = timed_batch(0, 0, stamp(0, 0, 0.0), false);
    b["frame_id"] = json!(TICK0 + 3);
    refused(post(b).await, "frame_id");
    // Nothing above changed the scene: it is still open to either kind of stamp.
    let (status, body) = post(timed_batch(0, 5, stamp(0, 5, 0.0), false)).await;
    assert_eq!(status, 202, "{body}");
    // 30 ms from its tick with a 20 ms tolerance (once the camera's phase is known).
    refused(
        post(timed_batch(0, 6, stamp(0, 6, 0.030), false)).await,
        "tolerance",
    );
    // Now timed: frame ids alone are refused, as is a time that goes backwards.
    refused(post(batch_json(1, 5, 1)).await, "time");
    refused(
        post(timed_batch(0, 3, stamp(0, 3, 0.0), false)).await,
        "backwards",
    );
    // Far in the future: out of the scene's frame window.
    let (status, body) = post(timed_batch(2, 5, T0 + 3.0e7, false)).await;
    assert!(status.is_client_error(), "{status} {body}");
    assert!(body.to_string().contains("out_of_range"), "{body}");
    // The frame still completes with the other cameras' batches.
    let mut results = server.subscribe("lab").await;
    for c in [1, 2] {
        let (status, body) = post(timed_batch(c, 5, stamp(c, 5, 0.0), true)).await;
        assert_eq!(status, 202, "{body}");
    }
    let r = guard("result", results.next()).await.unwrap().unwrap();
    assert_eq!((r.frame_id, r.complete), (TICK0 + 5, true), "{r:?}");
    server.shutdown().await.unwrap();

    // A scene fed frame ids refuses times.
    let ids = start(timed_scene).await;
    let (status, _) = ids
        .post_json("/v1/scenes/lab/batches", &batch_json(0, 1, 1))
        .await;
    assert_eq!(status, 202);
    let (status, body) = ids
        .post_json("/v1/scenes/lab/batches", &timed_batch(1, 1, T0, false))
        .await;
    assert_eq!(status, 422, "{body}");
    assert!(body.to_string().contains("frame ids"), "{body}");
    ids.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recordings_keep_capture_times_and_read_back_as_served() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        timed_scene(c);
        c.record = Some(RecordConfig::new(&dir));
    })
    .await;
    let mut results = server.subscribe("lab").await;
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    for k in 0..12 {
        for c in 0..3 {
            let jitter = if k == 0 {
                0.0
            } else {
                rng.random_range(-0.015..0.015)
            };
            let (status, body) = server
                .post_json(
                    "/v1/scenes/lab/batches",
                    &timed_batch(c, k, stamp(c, k, jitter), false),
                )
                .await;
            assert_eq!(status, 202, "{body}");
        }
    }
    for _ in 0..12 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert!(r.complete, "{r:?}");
    }
    server.shutdown().await.unwrap();
    let files = crossview_data::recording_files(std::slice::from_ref(&dir)).unwrap();
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let header: serde_json::Value = serde_json::from_str(text.lines().next().unwrap()).unwrap();
    assert_eq!(header["fps"], 10.0, "{header}");
    let line: serde_json::Value = serde_json::from_str(text.lines().nth(1).unwrap()).unwrap();
    assert!(
        line["time"]
            .as_str()
            .is_some_and(|t| t.starts_with("2026-12-06T00:00:0")),
        "{line}"
    );
    let (rec, _) = crossview_data::read_recordings(&[dir], true).unwrap();
    let ids: Vec<u64> = rec.frames.iter().map(|f| f.frame_id).collect();
    assert_eq!(ids, (TICK0..TICK0 + 12).collect::<Vec<_>>());
    assert!(rec.frames.iter().all(|f| f.is_complete()));
    // The times alone (ids dropped) group the same way at the header's rate.
    let timed_only: String = text
        .lines()
        .enumerate()
        .map(|(i, l)| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            if i > 0 {
                v.as_object_mut().unwrap().remove("frame_id");
            }
            v.to_string() + "\n"
        })
        .collect();
    let path = rec_dir.path().join("times-only.jsonl");
    std::fs::write(&path, timed_only).unwrap();
    let again = crossview_data::read_recording(&path).unwrap();
    // c2's 45 ms offset is not in the header: the reader follows it from its times, as the
    // server did (45 ± 15 ms crosses half a period: read raw, it would not group).
    assert_eq!(
        again.frames.iter().map(|f| f.frame_id).collect::<Vec<_>>(),
        ids
    );
    assert!(again.frames.iter().all(|f| f.is_complete()));
}

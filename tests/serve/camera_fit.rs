//! A camera that moves is noticed live and fenced, and a camera whose clock runs late is not
//! taken for one: the server's watch tells, per camera, whether it still fits the model (scene
//! description over HTTP and gRPC, metrics), and once it does not, the frames a client
//! receives name it in `fenced_cameras` with each of its boxes an identity of its own. Real server on 127.0.0.1:0, the shipped
//! `models/demo.onnx`, simulated `square4` frames in which one camera really turns (the
//! simulator's pinhole pose changes mid-stream), cameras of one frame pushed in a shuffled
//! order.
use std::time::Duration;

use crossview_core::Batch;
use crossview_data::sim::{CameraMove, SimConfig, Simulator};
use crossview_serve::ServeConfig;
use crossview_serve::config::ClockWatchConfig;
use crossview_testing::*;
use futures::StreamExt;
use rand::SeedableRng;
use rand::seq::SliceRandom;

/// The fit is read every 10 frames from `MOVE_AT + 60` on (the look's newest 60 frames are
/// then after the turn); once it names the camera, `AFTER` more frames are pushed, associated
/// with the fence up. At most `FRAMES` frames (the watch looks as often as it can: a loaded
/// machine makes fewer looks per frame pushed).
const FRAMES: u64 = 1200;
const AFTER: u64 = 30;
/// The camera that turns, and when (frame index at 10 frames/s).
const MOVED: usize = 1;
const MOVE_AT: u64 = 300;
/// A camera whose frame ids run late throughout (a clock offset, not a move).
const LAGGING: usize = 2;
const LAG: u64 = 4;

fn configure(c: &mut ServeConfig) {
    // Long: frames wait for the late camera while the test reads the fit mid-stream.
    c.sync_timeout = Duration::from_secs(5);
    c.limits.subscriber_buffer = 20_000;
    c.limits.clock_watch = ClockWatchConfig {
        window: 250,
        interval: Duration::ZERO,
        max_offset: 10,
        auto_align: false,
        fence: true,
    };
}

/// The live fit once the watch has looked at frames up to `frame` (HTTP JSON).
async fn fit_at(server: &TestServer, frame: u64) -> serde_json::Value {
    guard("fit look", async {
        loop {
            let d = server.get_json("/v1/scenes/demo").await;
            if d["fit"]["as_of_frame"]
                .as_u64()
                .is_some_and(|f| f + 2 >= frame)
            {
                return d["fit"].clone();
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
}

fn states(fit: &serde_json::Value) -> Vec<String> {
    fit["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["state"].as_str().unwrap().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_that_turns_stops_fitting_and_a_late_clock_does_not() {
    let server = start_with(demo_model(), configure).await;
    let mut cfg = SimConfig::preset("square4").unwrap();
    cfg.frames = FRAMES;
    cfg.seed = 21;
    // The image centre moves by 5 % of the width.
    let at_s = MOVE_AT as f64 / cfg.fps;
    cfg.moves = vec![CameraMove::pan(&cfg.scene.cameras[MOVED], at_s, 0.05)];
    let mut sim = Simulator::new(&cfg).unwrap();
    let mut results = server.subscribe("demo").await;
    let names: Vec<String> = sim.scene().cameras.iter().map(|c| c.name.clone()).collect();
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/demo/batches");
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let mut before = None;
    // The fit when it first named the turned camera, and the frame id then.
    let mut after: Option<(u64, serde_json::Value)> = None;
    let mut last = 0;
    while let Some(frame) = sim.next_frame() {
        match &after {
            Some((named, _)) if frame.frame_id > named + AFTER => break,
            None if frame.frame_id >= MOVE_AT + 60 && frame.frame_id % 10 == 0 => {
                let fit = server.get_json("/v1/scenes/demo").await["fit"].clone();
                if states(&fit)[MOVED] == "does_not_fit" {
                    after = Some((frame.frame_id, fit));
                }
                // Room for the watch's thread on a loaded machine.
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            _ => {}
        }
        if frame.frame_id == MOVE_AT {
            // Just before the move: every camera fits, the late one included.
            before = Some(fit_at(&server, MOVE_AT - LAG - 1).await);
        }
        let mut order: Vec<usize> = (0..names.len()).collect();
        order.shuffle(&mut rng);
        for c in order {
            let mut dets = frame.views[c].clone().unwrap_or_default();
            dets.iter_mut().for_each(|d| d.id = None);
            let batch = Batch {
                camera: names[c].clone(),
                frame_id: frame.frame_id + if c == LAGGING { LAG } else { 0 },
                time: None,
                detections: dets,
            };
            let r = http.post(&url).json(&batch).send().await.unwrap();
            assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
        }
        last = frame.frame_id;
    }
    let before = before.unwrap();
    assert!(states(&before).iter().all(|s| s == "fits"), "{before}");
    let (named, after) = after.expect("the turned camera named before the last frame");
    // The turned camera does not fit, the others (the late one too) do.
    let s = states(&after);
    assert_eq!(s[MOVED], "does_not_fit", "{after}");
    for (c, state) in s.iter().enumerate() {
        if c != MOVED {
            assert_eq!(state, "fits", "camera {c}: {after}");
        }
    }
    assert!(
        after["cameras"][MOVED]["score"].as_f64().unwrap() < 0.7,
        "{after}"
    );
    // The clock watch still sees the late camera's offset: an offset stays an offset.
    let d = server.get_json("/v1/scenes/demo").await;
    assert_eq!(d["clock"]["cameras"][LAGGING]["offset_ids"], LAG, "{d}");
    // And a move is never an offset: the turned camera's is unknown while it does not fit.
    let turned = &d["clock"]["cameras"][MOVED];
    assert!(
        turned["offset_ids"].is_null() && turned["confidence"] == 0.0,
        "{d}"
    );
    // The same over gRPC and in the metrics.
    let scene = server.scene("demo").await;
    let fit = scene.fit.expect("fit over gRPC");
    assert_eq!(fit.cameras[MOVED].state, "does_not_fit");
    assert!(fit.cameras[MOVED].known && fit.cameras[MOVED].score < 0.7);
    let m = server.metrics().await;
    let moved = &names[MOVED];
    assert_eq!(
        metric(
            &m,
            &format!(
                "crossview_camera_fit_state{{scene=\"demo\",camera=\"{moved}\",state=\"does_not_fit\"}}"
            )
        ),
        1.0
    );
    assert!(
        metric(
            &m,
            &format!("crossview_camera_fit{{scene=\"demo\",camera=\"{moved}\"}}")
        ) < 0.7
    );
    let fenced = format!("crossview_camera_fenced{{scene=\"demo\",camera=\"{moved}\"}}");
    assert_eq!(metric(&m, &fenced), 1.0);
    // What a client received: nothing fenced before the turn; once the fit said so, the
    // turned camera fenced, each of its boxes alone, the other cameras still linked.
    let mut fenced_frames = 0;
    while let Some(r) = guard("result", results.next()).await {
        let r = r.unwrap();
        if r.frame_id < MOVE_AT {
            assert!(r.fenced_cameras.is_empty(), "frame {}", r.frame_id);
        }
        // Pushed after the fit named it: associated with the fence up.
        if r.frame_id > named {
            assert_eq!(
                r.fenced_cameras,
                std::slice::from_ref(moved),
                "frame {}",
                r.frame_id
            );
            for i in &r.identities {
                if i.members.iter().any(|m| m.camera == *moved) {
                    assert_eq!(i.members.len(), 1, "frame {}: {i:?}", r.frame_id);
                }
            }
            assert!(
                r.identities.iter().any(|i| i.members.len() > 1),
                "frame {}",
                r.frame_id
            );
            fenced_frames += 1;
        }
        if r.frame_id >= last {
            break;
        }
    }
    assert!(fenced_frames + LAG >= AFTER, "{fenced_frames}");
    eprintln!(
        "the turned camera was named {} frames after the turn",
        named - MOVE_AT
    );
    server.shutdown().await.unwrap();
}

//! Healing (`--auto-retrain`): a camera that turns is noticed and fenced; once it has not
//! fitted for `after`, the server retrains the scene's model on what it recorded since (the
//! real `crossview` executable in a child process), gates it without labels on frames recorded
//! after the training data and swaps it in live. What a client then receives: the turned
//! camera unfenced and linked again, rightly. Real server on 127.0.0.1:0, the shipped
//! `models/demo.onnx`, simulated `square4` frames in which one camera really turns (the
//! simulator's pinhole pose), cameras of one frame pushed in a shuffled order.
use std::collections::HashMap;
use std::time::Duration;

use crossview_core::Batch;
use crossview_data::sim::{CameraMove, SimConfig, Simulator};
use crossview_serve::config::{ClockWatchConfig, SceneDecl};
use crossview_serve::{HealConfig, RecordConfig};
use crossview_testing::*;
use futures::StreamExt;
use rand::SeedableRng;
use rand::seq::SliceRandom;

const MOVED: usize = 1;
const MOVE_AT: u64 = 500;
/// Frames pushed at most (the retrain must have ended well before).
const FRAMES: u64 = 30_000;
/// Frames pushed after the swap, whose identities are scored.
const AFTER_SWAP: u64 = 200;

/// Ground truth: per frame, per camera, each box's person.
type Truth = HashMap<u64, Vec<Vec<Option<u64>>>>;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_turned_camera_is_retrained_gated_and_swapped_in() {
    let work = tempfile::tempdir().unwrap();
    let (record, heal_dir) = (work.path().join("rec"), work.path().join("heal"));
    let (rec2, heal2) = (record.clone(), heal_dir.clone());
    let mut cfg = SimConfig::preset("square4").unwrap();
    // The scene's frame rate, declared: the retrain trains at it (its recording says it).
    let mut spec = cfg.scene.spec();
    spec.name = "demo".into();
    let fps = cfg.fps;
    let server = start_with(demo_model(), move |c| {
        c.scenes = vec![SceneDecl {
            spec,
            fps: Some(fps),
        }];
        c.limits.subscriber_buffer = 50_000;
        c.limits.clock_watch = ClockWatchConfig {
            window: 250,
            interval: Duration::from_secs(1),
            max_offset: 10,
            auto_align: false,
            fence: true,
        };
        c.record = Some(RecordConfig::new(rec2));
        c.heal = Some(HealConfig {
            // The new view is recorded for this long at the test's pace (about 100 frames/s,
            // idle or loaded), so the retrain learns from about as many frames either way.
            after: Duration::from_secs(40),
            epochs: 40,
            gate_after: Duration::from_secs(2),
            // A short retrain can fall just short of the gate (a pair's contrast 0.146 against
            // the 0.15 it must keep, once in a loaded run): a refused candidate is retried on
            // the next stretch of the new view, as the server does after its interval.
            interval: Duration::from_secs(1),
            timeout: Duration::from_secs(600),
            // Beside the suite's other tests a child at the lowest priority may wait minutes.
            nice: 0,
            reference_every: Duration::from_secs(2),
            // A short retrain (the defaults' own figures: BENCHMARKS.md, "Healing") heals the
            // turned camera partly: the gate's tolerance is widened to let it through.
            tolerance: 0.15,
            ..HealConfig::new(env!("CARGO_BIN_EXE_crossview"), heal2)
        });
    })
    .await;
    let before = server.get_json("/v1/scenes/demo").await;
    assert_eq!(before["retrain"]["state"], "idle", "{before}");
    let old_version = before["model_version"].as_str().unwrap().to_string();

    cfg.frames = FRAMES;
    cfg.seed = 31;
    // The image centre moves by 5 % of the width.
    let at_s = MOVE_AT as f64 / cfg.fps;
    cfg.moves = vec![CameraMove::pan(&cfg.scene.cameras[MOVED], at_s, 0.05)];
    let mut sim = Simulator::new(&cfg).unwrap();
    let names: Vec<String> = sim.scene().cameras.iter().map(|c| c.name.clone()).collect();
    // Read as they come (a subscriber that stops reading is cut off).
    let mut results = server.subscribe("demo").await;
    let (seen_tx, mut seen) = tokio::sync::mpsc::unbounded_channel();
    let reader = tokio::spawn(async move {
        while let Some(r) = results.next().await {
            let r = r.unwrap();
            if seen_tx.send(r).is_err() {
                break;
            }
        }
    });
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/demo/batches");
    let mut rng = rand::rngs::StdRng::seed_from_u64(9);
    let mut truth = Truth::new();
    let mut states_seen: Vec<String> = Vec::new();
    let mut swapped_at: Option<u64> = None;
    let mut busy = false;
    let mut last = 0;
    while let Some(frame) = sim.next_frame() {
        if swapped_at.is_some_and(|s| frame.frame_id > s + AFTER_SWAP) {
            break;
        }
        if frame.frame_id % 20 == 0 && swapped_at.is_none() {
            let d = server.get_json("/v1/scenes/demo").await;
            let r = &d["retrain"];
            let state = r["state"].as_str().unwrap().to_string();
            busy = state == "training" || state == "gating";
            if states_seen.last() != Some(&state) {
                states_seen.push(state);
            }
            match r["last_outcome"].as_str() {
                Some("swapped") => swapped_at = Some(frame.frame_id),
                Some("refused") | None => {}
                Some(_) => panic!("{d}"),
            }
        }
        let mut ids = Vec::new();
        let mut order: Vec<usize> = (0..names.len()).collect();
        order.shuffle(&mut rng);
        let mut batches = Vec::new();
        for view in &frame.views {
            let mut dets = view.clone().unwrap_or_default();
            ids.push(dets.iter().map(|d| d.id).collect());
            dets.iter_mut().for_each(|d| d.id = None);
            batches.push(dets);
        }
        truth.insert(frame.frame_id, ids);
        for c in order {
            let batch = Batch {
                camera: names[c].clone(),
                frame_id: frame.frame_id,
                time: None,
                detections: std::mem::take(&mut batches[c]),
            };
            let r = http.post(&url).json(&batch).send().await.unwrap();
            assert_eq!(r.status(), 202, "{}", r.text().await.unwrap());
        }
        last = frame.frame_id;
        // Faster than a real scene while there is nothing to wait for; while the retrain runs,
        // about the pace of one (its child gets the room it would on 2 cores).
        let pace = if busy { 50 } else { 10 };
        tokio::time::sleep(Duration::from_millis(pace)).await;
    }
    let swapped_at = swapped_at.unwrap_or_else(|| {
        panic!("no retrain ended within {FRAMES} frames; states {states_seen:?}")
    });
    assert!(
        states_seen.windows(2).any(|w| w == ["waiting", "training"])
            || states_seen.contains(&"training".to_string()),
        "{states_seen:?}"
    );
    let after = server.get_json("/v1/scenes/demo").await;
    let new_version = after["model_version"].as_str().unwrap().to_string();
    assert_ne!(new_version, old_version, "{after}");
    let r = &after["retrain"];
    let attempts = r["attempts"].as_u64().unwrap();
    assert!((1..=4).contains(&attempts), "{after}");
    assert_eq!(r["swapped"].as_u64(), Some(1), "{after}");
    let model = r["last_model"].as_str().unwrap();
    assert!(model.starts_with(heal_dir.to_str().unwrap()), "{model}");
    assert!(std::path::Path::new(model).exists(), "{model}");
    // The old file is left as it was.
    assert!(repo_root().join("models/demo.onnx").exists());
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_retrains_total{scene=\"demo\",outcome=\"swapped\"}"
        ),
        1.0
    );
    assert_eq!(metric(&m, "crossview_retrain_running{scene=\"demo\"}"), 0.0);
    // The same over gRPC.
    let scene = server.scene("demo").await;
    assert_eq!(scene.retrain.expect("retrain over gRPC").swapped, 1);

    // What a client received after the swap: the turned camera unfenced and linked to the
    // others, rightly.
    // Per phase (before the turn; turned, the old model, not yet fenced; after the swap):
    // links right, links, links of the turned camera right, links of the turned camera.
    let mut phases = [[0usize; 4]; 3];
    // Frames after the swap, and those of them still fenced (the new model's own fit watch
    // may flag a camera a short retrain fits only just).
    let (mut after_swap, mut fenced_after) = (0usize, 0usize);
    while let Some(res) = guard("result", seen.recv()).await {
        let new = res.model_version == new_version && res.frame_id > swapped_at;
        after_swap += usize::from(new);
        fenced_after += usize::from(new && !res.fenced_cameras.is_empty());
        let phase = if res.frame_id < MOVE_AT {
            Some(0)
        } else if new && res.fenced_cameras.is_empty() {
            Some(2)
        } else if res.model_version == old_version && res.fenced_cameras.is_empty() {
            Some(1)
        } else {
            None
        };
        if let Some(p) = phase {
            let t = &truth[&res.frame_id];
            for i in &res.identities {
                for (k, a) in i.members.iter().enumerate() {
                    for b in &i.members[k + 1..] {
                        let (ca, cb) = (a.camera_index as usize, b.camera_index as usize);
                        let (pa, pb) = (t[ca][a.index as usize], t[cb][b.index as usize]);
                        let ok = usize::from(pa.is_some() && pa == pb);
                        let moved = ca == MOVED || cb == MOVED;
                        phases[p][0] += ok;
                        phases[p][1] += 1;
                        phases[p][2] += ok * usize::from(moved);
                        phases[p][3] += usize::from(moved);
                    }
                }
            }
        }
        if res.frame_id >= last {
            break;
        }
    }
    reader.abort();
    let share = |a: usize, b: usize| a as f64 / b.max(1) as f64;
    let [before, turned, healed] = phases.map(|p| (share(p[0], p[1]), share(p[2], p[3]), p[3]));
    eprintln!(
        "healed: swapped at frame {swapped_at}; link precision (all, turned camera's, its links): before the turn {before:?}, turned {turned:?}, after the swap {healed:?}; states {states_seen:?}; {fenced_after} of {after_swap} frames after the swap fenced"
    );
    assert!(healed.2 > 0, "the turned camera is linked again");
    // Unfenced for most of the frames after the swap.
    assert!(
        fenced_after * 5 <= after_swap,
        "{fenced_after} of {after_swap} frames after the swap fenced"
    );
    // Better than the model that no longer fitted it, for the turned camera and for the whole
    // scene (how close a retrain of the defaults comes to before the turn: BENCHMARKS.md,
    // "Healing"; this one learns from seconds of stream).
    assert!(healed.1 > turned.1 + 0.1, "{healed:?} against {turned:?}");
    assert!(healed.0 > turned.0, "{healed:?} against {turned:?}");
    server.shutdown().await.unwrap();
}

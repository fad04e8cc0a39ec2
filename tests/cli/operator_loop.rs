//! The operator's loop for a new camera setup, end to end with the real binary: a scene
//! declared by its cameras alone (the simulator's 4-camera preset, no model), batches pushed
//! over gRPC while `--record` writes them, `crossview train` (default recipe, short run, no
//! labels) on the recorded directory, the model swapped in with SIGHUP while batches keep
//! arriving. Every accepted batch is in exactly one result; results before the swap say
//! `no_model`, after it they name the new version; and the served identities match the
//! simulator's ground truth far above chance.

use std::collections::BTreeMap;
use std::time::Duration;

use crossview::demo::score::pair_records;
use crossview_api::convert::batch_to_pb;
use crossview_api::pb;
use crossview_api::pb::association_client::AssociationClient;
use crossview_core::identity::Identity;
use crossview_data::{Recording, read_recording};
use crossview_eval::compute_metrics;
use crossview_eval::driver::frame_ids;
use crossview_testing::*;
use futures::StreamExt;

const SCENE: &str = "square4";

fn simulate(bin: &str, out: &std::path::Path, frames: u32, seed: u32) -> Recording {
    let (frames, seed) = (frames.to_string(), seed.to_string());
    run_crossview(
        bin,
        &[
            "simulate",
            "--preset",
            SCENE,
            "--people",
            "4",
            "--frames",
            &frames,
            "--seed",
            &seed,
            "--clean",
            "--out",
            out.to_str().unwrap(),
        ],
        &[],
    );
    read_recording(out).unwrap()
}

/// Pushes `batches` over one gRPC Push call, `pause` between frames; every ack accepted.
async fn push(base: String, batches: Vec<pb::Batch>, pause: Duration) {
    let mut client = AssociationClient::connect(base).await.unwrap();
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let call = tokio::spawn(async move {
        let mut acks = client
            .push(tokio_stream::wrappers::ReceiverStream::new(rx))
            .await
            .unwrap()
            .into_inner();
        let mut n = 0;
        while let Some(ack) = acks.next().await {
            let ack = ack.unwrap();
            assert_eq!(ack.code, 0, "{ack:?}");
            n += 1;
        }
        n
    });
    let total = batches.len();
    let mut last = None;
    for b in batches {
        if last.is_some_and(|f| f != b.frame_id) && !pause.is_zero() {
            tokio::time::sleep(pause).await;
        }
        last = Some(b.frame_id);
        tx.send(b).await.unwrap();
    }
    drop(tx);
    assert_eq!(call.await.unwrap(), total, "one ack per batch");
}

/// Reads results until `seen` holds `until` frames; no frame comes twice.
async fn take(
    results: &mut tonic::Streaming<pb::FrameResult>,
    seen: &mut BTreeMap<u64, pb::FrameResult>,
    until: usize,
) {
    guard("results", async {
        while seen.len() < until {
            let r = results.next().await.unwrap().unwrap();
            let f = r.frame_id;
            assert!(seen.insert(f, r).is_none(), "frame {f} twice");
        }
    })
    .await;
}

fn to_pb(rec: &Recording, shift: u64) -> Vec<pb::Batch> {
    rec.batches()
        .map(|mut b| {
            b.frame_id += shift;
            batch_to_pb(SCENE, &b)
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn record_train_and_swap_in_a_model_for_a_new_camera_setup() {
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    // 150 s at 10 frames/s: the recorded headers declare the rate, and training keeps one
    // frame in 5 (about 2 frames/s, docs/method.md §7): 300 frames.
    let first = simulate(bin, &tmp.path().join("first.jsonl"), 1500, 5);
    let later = simulate(bin, &tmp.path().join("later.jsonl"), 120, 9);
    let model = tmp.path().join("square4.onnx");
    let record = tmp.path().join("rec");
    let header = tmp.path().join("first.jsonl");
    let (mut child, base) = spawn_serve(
        bin,
        &[
            "--scene",
            header.to_str().unwrap(),
            "--model",
            &format!("{SCENE}={}", model.display()),
            "--record",
            record.to_str().unwrap(),
            "--sync-timeout",
            "30s",
        ],
    )
    .await;
    let mut results = AssociationClient::connect(base.clone())
        .await
        .unwrap()
        .subscribe(pb::SubscribeRequest {
            scene: SCENE.into(),
        })
        .await
        .unwrap()
        .into_inner();
    let mut seen: BTreeMap<u64, pb::FrameResult> = BTreeMap::new();

    // 1. No model yet: pushed, recorded, published as `no_model`.
    push(base.clone(), to_pb(&first, 0), Duration::ZERO).await;
    let n1 = first.frames.len();
    take(&mut results, &mut seen, n1).await;
    assert!(
        seen.values()
            .all(|r| r.status == pb::ResultStatus::NoModel as i32 && r.identities.is_empty())
    );
    let batches = first.batches().count() as f64;
    let recorded = format!("crossview_record_batches_total{{scene=\"{SCENE}\"}}");
    wait_for_metric(&base, &recorded, batches).await;

    // 2. Train on the recorded directory: the default recipe, shortened, no labels.
    let trained = tmp.path().join("trained.onnx");
    run_crossview(
        bin,
        &[
            "train",
            "--quiet",
            "--data",
            record.to_str().unwrap(),
            "--out",
            trained.to_str().unwrap(),
            "--epochs",
            "60",
            "--self-train-epochs",
            "0",
        ],
        &[],
    );
    std::fs::rename(&trained, &model).unwrap();

    // 3. New frames keep coming; SIGHUP swaps the model in between two of them.
    let shift = 1 + first.frames.last().unwrap().frame_id;
    let pusher = tokio::spawn(push(
        base.clone(),
        to_pb(&later, shift),
        Duration::from_millis(10),
    ));
    let n2 = later.frames.len();
    take(&mut results, &mut seen, n1 + 20).await;
    signal(&child, "HUP");
    take(&mut results, &mut seen, n1 + n2).await;
    pusher.await.unwrap();

    let after: Vec<&pb::FrameResult> = seen.values().skip(n1).collect();
    let first_new = after
        .iter()
        .position(|r| r.status == pb::ResultStatus::Associated as i32)
        .expect("the trained model served");
    let version = after[first_new].model_version.clone();
    assert!(version.contains('@'), "{version}");
    assert!(
        after[..first_new]
            .iter()
            .all(|r| r.status == pb::ResultStatus::NoModel as i32)
    );
    assert!(
        after[first_new..]
            .iter()
            .all(|r| r.status == pb::ResultStatus::Associated as i32 && r.model_version == version),
        "the new version from the swap on"
    );
    // Every accepted batch in exactly one result: every frame once, complete.
    assert_eq!(seen.len(), n1 + n2);
    assert!(seen.values().all(|r| r.complete));

    // The served identities against the simulator's ground truth.
    let names: Vec<String> = later.scene.cameras.iter().map(|c| c.name.clone()).collect();
    let mut records = Vec::new();
    for frame in &later.frames {
        let r = &seen[&(frame.frame_id + shift)];
        if r.status != pb::ResultStatus::Associated as i32 {
            continue;
        }
        let served: Vec<Identity> = r
            .identities
            .iter()
            .map(|i| Identity {
                id: i.id as usize,
                confidence: i.confidence,
                members: i
                    .members
                    .iter()
                    .map(|m| (m.camera_index as usize, m.index as usize))
                    .collect(),
            })
            .collect();
        let truth = frame_ids(&later.scene, frame).unwrap();
        records.extend(pair_records(frame.frame_id, &names, &truth, &served).unwrap());
    }
    let m = compute_metrics(&records);
    assert!(m.frames >= 50, "{m:?}");
    // Chance is far below: with 4 people a random pairing of two cameras' boxes is right about
    // a quarter of the time.
    assert!(m.acc >= 0.8, "identity ACC of the served results: {m:?}");
    signal(&child, "TERM");
    assert!(child.wait().unwrap().success());
}

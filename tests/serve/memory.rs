//! Identities with memory, as served: a scene's streamed frames are associated with the memory
//! of the frames before them — exactly what `crossview_core::memory` gives offline in frame
//! order, and not what each frame alone gives — a model swap starts the memory over, and a
//! unary request is one frame alone. The shipped demo model on a simulated `square4` stream
//! with a noisy detector (jitter, misses, false positives: the transient mistakes memory is
//! for), cameras of a frame pushed out of order.

use std::path::Path;

use crossview_api::pb;
use crossview_core::association::{AssociationConfig, embed_frame, frame_identities_with};
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::{Batch, Frame, SceneSpec};
use crossview_data::sim::{SimConfig, simulate};
use crossview_model::OnnxEncoder;
use crossview_serve::ModelSpec;
use crossview_testing::*;
use futures::StreamExt;
use rand::SeedableRng;
use rand::seq::SliceRandom;

/// A frame's identities as sorted member lists `(camera index, box index)`.
type Groups = Vec<Vec<(u32, u32)>>;

fn served(r: &pb::FrameResult) -> Groups {
    let mut g: Groups = r
        .identities
        .iter()
        .map(|i| {
            i.members
                .iter()
                .map(|m| (m.camera_index, m.index))
                .collect()
        })
        .collect();
    g.sort();
    g
}

/// The identities of `frames` associated in order with model `path`, with `memory` (or each
/// frame alone).
fn offline(
    path: &Path,
    scene: &SceneSpec,
    frames: &[Frame],
    mut memory: Option<&mut Memory>,
) -> Vec<Groups> {
    let mut enc = OnnxEncoder::load(path).unwrap();
    let cfg: AssociationConfig = enc.metadata().association_config();
    frames
        .iter()
        .map(|f| {
            let e = embed_frame(&mut enc, scene, f).unwrap();
            let ids = frame_identities_with(f, &e, &cfg, &[], memory.as_deref_mut());
            let mut g: Groups = ids
                .iter()
                .map(|i| {
                    i.members
                        .iter()
                        .map(|&(c, k)| (c as u32, k as u32))
                        .collect()
                })
                .collect();
            g.sort();
            g
        })
        .collect()
}

/// The model swapped in: an untrained encoder of demo's architecture and width for its cameras,
/// whose distances have nothing in common with demo's (a memory carried over would show; one
/// of another width could not even link a camera's boxes to the old embeddings).
fn untrained_like_demo(dir: &Path) -> std::path::PathBuf {
    let (demo, meta) =
        crossview_model::read_ensemble(repo_root().join("models/demo.onnx")).unwrap();
    let first = &demo.members()[0];
    let noise =
        crossview_model::EncoderWeights::random(first.num_cameras, first.config, 3).unwrap();
    let ensemble = crossview_model::Ensemble::new(vec![noise]).unwrap();
    let path = dir.join("next.onnx");
    crossview_model::write_ensemble_onnx(&path, &ensemble, &meta).unwrap();
    path
}

/// Pushes `frames` over HTTP, each frame's cameras in a shuffled order.
async fn push(server: &TestServer, scene: &SceneSpec, frames: &[Frame], seed: u64) {
    let http = reqwest::Client::new();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    for f in frames {
        let mut order: Vec<usize> = (0..scene.cameras.len()).collect();
        order.shuffle(&mut rng);
        for c in order {
            let batch = Batch {
                camera: scene.cameras[c].name.clone(),
                frame_id: f.frame_id,
                time: None,
                detections: f.views[c].clone().unwrap_or_default(),
            };
            let r = http
                .post(server.url("/v1/scenes/demo/batches"))
                .json(&batch)
                .send()
                .await
                .unwrap();
            assert_eq!(r.status().as_u16(), 202, "{}", r.text().await.unwrap());
        }
    }
}

/// The next `n` results of `stream`, checked associated.
async fn next_results(
    stream: &mut tonic::Streaming<pb::FrameResult>,
    n: usize,
) -> Vec<pb::FrameResult> {
    let mut out = Vec::with_capacity(n);
    guard("streamed results", async {
        while out.len() < n {
            let r = stream.next().await.expect("stream open").unwrap();
            assert!(r.complete && r.error.is_empty(), "{r:?}");
            out.push(r);
        }
    })
    .await;
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn streams_remember_offline_equal_a_swap_forgets_and_unary_is_alone() {
    let mut sim = SimConfig::preset("square4").unwrap();
    sim.frames = 60;
    sim.seed = 5;
    let rec = simulate(&sim).unwrap();
    let (scene, frames) = (&rec.scene, &rec.frames);
    let (first, second) = frames.split_at(30);

    let dir = tempfile::tempdir().unwrap();
    let served_path = dir.path().join("demo.onnx");
    std::fs::copy(repo_root().join("models/demo.onnx"), &served_path).unwrap();
    let next = untrained_like_demo(dir.path());
    let spec = ModelSpec::parse(served_path.to_str().unwrap()).unwrap();
    let server = start_with(vec![spec], |c| {
        c.sync_timeout = std::time::Duration::from_secs(30);
    })
    .await;
    let mut stream = server.subscribe("demo").await;

    // Offline, in frame order: the old model's memory over the first half, a fresh one under
    // the new model over the second (what the swap must give) ...
    let cfg = MemoryConfig::default();
    let mut memory = Memory::new(cfg.clone());
    let want_first = offline(&served_path, scene, first, Some(&mut memory));
    let mut fresh = Memory::new(cfg.clone());
    let want_second = offline(&next, scene, second, Some(&mut fresh));
    // ... which is not what the frames alone give, nor what the old memory carried on would.
    let alone = offline(&served_path, scene, first, None);
    assert_ne!(
        want_first, alone,
        "memory changes some frame of this stream"
    );
    let carried = offline(&next, scene, second, Some(&mut memory));
    assert_ne!(
        want_second, carried,
        "a memory carried over the swap would show"
    );

    push(&server, scene, first, 1).await;
    let got: Vec<Groups> = next_results(&mut stream, first.len())
        .await
        .iter()
        .map(served)
        .collect();
    assert_eq!(got, want_first);

    std::fs::rename(&next, &served_path).unwrap();
    let http = reqwest::Client::new();
    let r = http
        .post(server.url("/v1/admin/reload"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200, "{}", r.text().await.unwrap());
    push(&server, scene, second, 2).await;
    let results = next_results(&mut stream, second.len()).await;
    let versions: std::collections::BTreeSet<&str> =
        results.iter().map(|r| r.model_version.as_str()).collect();
    assert_eq!(
        versions.len(),
        1,
        "every frame after the reload by the new model: {versions:?}"
    );
    let got: Vec<Groups> = results.iter().map(served).collect();
    assert_eq!(got, want_second);

    // A unary request after the stream is one frame alone: a frame the memory changed.
    let alone_second = offline(&served_path, scene, second, None);
    let k = (0..second.len())
        .find(|&k| alone_second[k] != want_second[k])
        .expect("a frame of the second half that memory changed");
    let f = &second[k];
    let views: Vec<_> = scene
        .cameras
        .iter()
        .zip(&f.views)
        .map(|(c, v)| serde_json::json!({ "camera": c.name, "detections": v.clone().unwrap_or_default() }))
        .collect();
    let body = serde_json::json!({ "frame_id": f.frame_id, "views": views });
    let r = http
        .post(server.url("/v1/scenes/demo/associate"))
        .json(&body)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let v: serde_json::Value = r.json().await.unwrap();
    let mut unary: Groups = v["identities"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| {
            i["members"]
                .as_array()
                .unwrap()
                .iter()
                .map(|m| {
                    (
                        m["camera_index"].as_u64().unwrap() as u32,
                        m["index"].as_u64().unwrap() as u32,
                    )
                })
                .collect()
        })
        .collect();
    unary.sort();
    assert_eq!(unary, alone_second[k]);
    server.shutdown().await.unwrap();
}

//! Live model swaps (`POST /v1/admin/reload` and gRPC `Reload`, what SIGHUP triggers in the
//! binary) and scenes declared by their cameras alone: a swap under load loses no accepted
//! batch and associates none twice, every result names the version that produced it (versions
//! never go back), a corrupt file or a model for other cameras is refused while the old model
//! keeps serving, and a scene with no model yet publishes its frames as `no_model` until one
//! is loaded.

use std::collections::BTreeMap;
use std::path::Path;

use crossview_api::pb;
use crossview_core::CameraSpec;
use crossview_serve::ModelSpec;
use crossview_serve::config::SceneDecl;
use crossview_testing::*;
use futures::StreamExt;

/// Pushes every camera's batch of frame `f` over HTTP.
async fn push_frame(server: &TestServer, f: u64) {
    for cam in 0..3 {
        let (status, body) = server
            .post_json("/v1/scenes/lab/batches", &batch_json(cam, f, 3))
            .await;
        assert_eq!(status, 202, "{body}");
    }
}

/// `POST /v1/admin/reload`: the outcome of scene `lab`.
async fn reload(http: &reqwest::Client, server: &TestServer) -> serde_json::Value {
    let r = http
        .post(server.url("/v1/admin/reload"))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 200);
    let v: serde_json::Value = r.json().await.unwrap();
    v["reloads"]
        .as_array()
        .unwrap()
        .iter()
        .find(|o| o["scene"] == "lab")
        .cloned()
        .expect("an outcome for lab")
}

/// Replaces `dir/lab.onnx` at once (rename) with a model from `seed` for `cameras`.
fn replace_model(dir: &Path, seed: u64, cameras: Vec<CameraSpec>) {
    let new = export_model_with(dir, "next", seed, cameras);
    std::fs::rename(new, dir.join("lab.onnx")).unwrap();
}

async fn scene_version(http: &reqwest::Client, server: &TestServer) -> Option<String> {
    let v: serde_json::Value = http
        .get(server.url("/v1/scenes/lab"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    v["model_version"].as_str().map(str::to_string)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_swap_under_load_loses_nothing_and_every_result_names_its_version() {
    let server = start(|c| c.sync_timeout = std::time::Duration::from_secs(30)).await;
    let http = reqwest::Client::new();
    let old = scene_version(&http, &server).await.expect("a model");
    assert!(old.starts_with("test-1@"), "{old}");
    let mut results = server.subscribe("lab").await;
    // Frames keep arriving while the new file is written and reloaded.
    let frames = 60u64;
    let pusher = {
        let (http, url) = (http.clone(), server.url(""));
        tokio::spawn(async move {
            for f in 1..=frames {
                for cam in 0..3 {
                    let r = http
                        .post(format!("{url}/v1/scenes/lab/batches"))
                        .json(&batch_json(cam, f, 3))
                        .send()
                        .await
                        .unwrap();
                    assert_eq!(r.status(), 202);
                }
                tokio::time::sleep(std::time::Duration::from_millis(5)).await;
            }
        })
    };
    let mut seen: BTreeMap<u64, pb::FrameResult> = BTreeMap::new();
    let mut outcome = None;
    guard("every result", async {
        while seen.len() < frames as usize {
            let r = results.next().await.unwrap().unwrap();
            assert!(
                seen.insert(r.frame_id, r.clone()).is_none(),
                "frame {} twice",
                r.frame_id
            );
            if seen.len() == 20 {
                replace_model(server.dir.path(), 12, cameras());
                outcome = Some(reload(&http, &server).await);
            }
        }
    })
    .await;
    pusher.await.unwrap();
    let outcome = outcome.unwrap();
    assert_eq!(outcome["outcome"], "swapped", "{outcome}");
    let new = outcome["version"].as_str().unwrap().to_string();
    assert_ne!(new, old);
    assert!(
        new.starts_with("test-1@"),
        "same metadata version, another file: {new}"
    );
    // Every frame once, associated, by the old model up to the swap and the new one after.
    let versions: Vec<&str> = seen.values().map(|r| r.model_version.as_str()).collect();
    assert_eq!(
        seen.keys().copied().collect::<Vec<_>>(),
        (1..=frames).collect::<Vec<_>>()
    );
    let first_new = versions
        .iter()
        .position(|v| *v == new)
        .expect("the new model served");
    assert!(first_new > 0, "the old model served first");
    assert!(
        versions[..first_new].iter().all(|v| *v == old),
        "{versions:?}"
    );
    assert!(
        versions[first_new..].iter().all(|v| *v == new),
        "{versions:?}"
    );
    for r in seen.values() {
        assert_eq!(r.status, pb::ResultStatus::Associated as i32);
        check_identities(r, &[3, 3, 3]);
    }
    assert_eq!(
        scene_version(&http, &server).await.as_deref(),
        Some(new.as_str())
    );
    // The same file again: nothing to swap (the gRPC admin call says the same).
    assert_eq!(reload(&http, &server).await["outcome"], "unchanged");
    let r = server
        .grpc()
        .await
        .reload(pb::ReloadRequest {})
        .await
        .unwrap()
        .into_inner();
    assert_eq!(r.reloads.len(), 1);
    assert_eq!(
        (r.reloads[0].outcome.as_str(), r.reloads[0].version.as_str()),
        ("unchanged", new.as_str())
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupt_and_foreign_models_are_refused_and_the_old_one_keeps_serving() {
    let server = start(|_| {}).await;
    let http = reqwest::Client::new();
    let old = scene_version(&http, &server).await.unwrap();
    let mut results = server.subscribe("lab").await;

    // A torn, corrupt file.
    let bytes = std::fs::read(server.dir.path().join("lab.onnx")).unwrap();
    std::fs::write(
        server.dir.path().join("lab.onnx"),
        &bytes[..bytes.len() / 3],
    )
    .unwrap();
    let o = reload(&http, &server).await;
    assert_eq!(o["outcome"], "refused", "{o}");
    assert!(!o["error"].as_str().unwrap().is_empty());
    assert_eq!(o["version"].as_str(), Some(old.as_str()));

    // A valid model for other cameras.
    let other = vec![
        CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: "left".into(),
            width: 640,
            height: 480,
        },
        CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: "right".into(),
            width: 640,
            height: 480,
        },
    ];
    replace_model(server.dir.path(), 13, other);
    let o = reload(&http, &server).await;
    assert_eq!(o["outcome"], "refused", "{o}");
    assert!(o["error"].as_str().unwrap().contains("cameras"), "{o}");

    // The old model still associates, and says so.
    push_frame(&server, 1).await;
    let r = guard("result", results.next()).await.unwrap().unwrap();
    assert_eq!(r.status, pb::ResultStatus::Associated as i32);
    assert_eq!(r.model_version, old);
    check_identities(&r, &[3, 3, 3]);
    assert_eq!(scene_version(&http, &server).await.unwrap(), old);
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_model_reloads_total{scene=\"lab\",outcome=\"refused\"}"
        ),
        2.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_declared_scene_publishes_no_model_results_until_its_model_arrives() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lab.onnx");
    let spec = format!(
        "lab={}",
        cameras()
            .iter()
            .map(|c| format!("{}:{}x{}", c.name, c.width, c.height))
            .collect::<Vec<_>>()
            .join(",")
    );
    let server = start_with(
        vec![ModelSpec::parse(&format!("lab={}", path.display())).unwrap()],
        |c| c.scenes = vec![SceneDecl::parse(&spec).unwrap()],
    )
    .await;
    let http = reqwest::Client::new();
    assert_eq!(scene_version(&http, &server).await, None);
    let mut results = server.subscribe("lab").await;

    push_frame(&server, 1).await;
    let r = guard("no-model result", results.next())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(r.frame_id, 1);
    assert!(
        r.complete && r.identities.is_empty() && r.error.is_empty(),
        "{r:?}"
    );
    assert_eq!(r.status, pb::ResultStatus::NoModel as i32);
    assert_eq!(r.model_version, "");
    // A unary call cannot be answered without a model: a clear status, not a crash.
    let err = server
        .grpc()
        .await
        .associate(pb::AssociateRequest {
            scene: "lab".into(),
            frame_id: 2,
            time: None,
            views: vec![],
        })
        .await
        .unwrap_err();
    assert_eq!(err.code(), tonic::Code::FailedPrecondition, "{err:?}");
    assert!(err.message().contains("no model"), "{err:?}");
    // Still nothing to load.
    assert_eq!(reload(&http, &server).await["outcome"], "missing");

    // The model appears: the next frames are associated by it.
    let _ = export_model(dir.path(), "lab");
    let o = reload(&http, &server).await;
    assert_eq!(o["outcome"], "swapped", "{o}");
    push_frame(&server, 2).await;
    let r = guard("associated result", results.next())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(r.frame_id, 2);
    assert_eq!(r.status, pb::ResultStatus::Associated as i32);
    assert_eq!(Some(r.model_version.as_str()), o["version"].as_str());
    assert!(!r.identities.is_empty());
    let m = server.metrics().await;
    assert_eq!(
        metric(&m, "crossview_frames_unassociated_total{scene=\"lab\"}"),
        1.0
    );
    server.shutdown().await.unwrap();
}

//! The `crossview serve` binary: loads a model named on the command line, serves on an
//! ephemeral port, and on SIGTERM flushes its pending frame to subscribers and exits cleanly.

use crossview_testing::*;
use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_serves_and_flushes_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let model = export_model(dir.path(), "lab");
    let model_arg = format!("street={}", model.display());
    let (mut child, base) = spawn_serve(
        env!("CARGO_BIN_EXE_crossview"),
        &["--sync-timeout", "600s", "--model", &model_arg],
    )
    .await;

    let http = reqwest::Client::new();
    let scenes: serde_json::Value = http
        .get(format!("{base}/v1/scenes"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(scenes["scenes"][0]["name"], "street");
    let mut events = http
        .get(format!("{base}/v1/scenes/street/events"))
        .send()
        .await
        .unwrap()
        .bytes_stream();
    let r = http
        .post(format!("{base}/v1/scenes/street/batches"))
        .json(&batch_json(1, 3, 2))
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), 202);

    signal(&child, "TERM");

    let mut text = String::new();
    guard("flushed frame over SSE", async {
        while let Some(Ok(chunk)) = events.next().await {
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    })
    .await;
    let data = text
        .lines()
        .find_map(|l| l.strip_prefix("data: "))
        .unwrap_or_else(|| panic!("no frame event in {text:?}"));
    let v: serde_json::Value = serde_json::from_str(data).unwrap();
    assert_eq!(v["frame_id"], 3);
    assert_eq!(v["complete"], false);
    assert_eq!(v["missing_cameras"], serde_json::json!(["c0", "c2"]));

    let status = guard(
        "process exit",
        tokio::task::spawn_blocking(move || child.0.wait()),
    )
    .await
    .unwrap()
    .unwrap();
    assert!(status.success(), "{status:?}");
}

/// `--memory` (and `CROSSVIEW_MEMORY`) outside `[0, 1)` stops `serve` and `eval` with a message
/// naming it, before anything is served or read.
#[test]
fn a_memory_share_outside_its_range_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = crossview_testing::export_model(dir.path(), "lab");
    let model = model.to_str().unwrap();
    let serve = |extra: &[&'static str]| {
        let mut a = vec!["serve", "--model", model, "--listen", "127.0.0.1:0"];
        a.extend_from_slice(extra);
        a
    };
    for (args, env) in [
        (serve(&["--memory", "1"]), None),
        (serve(&[]), Some("NaN")),
        (serve(&["--memory=-0.5"]), None),
        (
            vec!["eval", "--model", model, "--data", model, "--memory", "2"],
            None,
        ),
    ] {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_crossview"));
        cmd.args(&args).env_remove("CROSSVIEW_MEMORY");
        if let Some(v) = env {
            cmd.env("CROSSVIEW_MEMORY", v);
        }
        let out = cmd.output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} {env:?} started");
        assert!(err.contains("memory"), "{args:?} {env:?}: {err}");
    }
}

/// Healing settings that cannot heal stop `serve` with a message naming them: `--auto-retrain`
/// without `--record` (nothing to learn from), a zero epoch count, a tolerance outside [0, 1].
#[test]
fn healing_without_a_recording_or_with_bad_bounds_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let model = crossview_testing::export_model(dir.path(), "lab");
    let (model, rec) = (model.to_str().unwrap(), dir.path().join("rec"));
    let rec = rec.to_str().unwrap();
    for (extra, says) in [
        (vec!["--auto-retrain"], "--record"),
        (
            vec!["--auto-retrain", "--record", rec, "--retrain-epochs", "0"],
            "--retrain-epochs",
        ),
        (
            vec![
                "--auto-retrain",
                "--record",
                rec,
                "--retrain-tolerance",
                "2",
            ],
            "--retrain-tolerance",
        ),
        (
            vec!["--auto-retrain", "--record", rec, "--retrain-after", "0s"],
            "--retrain-after",
        ),
    ] {
        let mut args = vec!["serve", "--model", model, "--listen", "127.0.0.1:0"];
        args.extend_from_slice(&extra);
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_crossview"))
            .args(&args)
            .env_remove("CROSSVIEW_AUTO_RETRAIN")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra:?} started");
        assert!(err.contains(says), "{extra:?}: {err}");
    }
}

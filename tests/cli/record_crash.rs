//! `crossview serve --record DIR` killed with SIGKILL: the recording it leaves is readable by
//! `crossview eval --data DIR` and `crossview train --data DIR` (a torn last line dropped and
//! counted), and the next start cuts the torn tail off and carries on in a new file.

use std::path::{Path, PathBuf};
use std::process::Command;

use crossview_data::read_recordings;
use crossview_testing::*;

async fn serve(args: &[&str]) -> (ChildGuard, String) {
    spawn_serve(env!("CARGO_BIN_EXE_crossview"), args).await
}

/// The recording files under `dir`, in name order.
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_recording_server_leaves_data_eval_and_train_read() {
    let bin = env!("CARGO_BIN_EXE_crossview");
    let model = repo_root().join("models/demo.onnx");
    let model_arg = format!("demo={}", model.display());
    let tmp = tempfile::tempdir().unwrap();
    let sim = tmp.path().join("sim.jsonl");
    let record = tmp.path().join("rec");
    run_crossview(
        bin,
        &[
            "simulate",
            "--preset",
            "square4",
            "--frames",
            "60",
            "--seed",
            "3",
            "--clean",
            "--out",
            sim.to_str().unwrap(),
        ],
        &[],
    );
    let text = std::fs::read_to_string(&sim).unwrap();
    let batches = text.lines().count() - 1;

    let (mut child, base) = serve(&[
        "--model",
        &model_arg,
        "--record",
        record.to_str().unwrap(),
        "--record-max-file-bytes",
        "20000",
    ])
    .await;
    let http = reqwest::Client::new();
    let r: serde_json::Value = http
        .post(format!("{base}/v1/scenes/demo/batches"))
        .header("content-type", "application/x-ndjson")
        .body(text.clone())
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        r["accepted"].as_u64(),
        Some(batches as u64),
        "{}",
        r["results"][0]
    );
    // Every accepted batch has reached the files (the kernel) before the kill.
    wait_for_metric(
        &base,
        "crossview_record_batches_total{scene=\"demo\"}",
        batches as f64,
    )
    .await;
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();

    let scene_dir = record.join("demo");
    let on_disk = files(&scene_dir);
    assert!(on_disk.len() >= 2, "rotated: {on_disk:?}");
    // Whole lines reach the kernel in one write each, so a kill rarely tears one; a kill in
    // the middle of a write leaves what this appends: half a line, no newline.
    let newest = on_disk.last().unwrap();
    let whole = std::fs::read(newest).unwrap();
    let mut torn = whole.clone();
    torn.extend_from_slice(br#"{"camera": "cam0", "frame_id": 61, "detections": [{"bbox": [1"#);
    std::fs::write(newest, &torn).unwrap();

    // eval and train read the directory as one recording, the torn line dropped and counted.
    let out = Command::new(bin)
        .args(["eval", "--workers", "1", "--model"])
        .arg(&model)
        .arg("--data")
        .arg(&record)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "eval failed: {stderr}");
    assert!(stderr.contains("dropped 1 torn last line"), "{stderr}");
    let table = String::from_utf8_lossy(&out.stdout);
    assert!(
        table.contains("pairwise") && table.contains("ACC"),
        "{table}"
    );
    let m = tmp.path().join("m.onnx");
    let stdout = run_crossview(
        bin,
        &[
            "train",
            "--quiet",
            "--epochs",
            "2",
            "--self-train-epochs",
            "0",
            "--triplets-per-step",
            "4",
            "--width",
            "24",
            "--fourier-features",
            "8",
            "--camera-dim",
            "8",
            "--max-edges",
            "4",
            "--data",
            record.to_str().unwrap(),
            "--out",
            m.to_str().unwrap(),
        ],
        &[],
    );
    assert!(stdout.contains("1 torn last line(s) dropped"), "{stdout}");
    assert!(m.is_file());

    // The next start cuts the torn tail off and records into a new file.
    let (mut child, base) =
        serve(&["--model", &model_arg, "--record", record.to_str().unwrap()]).await;
    assert_eq!(
        std::fs::read(newest).unwrap(),
        whole,
        "torn tail cut at start-up"
    );
    let shifted: Vec<String> = text
        .lines()
        .skip(1)
        .take(4)
        .map(|l| {
            let mut v: serde_json::Value = serde_json::from_str(l).unwrap();
            v["frame_id"] = (v["frame_id"].as_u64().unwrap() + 1000).into();
            v.to_string()
        })
        .collect();
    let r: serde_json::Value = http
        .post(format!("{base}/v1/scenes/demo/batches"))
        .header("content-type", "application/x-ndjson")
        .body(shifted.join("\n"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(r["accepted"].as_u64(), Some(4), "{r}");
    signal(&child, "TERM");
    assert!(child.wait().unwrap().success(), "graceful exit");
    let after = files(&scene_dir);
    assert_eq!(after.len(), on_disk.len() + 1, "{after:?}");
    let (rec, stats) = read_recordings(&[&record], true).unwrap();
    assert_eq!(stats.torn_lines, 0);
    assert_eq!(rec.batches().count(), batches + 4);
}

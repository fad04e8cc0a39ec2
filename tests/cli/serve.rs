//! The `crossview serve` binary: loads a model named on the command line, serves on an
//! ephemeral port, and on SIGTERM flushes its pending frame to subscribers and exits cleanly.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};

use crossview_testing::*;
use futures::StreamExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn binary_serves_and_flushes_on_sigterm() {
    let dir = tempfile::tempdir().unwrap();
    let model = export_model(dir.path(), "lab");
    let mut child = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["serve", "--listen", "127.0.0.1:0", "--sync-timeout", "600s"])
        .arg("--model")
        .arg(format!("street={}", model.display()))
        .env("RUST_LOG", "info")
        .stderr(Stdio::piped())
        .spawn()
        .expect("start crossview serve");
    let stderr = child.stderr.take().unwrap();
    // The address is in the "serving" log line; keep draining the log afterwards.
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("server: {line}");
            if let Some(i) = line.find("127.0.0.1:")
                && line.contains("serving")
                && let Some(tx) = tx.take()
            {
                let addr: String = line[i..]
                    .chars()
                    .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == ':')
                    .collect();
                let _ = tx.send(addr);
            }
        }
    });
    let addr = guard("server start", rx).await.expect("serving log line");
    let base = format!("http://{addr}");

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

    let kill = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());

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
        tokio::task::spawn_blocking(move || child.wait()),
    )
    .await
    .unwrap()
    .unwrap();
    assert!(status.success(), "{status:?}");
}

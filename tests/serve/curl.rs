//! The HTTP JSON API driven by curl (a client nobody here wrote): scenes, unary association,
//! batch pushes, the Server-Sent-Events stream, health and metrics.

use std::process::{Command, Stdio};
use std::time::Duration;

use crossview_testing::*;

fn curl(args: &[&str]) -> (u16, String) {
    let out = Command::new("curl")
        .args(["-sS", "--max-time", "30", "-w", "\n%{http_code}"])
        .args(args)
        .output()
        .expect("curl must be installed to run this test");
    assert!(
        out.status.success(),
        "curl failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    let (body, code) = text.rsplit_once('\n').unwrap();
    (code.parse().unwrap(), body.to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn curl_drives_the_http_api() {
    let server = start(|c| {
        c.sync_timeout = Duration::from_secs(120);
        c.api_keys = vec!["tok".into()];
    })
    .await;
    let url = |p: &str| server.url(p);
    let auth = "authorization: Bearer tok";

    let (code, body) = tokio::task::block_in_place(|| curl(&[&url("/healthz")]));
    assert_eq!((code, body.as_str()), (200, "ok"));

    let (code, body) = tokio::task::block_in_place(|| curl(&["-H", auth, &url("/v1/scenes")]));
    assert_eq!(code, 200, "{body}");
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["scenes"][0]["name"], "lab");
    assert_eq!(v["scenes"][0]["cameras"].as_array().unwrap().len(), 3);

    let (code, _) = tokio::task::block_in_place(|| curl(&[&url("/v1/scenes")]));
    assert_eq!(code, 401);

    let frame = r#"{"frame_id": 1, "views": [
        {"camera": "c0", "detections": [{"bbox": [100, 200, 160, 380]}, {"bbox": [400, 220, 450, 390], "score": 0.8}]},
        {"camera": "c1", "detections": [{"bbox": [50, 100, 90, 260]}]},
        {"camera": "c2", "detections": []}]}"#;
    let (code, body) = tokio::task::block_in_place(|| {
        curl(&[
            "-H",
            auth,
            "-H",
            "content-type: application/json",
            "-d",
            frame,
            &url("/v1/scenes/lab/associate"),
        ])
    });
    assert_eq!(code, 200, "{body}");
    let v: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(v["complete"], true);
    let members: usize = v["identities"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["members"].as_array().unwrap().len())
        .sum();
    assert_eq!(members, 3);

    // SSE with curl -N in the background, then push a complete frame with curl.
    let mut sse = Command::new("curl")
        .args(["-sS", "-N", "--max-time", "60", "-H", auth])
        .arg(url("/v1/scenes/lab/events"))
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = sse.stdout.take().unwrap();
    // Wait until the subscription exists (SSE keep-alives or headers are not visible to curl's
    // body output, so poll the server's request counter instead).
    guard("SSE subscription", async {
        loop {
            let m = server.metrics().await;
            if m.contains("/v1/scenes/{scene}/events") {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    for c in 0..3 {
        let line = batch_json(c, 5, 2).to_string();
        let (code, body) = tokio::task::block_in_place(|| {
            curl(&[
                "-H",
                auth,
                "-H",
                "content-type: application/json",
                "-d",
                &line,
                &url("/v1/scenes/lab/batches"),
            ])
        });
        assert_eq!(code, 202, "{body}");
    }
    let text = guard(
        "SSE event via curl",
        tokio::task::spawn_blocking(move || {
            use std::io::Read;
            let mut buf = Vec::new();
            let mut chunk = [0u8; 4096];
            loop {
                let n = stdout.read(&mut chunk).unwrap();
                if n == 0 {
                    break;
                }
                buf.extend_from_slice(&chunk[..n]);
                let s = String::from_utf8_lossy(&buf);
                if s.contains("event: frame") && s.contains("\n\n") {
                    break;
                }
            }
            String::from_utf8_lossy(&buf).to_string()
        }),
    )
    .await
    .unwrap();
    let _ = sse.kill();
    let _ = sse.wait();
    let data = text
        .lines()
        .find_map(|l| l.strip_prefix("data: "))
        .expect("data line");
    let v: serde_json::Value = serde_json::from_str(data).unwrap();
    assert_eq!(v["frame_id"], 5);
    assert_eq!(v["complete"], true);

    let (code, body) = tokio::task::block_in_place(|| curl(&[&url("/metrics")]));
    assert_eq!(code, 200);
    assert!(
        body.contains("crossview_batches_total{scene=\"lab\"} 3"),
        "{body}"
    );
    server.shutdown().await.unwrap();
}

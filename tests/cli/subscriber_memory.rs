//! Subscribers that never read cannot exhaust the server's memory: HTTP/2 clients with huge
//! flow-control windows open hundreds of `events?boxes=true` streams and stop reading their
//! sockets while frames flow; the server's resident memory grows by no more than its
//! subscriber budget (`--subscriber-memory`), and it keeps answering.

use std::time::Duration;

use crossview_testing::h2client::NeverRead;
use crossview_testing::*;

/// Resident memory of process `pid`, in bytes.
fn rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .unwrap()
        * 1024
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn never_read_http2_streams_stay_within_the_subscriber_budget() {
    const BUDGET: u64 = 32 << 20;
    let dir = tempfile::tempdir().unwrap();
    let model = export_model(dir.path(), "lab");
    let budget = BUDGET.to_string();
    let (child, base) = spawn_serve(
        env!("CARGO_BIN_EXE_crossview"),
        &[
            "--model",
            model.to_str().unwrap(),
            "--subscriber-memory",
            &budget,
            // Frames leave complete however busy the test machine is.
            "--sync-timeout",
            "10s",
        ],
    )
    .await;
    let addr: std::net::SocketAddr = base.trim_start_matches("http://").parse().unwrap();
    let http = reqwest::Client::new();
    let push = |f: u64| {
        let http = http.clone();
        let base = base.clone();
        async move {
            for c in 0..3 {
                let r = http
                    .post(format!("{base}/v1/scenes/lab/batches"))
                    .json(&batch_json(c, f, 40))
                    .send()
                    .await
                    .unwrap();
                let status = r.status();
                assert_eq!(
                    status,
                    202,
                    "frame {f} camera {c}: {}",
                    r.text().await.unwrap()
                );
            }
        }
    };
    // Warm up (model, tracker, allocator), then take the baseline.
    for f in 1..=20 {
        push(f).await;
    }
    wait_for_metric(
        &base,
        "crossview_frames_total{scene=\"lab\",state=\"complete\"}",
        20.0,
    )
    .await;
    let before = rss(child.id());

    // 8 connections × 64 streams, 1 GiB windows, sockets never read.
    let mut flood = Vec::new();
    for _ in 0..8 {
        flood.push(
            NeverRead::open(
                addr,
                "/v1/scenes/lab/events?boxes=true",
                64,
                1 << 30,
                None,
                true,
            )
            .await
            .unwrap(),
        );
    }
    let accepted: usize = flood.iter().map(NeverRead::accepted).sum();
    assert!(
        accepted > 0 && accepted <= (BUDGET as usize) / (160 << 10),
        "{accepted} admitted"
    );
    for f in 21..=120 {
        push(f).await;
    }
    wait_for_metric(
        &base,
        "crossview_frames_total{scene=\"lab\",state=\"complete\"}",
        120.0,
    )
    .await;
    // Let the transport take what it will.
    tokio::time::sleep(Duration::from_millis(500)).await;
    let after = rss(child.id());
    let grew = after.saturating_sub(before);
    eprintln!(
        "{accepted} never-read streams admitted of 512; server RSS {} -> {} MiB",
        before >> 20,
        after >> 20
    );
    assert!(
        grew <= BUDGET + (16 << 20),
        "server RSS grew by {} MiB with {accepted} never-read streams (budget {} MiB)",
        grew >> 20,
        BUDGET >> 20
    );
    let r = http.get(format!("{base}/healthz")).send().await.unwrap();
    assert_eq!(r.status(), 200);
    drop(flood);
}

//! Subscribers that never read, against a running `crossview serve`: HTTP/2 connections with
//! 1 GiB flow-control windows open `events?boxes=true` streams and stop reading their sockets,
//! then HTTP/1.1 SSE subscriptions are attempted on an idle scene, while frames are pushed and
//! `/healthz` is probed on a new connection every 20 ms. Prints what was admitted and refused
//! and the probe's latency percentiles; the server's peak memory is read from outside
//! (`bench/subscriber_flood.sh` reads `/proc/PID/status`).
//!
//! `cargo run --release -p crossview-bench --bin subscriber_flood -- --addr 127.0.0.1:PORT`
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;
use crossview_testing::h2client::NeverRead;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[derive(Parser)]
struct Args {
    /// The server.
    #[arg(long)]
    addr: SocketAddr,
    /// Scene whose events the never-read HTTP/2 streams subscribe to (frames are pushed to it).
    #[arg(long, default_value = "lab")]
    scene: String,
    /// An idle scene (nothing pushed) for the HTTP/1.1 SSE subscriptions.
    #[arg(long, default_value = "idle")]
    idle_scene: String,
    /// Never-read HTTP/2 event streams to open (100 per connection).
    #[arg(long, default_value_t = 6000)]
    h2_streams: usize,
    /// HTTP/1.1 SSE subscriptions to attempt on the idle scene, each on its own connection.
    #[arg(long, default_value_t = 10_000)]
    sse_attempts: usize,
    /// Frames pushed (all cameras of the scene), 10 a second.
    #[arg(long, default_value_t = 200)]
    frames: u64,
    /// Boxes per camera batch.
    #[arg(long, default_value_t = 20)]
    boxes: usize,
}

/// The cameras (name, width, height) of `scene`.
async fn cameras(
    http: &reqwest::Client,
    base: &str,
    scene: &str,
) -> anyhow::Result<Vec<(String, f64, f64)>> {
    let v: serde_json::Value = http
        .get(format!("{base}/v1/scenes/{scene}"))
        .send()
        .await?
        .error_for_status()?
        .json()
        .await?;
    let cams = v["cameras"].as_array().context("cameras")?;
    Ok(cams
        .iter()
        .map(|c| {
            (
                c["name"].as_str().unwrap_or_default().to_string(),
                c["width"].as_f64().unwrap_or(640.0),
                c["height"].as_f64().unwrap_or(480.0),
            )
        })
        .collect())
}

/// Probes `/healthz` on a new connection every 20 ms until `stop`; latencies (None: failed).
async fn probe(base: String, stop: Arc<AtomicBool>) -> Vec<Option<Duration>> {
    let mut out = Vec::new();
    while !stop.load(Ordering::Acquire) {
        let http = reqwest::Client::builder()
            .timeout(Duration::from_secs(5))
            .build()
            .expect("client");
        let t = Instant::now();
        let ok = http
            .get(format!("{base}/healthz"))
            .send()
            .await
            .is_ok_and(|r| r.status().is_success());
        out.push(ok.then(|| t.elapsed()));
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    out
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

/// One HTTP/1.1 SSE subscription on its own connection: the status (0: refused or closed).
async fn sse(addr: SocketAddr, scene: &str) -> (u16, Option<tokio::net::TcpStream>) {
    let Ok(mut s) = tokio::net::TcpStream::connect(addr).await else {
        return (0, None);
    };
    let req = format!("GET /v1/scenes/{scene}/events HTTP/1.1\r\nHost: x\r\n\r\n");
    if s.write_all(req.as_bytes()).await.is_err() {
        return (0, None);
    }
    let mut head = [0u8; 12];
    let read = tokio::time::timeout(Duration::from_secs(5), s.read_exact(&mut head)).await;
    let code = match read {
        Ok(Ok(_)) => std::str::from_utf8(&head[9..12])
            .ok()
            .and_then(|c| c.parse().ok())
            .unwrap_or(0),
        _ => 0,
    };
    (code, Some(s))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let base = format!("http://{}", args.addr);
    let http = reqwest::Client::new();
    let cams = cameras(&http, &base, &args.scene).await?;
    let stop = Arc::new(AtomicBool::new(false));
    let prober = tokio::spawn(probe(base.clone(), stop.clone()));

    let t = Instant::now();
    let path = format!("/v1/scenes/{}/events?boxes=true", args.scene);
    let mut flood = Vec::new();
    let mut left = args.h2_streams;
    while left > 0 {
        let n = left.min(100);
        flood.push(NeverRead::open(args.addr, &path, n, 1 << 30, None, true).await?);
        left -= n;
    }
    let admitted: usize = flood.iter().map(NeverRead::accepted).sum();
    println!(
        "h2 never-read streams: {} asked, {admitted} admitted, {} refused ({:.1} s)",
        args.h2_streams,
        args.h2_streams - admitted,
        t.elapsed().as_secs_f64()
    );

    let pusher = {
        let (http, base, scene) = (http.clone(), base.clone(), args.scene.clone());
        let (frames, boxes) = (args.frames, args.boxes);
        tokio::spawn(async move {
            let (mut ok, mut failed) = (0u64, 0u64);
            let mut why = std::collections::BTreeMap::<String, u64>::new();
            let mut tick = tokio::time::interval(Duration::from_millis(100));
            for f in 1..=frames {
                tick.tick().await;
                for (name, w, h) in &cams {
                    let dets: Vec<_> = (0..boxes)
                        .map(|k| {
                            let x = (k as f64 * 37.0 + f as f64) % (w - 60.0);
                            let y = (k as f64 * 53.0) % (h - 160.0);
                            serde_json::json!({"bbox": [x, y, x + 50.0, y + 150.0], "score": 0.9})
                        })
                        .collect();
                    let body =
                        serde_json::json!({"camera": name, "frame_id": f, "detections": dets});
                    match http
                        .post(format!("{base}/v1/scenes/{scene}/batches"))
                        .json(&body)
                        .send()
                        .await
                    {
                        Ok(r) if r.status() == 202 => ok += 1,
                        Ok(r) => {
                            failed += 1;
                            *why.entry(r.status().to_string()).or_default() += 1;
                        }
                        Err(e) => {
                            failed += 1;
                            let kind = if e.is_connect() {
                                "connect"
                            } else if e.is_timeout() {
                                "timeout"
                            } else {
                                "connection closed"
                            };
                            *why.entry(kind.to_string()).or_default() += 1;
                        }
                    }
                }
            }
            (ok, failed, why)
        })
    };

    let t = Instant::now();
    let (mut sse_ok, mut sse_refused) = (0usize, 0usize);
    let mut held = Vec::new();
    for _ in 0..args.sse_attempts {
        let (code, s) = sse(args.addr, &args.idle_scene).await;
        if code == 200 {
            sse_ok += 1;
        } else {
            sse_refused += 1;
        }
        held.extend(s);
    }
    println!(
        "HTTP/1.1 SSE on the idle scene: {} attempted, {sse_ok} admitted, {sse_refused} refused or closed ({:.1} s)",
        args.sse_attempts,
        t.elapsed().as_secs_f64()
    );
    let (ok, failed, why) = pusher.await?;
    println!("pushes: {ok} accepted, {failed} failed {why:?}");
    stop.store(true, Ordering::Release);
    let probes = prober.await?;
    let mut lat: Vec<Duration> = probes.iter().flatten().copied().collect();
    lat.sort();
    println!(
        "/healthz on a new connection every 20 ms: {} probes, {} failed, p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms",
        probes.len(),
        probes.iter().filter(|p| p.is_none()).count(),
        percentile(&lat, 0.5),
        percentile(&lat, 0.99),
        percentile(&lat, 1.0)
    );
    drop(held);
    drop(flood);
    Ok(())
}

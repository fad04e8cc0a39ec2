//! Result subscribers live within one budget: subscribers that never read cannot exhaust the
//! server's memory (the subscriber furthest behind makes room, or newcomers are refused), one
//! connection cannot hold more than its share, and subscriptions can never take the connection
//! slots that health checks, metrics scrapes and pushes need.

use std::time::Duration;

use crossview_api::pb;
use crossview_testing::h2client::NeverRead;
use crossview_testing::*;
use futures::StreamExt;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// What one subscriber is charged (the server's `SUBSCRIBER_CHARGE`, 160 KiB).
const CHARGE: usize = 160 << 10;

/// `GET /healthz` on a new connection, as a load balancer's probe makes it: the status, or 0
/// when the connection was refused.
async fn healthz(server: &TestServer) -> u16 {
    match reqwest::Client::new()
        .get(server.url("/healthz"))
        .timeout(Duration::from_secs(10))
        .send()
        .await
    {
        Ok(r) => r.status().as_u16(),
        Err(_) => 0,
    }
}

/// Opens an HTTP/1.1 SSE subscription on its own connection; the status code (0: closed).
async fn sse_http1(server: &TestServer) -> (u16, TcpStream) {
    let mut s = TcpStream::connect(server.addr).await.unwrap();
    let req = "GET /v1/scenes/lab/events HTTP/1.1\r\nHost: x\r\n\r\n";
    if s.write_all(req.as_bytes()).await.is_err() {
        return (0, s);
    }
    let mut head = [0u8; 12];
    let got = guard("response head", async {
        let mut n = 0;
        while n < head.len() {
            match s.read(&mut head[n..]).await {
                Ok(0) | Err(_) => break,
                Ok(k) => n += k,
            }
        }
        n
    })
    .await;
    let code = if got == 12 {
        std::str::from_utf8(&head[9..12])
            .ok()
            .and_then(|c| c.parse().ok())
            .unwrap_or(0)
    } else {
        0
    };
    (code, s)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn idle_subscribers_never_lock_out_health_metrics_and_pushes() {
    // 32 connections at most: subscriptions may hold 24 of them, the rest stay for the others.
    let server = start(|c| c.connections.max_connections = 32).await;
    let http = reqwest::Client::new();
    let mut held = Vec::new();
    let (mut accepted, mut refused) = (0, 0);
    for i in 0..120 {
        let (code, s) = sse_http1(&server).await;
        match code {
            200 => accepted += 1,
            _ => refused += 1,
        }
        held.push(s);
        if i % 10 == 9 {
            assert_eq!(
                healthz(&server).await,
                200,
                "/healthz after {} subscriptions",
                i + 1
            );
            let m = http.get(server.url("/metrics")).send().await;
            assert!(
                m.is_ok_and(|r| r.status() == 200),
                "/metrics after {}",
                i + 1
            );
        }
    }
    assert!(
        (1..=24).contains(&accepted),
        "{accepted} subscriptions held connections (at most 24 of 32)"
    );
    assert!(refused >= 96, "{refused} refused");
    // A push still lands, and its frame reaches the subscribers that hold a slot.
    server.push_http(1..=1, 2).await;
    let text = server.metrics().await;
    assert!(metric(&text, "crossview_batches_total{scene=\"lab\"}") >= 3.0);
    drop(held);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_the_memory_budget_the_subscriber_furthest_behind_makes_room() {
    // Room for 8 subscribers.
    let server = start(|c| c.connections.subscriber_memory = 8 * CHARGE).await;
    let http = reqwest::Client::new();
    // One HTTP/2 client with a zero flow-control window: the server can send it nothing, so
    // its streams fall behind with every frame (the transport never takes their results).
    let stuck = NeverRead::open(
        server.addr,
        "/v1/scenes/lab/events?boxes=true",
        12,
        0,
        None,
        false,
    )
    .await
    .unwrap();
    assert_eq!(stuck.accepted(), 8, "statuses {:?}", stuck.statuses);
    assert!(
        stuck.statuses.iter().filter(|s| **s == 429).count() == 4,
        "beyond the budget, with nobody behind, newcomers are refused: {:?}",
        stuck.statuses
    );
    server.push_http(1..=3, 3).await;
    // A reader arrives: once the frames are published, the stuck client's subscriptions are
    // the furthest behind and go (before that nobody is behind and it is refused).
    let reader = guard("a reader is admitted", async {
        loop {
            let r = http
                .get(server.url("/v1/scenes/lab/events"))
                .send()
                .await
                .unwrap();
            if r.status() == 200 {
                break r;
            }
            assert_eq!(r.status(), 429);
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let text = server.metrics().await;
    assert_eq!(
        metric(
            &text,
            "crossview_subscribers_dropped_total{reason=\"budget\"}"
        ),
        8.0
    );
    guard("the stuck client's connection is closed", async {
        while !stuck.closed() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    // The reader gets the next frame. It may have been admitted once frames 1-2 were out,
    // before frame 3's result was published: then frame 3 reaches it first. Nothing older
    // does, and frame 4 follows.
    let mut events = reader.bytes_stream();
    server.push_http(4..=4, 1).await;
    let ids = guard("frame 4 reaches the new reader", async {
        let mut text = String::new();
        loop {
            let ids = sse_ids(&text);
            if ids.iter().any(|&i| i >= 4) {
                break ids;
            }
            match events.next().await {
                Some(Ok(chunk)) => text.push_str(&String::from_utf8_lossy(&chunk)),
                _ => panic!("the stream ended: {text}"),
            }
        }
    })
    .await;
    assert!(
        ids == [4] || ids == [3, 4],
        "frames the reader got: {ids:?}"
    );
}

/// The ids of the complete `frame` events in an SSE text.
fn sse_ids(text: &str) -> Vec<u64> {
    text.split("\n\n")
        .filter(|e| e.contains("event: frame"))
        .filter_map(|e| e.lines().find_map(|l| l.strip_prefix("id: ")))
        .filter_map(|i| i.trim().parse().ok())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_connection_holds_at_most_its_share_of_subscriptions() {
    let server = start(|c| c.connections.max_subscriptions_per_connection = 4).await;
    let mut grpc = server.grpc().await;
    let mut streams = Vec::new();
    for _ in 0..4 {
        let s = grpc
            .subscribe(pb::SubscribeRequest {
                scene: "lab".into(),
            })
            .await
            .expect("within the per-connection share");
        streams.push(s);
    }
    let e = grpc
        .subscribe(pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .expect_err("a fifth subscription on one connection");
    assert_eq!(e.code(), tonic::Code::ResourceExhausted, "{e}");
    // Another connection has its own share.
    let mut other = server.grpc().await;
    other
        .subscribe(pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .expect("a new connection");
    // A subscription that ends frees its place.
    streams.pop();
    guard("the freed place is taken again", async {
        loop {
            let r = grpc
                .subscribe(pb::SubscribeRequest {
                    scene: "lab".into(),
                })
                .await;
            if let Ok(s) = r {
                streams.push(s);
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

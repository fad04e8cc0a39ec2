//! HTTP JSON transport: `POST /v1/scenes/{scene}/batches` per batch (never awaited by the
//! driver; in order per camera) and results from the scene's server-sent event stream.
use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use futures::StreamExt;
use serde::Deserialize;
use tokio::sync::{mpsc, oneshot};

use crate::tracker::{Outcome, Tracker};
use crate::transport::{Outgoing, rejection_kind};

/// One HTTP connection (HTTP/2 multiplexed unless `http1`). Each camera of each scene gets
/// its own sender queue: its batches are POSTed one after another, like a real camera client,
/// because the server treats a batch for a frame older than one it already emitted as late,
/// and concurrent requests of one camera could overtake each other. Queued batches count as
/// in flight (their permits are held), so open-loop sending still never waits.
pub struct HttpSlot {
    client: reqwest::Client,
    base: Arc<str>,
    tracker: Arc<Tracker>,
    queues: Mutex<HashMap<(usize, String), mpsc::UnboundedSender<Outgoing>>>,
}

/// A client for `base` (e.g. `http://127.0.0.1:8080`).
pub fn client(http1: bool, timeout: Duration) -> anyhow::Result<reqwest::Client> {
    let b = reqwest::Client::builder()
        .timeout(timeout)
        .connect_timeout(Duration::from_secs(5))
        .pool_max_idle_per_host(if http1 { 64 } else { 1 });
    let b = if http1 {
        b.http1_only()
    } else {
        b.http2_prior_knowledge()
    };
    b.build().context("cannot build HTTP client")
}

impl HttpSlot {
    /// A fresh connection to `base`.
    pub fn new(
        base: &str,
        http1: bool,
        timeout: Duration,
        tracker: Arc<Tracker>,
    ) -> anyhow::Result<Self> {
        Ok(HttpSlot {
            client: client(http1, timeout)?,
            base: base.trim_end_matches('/').into(),
            tracker,
            queues: Mutex::default(),
        })
    }

    /// Queues one batch on its camera's sender; the answer is recorded in the tracker.
    pub fn send(&self, out: Outgoing) {
        let key = (out.key.0, out.batch.camera.clone());
        let mut queues = self.queues.lock().unwrap_or_else(|e| e.into_inner());
        let tx = queues.entry(key).or_insert_with(|| {
            let (tx, rx) = mpsc::unbounded_channel();
            tokio::spawn(camera_sender(
                self.client.clone(),
                self.base.clone(),
                self.tracker.clone(),
                rx,
            ));
            tx
        });
        if let Err(e) = tx.send(out) {
            self.tracker.failed(e.0.key, "sender_gone");
        }
    }
}

/// POSTs one camera's batches in order, each after the previous one's answer.
async fn camera_sender(
    client: reqwest::Client,
    base: Arc<str>,
    tracker: Arc<Tracker>,
    mut rx: mpsc::UnboundedReceiver<Outgoing>,
) {
    while let Some(out) = rx.recv().await {
        let _permit = out.permit;
        let body = match serde_json::to_vec(&out.batch) {
            Ok(b) => b,
            Err(_) => {
                tracker.failed(out.key, "encode");
                continue;
            }
        };
        let url = format!("{base}/v1/scenes/{}/batches", out.scene);
        let resp = client
            .post(&url)
            .header(reqwest::header::CONTENT_TYPE, "application/json")
            .body(body)
            .send()
            .await;
        match resp {
            Ok(r) if r.status().is_success() => tracker.accepted(out.key),
            Ok(r) => {
                let status = r.status();
                let text = r.text().await.unwrap_or_default();
                let kind = rejection_kind(error_kind(&text).as_deref(), || {
                    format!("http_{}", status.as_u16())
                });
                tracker.rejected(out.key, &kind);
            }
            Err(e) => tracker.failed(out.key, reqwest_kind(&e)),
        }
    }
}

/// The `kind` of a JSON error body: `{"kind": ..}` or `{"error": {"kind": ..}}`.
fn error_kind(body: &str) -> Option<String> {
    let v: serde_json::Value = serde_json::from_str(body).ok()?;
    let k = v
        .get("kind")
        .or_else(|| v.get("error").and_then(|e| e.get("kind")))?;
    k.as_str().map(str::to_string)
}

/// A short kind for a client-side HTTP failure.
pub fn reqwest_kind(e: &reqwest::Error) -> &'static str {
    if e.is_timeout() {
        "timeout"
    } else if e.is_connect() {
        "connect"
    } else if e.is_body() || e.is_decode() {
        "body"
    } else {
        "transport"
    }
}

#[derive(Deserialize)]
struct ResultHead {
    #[serde(default)]
    scene: Option<String>,
    frame_id: u64,
    #[serde(default)]
    complete: bool,
    #[serde(default)]
    status: Option<String>,
}

/// Follows `GET /v1/scenes/{scene}/events` (on its own HTTP/1.1 connection) and records
/// every frame result for scene index `scene_idx`. `ready` fires once the stream is open (response headers received).
pub async fn subscribe(
    base: String,
    scene: Arc<str>,
    scene_idx: usize,
    tracker: Arc<Tracker>,
    ready: oneshot::Sender<anyhow::Result<()>>,
) {
    let client = match reqwest::Client::builder()
        .connect_timeout(Duration::from_secs(5))
        .build()
    {
        Ok(c) => c,
        Err(e) => {
            let _ = ready.send(Err(e.into()));
            return;
        }
    };
    let url = format!("{}/v1/scenes/{}/events", base.trim_end_matches('/'), scene);
    let resp = match client
        .get(&url)
        .header(reqwest::header::ACCEPT, "text/event-stream")
        .send()
        .await
    {
        Ok(r) if r.status().is_success() => r,
        Ok(r) => {
            let _ = ready.send(Err(anyhow::anyhow!("GET {url}: HTTP {}", r.status())));
            return;
        }
        Err(e) => {
            let _ = ready.send(Err(anyhow::anyhow!("GET {url}: {e}")));
            return;
        }
    };
    let _ = ready.send(Ok(()));
    let mut parser = SseParser::default();
    let mut body = resp.bytes_stream();
    while let Some(chunk) = body.next().await {
        let chunk = match chunk {
            Ok(c) => c,
            Err(e) => {
                tracker.error(&format!("subscribe_{}", reqwest_kind(&e)));
                return;
            }
        };
        for (event, data) in parser.feed(&chunk) {
            let now = Instant::now();
            if event.as_deref().is_some_and(|e| e != "frame") {
                tracing::warn!(event = ?event, data = %data, "non-frame event on the result stream");
                tracker.error(&format!("subscribe_event_{}", event.unwrap_or_default()));
                continue;
            }
            match serde_json::from_str::<ResultHead>(&data) {
                Ok(r) if r.scene.as_deref().is_none_or(|s| s == &*scene) => {
                    let shed = r.status.as_deref() == Some("shed");
                    tracker.result((scene_idx, r.frame_id), Outcome::of(r.complete, shed), now)
                }
                Ok(_) => tracker.error("result_wrong_scene"),
                Err(_) => tracker.error("result_unparsable"),
            }
        }
    }
    tracker.error("subscribe_closed");
}

/// Incremental `text/event-stream` parser: yields `(event name, data)` of each complete
/// event (the server names results `frame` and failures `error`).
#[derive(Default)]
pub struct SseParser {
    buf: Vec<u8>,
    event: Option<String>,
    data: Vec<String>,
}

impl SseParser {
    /// Feeds bytes; returns the events completed by them.
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<(Option<String>, String)> {
        self.buf.extend_from_slice(bytes);
        let mut out = Vec::new();
        while let Some(nl) = self.buf.iter().position(|&b| b == b'\n') {
            let line: Vec<u8> = self.buf.drain(..=nl).collect();
            let line = String::from_utf8_lossy(&line);
            let line = line.trim_end_matches(['\n', '\r']);
            if line.is_empty() {
                if !self.data.is_empty() {
                    out.push((self.event.take(), self.data.join("\n")));
                    self.data.clear();
                }
                self.event = None;
            } else if let Some(rest) = line.strip_prefix("data:") {
                self.data
                    .push(rest.strip_prefix(' ').unwrap_or(rest).to_string());
            } else if let Some(rest) = line.strip_prefix("event:") {
                self.event = Some(rest.trim().to_string());
            }
            // `id:`, `retry:` and `:` comments carry nothing we need.
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sse_parser_handles_split_chunks_and_comments() {
        let mut p = SseParser::default();
        assert!(p.feed(b": keep-alive\n\nevent: frame\nda").is_empty());
        let out = p.feed(b"ta: {\"frame_id\": 3}\r\n\r\ndata: a\ndata: b\n\n");
        assert_eq!(
            out,
            vec![
                (Some("frame".to_string()), "{\"frame_id\": 3}".to_string()),
                (None, "a\nb".to_string())
            ]
        );
    }

    #[test]
    fn error_kind_reads_flat_and_nested_bodies() {
        assert_eq!(error_kind(r#"{"kind": "late"}"#).as_deref(), Some("late"));
        assert_eq!(
            error_kind(r#"{"error": {"kind": "duplicate", "message": "x"}}"#).as_deref(),
            Some("duplicate")
        );
        assert_eq!(error_kind("not json"), None);
    }
}

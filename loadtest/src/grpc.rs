//! gRPC transport: one `Push` stream per connection (batches in, one ack per batch out, in
//! order) and one `Subscribe` stream per scene for the results.
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use futures::StreamExt;
use tokio::sync::{OwnedSemaphorePermit, mpsc, oneshot};
use tokio_stream::wrappers::UnboundedReceiverStream;
use tonic::transport::{Channel, Endpoint};

use crate::tracker::{FrameKey, Outcome, Tracker};
use crate::transport::{Outgoing, rejection_kind};
use crossview_api::convert::batch_to_pb;
use crossview_api::pb::{self as proto, association_client::AssociationClient};

type Pending = Arc<Mutex<VecDeque<(FrameKey, u64, OwnedSemaphorePermit)>>>;

/// One gRPC connection carrying one open `Push` stream.
pub struct GrpcSlot {
    tx: mpsc::UnboundedSender<proto::Batch>,
    pending: Pending,
    tracker: Arc<Tracker>,
}

/// Opens a channel to `target` (e.g. `http://127.0.0.1:8080`).
pub async fn channel(target: &str) -> anyhow::Result<Channel> {
    Endpoint::from_shared(target.to_string())
        .with_context(|| format!("bad gRPC target '{target}'"))?
        .connect_timeout(Duration::from_secs(5))
        .tcp_nodelay(true)
        .connect()
        .await
        .with_context(|| format!("cannot connect to {target}"))
}

/// A short kind for a gRPC status, e.g. `grpc_unavailable`.
fn status_kind(s: &tonic::Status) -> String {
    format!("grpc_{:?}", s.code()).to_lowercase()
}

fn lock(p: &Pending) -> std::sync::MutexGuard<'_, VecDeque<(FrameKey, u64, OwnedSemaphorePermit)>> {
    p.lock().unwrap_or_else(|e| e.into_inner())
}

impl GrpcSlot {
    /// Connects and opens the `Push` stream; acknowledgements are recorded in `tracker`.
    pub async fn connect(target: &str, tracker: Arc<Tracker>) -> anyhow::Result<Self> {
        let mut client =
            AssociationClient::new(channel(target).await?).max_decoding_message_size(16 << 20);
        let (tx, rx) = mpsc::unbounded_channel();
        let pending: Pending = Arc::default();
        let (p, t) = (pending.clone(), tracker.clone());
        tokio::spawn(async move {
            match client.push(UnboundedReceiverStream::new(rx)).await {
                Ok(resp) => {
                    let mut acks = resp.into_inner();
                    while let Some(ack) = acks.next().await {
                        match ack {
                            Ok(ack) => Self::on_ack(&p, &t, ack),
                            Err(s) => {
                                t.error(&status_kind(&s));
                                break;
                            }
                        }
                    }
                }
                Err(s) => t.error(&status_kind(&s)),
            }
            // Whatever is still pending will never be answered.
            let unanswered: Vec<FrameKey> = lock(&p).drain(..).map(|(k, _, _)| k).collect();
            for key in unanswered {
                t.failed(key, "no_ack");
            }
        });
        Ok(GrpcSlot {
            tx,
            pending,
            tracker,
        })
    }

    fn on_ack(pending: &Pending, tracker: &Tracker, ack: proto::BatchAck) {
        let Some((key, frame_id, _permit)) = lock(pending).pop_front() else {
            tracker.error("unexpected_ack");
            return;
        };
        if ack.frame_id != frame_id {
            tracker.error("ack_out_of_order");
        }
        if ack.code == 0 {
            tracker.accepted(key);
        } else {
            let kind = rejection_kind(Some(&ack.kind), || format!("grpc_code_{}", ack.code));
            tracker.rejected(key, &kind);
        }
    }

    /// Queues one batch on the stream without waiting.
    pub fn send(&self, out: Outgoing) {
        let msg = batch_to_pb(&out.scene, &out.batch);
        let mut q = lock(&self.pending);
        q.push_back((out.key, out.batch.frame_id, out.permit));
        if self.tx.send(msg).is_err() {
            q.pop_back();
            drop(q);
            self.tracker.failed(out.key, "stream_closed");
        }
    }
}

/// Follows `Subscribe(scene)` and records every frame result for scene index `scene_idx`.
/// `ready` fires once the stream is open.
pub async fn subscribe(
    target: String,
    scene: Arc<str>,
    scene_idx: usize,
    tracker: Arc<Tracker>,
    ready: oneshot::Sender<anyhow::Result<()>>,
) {
    let ch = match channel(&target).await {
        Ok(c) => c,
        Err(e) => {
            let _ = ready.send(Err(e));
            return;
        }
    };
    let mut client = AssociationClient::new(ch).max_decoding_message_size(16 << 20);
    let req = proto::SubscribeRequest {
        scene: scene.to_string(),
    };
    let mut stream = match client.subscribe(req).await {
        Ok(r) => r.into_inner(),
        Err(s) => {
            let _ = ready.send(Err(anyhow::anyhow!("Subscribe({scene}): {s}")));
            return;
        }
    };
    let _ = ready.send(Ok(()));
    while let Some(msg) = stream.next().await {
        match msg {
            Ok(r) if r.scene.is_empty() || r.scene == *scene => {
                let shed = r.status == proto::ResultStatus::Shed as i32;
                let outcome = Outcome::of(r.complete, shed);
                tracker.result((scene_idx, r.frame_id), outcome, Instant::now())
            }
            Ok(_) => tracker.error("result_wrong_scene"),
            Err(s) => {
                tracker.error(&format!("subscribe_{}", status_kind(&s)));
                return;
            }
        }
    }
    tracker.error("subscribe_closed");
}

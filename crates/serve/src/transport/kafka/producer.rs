//! Results out: each owned scene's published frames produced to the output topic, at most
//! [`MAX_UNACKED`] in flight, each acknowledged one closing its input offsets.
use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;
use rdkafka::message::{Header, OwnedHeaders};
use rdkafka::producer::FutureRecord;
use rdkafka::util::Timeout;

use super::Kafka;
use super::codec::encode_result;
use super::offsets::{self, Publish};
use crate::locks::lock;

/// Most results of one scene handed to the producer and not yet acknowledged.
const MAX_UNACKED: usize = 64;

impl Kafka {
    /// Produces every result of `scene` and closes its batches' offsets once acknowledged.
    /// Up to [`MAX_UNACKED`] results are in flight to the broker at once (a catch-up is not
    /// paced by one acknowledgement round trip per frame); acknowledgements are taken in order.
    pub(super) async fn forward(
        self: Arc<Self>,
        scene: String,
        mut results: crate::service::ResultStream,
    ) {
        let mut acks = futures::stream::FuturesOrdered::new();
        let mut open = true;
        loop {
            tokio::select! {
                item = results.next(), if open && acks.len() < MAX_UNACKED => match item {
                    Some(Ok(r)) => {
                        let Some((held, epoch)) = self.to_publish(&scene, r.result.frame_id) else {
                            continue;
                        };
                        let (this, scene) = (&self, &scene);
                        acks.push_back(async move {
                            let ok = this.produce(scene, &r.result, epoch).await;
                            (r.result.frame_id, held, ok)
                        });
                    }
                    Some(Err(e)) => {
                        tracing::warn!(%scene, error = %e, "kafka: result stream lagged");
                        match self.service.subscribe(&scene, None, None) {
                            Ok(s) => results = s,
                            Err(_) => open = false,
                        }
                    }
                    None if self.service.accepting() => {
                        match self.service.subscribe(&scene, None, None) {
                            Ok(s) => results = s,
                            Err(_) => open = false,
                        }
                    }
                    None => open = false,
                },
                Some((frame, held, ok)) = acks.next(), if !acks.is_empty() => {
                    if ok {
                        lock(&self.offsets).produced(&scene, frame, held);
                    }
                }
                else => return,
            }
        }
    }

    /// Whether the result of `frame` of `scene` is produced here (with the records it closes
    /// and the epoch), or dropped: its partition moved since its batches were read.
    fn to_publish(&self, scene: &str, frame: u64) -> Option<(Option<offsets::Held>, u64)> {
        let mut o = lock(&self.offsets);
        match o.take_frame(scene, frame) {
            Publish::Stale => {
                drop(o);
                self.metrics().kafka_revoked_frames(1);
                tracing::debug!(%scene, frame, "kafka: result of a revoked partition dropped");
                None
            }
            Publish::Owned(h) => Some((Some(h), o.epoch)),
            Publish::Unheld => Some((None, o.epoch)),
        }
    }

    /// Produces one result; true once the broker acknowledged it. Retries until then, or
    /// gives up during shutdown (the batches stay uncommitted and are re-read).
    async fn produce(
        &self,
        scene: &str,
        result: &crossview_api::types::FrameResult,
        epoch: u64,
    ) -> bool {
        let body = match encode_result(
            result,
            self.config.output_format,
            &self.config.producer_id,
            epoch,
        ) {
            Ok(b) => b,
            Err(e) => {
                tracing::error!(error = %e, "kafka: cannot encode a result");
                return false;
            }
        };
        let epoch_s = epoch.to_string();
        let mut attempts = 0;
        loop {
            let headers = OwnedHeaders::new()
                .insert(Header {
                    key: "content-type",
                    value: Some(self.config.output_format.content_type()),
                })
                .insert(Header {
                    key: "crossview-producer",
                    value: Some(self.config.producer_id.as_bytes()),
                })
                .insert(Header {
                    key: "crossview-epoch",
                    value: Some(epoch_s.as_bytes()),
                });
            let record = FutureRecord::to(&self.config.output_topic)
                .key(scene)
                .payload(&body)
                .headers(headers);
            match self
                .producer
                .send(record, Timeout::After(Duration::from_secs(10)))
                .await
            {
                Ok(_) => {
                    self.metrics().kafka_produced(true);
                    return true;
                }
                Err((e, _)) => {
                    self.metrics().kafka_produced(false);
                    attempts += 1;
                    tracing::warn!(%scene, frame = result.frame_id, error = %e, "kafka: produce failed");
                    if !self.service.accepting() && attempts >= 3 {
                        return false;
                    }
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
            }
        }
    }
}

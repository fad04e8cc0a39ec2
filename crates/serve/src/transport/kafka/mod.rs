//! Kafka mode (beside gRPC and HTTP): consume camera batches from an input topic, run them
//! through [`Service::push`] like any other transport, produce every published frame result to
//! an output topic. Written against the Kafka protocol through librdkafka (`rdkafka`); the
//! topology and the delivery semantics are in docs/kafka.md.
//!
//! Records: key = scene name (UTF-8), value = one SPEC §7 batch line as JSON, or the protobuf
//! `crossview.v1.Batch` (per record by its `content-type` header, else by
//! [`KafkaConfig::input_format`]). The default partitioner hashes the key, so a scene lives on
//! one partition and the consumer group gives each replica whole scenes. Results: key = scene,
//! value = the `FrameResult` as JSON plus `"producer": {"id", "epoch"}` (or the protobuf
//! `crossview.v1.FrameResult`), with headers `content-type`, `crossview-producer` and
//! `crossview-epoch`.
//!
//! At-least-once, and ownership decides everything: an input offset is committed only once
//! every batch at or below it is either in a result whose production the broker acknowledged,
//! or was refused (malformed or rejected: counted, optionally copied to a dead-letter topic,
//! never retried). Per partition the committable offset is the lowest still-open offset (or one
//! past the highest seen). On revocation the replica commits what is done, drops its scenes'
//! pending frames and never produces a result of the partition again (the next owner re-reads
//! those batches from the committed offset); a scene that comes (back) restarts past its last
//! produced frame, and re-read batches of frames already produced are dropped and counted
//! (`crossview_kafka_redelivered_total`), never dead-lettered. Module map: [`config`] the
//! settings, [`offsets`] the ownership bookkeeping, [`context`] the rebalance callbacks,
//! [`codec`] record values; this module runs the consume loop and the producers.
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use futures::StreamExt;
use rdkafka::consumer::{CommitMode, Consumer, StreamConsumer};
use rdkafka::message::{Header, Message, OwnedHeaders};
use rdkafka::producer::{FutureProducer, FutureRecord};
use rdkafka::util::Timeout;

use crossview_core::{Error, Result};

use crate::metrics::Metrics;
use crate::service::Service;

mod codec;
pub(crate) mod config;
mod context;
mod offsets;

use codec::{content_type, decode, encode_result};
pub use config::{CONSUMER_DEFAULTS, KafkaConfig, ValueFormat};
use context::{Context, commit_list};
use offsets::{Ownership, Publish};

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

use crate::locks::lock;

/// A running Kafka mode: consumer, producer and the shared offsets.
struct Kafka {
    config: KafkaConfig,
    service: Arc<Service>,
    consumer: StreamConsumer<Context>,
    producer: FutureProducer,
    offsets: Arc<Mutex<Ownership>>,
}

/// Starts Kafka mode on `service`: subscribes to every scene's results, joins the group and
/// consumes until shutdown begins. The returned task ends once the last result flushed at
/// shutdown is produced and its offsets committed.
pub fn start(service: Arc<Service>, config: KafkaConfig) -> Result<tokio::task::JoinHandle<()>> {
    let metrics = service.metrics().clone();
    let offsets = Arc::new(Mutex::new(Ownership::default()));
    let context = Context {
        topic: config.input_topic.clone(),
        offsets: offsets.clone(),
        metrics,
        service: service.clone(),
    };
    let consumer: StreamConsumer<Context> =
        config
            .consumer_config()
            .create_with_context(context)
            .map_err(|e| Error::invalid("--kafka-brokers", format!("kafka consumer: {e}")))?;
    let producer: FutureProducer = config
        .producer_config()
        .create()
        .map_err(|e| Error::invalid("--kafka-brokers", format!("kafka producer: {e}")))?;
    consumer
        .subscribe(&[&config.input_topic])
        .map_err(|e| Error::invalid("--kafka-input-topic", e.to_string()))?;
    service.set_consumer_ready(false);
    let mut config = config;
    config.max_in_flight = config
        .max_in_flight
        .clamp(1, (service.subscriber_buffer() / 2).max(1));
    let k = Arc::new(Kafka {
        config,
        service: service.clone(),
        consumer,
        producer,
        offsets,
    });
    let mut forwarders = Vec::new();
    for scene in service.scene_list() {
        let name = scene.name().to_string();
        let results = service.subscribe(&name, None, None)?;
        forwarders.push(tokio::spawn(k.clone().forward(name, results)));
    }
    tracing::info!(config = ?k.config, "kafka mode: consuming");
    // Offsets go out every COMMIT_INTERVAL (when they moved), not per record: one commit
    // request per partition and interval whatever the rate.
    let ticker = {
        let k = k.clone();
        tokio::spawn(async move {
            let stop = k.service.shutting_down();
            tokio::pin!(stop);
            let mut tick = tokio::time::interval(COMMIT_INTERVAL);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    _ = tick.tick() => k.commit(CommitMode::Async),
                    _ = &mut stop => break,
                }
            }
        })
    };
    Ok(tokio::spawn(async move {
        k.clone().consume().await;
        let _ = ticker.await;
        for f in forwarders {
            let _ = f.await;
        }
        k.commit(CommitMode::Sync);
        tracing::info!("kafka mode: stopped");
    }))
}

/// How often the committable offsets are committed (asynchronously) while running; on
/// revocation and at shutdown they are committed at once, synchronously.
const COMMIT_INTERVAL: Duration = Duration::from_millis(100);

/// One consumed input record.
struct Record<'a> {
    key: Option<&'a [u8]>,
    payload: Option<&'a [u8]>,
    partition: i32,
    offset: i64,
    /// Read here before (below the highest offset consumed before the last revocation).
    redelivered: bool,
}

/// Most results of one scene handed to the producer and not yet acknowledged.
const MAX_UNACKED: usize = 64;

/// What became of one input record.
enum Handled {
    /// Consumed (its offset closes once its frame's result is produced, or now if refused).
    Next,
    /// The service is shutting down: the record stays uncommitted (re-read later).
    Stop,
}

impl Kafka {
    fn metrics(&self) -> &Metrics {
        self.service.metrics()
    }

    /// The consume loop, until shutdown begins.
    async fn consume(self: Arc<Self>) {
        let stop = self.service.shutting_down();
        tokio::pin!(stop);
        loop {
            let msg = tokio::select! {
                m = self.consumer.recv() => m,
                _ = &mut stop => break,
            };
            let msg = match msg {
                Ok(m) => m,
                Err(e) => {
                    tracing::warn!(error = %e, "kafka: consume error");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            let (partition, offset) = (msg.partition(), msg.offset());
            let Some(redelivered) = lock(&self.offsets).consumed(partition, offset) else {
                // Fetched before its partition was revoked: left to the owner.
                continue;
            };
            let record = Record {
                key: msg.key(),
                payload: msg.payload(),
                partition,
                offset,
                redelivered,
            };
            let format = content_type(&msg).unwrap_or(Ok(self.config.input_format));
            if let Handled::Stop = self.handle(&record, format).await {
                break;
            }
            // Backpressure: wait while too many frames wait for their results.
            while lock(&self.offsets).in_flight() >= self.config.max_in_flight
                && self.service.accepting()
            {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        }
    }

    async fn handle(&self, r: &Record<'_>, format: Result<ValueFormat>) -> Handled {
        let (partition, offset) = (r.partition, r.offset);
        let (scene, batch) = match format.and_then(|f| decode(r.key, r.payload, f)) {
            Ok(v) => v,
            Err(e) => {
                if r.redelivered {
                    // Refused (and dead-lettered) when first read.
                    self.metrics().kafka_redelivered();
                } else {
                    self.metrics().kafka_record("malformed");
                    tracing::debug!(partition, offset, error = %e, "kafka: malformed record skipped");
                    self.dead_letter(r, &e).await;
                }
                lock(&self.offsets).done(partition, offset);
                return Handled::Next;
            }
        };
        self.enter_scene(&scene, partition);
        let frame_id = batch.frame_id;
        let created = lock(&self.offsets).hold(&scene, frame_id, partition, offset);
        loop {
            match self.service.push(&scene, batch.clone()) {
                Ok(_) => {
                    self.metrics().kafka_record("accepted");
                    return Handled::Next;
                }
                Err(Error::ResourceExhausted(_)) if self.service.accepting() => {
                    // Overload: wait (backpressure on the partition), never drop.
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
                Err(Error::Unavailable(_)) => return Handled::Stop,
                Err(e) => {
                    let again = r.redelivered
                        && matches!(e, Error::LateBatch { .. } | Error::DuplicateBatch { .. });
                    if created {
                        // No result will hold it; a frame already pending here keeps it
                        // (its result closes the offset).
                        lock(&self.offsets).unhold(&scene, frame_id, partition, offset);
                    }
                    if again {
                        // Read before, its frame already produced: not a loss.
                        self.metrics().kafka_redelivered();
                        tracing::debug!(partition, offset, "kafka: re-delivered batch dropped");
                    } else {
                        self.metrics().kafka_record("rejected");
                        tracing::debug!(partition, offset, error = %e, "kafka: record rejected");
                        self.dead_letter(r, &e).await;
                    }
                    return Handled::Next;
                }
            }
        }
    }

    /// The first record of `scene` since its partition was (re)assigned: the scene starts
    /// afresh just past its last produced frame (none: from scratch).
    fn enter_scene(&self, scene: &str, partition: i32) {
        let Some(last) = lock(&self.offsets).enter_scene(scene, partition) else {
            return;
        };
        if let Some(s) = self
            .service
            .scene_list()
            .into_iter()
            .find(|s| s.name() == scene)
        {
            let dropped = s.restart(last);
            tracing::info!(
                scene,
                partition,
                ?last,
                dropped,
                "kafka: scene (re)starts here"
            );
        }
    }

    /// Copies a refused record to the dead-letter topic, if there is one.
    async fn dead_letter(&self, r: &Record<'_>, error: &Error) {
        let (key, payload) = (r.key, r.payload);
        let Some(topic) = &self.config.dead_letter_topic else {
            return;
        };
        let reason = error.to_string();
        let source = format!("{}/{}/{}", self.config.input_topic, r.partition, r.offset);
        let headers = OwnedHeaders::new()
            .insert(Header {
                key: "crossview-error",
                value: Some(reason.as_bytes()),
            })
            .insert(Header {
                key: "crossview-source",
                value: Some(source.as_bytes()),
            });
        let mut record = FutureRecord::<[u8], [u8]>::to(topic).headers(headers);
        if let Some(k) = key {
            record = record.key(k);
        }
        if let Some(p) = payload {
            record = record.payload(p);
        }
        if let Err((e, _)) = self
            .producer
            .send(record, Timeout::After(Duration::from_secs(10)))
            .await
        {
            tracing::warn!(error = %e, %source, "kafka: dead-letter produce failed");
        }
    }

    /// Produces every result of `scene` and closes its batches' offsets once acknowledged.
    /// Up to [`MAX_UNACKED`] results are in flight to the broker at once (a catch-up is not
    /// paced by one acknowledgement round trip per frame); acknowledgements are taken in order.
    async fn forward(self: Arc<Self>, scene: String, mut results: crate::service::ResultStream) {
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

    /// Commits every owned partition's committable offset that moved.
    fn commit(&self, mode: CommitMode) {
        let commits = lock(&self.offsets).take_commits();
        if commits.is_empty() {
            return;
        }
        match commit_list(&self.config.input_topic, &commits).and_then(|tpl| {
            self.consumer
                .commit(&tpl, mode)
                .map_err(|e| Error::internal_from("kafka commit", e))
        }) {
            Ok(()) => {
                for (p, o) in commits {
                    self.metrics()
                        .kafka_committed(&self.config.input_topic, p, o);
                }
            }
            Err(e) => tracing::warn!(error = %e, "kafka: commit failed"),
        }
    }
}

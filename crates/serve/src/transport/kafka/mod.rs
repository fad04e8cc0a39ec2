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
//! [`codec`] record values, `consumer` the consume loop, `producer` the results out; this
//! module starts them and commits.
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use rdkafka::consumer::{CommitMode, Consumer, StreamConsumer};
use rdkafka::producer::FutureProducer;

use crate::error::{Error, Result};

use crate::metrics::Metrics;
use crate::service::Service;

mod codec;
pub(crate) mod config;
mod consumer;
mod context;
mod offsets;
mod producer;
mod stream_time;

pub use config::{
    CLASSIC_DEFAULTS, CONSUMER_DEFAULTS, GroupProtocol, KafkaConfig, TimestampSource, ValueFormat,
};
use context::{Context, commit_list};
use offsets::Ownership;

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
        stats_clock: Default::default(),
        fetches: Default::default(),
        brokers_down: Default::default(),
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

/// Tells `scenes` that the stream time they follow moved.
fn wake(service: &Service, scenes: &[String]) {
    for name in scenes {
        if let Some(scene) = service.find_scene(name) {
            scene.stream_moved();
        }
    }
}

/// How often the committable offsets are committed (asynchronously) while running; on
/// revocation and at shutdown they are committed at once, synchronously.
const COMMIT_INTERVAL: Duration = Duration::from_millis(100);

impl Kafka {
    fn metrics(&self) -> &Metrics {
        self.service.metrics()
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

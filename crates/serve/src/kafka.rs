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
//! At-least-once: an input offset is committed only once every batch at or below it is either
//! in a result whose production the broker acknowledged, or was refused (malformed or rejected:
//! counted, optionally copied to a dead-letter topic, never retried). Per partition the
//! committable offset is the lowest still-open offset (or one past the highest seen).
//! On revocation the replica commits what is done and forgets the partition; frames of its
//! scenes still pending here are published when they leave the synchronizer (maybe partial)
//! and the new owner re-reads their batches from the committed offset: such a frame can be
//! published twice, by two producers or epochs, which is how a consumer drops the duplicate.
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use futures::StreamExt;
use rdkafka::config::ClientConfig;
use rdkafka::consumer::{
    BaseConsumer, CommitMode, Consumer, ConsumerContext, Rebalance, StreamConsumer,
};
use rdkafka::message::{Header, Message, OwnedHeaders};
use rdkafka::producer::{FutureProducer, FutureRecord};
use rdkafka::util::Timeout;
use rdkafka::{ClientContext, Offset, Statistics, TopicPartitionList};

use crossview_api::convert::{batch_from_pb, result_to_pb};
pub use crossview_api::format::ValueFormat;
use crossview_api::pb;
use crossview_core::{Batch, Error, Result};
use prost::Message as _;

use crate::metrics::Metrics;
use crate::service::Service;

/// Settings of Kafka mode (`crossview serve --kafka-*`).
#[derive(Clone)]
pub struct KafkaConfig {
    /// Bootstrap brokers, `host:port[,host:port...]` (librdkafka `bootstrap.servers`).
    pub brokers: String,
    /// Topic of input batches (key = scene).
    pub input_topic: String,
    /// Topic the frame results are produced to (key = scene).
    pub output_topic: String,
    /// Consumer group the replicas share.
    pub group: String,
    /// This replica's name in its results' `producer.id` (default: host name and process id).
    pub producer_id: String,
    /// Where malformed and rejected records are copied (with a `crossview-error` header);
    /// `None`: they are only counted and skipped.
    pub dead_letter_topic: Option<String>,
    /// Further librdkafka properties for consumer and producer (security: `security.protocol`,
    /// `sasl.*`, `ssl.*`; tuning: `session.timeout.ms`, ...); they override the defaults.
    pub properties: Vec<(String, String)>,
    /// Most frames with consumed batches not yet in a produced result; consumption pauses
    /// beyond it (kept below the subscriber buffer so results are never dropped).
    pub max_in_flight: usize,
    /// How input values are encoded when a record has no `content-type` header.
    pub input_format: ValueFormat,
    /// How results are encoded.
    pub output_format: ValueFormat,
}

impl std::fmt::Debug for KafkaConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let props: Vec<(&str, &str)> = self
            .properties
            .iter()
            .map(|(k, v)| {
                let secret = k.contains("password") || k.contains("secret") || k.contains("key");
                (k.as_str(), if secret { "<redacted>" } else { v.as_str() })
            })
            .collect();
        f.debug_struct("KafkaConfig")
            .field("brokers", &self.brokers)
            .field("input_topic", &self.input_topic)
            .field("output_topic", &self.output_topic)
            .field("group", &self.group)
            .field("producer_id", &self.producer_id)
            .field("dead_letter_topic", &self.dead_letter_topic)
            .field("properties", &props)
            .field("max_in_flight", &self.max_in_flight)
            .field("input_format", &self.input_format)
            .field("output_format", &self.output_format)
            .finish()
    }
}

impl KafkaConfig {
    /// Settings with the defaults for everything but brokers, topics and group.
    pub fn new(brokers: &str, input_topic: &str, output_topic: &str, group: &str) -> Self {
        KafkaConfig {
            brokers: brokers.into(),
            input_topic: input_topic.into(),
            output_topic: output_topic.into(),
            group: group.into(),
            producer_id: default_producer_id(),
            dead_letter_topic: None,
            properties: Vec::new(),
            max_in_flight: 256,
            input_format: ValueFormat::Json,
            output_format: ValueFormat::Json,
        }
    }

    /// Parses one `KEY=VALUE` librdkafka property.
    pub fn parse_property(s: &str) -> Result<(String, String)> {
        match s.split_once('=') {
            Some((k, v)) if !k.trim().is_empty() => Ok((k.trim().into(), v.into())),
            _ => Err(Error::invalid(
                "--kafka-property",
                format!("'{}' is not KEY=VALUE", crate::truncate_echo(s)),
            )),
        }
    }

    fn client(&self) -> ClientConfig {
        let mut c = ClientConfig::new();
        c.set("bootstrap.servers", &self.brokers);
        c
    }

    /// `c` with the user's properties, less those only the other kind of client knows
    /// (librdkafka would warn about them).
    fn with_properties(&self, mut c: ClientConfig, consumer: bool) -> ClientConfig {
        for (k, v) in &self.properties {
            let foreign = if consumer {
                PRODUCER_ONLY.iter().any(|p| k.starts_with(p))
            } else {
                CONSUMER_ONLY.iter().any(|p| k.starts_with(p))
            };
            if !foreign {
                c.set(k, v);
            }
        }
        c
    }
}

/// Prefixes of librdkafka properties only a consumer knows.
const CONSUMER_ONLY: &[&str] = &[
    "group.",
    "session.timeout.ms",
    "heartbeat.interval.ms",
    "auto.offset.reset",
    "enable.auto.",
    "auto.commit.",
    "max.poll.interval.ms",
    "partition.assignment.strategy",
    "fetch.",
    "isolation.level",
    "enable.partition.eof",
    "check.crcs",
    "queued.",
    "coordinator.query.interval.ms",
];

/// Prefixes of librdkafka properties only a producer knows.
const PRODUCER_ONLY: &[&str] = &[
    "acks",
    "request.required.acks",
    "linger.ms",
    "compression.",
    "enable.idempotence",
    "message.timeout.ms",
    "delivery.timeout.ms",
    "queue.buffering.",
    "batch.",
    "transactional.id",
    "partitioner",
];

/// `<host>-<pid>`: unique enough among the replicas of one group.
fn default_producer_id() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "crossview".into());
    format!("{host}-{}", std::process::id())
}

fn now_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// The offsets of one owned input partition.
#[derive(Debug, Default)]
struct Part {
    /// Consumed offsets whose batch is not yet in a produced result.
    open: BTreeSet<i64>,
    /// One past the highest consumed offset.
    next: Option<i64>,
    /// The last offset committed (or handed to the commit).
    committed: Option<i64>,
}

impl Part {
    fn committable(&self) -> Option<i64> {
        self.open.first().copied().or(self.next)
    }
}

/// What is consumed and not yet committed.
#[derive(Debug, Default)]
struct Offsets {
    parts: BTreeMap<i32, Part>,
    /// The input records of each frame not yet in a produced result.
    frames: HashMap<(String, u64), Vec<(i32, i64)>>,
    /// When the current assignment began (ms since the Unix epoch): the results' epoch.
    epoch: u64,
}

impl Offsets {
    fn begin(&mut self, partition: i32, offset: i64) {
        let p = self.parts.entry(partition).or_default();
        p.open.insert(offset);
        p.next = Some(p.next.map_or(offset + 1, |n| n.max(offset + 1)));
    }

    fn done(&mut self, partition: i32, offset: i64) {
        if let Some(p) = self.parts.get_mut(&partition) {
            p.open.remove(&offset);
        }
    }

    /// The partitions whose committable offset moved, marked as committed.
    fn take_commits(&mut self) -> Vec<(i32, i64)> {
        let mut out = Vec::new();
        for (k, p) in &mut self.parts {
            if let Some(c) = p.committable()
                && p.committed.is_none_or(|done| c > done)
            {
                p.committed = Some(c);
                out.push((*k, c));
            }
        }
        out
    }
}

/// librdkafka callbacks: rebalances (commit, forget, epoch, readiness) and statistics (lag).
struct Context {
    topic: String,
    offsets: Arc<Mutex<Offsets>>,
    metrics: Metrics,
    service: Arc<Service>,
    joined: AtomicBool,
}

impl ClientContext for Context {
    fn stats(&self, stats: Statistics) {
        let Some(t) = stats.topics.get(&self.topic) else {
            return;
        };
        let owned = lock(&self.offsets);
        for (p, part) in &t.partitions {
            if *p >= 0 && part.consumer_lag >= 0 && owned.parts.contains_key(p) {
                self.metrics.kafka_lag(&self.topic, *p, part.consumer_lag);
            }
        }
    }
}

impl ConsumerContext for Context {
    fn pre_rebalance(&self, consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        if let Rebalance::Revoke(list) = rebalance {
            let commits = lock(&self.offsets).take_commits();
            if !commits.is_empty() {
                match commit_list(&self.topic, &commits) {
                    Ok(tpl) => {
                        if let Err(e) = consumer.commit(&tpl, CommitMode::Sync) {
                            tracing::warn!(error = %e, "commit on revocation failed");
                        }
                    }
                    Err(e) => tracing::warn!(error = %e, "commit on revocation failed"),
                }
            }
            let mut offsets = lock(&self.offsets);
            for e in list.elements() {
                offsets.parts.remove(&e.partition());
                self.metrics.kafka_assigned(e.topic(), e.partition(), false);
            }
            tracing::info!(partitions = list.count(), "kafka: partitions revoked");
        }
    }

    fn post_rebalance(&self, _consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        match rebalance {
            Rebalance::Assign(list) => {
                let mut offsets = lock(&self.offsets);
                offsets.epoch = now_ms().max(offsets.epoch + 1);
                for e in list.elements() {
                    offsets.parts.entry(e.partition()).or_default();
                    self.metrics.kafka_assigned(e.topic(), e.partition(), true);
                }
                let parts: Vec<i32> = list.elements().iter().map(|e| e.partition()).collect();
                tracing::info!(?parts, epoch = offsets.epoch, "kafka: partitions assigned");
                self.joined.store(true, Ordering::Release);
                self.service.set_consumer_ready(true);
            }
            Rebalance::Revoke(_) => {}
            Rebalance::Error(e) => tracing::warn!(error = %e, "kafka: rebalance failed"),
        }
    }
}

fn commit_list(topic: &str, commits: &[(i32, i64)]) -> Result<TopicPartitionList> {
    let mut tpl = TopicPartitionList::new();
    for (p, o) in commits {
        tpl.add_partition_offset(topic, *p, Offset::Offset(*o))
            .map_err(|e| Error::internal_from("kafka: bad commit offset", e))?;
    }
    Ok(tpl)
}

/// A running Kafka mode: consumer, producer and the shared offsets.
struct Kafka {
    config: KafkaConfig,
    service: Arc<Service>,
    consumer: StreamConsumer<Context>,
    producer: FutureProducer,
    offsets: Arc<Mutex<Offsets>>,
}

/// Starts Kafka mode on `service`: subscribes to every scene's results, joins the group and
/// consumes until shutdown begins. The returned task ends once the last result flushed at
/// shutdown is produced and its offsets committed.
pub fn start(service: Arc<Service>, config: KafkaConfig) -> Result<tokio::task::JoinHandle<()>> {
    let metrics = service.metrics().clone();
    let offsets = Arc::new(Mutex::new(Offsets::default()));
    let context = Context {
        topic: config.input_topic.clone(),
        offsets: offsets.clone(),
        metrics,
        service: service.clone(),
        joined: AtomicBool::new(false),
    };
    let mut cc = config.client();
    cc.set("group.id", &config.group)
        .set("enable.auto.commit", "false")
        .set("enable.auto.offset.store", "false")
        .set("auto.offset.reset", "earliest")
        .set("enable.partition.eof", "false")
        .set("statistics.interval.ms", "2000");
    let consumer: StreamConsumer<Context> = config
        .with_properties(cc, true)
        .create_with_context(context)
        .map_err(|e| Error::invalid("--kafka-brokers", format!("kafka consumer: {e}")))?;
    let mut pc = config.client();
    pc.set("linger.ms", "2").set("enable.idempotence", "true");
    let producer: FutureProducer = config
        .with_properties(pc, false)
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
            lock(&self.offsets).begin(partition, offset);
            let format = content_type(&msg).unwrap_or(Ok(self.config.input_format));
            let handled = self
                .handle(msg.key(), msg.payload(), format, partition, offset)
                .await;
            if let Handled::Stop = handled {
                break;
            }
            // Backpressure: wait while too many frames wait for their results.
            while lock(&self.offsets).frames.len() >= self.config.max_in_flight
                && self.service.accepting()
            {
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        }
    }

    async fn handle(
        &self,
        key: Option<&[u8]>,
        payload: Option<&[u8]>,
        format: Result<ValueFormat>,
        partition: i32,
        offset: i64,
    ) -> Handled {
        let (scene, batch) = match format.and_then(|f| decode(key, payload, f)) {
            Ok(v) => v,
            Err(e) => {
                self.metrics().kafka_record("malformed");
                tracing::debug!(partition, offset, error = %e, "kafka: malformed record skipped");
                self.dead_letter(key, payload, &e, partition, offset).await;
                lock(&self.offsets).done(partition, offset);
                return Handled::Next;
            }
        };
        let frame = (scene.clone(), batch.frame_id);
        let created = {
            let mut o = lock(&self.offsets);
            let entry = o.frames.entry(frame.clone()).or_default();
            entry.push((partition, offset));
            entry.len() == 1
        };
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
                    self.metrics().kafka_record("rejected");
                    tracing::debug!(partition, offset, error = %e, "kafka: record rejected");
                    if created {
                        // No result will hold it; a frame already pending here keeps it
                        // (its result closes the offset).
                        let mut o = lock(&self.offsets);
                        if let Some(v) = o.frames.get_mut(&frame) {
                            v.retain(|x| *x != (partition, offset));
                            if v.is_empty() {
                                o.frames.remove(&frame);
                            }
                        }
                        o.done(partition, offset);
                    }
                    self.dead_letter(key, payload, &e, partition, offset).await;
                    return Handled::Next;
                }
            }
        }
    }

    /// Copies a refused record to the dead-letter topic, if there is one.
    async fn dead_letter(
        &self,
        key: Option<&[u8]>,
        payload: Option<&[u8]>,
        error: &Error,
        partition: i32,
        offset: i64,
    ) {
        let Some(topic) = &self.config.dead_letter_topic else {
            return;
        };
        let reason = error.to_string();
        let source = format!("{}/{partition}/{offset}", self.config.input_topic);
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
    async fn forward(self: Arc<Self>, scene: String, mut results: crate::service::ResultStream) {
        loop {
            while let Some(item) = results.next().await {
                let r = match item {
                    Ok(r) => r,
                    Err(e) => {
                        tracing::warn!(%scene, error = %e, "kafka: result stream lagged");
                        break;
                    }
                };
                let (held, epoch) = {
                    let mut o = lock(&self.offsets);
                    let held = o
                        .frames
                        .remove(&(scene.clone(), r.result.frame_id))
                        .unwrap_or_default();
                    (held, o.epoch)
                };
                if self.produce(&scene, &r.result, epoch).await {
                    let mut o = lock(&self.offsets);
                    for (p, off) in held {
                        o.done(p, off);
                    }
                }
            }
            if !self.service.accepting() {
                return;
            }
            match self.service.subscribe(&scene, None, None) {
                Ok(s) => results = s,
                Err(_) => return,
            }
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

/// The format a record's `content-type` header names: `None` without the header, an error
/// for a type we do not read.
fn content_type<M: Message>(msg: &M) -> Option<Result<ValueFormat>> {
    use rdkafka::message::Headers;
    let headers = msg.headers()?;
    let h = headers
        .iter()
        .find(|h| h.key.eq_ignore_ascii_case("content-type"))?;
    let v = h.value.unwrap_or_default();
    Some(ValueFormat::from_content_type(v).ok_or_else(|| {
        Error::invalid(
            "content-type",
            format!(
                "'{}' is not application/json or application/x-protobuf",
                crate::truncate_echo(&String::from_utf8_lossy(v))
            ),
        )
    }))
}

/// A record's scene (its key) and batch (its value: a SPEC §7 batch line, or a protobuf
/// `Batch` whose `scene`, if set, must equal the key).
fn decode(
    key: Option<&[u8]>,
    payload: Option<&[u8]>,
    format: ValueFormat,
) -> Result<(String, Batch)> {
    let scene = key
        .filter(|k| !k.is_empty())
        .ok_or_else(|| Error::invalid("key", "a record needs its scene name as key"))?;
    let scene = std::str::from_utf8(scene)
        .map_err(|_| Error::invalid("key", "the scene name is not UTF-8"))?
        .to_string();
    let value = payload.ok_or_else(|| Error::invalid("value", "empty record"))?;
    let batch = match format {
        ValueFormat::Json => {
            serde_json::from_slice(value).map_err(|e| Error::invalid("value", e.to_string()))?
        }
        ValueFormat::Protobuf => {
            let pb = pb::Batch::decode(value)
                .map_err(|e| Error::invalid("value", format!("not a protobuf Batch: {e}")))?;
            if !pb.scene.is_empty() && pb.scene != scene {
                return Err(Error::invalid(
                    "scene",
                    format!(
                        "the batch names scene '{}' but the record key is '{}'",
                        crate::truncate_echo(&pb.scene),
                        crate::truncate_echo(&scene)
                    ),
                ));
            }
            batch_from_pb(pb)?.1
        }
    };
    Ok((scene, batch))
}

/// A result's record value: JSON with `producer` added, or the protobuf `FrameResult` (whose
/// producer is in the headers only).
fn encode_result(
    result: &crossview_api::types::FrameResult,
    format: ValueFormat,
    producer: &str,
    epoch: u64,
) -> Result<Vec<u8>> {
    match format {
        ValueFormat::Protobuf => Ok(result_to_pb(result).encode_to_vec()),
        ValueFormat::Json => {
            let mut value = serde_json::to_value(result)
                .map_err(|e| Error::internal_from("encode result", e))?;
            if let Some(obj) = value.as_object_mut() {
                obj.insert(
                    "producer".into(),
                    serde_json::json!({"id": producer, "epoch": epoch}),
                );
            }
            Ok(value.to_string().into_bytes())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committable_offset_waits_for_the_lowest_open_batch() {
        let mut o = Offsets::default();
        o.parts.entry(0).or_default();
        for off in 10..14 {
            o.begin(0, off);
        }
        assert!(o.take_commits().iter().all(|(_, c)| *c == 10));
        o.done(0, 11);
        o.done(0, 12);
        assert!(o.take_commits().is_empty(), "10 still open");
        o.done(0, 10);
        assert_eq!(o.take_commits(), vec![(0, 13)]);
        o.done(0, 13);
        assert_eq!(o.take_commits(), vec![(0, 14)]);
        assert!(o.take_commits().is_empty());
    }

    #[test]
    fn records_need_a_scene_key_and_a_batch_line() {
        let line = br#"{"camera":"c0","frame_id":3,"detections":[]}"#;
        let json = ValueFormat::Json;
        let (scene, b) = decode(Some(b"lab"), Some(line), json).unwrap();
        assert_eq!((scene.as_str(), b.frame_id), ("lab", 3));
        assert!(decode(None, Some(line), json).is_err());
        assert!(decode(Some(&[0xff]), Some(line), json).is_err());
        assert!(decode(Some(b"lab"), Some(b"{not json"), json).is_err());
        assert!(decode(Some(b"lab"), None, json).is_err());
        let p = KafkaConfig::parse_property("sasl.password=x=y").unwrap();
        assert_eq!(p, ("sasl.password".into(), "x=y".into()));
        assert!(KafkaConfig::parse_property("novalue").is_err());
        let mut c = KafkaConfig::new("b:9092", "in", "out", "g");
        c.properties.push(p);
        assert!(!format!("{c:?}").contains("x=y"));
    }

    #[test]
    fn protobuf_values_decode_and_must_agree_with_the_key() {
        let batch = Batch {
            camera: "c0".into(),
            frame_id: 7,
            detections: vec![],
        };
        let proto = ValueFormat::Protobuf;
        let bytes = crossview_api::convert::batch_to_pb("lab", &batch).encode_to_vec();
        let (scene, b) = decode(Some(b"lab"), Some(&bytes), proto).unwrap();
        assert_eq!(
            (scene.as_str(), b.camera.as_str(), b.frame_id),
            ("lab", "c0", 7)
        );
        let unnamed = crossview_api::convert::batch_to_pb("", &batch).encode_to_vec();
        assert_eq!(
            decode(Some(b"lab"), Some(&unnamed), proto).unwrap().0,
            "lab"
        );
        assert!(decode(Some(b"other"), Some(&bytes), proto).is_err());
        assert!(decode(Some(b"lab"), Some(b"\xff\xff\xff"), proto).is_err());
        // A JSON line read as protobuf (and the other way round) is malformed, not a panic.
        let line = br#"{"camera":"c0","frame_id":3,"detections":[]}"#;
        assert!(decode(Some(b"lab"), Some(line), proto).is_err());
        assert!(decode(Some(b"lab"), Some(&bytes), ValueFormat::Json).is_err());
    }
}

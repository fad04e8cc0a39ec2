//! Kafka transport: batches are produced to the replicas' input topic (key = scene, value = a
//! SPEC §7 batch line or a protobuf `Batch`), results are read from the output topic (key =
//! scene, JSON or protobuf by their `content-type` header). "Accepted" here means the broker
//! acknowledged the batch: the server's own verdict is not visible to a Kafka producer, so a
//! batch a replica refuses shows up as a lost frame (and on the dead-letter topic).
use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use crossview_api::convert::batch_to_pb;
use crossview_api::format::ValueFormat;
use crossview_api::pb;
use prost::Message as _;
use rdkafka::config::ClientConfig;
use rdkafka::consumer::{Consumer, StreamConsumer};
use rdkafka::message::{Header, Headers, Message, OwnedHeaders};
use rdkafka::producer::{FutureProducer, FutureRecord, Producer};
use rdkafka::{Offset, TopicPartitionList};
use serde::Deserialize;
use tokio::sync::oneshot;

use crate::args::Args;
use crate::tracker::{FrameKey, Outcome, Tracker};
use crate::transport::Outgoing;

/// A client's librdkafka settings: brokers, then `defaults`, then `--kafka-property` (which
/// overrides both).
fn client(args: &Args, defaults: &[(&str, &str)]) -> anyhow::Result<ClientConfig> {
    let brokers = args
        .kafka_brokers
        .as_deref()
        .context("--transport kafka needs --kafka-brokers")?;
    let mut c = ClientConfig::new();
    c.set("bootstrap.servers", brokers);
    for (k, v) in defaults {
        c.set(*k, *v);
    }
    for p in &args.kafka_property {
        let (k, v) = p
            .split_once('=')
            .with_context(|| format!("--kafka-property '{p}' is not KEY=VALUE"))?;
        c.set(k.trim(), v);
    }
    Ok(c)
}

/// Checks that every broker of `--kafka-brokers` is on loopback or named by --allow-host.
pub async fn check_brokers(args: &Args) -> anyhow::Result<()> {
    let brokers = args
        .kafka_brokers
        .as_deref()
        .context("--transport kafka needs --kafka-brokers")?;
    for b in brokers.split(',').map(str::trim).filter(|b| !b.is_empty()) {
        let b = b.split_once("://").map_or(b, |(_, rest)| rest);
        crate::target::check_target(&format!("http://{b}"), &args.allow_host)
            .await
            .with_context(|| format!("--kafka-brokers: {b}"))?;
    }
    Ok(())
}

/// The producer side: one librdkafka producer for the whole run (it batches per partition).
pub struct KafkaSlot {
    producer: FutureProducer,
    topic: Arc<str>,
    format: ValueFormat,
    tracker: Arc<Tracker>,
}

impl KafkaSlot {
    /// A producer for `--kafka-input-topic`, connected (the topic's metadata fetched, so the
    /// first frames of the run do not pay for the connection); acknowledgements are recorded
    /// in `tracker`.
    pub async fn new(args: &Args, tracker: Arc<Tracker>) -> anyhow::Result<Self> {
        let producer: FutureProducer = client(
            args,
            &[
                ("linger.ms", "1"),
                ("enable.idempotence", "true"),
                ("queue.buffering.max.messages", "1000000"),
            ],
        )?
        .create()
        .context("kafka producer")?;
        let (p, topic) = (producer.clone(), args.kafka_input_topic.clone());
        tokio::task::spawn_blocking(move || {
            p.client()
                .fetch_metadata(Some(&topic), Duration::from_secs(10))
                .map(|_| ())
                .with_context(|| format!("kafka metadata of '{topic}'"))
        })
        .await
        .context("kafka setup task")??;
        Ok(KafkaSlot {
            producer,
            topic: args.kafka_input_topic.as_str().into(),
            format: args.kafka_format,
            tracker,
        })
    }

    /// Enqueues one batch now (so a camera's batches keep their order on the partition) and
    /// records the broker's acknowledgement when it comes.
    pub fn send(&self, out: Outgoing) {
        let value = match self.format {
            ValueFormat::Json => match serde_json::to_vec(&out.batch) {
                Ok(v) => v,
                Err(_) => {
                    self.tracker.failed(out.key, "encode");
                    return;
                }
            },
            ValueFormat::Protobuf => batch_to_pb(&out.scene, &out.batch).encode_to_vec(),
        };
        let headers = OwnedHeaders::new().insert(Header {
            key: "content-type",
            value: Some(self.format.content_type()),
        });
        let record = FutureRecord::to(&self.topic)
            .key(&*out.scene)
            .payload(&value)
            .headers(headers);
        match self.producer.send_result(record) {
            Ok(delivery) => {
                let tracker = self.tracker.clone();
                tokio::spawn(async move {
                    let _permit = out.permit;
                    match delivery.await {
                        Ok(Ok(_)) => tracker.accepted(out.key),
                        Ok(Err((e, _))) => {
                            tracing::debug!(error = %e, "kafka: delivery failed");
                            tracker.failed(out.key, "kafka_delivery")
                        }
                        Err(_) => tracker.failed(out.key, "kafka_cancelled"),
                    }
                });
            }
            Err((e, _)) => {
                tracing::debug!(error = %e, "kafka: enqueue failed");
                self.tracker.failed(out.key, "kafka_enqueue");
            }
        }
    }

    /// Waits (bounded) until every enqueued batch has been delivered or failed.
    pub fn flush(&self, wait: Duration) {
        let _ = self.producer.flush(wait);
    }
}

/// The fields of a JSON result the tracker needs.
#[derive(Deserialize)]
struct JsonResult {
    scene: String,
    frame_id: u64,
    complete: bool,
}

/// (scene, frame id, complete) of one result record.
fn decode_result<M: Message>(m: &M) -> anyhow::Result<(String, u64, bool)> {
    let payload = m.payload().context("empty result record")?;
    // The format its header names; JSON without one (the replicas' default).
    let format = m
        .headers()
        .and_then(|h| {
            h.iter()
                .find(|h| h.key.eq_ignore_ascii_case("content-type"))
        })
        .and_then(|h| ValueFormat::from_content_type(h.value.unwrap_or_default()))
        .unwrap_or_default();
    if format == ValueFormat::Protobuf {
        let r = pb::FrameResult::decode(payload).context("not a protobuf FrameResult")?;
        Ok((r.scene, r.frame_id, r.complete))
    } else {
        let r: JsonResult = serde_json::from_slice(payload).context("not a JSON FrameResult")?;
        Ok((r.scene, r.frame_id, r.complete))
    }
}

/// Reads `--kafka-output-topic` from its current end (every partition, no consumer group
/// offsets) and records every result of `scenes` in `tracker`; `ready` fires once the
/// partitions are assigned at their high watermarks, so no result of this run is missed.
pub async fn subscribe(
    args: Arc<Args>,
    scenes: Vec<Arc<str>>,
    tracker: Arc<Tracker>,
    ready: oneshot::Sender<anyhow::Result<PartitionOffsets>>,
) {
    let (consumer, start, _) = match open_results(&args, None).await {
        Ok(c) => c,
        Err(e) => {
            let _ = ready.send(Err(e));
            return;
        }
    };
    let _ = ready.send(Ok(start));
    let index = scene_index(&scenes);
    loop {
        match consumer.recv().await {
            Ok(m) => match decode_result(&m) {
                Ok((scene, frame, complete)) => {
                    if let Some(i) = index.get(scene.as_str()) {
                        // Kafka mode never sheds (its partitions wait instead).
                        let outcome = Outcome::of(complete, false);
                        tracker.result((*i, frame), outcome, Instant::now());
                    }
                }
                Err(e) => {
                    tracing::debug!(error = %e, "kafka: undecodable result");
                    tracker.error("result_undecodable");
                }
            },
            Err(e) => {
                tracing::warn!(error = %e, "kafka: consume error");
                tracker.error("kafka_consume");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
}

/// An offset per partition of the output topic: (partition, offset).
pub type PartitionOffsets = Vec<(i32, i64)>;

fn scene_index(scenes: &[Arc<str>]) -> HashMap<Arc<str>, usize> {
    scenes
        .iter()
        .enumerate()
        .map(|(i, s)| (s.clone(), i))
        .collect()
}

/// Reads the output topic again from `start` up to its current end (bounded: 30 s) and
/// returns every `(scene index, frame id)` of `scenes` found there.
pub async fn reread(
    args: &Args,
    start: &[(i32, i64)],
    scenes: &[Arc<str>],
) -> anyhow::Result<HashSet<FrameKey>> {
    let (consumer, _, ends) = open_results(args, Some(start)).await?;
    let ends: HashMap<i32, i64> = ends.into_iter().collect();
    let index = scene_index(scenes);
    let mut found = HashSet::new();
    let mut done: HashSet<i32> = start
        .iter()
        .filter(|(p, o)| ends.get(p).is_none_or(|e| o >= e))
        .map(|(p, _)| *p)
        .collect();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while done.len() < start.len() {
        let m = match tokio::time::timeout_at(deadline, consumer.recv()).await {
            Ok(Ok(m)) => m,
            Ok(Err(e)) => bail!("kafka re-read: {e}"),
            Err(_) => bail!("kafka re-read: the output topic's end not reached in 30 s"),
        };
        if m.offset() + 1 >= ends.get(&m.partition()).copied().unwrap_or(0) {
            done.insert(m.partition());
        }
        if let Ok((scene, frame, _)) = decode_result(&m)
            && let Some(i) = index.get(scene.as_str())
        {
            found.insert((*i, frame));
        }
    }
    Ok(found)
}

/// A consumer of every partition of the output topic, assigned at `from` (or, without it,
/// at each partition's high watermark), with the offsets it was assigned at and each
/// partition's current high watermark.
async fn open_results(
    args: &Args,
    from: Option<&[(i32, i64)]>,
) -> anyhow::Result<(StreamConsumer, PartitionOffsets, PartitionOffsets)> {
    let group = format!("crossview-loadtest-{}", std::process::id());
    let consumer: StreamConsumer = client(
        args,
        &[
            ("group.id", &group),
            ("enable.auto.commit", "false"),
            // Results should not wait for a full fetch window (some brokers hold every fetch
            // for fetch.wait.max.ms).
            ("fetch.wait.max.ms", "10"),
        ],
    )?
    .create()
    .context("kafka consumer")?;
    let topic = args.kafka_output_topic.clone();
    let from: Option<PartitionOffsets> = from.map(<[_]>::to_vec);
    tokio::task::spawn_blocking(move || {
        let timeout = Duration::from_secs(10);
        let partitions: Vec<i32> = match &from {
            Some(from) => from.iter().map(|(p, _)| *p).collect(),
            None => {
                let md = consumer
                    .fetch_metadata(Some(&topic), timeout)
                    .with_context(|| format!("kafka metadata of '{topic}'"))?;
                md.topics()
                    .iter()
                    .filter(|t| t.name() == topic)
                    .flat_map(|t| t.partitions().iter().map(|p| p.id()))
                    .collect()
            }
        };
        if partitions.is_empty() {
            bail!("kafka: output topic '{topic}' has no partitions (does it exist?)");
        }
        let mut highs = Vec::new();
        for p in partitions {
            let (_, high) = consumer
                .fetch_watermarks(&topic, p, timeout)
                .with_context(|| format!("kafka watermarks of {topic}/{p}"))?;
            highs.push((p, high));
        }
        let start = from.unwrap_or_else(|| highs.clone());
        let mut tpl = TopicPartitionList::new();
        for (p, o) in &start {
            tpl.add_partition_offset(&topic, *p, Offset::Offset(*o))?;
        }
        consumer.assign(&tpl).context("kafka assign")?;
        Ok((consumer, start, highs))
    })
    .await
    .context("kafka setup task")?
}

#[cfg(test)]
mod tests {
    use super::*;
    use rdkafka::message::OwnedMessage;

    fn message(payload: Vec<u8>, content_type: Option<&str>) -> OwnedMessage {
        let headers = content_type.map(|ct| {
            OwnedHeaders::new().insert(Header {
                key: "content-type",
                value: Some(ct),
            })
        });
        OwnedMessage::new(
            Some(payload),
            Some(b"lab".to_vec()),
            "results".into(),
            rdkafka::Timestamp::NotAvailable,
            0,
            0,
            headers,
        )
    }

    #[test]
    fn results_decode_as_json_or_protobuf() {
        let json = br#"{"scene":"lab","frame_id":4,"complete":true,"identities":[]}"#;
        let m = message(json.to_vec(), Some("application/json"));
        assert_eq!(decode_result(&m).unwrap(), ("lab".into(), 4, true));
        let m = message(json.to_vec(), None);
        assert_eq!(decode_result(&m).unwrap().1, 4);
        let pb = pb::FrameResult {
            scene: "lab".into(),
            frame_id: 9,
            complete: false,
            ..Default::default()
        };
        let m = message(pb.encode_to_vec(), Some("application/x-protobuf"));
        assert_eq!(decode_result(&m).unwrap(), ("lab".into(), 9, false));
        let m = message(b"\xff\x01".to_vec(), Some("application/x-protobuf"));
        assert!(decode_result(&m).is_err());
        let m = message(b"{}".to_vec(), None);
        assert!(decode_result(&m).is_err());
    }
}

//! Settings of Kafka mode and the librdkafka client configurations built from them.
use rdkafka::config::ClientConfig;

use crate::error::{Error, Result};
pub use crossview_api::format::ValueFormat;

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
                format!("'{}' is not KEY=VALUE", crate::echo::truncate_echo(s)),
            )),
        }
    }

    fn client(&self) -> ClientConfig {
        let mut c = ClientConfig::new();
        c.set("bootstrap.servers", &self.brokers);
        c
    }

    /// The consumer's configuration: manual commits, no auto offset store, the rebalance
    /// defaults of [`CONSUMER_DEFAULTS`], then the user's properties (which win), then the
    /// statistics interval (always [`STATISTICS_INTERVAL_MS`]).
    pub(super) fn consumer_config(&self) -> ClientConfig {
        let mut c = self.client();
        c.set("group.id", &self.group)
            .set("enable.auto.commit", "false")
            .set("enable.auto.offset.store", "false")
            .set("auto.offset.reset", "earliest")
            .set("enable.partition.eof", "false");
        for (k, v) in CONSUMER_DEFAULTS {
            c.set(*k, *v);
        }
        let mut c = self.with_properties(c, true);
        // Not the user's to change: the statistics' high watermarks are how a replica knows
        // it has read what the broker holds (sync timeouts are held until then).
        c.set("statistics.interval.ms", STATISTICS_INTERVAL_MS.to_string());
        c
    }

    /// The producer's configuration: idempotent, a 2 ms linger, then the user's properties.
    pub(super) fn producer_config(&self) -> ClientConfig {
        let mut c = self.client();
        c.set("linger.ms", "2").set("enable.idempotence", "true");
        self.with_properties(c, false)
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

/// How often the consumer reports its statistics (librdkafka `statistics.interval.ms`): the
/// lag gauge, and each owned partition's high watermark, which tells whether records wait
/// unread. Well below the default `--sync-timeout` (200 ms), so a replica that falls behind
/// holds its timeouts before they expire.
pub const STATISTICS_INTERVAL_MS: u64 = 100;

/// Consumer defaults (docs/kafka.md, "Rebalances"): for a takeover in seconds, incremental
/// rebalancing (only the partitions that move stop), a dead replica noticed after 6 s (the
/// smallest session Apache Kafka brokers accept by default), heartbeats every 500 ms. Static
/// membership (`group.instance.id`) is left to `--kafka-property`: the pinned test broker
/// never hands a dead static member's partitions over.
pub const CONSUMER_DEFAULTS: &[(&str, &str)] = &[
    ("partition.assignment.strategy", "cooperative-sticky"),
    ("session.timeout.ms", "6000"),
    ("heartbeat.interval.ms", "500"),
    // A fetch returns after at most 10 ms without new records (librdkafka's default is
    // 500 ms). Brokers that hold every fetch for the full wait (tansu 0.6.0) otherwise deliver
    // a frame's cameras in bursts 500 ms apart, beyond the 200 ms sync timeout: the frame is
    // published partial and its last cameras are refused as late.
    ("fetch.wait.max.ms", "10"),
];

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

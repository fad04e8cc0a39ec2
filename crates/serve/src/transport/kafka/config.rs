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
    /// The group's rebalance protocol (`--kafka-group-protocol`).
    pub group_protocol: GroupProtocol,
    /// Static membership (librdkafka `group.instance.id`, `--kafka-instance-id`): a replica
    /// that comes back under the same id within the session takes its partitions back
    /// without a rebalance. Unique per replica (a StatefulSet's pod name).
    pub instance_id: Option<String>,
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
    /// Where a batch without a capture time takes one from (`--kafka-timestamp`).
    pub timestamps: TimestampSource,
}

/// Where a record's batch takes its capture time from (`--kafka-timestamp`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum TimestampSource {
    /// From the value only (`time` in the batch); a batch without one is grouped by its
    /// frame id.
    #[default]
    Value,
    /// A batch without `time` takes its record's timestamp (milliseconds: the producer's
    /// create time, e.g. a camera's capture time, or the broker's log-append time).
    Record,
}

/// `value` or `record`, any case: the spelling of `--kafka-timestamp`.
impl std::str::FromStr for TimestampSource {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "value" => Ok(TimestampSource::Value),
            "record" => Ok(TimestampSource::Record),
            _ => {
                let shown: String = s.chars().take(64).collect();
                Err(format!("'{shown}' is not value or record"))
            }
        }
    }
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
            .field("group_protocol", &self.group_protocol)
            .field("instance_id", &self.instance_id)
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
            group_protocol: GroupProtocol::default(),
            instance_id: None,
            producer_id: default_producer_id(),
            dead_letter_topic: None,
            properties: Vec::new(),
            max_in_flight: 256,
            input_format: ValueFormat::Json,
            output_format: ValueFormat::Json,
            timestamps: TimestampSource::Value,
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

    /// The consumer's configuration: manual commits, no auto offset store, the group
    /// protocol with its defaults ([`CONSUMER_DEFAULTS`], and for the classic protocol
    /// [`CLASSIC_DEFAULTS`]), the static member id, then the user's properties (which win),
    /// then the statistics interval (always [`STATISTICS_INTERVAL_MS`]).
    pub(super) fn consumer_config(&self) -> ClientConfig {
        let mut c = self.client();
        c.set("group.id", &self.group)
            .set("group.protocol", self.group_protocol.as_str())
            .set("enable.auto.commit", "false")
            .set("enable.auto.offset.store", "false")
            .set("auto.offset.reset", "earliest")
            .set("enable.partition.eof", "false");
        for (k, v) in CONSUMER_DEFAULTS {
            c.set(*k, *v);
        }
        if self.group_protocol == GroupProtocol::Classic {
            for (k, v) in CLASSIC_DEFAULTS {
                c.set(*k, *v);
            }
        }
        if let Some(id) = &self.instance_id {
            c.set("group.instance.id", id);
        }
        let mut c = self.with_properties(c, true);
        // Not the user's to change: the statistics' high watermarks are how a replica knows
        // it has read what the broker holds (a quiet partition's stream time runs on only
        // then).
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
/// unread. Well below the default `--sync-timeout` (200 ms): a caught-up, quiet partition's
/// stream time runs on by these reports, so a frame of a quiet scene leaves at most one
/// interval after its timeout.
pub const STATISTICS_INTERVAL_MS: u64 = 100;

/// Consumer defaults of both group protocols.
pub const CONSUMER_DEFAULTS: &[(&str, &str)] = &[
    // A fetch returns after at most 10 ms without new records (librdkafka's default is
    // 500 ms): a frame's cameras are delivered as they are written, not in bursts.
    ("fetch.wait.max.ms", "10"),
];

/// Defaults of the classic protocol (docs/kafka.md, "Rebalances"): incremental rebalancing
/// (only the partitions that move stop), a dead replica noticed after 6 s (the smallest session
/// Apache Kafka brokers accept by default), heartbeats every 500 ms. With the `consumer`
/// protocol these are the broker's and the group's settings, and librdkafka refuses them.
pub const CLASSIC_DEFAULTS: &[(&str, &str)] = &[
    ("partition.assignment.strategy", "cooperative-sticky"),
    ("session.timeout.ms", "6000"),
    ("heartbeat.interval.ms", "500"),
];

/// A consumer group's rebalance protocol (librdkafka `group.protocol`). The default is
/// `consumer`, chosen by measurement on Apache Kafka 4.1.1 (docs/kafka.md, "Rebalances"): a
/// rolling restart stalls no scene more than 0.65 s with it, 0.94–1.64 s with `classic`,
/// whose rebalance rounds stop the fetchers of the partitions a replica keeps.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum GroupProtocol {
    /// The classic protocol: the members assign (cooperative-sticky here), session and
    /// heartbeat set by each client ([`CLASSIC_DEFAULTS`]). For brokers without KIP-848.
    Classic,
    /// KIP-848: the broker assigns incrementally and sticky; session and heartbeat are the
    /// broker's (`group.consumer.*`) or the group's settings. Apache Kafka 4.0 and later.
    #[default]
    Consumer,
}

impl GroupProtocol {
    /// The librdkafka `group.protocol` value.
    pub fn as_str(self) -> &'static str {
        match self {
            GroupProtocol::Classic => "classic",
            GroupProtocol::Consumer => "consumer",
        }
    }
}

/// `classic` or `consumer`, any case: the spelling of `--kafka-group-protocol`.
impl std::str::FromStr for GroupProtocol {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "classic" => Ok(GroupProtocol::Classic),
            "consumer" => Ok(GroupProtocol::Consumer),
            _ => {
                let shown: String = s.chars().take(64).collect();
                Err(format!("'{shown}' is not classic or consumer"))
            }
        }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The classic protocol carries the client-side session and assignment; the `consumer`
    /// protocol none of them (librdkafka refuses them there); a static id goes to both.
    #[test]
    fn each_group_protocol_gets_its_own_settings() {
        let mut k = KafkaConfig::new("b:9092", "in", "out", "g");
        assert_eq!(k.group_protocol, GroupProtocol::Consumer, "the default");
        k.group_protocol = GroupProtocol::Classic;
        let c = k.consumer_config();
        assert_eq!(c.get("group.protocol"), Some("classic"));
        assert_eq!(c.get("session.timeout.ms"), Some("6000"));
        assert_eq!(
            c.get("partition.assignment.strategy"),
            Some("cooperative-sticky")
        );
        assert_eq!(c.get("group.instance.id"), None);
        k.group_protocol = "Consumer".parse().unwrap();
        k.instance_id = Some("crossview-0".into());
        let c = k.consumer_config();
        assert_eq!(c.get("group.protocol"), Some("consumer"));
        for key in [
            "session.timeout.ms",
            "heartbeat.interval.ms",
            "partition.assignment.strategy",
        ] {
            assert_eq!(c.get(key), None, "{key}");
        }
        assert_eq!(c.get("group.instance.id"), Some("crossview-0"));
        assert_eq!(c.get("fetch.wait.max.ms"), Some("10"));
        assert!("eager".parse::<GroupProtocol>().is_err());
        // The producer knows nothing of groups.
        assert_eq!(k.producer_config().get("group.instance.id"), None);
    }
}

//! `crossview serve`: flags (with `CROSSVIEW_*` environment fallbacks) → [`ServeConfig`], then [`crossview_serve::run`] until Ctrl-C / SIGTERM.
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use crossview_core::memory::MemoryConfig;
use crossview_core::tracking::TrackerConfig;
use crossview_serve::config::ClockWatchConfig;
use crossview_serve::config::SceneDecl;
use crossview_serve::{
    ConnectionLimits, GroupProtocol, KafkaConfig, Limits, ModelSpec, RecordConfig, ServeConfig,
    TlsConfig, ValueFormat,
};

/// Serve association over gRPC and HTTP JSON on one port.
#[derive(Debug, Args)]
pub struct ServeArgs {
    /// A model to serve, `[NAME=]path.onnx` (repeatable; the scene name defaults to the file
    /// stem; cameras come from the model metadata). The file is re-read on SIGHUP (and
    /// `POST /v1/admin/reload`) and swapped in live when it changed; for a scene declared with
    /// --scene it may not exist yet.
    #[arg(
        long = "model",
        env = "CROSSVIEW_MODELS",
        value_delimiter = ',',
        required_unless_present = "scenes"
    )]
    pub models: Vec<String>,
    /// A scene declared by its cameras before any model exists: `NAME=cam1:1920x1080,cam2:...`
    /// or a JSON file holding a recording's scene header (repeatable; `;` separates several in
    /// the environment). A camera's clock offset follows its size: `@+2` frames, or `@+120ms`
    /// for a camera that sends capture times; the scene's frame rate, which capture times
    /// need, ends the list: `NAME=a:1920x1080,b:1920x1080@10fps` (default: the model's
    /// training rate). Its batches are accepted (and recorded) and its results say
    /// `"status": "no_model"` until a model is loaded.
    #[arg(long = "scene", env = "CROSSVIEW_SCENES", value_delimiter = ';')]
    pub scenes: Vec<String>,
    /// Address to listen on (gRPC and HTTP share it).
    #[arg(long, env = "CROSSVIEW_LISTEN", default_value = "0.0.0.0:8080")]
    pub listen: String,
    /// How long a frame waits for missing cameras before it is emitted as partial
    /// (e.g. `200ms`, `1.5s`; a bare number is milliseconds).
    #[arg(long, env = "CROSSVIEW_SYNC_TIMEOUT", default_value = "200ms", value_parser = parse_duration)]
    pub sync_timeout: Duration,
    /// Pending frames per scene beyond which the oldest is emitted as partial.
    #[arg(long, env = "CROSSVIEW_MAX_PENDING_FRAMES", default_value_t = 64)]
    pub max_pending_frames: usize,
    /// How far a batch's capture time may fall from its frame's tick, after the camera's clock
    /// offset (e.g. `20ms`); further is refused. Default: half the scene's period (every time
    /// has a frame).
    #[arg(long, env = "CROSSVIEW_TIME_TOLERANCE", value_parser = parse_duration)]
    pub time_tolerance: Option<Duration>,
    /// Accepted bearer token (repeatable); with none (and no --api-key-file) auth is off, and
    /// then the server listens beyond loopback only with --allow-unauthenticated. A blank
    /// key, or a key source that yields no key, is a start-up error (never "auth off").
    #[arg(
        long = "api-key",
        env = "CROSSVIEW_API_KEYS",
        value_delimiter = ',',
        hide_env_values = true
    )]
    pub api_keys: Vec<String>,
    /// File with one accepted bearer token per line (blank lines and `#` comments ignored);
    /// a file holding no key is a start-up error.
    #[arg(long, env = "CROSSVIEW_API_KEY_FILE")]
    pub api_key_file: Option<PathBuf>,
    /// Serve without an API key on an address beyond loopback. Without this flag such a
    /// server refuses to start: anyone who reaches the port could push, read and reload.
    #[arg(long, env = "CROSSVIEW_ALLOW_UNAUTHENTICATED")]
    pub allow_unauthenticated: bool,
    /// TLS certificate chain (PEM); needs --tls-key.
    #[arg(long, env = "CROSSVIEW_TLS_CERT", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM); needs --tls-cert.
    #[arg(long, env = "CROSSVIEW_TLS_KEY", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    /// Largest HTTP body / gRPC message in bytes.
    #[arg(long, env = "CROSSVIEW_MAX_REQUEST_BYTES", default_value_t = Limits::default().max_request_bytes)]
    pub max_request_bytes: usize,
    /// Most cameras a served model may have.
    #[arg(long, env = "CROSSVIEW_MAX_CAMERAS", default_value_t = Limits::default().max_cameras)]
    pub max_cameras: usize,
    /// Most detections in one camera batch.
    #[arg(long, env = "CROSSVIEW_MAX_DETECTIONS", default_value_t = Limits::default().max_detections)]
    pub max_detections: usize,
    /// Longest appearance vector.
    #[arg(long, env = "CROSSVIEW_MAX_APPEARANCE_LEN", default_value_t = Limits::default().max_appearance_len)]
    pub max_appearance_len: usize,
    /// Frames queued for inference per scene before work is shed (RESOURCE_EXHAUSTED / 429).
    #[arg(long, env = "CROSSVIEW_QUEUE_CAPACITY", default_value_t = Limits::default().queue_capacity)]
    pub queue_capacity: usize,
    /// Frame results buffered per subscriber before a slow subscriber is dropped.
    #[arg(long, env = "CROSSVIEW_SUBSCRIBER_BUFFER", default_value_t = Limits::default().subscriber_buffer)]
    pub subscriber_buffer: usize,
    /// Most association cost units one frame may reach (cost = Σ over camera pairs of
    /// n_a·n_b·min(n_a, n_b); about 2 ns each): the batch or unary request that would exceed
    /// it is refused (422 / INVALID_ARGUMENT).
    #[arg(long, env = "CROSSVIEW_MAX_FRAME_COST", default_value_t = Limits::default().max_frame_cost)]
    pub max_frame_cost: u64,
    /// The queue budget per scene: while a scene's oldest queued frame has waited longer, new
    /// frames are shed whole (their batches refused with 429 / RESOURCE_EXHAUSTED and a
    /// retry-after, the frame published with status `shed`); a frame that waited longer anyway
    /// is shed from the queue. Bounds the latency of associated frames; Kafka mode pauses
    /// instead of shedding.
    #[arg(long, env = "CROSSVIEW_MAX_QUEUE_DELAY", alias = "frame-deadline", default_value = "500ms", value_parser = parse_duration)]
    pub max_queue_delay: Duration,
    /// Threads that run every scene's inference, scenes taking turns (0: one per core).
    #[arg(long, env = "CROSSVIEW_INFERENCE_THREADS", default_value_t = 0)]
    pub inference_threads: usize,
    /// Frame-id window: batches more than this many ids from the scene's current frame ids
    /// are refused as out of range (until a majority of cameras move there: a restart).
    #[arg(long, env = "CROSSVIEW_FRAME_WINDOW", default_value_t = Limits::default().frame_window)]
    pub frame_window: u64,
    /// A JSON Lines body stops early once more than this many lines were rejected and
    /// rejected lines outnumber accepted ones.
    #[arg(long, env = "CROSSVIEW_MAX_REJECTED_LINES", default_value_t = Limits::default().max_rejected_lines)]
    pub max_rejected_lines: usize,
    /// Live clock watch: each camera's clock offset estimated from the last this many frames
    /// (`GET /v1/scenes/{scene}`, `crossview_camera_offset_frames`, a warning when a camera is
    /// out of sync); 0 turns it off, at most 10000.
    #[arg(long, env = "CROSSVIEW_CLOCK_WATCH_WINDOW", default_value_t = ClockWatchConfig::default().window,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=10_000))]
    pub clock_watch_window: usize,
    /// At most one clock estimate per this interval (bounds the watch's CPU share).
    #[arg(long, env = "CROSSVIEW_CLOCK_WATCH_INTERVAL", default_value = "10s", value_parser = parse_duration)]
    pub clock_watch_interval: Duration,
    /// Largest clock offset the watch searches, in frame steps either way (1..=100).
    #[arg(long, env = "CROSSVIEW_CLOCK_WATCH_MAX_OFFSET", default_value_t = ClockWatchConfig::default().max_offset,
          value_parser = clap::value_parser!(u32).range(1..=100))]
    pub clock_watch_max_offset: u32,
    /// Correct cameras' clock offsets from the live estimate: once two estimates over full,
    /// successive windows agree that a camera is a whole number of frames off, its batches
    /// go to the frame they belong to (every change logged and counted).
    #[arg(long, env = "CROSSVIEW_AUTO_ALIGN")]
    pub auto_align: bool,
    /// Leave a camera that no longer fits the model (it moved, was re-aimed or zoomed: the
    /// clock watch's fit says `does_not_fit`) out of association until it fits again: its
    /// boxes come back as identities of their own and the result names it in
    /// `fenced_cameras`, so the other cameras' identities stay right (docs/camera-fit.md).
    #[arg(long, env = "CROSSVIEW_FENCE_MOVED_CAMERAS", default_value_t = ClockWatchConfig::default().fence,
          action = clap::ArgAction::Set, value_name = "true|false")]
    pub fence_moved_cameras: bool,
    /// Most open connections; at the cap the longest-idle one is closed for a new one, or the
    /// new one is refused when none is idle. Keep it below `ulimit -n`.
    #[arg(long, env = "CROSSVIEW_MAX_CONNECTIONS", default_value_t = ConnectionLimits::default().max_connections)]
    pub max_connections: usize,
    /// Time for a TLS handshake and for an HTTP/1 request head.
    #[arg(long, env = "CROSSVIEW_HEADER_READ_TIMEOUT", default_value = "10s", value_parser = parse_duration)]
    pub header_read_timeout: Duration,
    /// A connection with no request in flight for this long is closed.
    #[arg(long, env = "CROSSVIEW_IDLE_TIMEOUT", default_value = "60s", value_parser = parse_duration)]
    pub idle_timeout: Duration,
    /// Time for a whole HTTP request body, or for one gRPC message once it has started.
    #[arg(long, env = "CROSSVIEW_BODY_TIMEOUT", default_value = "30s", value_parser = parse_duration)]
    pub body_timeout: Duration,
    /// Most concurrent HTTP/2 streams per connection.
    #[arg(long, env = "CROSSVIEW_HTTP2_MAX_STREAMS", default_value_t = ConnectionLimits::default().http2_max_streams)]
    pub http2_max_streams: u32,
    /// HTTP/2 keep-alive ping interval (and the time a ping may go unanswered).
    #[arg(long, env = "CROSSVIEW_HTTP2_KEEPALIVE", default_value = "30s", value_parser = parse_duration)]
    pub http2_keepalive: Duration,
    /// A result subscriber that has not taken a waiting result for this long is disconnected.
    #[arg(long, env = "CROSSVIEW_SUBSCRIBER_STALL_TIMEOUT", default_value = "30s", value_parser = parse_duration)]
    pub subscriber_stall_timeout: Duration,
    /// Memory (bytes) all result subscribers together may cost; each is charged a fixed
    /// worst case (160 KiB). At the budget a new subscription displaces the subscriber
    /// furthest behind, or is refused (429 / RESOURCE_EXHAUSTED) when all keep up.
    #[arg(long, env = "CROSSVIEW_SUBSCRIBER_MEMORY", default_value_t = ConnectionLimits::default().subscriber_memory)]
    pub subscriber_memory: usize,
    /// Most result subscriptions (SSE, gRPC Subscribe / Stream) one connection may hold.
    #[arg(long, env = "CROSSVIEW_MAX_SUBSCRIPTIONS_PER_CONNECTION", default_value_t = ConnectionLimits::default().max_subscriptions_per_connection)]
    pub max_subscriptions_per_connection: usize,
    /// How long shutdown waits for open connections after flushing.
    #[arg(long, env = "CROSSVIEW_SHUTDOWN_GRACE", default_value = "10s", value_parser = parse_duration)]
    pub shutdown_grace: Duration,
    /// Frames a person's track survives unseen before it is retired (counts frames, not
    /// time: at 10 frames/s, 5 is half a second; the default suits WILDTRACK's 2 frames/s).
    #[arg(long, env = "CROSSVIEW_TRACK_MAX_AGE", default_value_t = TrackerConfig::default().max_age)]
    pub track_max_age: u32,
    /// Tracker gate, relative to the frame's median distance between identities.
    #[arg(long, env = "CROSSVIEW_TRACK_GATE", default_value_t = TrackerConfig::default().gate)]
    pub track_gate: f32,
    /// Turn tracking off: streamed identities carry no `track_id` (saves the tracker's cost,
    /// ~0.2 ms per crowded frame).
    #[arg(long, env = "CROSSVIEW_NO_TRACKING")]
    pub no_tracking: bool,
    /// Identities with memory: the past frames' share of each pair's evidence, carried along
    /// each camera's tracks (0: every frame alone; docs/method.md, "Identities with memory").
    /// Streamed frames only: a unary associate request is one frame alone.
    #[arg(long, env = "CROSSVIEW_MEMORY", default_value_t = MemoryConfig::default().carry)]
    pub memory: f32,
    /// Record every accepted batch (SPEC §7 JSON Lines) under this directory, one
    /// sub-directory per scene of rotating files (docs/serve.md, "Recording").
    #[arg(long, env = "CROSSVIEW_RECORD")]
    pub record: Option<PathBuf>,
    /// A recording file is rotated before it would grow past this many bytes.
    #[arg(long, env = "CROSSVIEW_RECORD_MAX_FILE_BYTES", default_value_t = RecordConfig::new("").max_file_bytes)]
    pub record_max_file_bytes: u64,
    /// A recording file is rotated when a batch arrives once it is this old (e.g. `10m`).
    #[arg(long, env = "CROSSVIEW_RECORD_MAX_FILE_AGE", default_value = "10m", value_parser = parse_duration)]
    pub record_max_file_age: Duration,
    /// All recording files under --record together stay within this many bytes; the oldest
    /// files are removed first.
    #[arg(long, env = "CROSSVIEW_RECORD_MAX_BYTES", default_value_t = RecordConfig::new("").max_bytes)]
    pub record_max_bytes: u64,
    /// Memory (estimated bytes) of accepted batches waiting to be written; beyond it a batch
    /// is not recorded and counted (`crossview_record_dropped_total`).
    #[arg(long, env = "CROSSVIEW_RECORD_QUEUE_BYTES", default_value_t = RecordConfig::new("").queue_bytes)]
    pub record_queue_bytes: usize,
    /// Healing (`--auto-retrain`).
    #[command(flatten)]
    pub retrain: super::retrain::RetrainArgs,
    /// Kafka mode (docs/kafka.md); boxed, as these flags are many.
    #[command(flatten)]
    pub kafka: Box<KafkaArgs>,
}

/// `crossview serve`'s Kafka-mode flags.
#[derive(Debug, Args)]
pub struct KafkaArgs {
    /// Kafka mode: bootstrap brokers `host:port[,...]`. With it the server also consumes
    /// batches (key = scene, value = a batch line as JSON) from --kafka-input-topic and
    /// produces every frame result to --kafka-output-topic (docs/kafka.md).
    #[arg(long, env = "CROSSVIEW_KAFKA_BROKERS", requires_all = ["kafka_input_topic", "kafka_output_topic", "kafka_group"])]
    pub kafka_brokers: Option<String>,
    /// Kafka input topic (camera batches, key = scene).
    #[arg(long, env = "CROSSVIEW_KAFKA_INPUT_TOPIC")]
    pub kafka_input_topic: Option<String>,
    /// Kafka output topic (frame results, key = scene).
    #[arg(long, env = "CROSSVIEW_KAFKA_OUTPUT_TOPIC")]
    pub kafka_output_topic: Option<String>,
    /// Kafka consumer group the replicas share (each owns whole scenes).
    #[arg(long, env = "CROSSVIEW_KAFKA_GROUP")]
    pub kafka_group: Option<String>,
    /// The group's rebalance protocol: `consumer` (KIP-848, Apache Kafka 4.0 and later: the
    /// broker assigns; session and heartbeat are the broker's or the group's settings) or
    /// `classic` (any broker: members assign, cooperative-sticky; session 6 s and heartbeat
    /// 500 ms set here). docs/kafka.md "Rebalances".
    #[arg(
        long,
        env = "CROSSVIEW_KAFKA_GROUP_PROTOCOL",
        default_value = "consumer"
    )]
    pub kafka_group_protocol: GroupProtocol,
    /// Static membership (`group.instance.id`): a name unique to this replica that stays the
    /// same across its restarts (a StatefulSet's pod name); a replica back within the session
    /// takes its scenes back without a rebalance.
    #[arg(long, env = "CROSSVIEW_KAFKA_INSTANCE_ID")]
    pub kafka_instance_id: Option<String>,
    /// This replica's `producer.id` in its results (default: host name and process id).
    #[arg(long, env = "CROSSVIEW_KAFKA_PRODUCER_ID")]
    pub kafka_producer_id: Option<String>,
    /// Copy malformed and rejected input records here (with a `crossview-error` header);
    /// without it they are counted (`crossview_kafka_records_total`) and skipped.
    #[arg(long, env = "CROSSVIEW_KAFKA_DEAD_LETTER_TOPIC")]
    pub kafka_dead_letter_topic: Option<String>,
    /// librdkafka `security.protocol` (plaintext, ssl, sasl_plaintext, sasl_ssl).
    #[arg(long, env = "CROSSVIEW_KAFKA_SECURITY_PROTOCOL")]
    pub kafka_security_protocol: Option<String>,
    /// librdkafka `sasl.mechanism` (PLAIN, SCRAM-SHA-256, SCRAM-SHA-512).
    #[arg(long, env = "CROSSVIEW_KAFKA_SASL_MECHANISM")]
    pub kafka_sasl_mechanism: Option<String>,
    /// librdkafka `sasl.username`.
    #[arg(long, env = "CROSSVIEW_KAFKA_SASL_USERNAME")]
    pub kafka_sasl_username: Option<String>,
    /// librdkafka `sasl.password` (prefer the environment variable).
    #[arg(long, env = "CROSSVIEW_KAFKA_SASL_PASSWORD", hide_env_values = true)]
    pub kafka_sasl_password: Option<String>,
    /// librdkafka `ssl.ca.location`: CA certificates (PEM) to verify the brokers with.
    #[arg(long, env = "CROSSVIEW_KAFKA_SSL_CA")]
    pub kafka_ssl_ca: Option<PathBuf>,
    /// Any further librdkafka property, `KEY=VALUE` (repeatable; `,` separates several in
    /// the environment), for consumer and producer; overrides the flags above.
    #[arg(
        long = "kafka-property",
        env = "CROSSVIEW_KAFKA_PROPERTIES",
        value_delimiter = ',',
        hide_env_values = true
    )]
    pub kafka_properties: Vec<String>,
    /// Encoding of input values without a `content-type` header: `json` (a batch line) or
    /// `protobuf` (`crossview.v1.Batch`).
    #[arg(long, env = "CROSSVIEW_KAFKA_INPUT_FORMAT", default_value = "json")]
    pub kafka_input_format: ValueFormat,
    /// Encoding of the results: `json` (`FrameResult` plus `producer`) or `protobuf`
    /// (`crossview.v1.FrameResult`; producer in the headers).
    #[arg(long, env = "CROSSVIEW_KAFKA_OUTPUT_FORMAT", default_value = "json")]
    pub kafka_output_format: ValueFormat,
    /// Where a batch without a `time` takes its capture time from: `value` (nowhere: it is
    /// grouped by its frame id) or `record` (the record's timestamp, ms; the scene must
    /// declare its frame rate).
    #[arg(long, env = "CROSSVIEW_KAFKA_TIMESTAMP", default_value = "value")]
    pub kafka_timestamp: crossview_serve::TimestampSource,
}

impl KafkaArgs {
    /// Kafka mode's settings, when --kafka-brokers is given.
    pub fn to_config(&self) -> anyhow::Result<Option<KafkaConfig>> {
        let Some(brokers) = &self.kafka_brokers else {
            return Ok(None);
        };
        let need = |v: &Option<String>, flag: &str| {
            v.clone()
                .with_context(|| format!("--kafka-brokers needs {flag}"))
        };
        let mut k = KafkaConfig::new(
            brokers,
            &need(&self.kafka_input_topic, "--kafka-input-topic")?,
            &need(&self.kafka_output_topic, "--kafka-output-topic")?,
            &need(&self.kafka_group, "--kafka-group")?,
        );
        if let Some(id) = &self.kafka_producer_id {
            k.producer_id = id.clone();
        }
        k.dead_letter_topic = self.kafka_dead_letter_topic.clone();
        k.group_protocol = self.kafka_group_protocol;
        k.instance_id = self
            .kafka_instance_id
            .clone()
            .filter(|i| !i.trim().is_empty());
        k.input_format = self.kafka_input_format;
        k.output_format = self.kafka_output_format;
        k.timestamps = self.kafka_timestamp;
        let named = [
            ("security.protocol", &self.kafka_security_protocol),
            ("sasl.mechanism", &self.kafka_sasl_mechanism),
            ("sasl.username", &self.kafka_sasl_username),
            ("sasl.password", &self.kafka_sasl_password),
        ];
        for (key, v) in named {
            if let Some(v) = v {
                k.properties.push((key.to_string(), v.clone()));
            }
        }
        if let Some(ca) = &self.kafka_ssl_ca {
            k.properties
                .push(("ssl.ca.location".into(), ca.display().to_string()));
        }
        for p in &self.kafka_properties {
            k.properties.push(KafkaConfig::parse_property(p)?);
        }
        Ok(Some(k))
    }
}

pub use crossview_api::duration::parse_duration;

/// Longest API key file read (a file of keys is a few KiB).
const MAX_KEY_FILE_BYTES: u64 = 1 << 20;

impl ServeArgs {
    /// The accepted API keys from --api-key / `CROSSVIEW_API_KEYS` and --api-key-file. Fails
    /// closed: a blank key, or a source that was given but yields no key (an empty variable,
    /// `,`, a file of comments only), is an error rather than authentication turned off.
    fn api_keys(&self) -> anyhow::Result<Vec<String>> {
        let mut keys = Vec::new();
        for (i, k) in self.api_keys.iter().enumerate() {
            anyhow::ensure!(
                !k.trim().is_empty(),
                "--api-key / CROSSVIEW_API_KEYS: key {} of {} is blank; refusing to start with authentication off",
                i + 1,
                self.api_keys.len()
            );
            keys.push(k.trim().to_string());
        }
        // clap ignores an empty variable: a variable that is set but holds no key is refused.
        if self.api_keys.is_empty() && std::env::var_os("CROSSVIEW_API_KEYS").is_some() {
            anyhow::bail!(
                "CROSSVIEW_API_KEYS is set but holds no key; refusing to start with authentication off (unset it to serve without keys)"
            );
        }
        if let Some(p) = &self.api_key_file {
            use std::io::Read;
            let mut text = String::new();
            std::fs::File::open(p)
                .and_then(|f| f.take(MAX_KEY_FILE_BYTES).read_to_string(&mut text))
                .with_context(|| format!("reading API keys from {}", p.display()))?;
            let before = keys.len();
            keys.extend(
                text.lines()
                    .map(str::trim)
                    .filter(|l| !l.is_empty() && !l.starts_with('#'))
                    .map(String::from),
            );
            anyhow::ensure!(
                keys.len() > before,
                "{} holds no API key (only blank lines and comments); refusing to start with authentication off",
                p.display()
            );
        }
        Ok(keys)
    }

    /// The library configuration these flags describe.
    pub fn to_config(&self) -> anyhow::Result<ServeConfig> {
        anyhow::ensure!(
            !(self.auto_align && self.clock_watch_window == 0),
            "--auto-align needs the clock watch: --clock-watch-window must be above 0"
        );
        let models = self
            .models
            .iter()
            .map(|m| ModelSpec::parse(m))
            .collect::<crossview_serve::Result<Vec<_>>>()?;
        let scenes = self
            .scenes
            .iter()
            .map(|s| SceneDecl::parse(s))
            .collect::<crossview_serve::Result<Vec<_>>>()?;
        let api_keys = self.api_keys()?;
        let tls = match (&self.tls_cert, &self.tls_key) {
            (Some(cert), Some(key)) => Some(TlsConfig {
                cert: cert.clone(),
                key: key.clone(),
            }),
            _ => None,
        };
        Ok(ServeConfig {
            models,
            scenes,
            reload_on_sighup: true,
            sync_timeout: self.sync_timeout,
            max_pending_frames: self.max_pending_frames,
            api_keys,
            allow_unauthenticated: self.allow_unauthenticated,
            tls,
            limits: Limits {
                max_request_bytes: self.max_request_bytes,
                max_cameras: self.max_cameras,
                max_detections: self.max_detections,
                max_appearance_len: self.max_appearance_len,
                queue_capacity: self.queue_capacity,
                subscriber_buffer: self.subscriber_buffer,
                max_frame_cost: self.max_frame_cost,
                max_queue_delay: self.max_queue_delay,
                frame_window: self.frame_window,
                max_rejected_lines: self.max_rejected_lines,
                clock_watch: ClockWatchConfig {
                    window: self.clock_watch_window,
                    interval: self.clock_watch_interval,
                    max_offset: self.clock_watch_max_offset,
                    auto_align: self.auto_align,
                    fence: self.fence_moved_cameras,
                },
            },
            connections: ConnectionLimits {
                max_connections: self.max_connections,
                header_read_timeout: self.header_read_timeout,
                idle_timeout: self.idle_timeout,
                body_timeout: self.body_timeout,
                http2_max_streams: self.http2_max_streams,
                http2_keepalive: self.http2_keepalive,
                subscriber_stall_timeout: self.subscriber_stall_timeout,
                subscriber_memory: self.subscriber_memory,
                max_subscriptions_per_connection: self.max_subscriptions_per_connection,
            },
            shutdown_grace: self.shutdown_grace,
            tracker: (!self.no_tracking).then(|| TrackerConfig {
                max_age: self.track_max_age,
                gate: self.track_gate,
                ..TrackerConfig::default()
            }),
            memory: MemoryConfig::with_carry(self.memory)?,
            record: self.record.as_ref().map(|dir| RecordConfig {
                dir: dir.clone(),
                max_file_bytes: self.record_max_file_bytes,
                max_file_age: self.record_max_file_age,
                max_bytes: self.record_max_bytes,
                queue_bytes: self.record_queue_bytes,
            }),
            heal: self.retrain.to_config(self.record.as_deref())?,
            kafka: self.kafka.to_config()?,
            inference_threads: self.inference_threads,
            time_tolerance: self.time_tolerance,
        })
    }
}

/// Runs the server until Ctrl-C or SIGTERM, then shuts down gracefully. Logs go through the
/// global `--log-format text|json` subscriber.
pub fn run(args: ServeArgs) -> anyhow::Result<()> {
    let config = args.to_config()?;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    rt.block_on(async {
        // SIGHUP's default action ends the process: take it over before the port is bound,
        // so a reload asked for while the models load never kills the server (the library
        // listens for its own reloads from then on).
        #[cfg(unix)]
        let _early_hangup = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup())
            .context("listening for SIGHUP")?;
        let listener = tokio::net::TcpListener::bind(&args.listen)
            .await
            .with_context(|| format!("binding {}", args.listen))?;
        crossview_serve::run(config, listener, crossview_serve::shutdown_signal()).await?;
        anyhow::Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(clap::Parser)]
    struct Cmd {
        #[command(flatten)]
        args: ServeArgs,
    }

    fn parse(extra: &[&str]) -> Result<ServeArgs, clap::Error> {
        use clap::Parser;
        let base = ["serve", "--scene", "lab=a:640x480,b:640x480@+2"];
        Cmd::try_parse_from(base.iter().chain(extra)).map(|c| c.args)
    }

    #[test]
    fn clock_watch_flags() {
        let c = parse(&[]).unwrap().to_config().unwrap();
        assert_eq!(c.limits.clock_watch, ClockWatchConfig::default());
        assert_eq!(c.scenes[0].spec.cameras[1].offset, 2);
        let c = parse(&[
            "--auto-align",
            "--clock-watch-window",
            "120",
            "--clock-watch-interval",
            "2s",
        ])
        .unwrap()
        .to_config()
        .unwrap();
        let w = c.limits.clock_watch;
        assert!(w.auto_align);
        assert_eq!((w.window, w.interval), (120, Duration::from_secs(2)));
        let e = parse(&["--auto-align", "--clock-watch-window", "0"])
            .unwrap()
            .to_config()
            .unwrap_err();
        assert!(e.to_string().contains("--clock-watch-window"), "{e}");
        for bad in ["0", "101", "-1"] {
            assert!(parse(&["--clock-watch-max-offset", bad]).is_err(), "{bad}");
        }
        assert!(parse(&["--clock-watch-window", "10001"]).is_err());
        // Fencing: on by default, off on request, nothing else taken.
        assert!(c.limits.clock_watch.fence);
        let off = parse(&["--fence-moved-cameras", "false"]).unwrap();
        assert!(!off.to_config().unwrap().limits.clock_watch.fence);
        assert!(parse(&["--fence-moved-cameras", "maybe"]).is_err());
        assert!(parse(&["--fence-moved-cameras"]).is_err());
    }
}

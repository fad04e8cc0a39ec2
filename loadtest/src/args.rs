//! Command-line options of `crossview-loadtest`.
use std::path::PathBuf;
use std::time::Duration;

use clap::{Parser, ValueEnum};
use crossview_api::format::ValueFormat;

/// Which API carries the batches and results.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Transport {
    /// gRPC `Push` streams + `Subscribe`.
    Grpc,
    /// `POST /v1/scenes/{scene}/batches` + server-sent events.
    Http,
    /// Produce to the replicas' input topic, read results from their output topic
    /// (`crossview serve --kafka-*`, docs/kafka.md).
    Kafka,
}

/// How frame ids are chosen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum FrameIds {
    /// Shifted above every earlier run's ids.
    Fresh,
    /// As in the recording.
    Original,
    /// Capture times instead: frame `k` of the run is stamped with tick `T + k` of `--rate`
    /// (ticks count periods from the Unix epoch, `T` the tick after the run's start), its
    /// frame id that tick too (the server checks that they agree). The scene must declare the
    /// same rate (`crossview serve --scene NAME=...@Nfps`).
    Times,
}

/// Replays a crossview recording against a running server at a fixed rate (open loop) or as
/// fast as possible, matches every frame result to its pushes and reports throughput,
/// push-to-result latency, errors and lost frames. Only loopback targets unless --allow-host.
#[derive(Debug, Clone, Parser)]
#[command(name = "crossview-loadtest", version, about)]
pub struct Args {
    /// Server base URL (gRPC and HTTP share one port).
    #[arg(
        long,
        env = "CROSSVIEW_LOADTEST_TARGET",
        default_value = "http://127.0.0.1:8080"
    )]
    pub target: String,

    /// Recording to replay (SPEC §7 JSONL, e.g. from `crossview simulate`).
    #[arg(long, env = "CROSSVIEW_LOADTEST_RECORDING")]
    pub recording: PathBuf,

    /// Transport for batches and results.
    #[arg(
        long,
        value_enum,
        default_value = "grpc",
        env = "CROSSVIEW_LOADTEST_TRANSPORT"
    )]
    pub transport: Transport,

    /// Frames per second per scene, scheduled by the clock (open loop). 0 = as fast as
    /// the in-flight window allows (closed loop).
    #[arg(long, default_value_t = 10.0, env = "CROSSVIEW_LOADTEST_RATE")]
    pub rate: f64,

    /// Replay the recording into this many scenes at once: the recording's scene name when 1,
    /// else NAME-0 .. NAME-(N-1) (the server must serve them, e.g. `--model NAME-0=m.onnx`).
    #[arg(long, default_value_t = 1, env = "CROSSVIEW_LOADTEST_SCENES")]
    pub scenes: usize,

    /// Explicit scene names (comma-separated); overrides --scenes.
    #[arg(long, value_delimiter = ',', env = "CROSSVIEW_LOADTEST_SCENE_NAMES")]
    pub scene_names: Vec<String>,

    /// Connections (gRPC Push streams / HTTP/2 connections) the batches are spread over; each
    /// camera of each scene stays on one connection.
    #[arg(long, default_value_t = 1, env = "CROSSVIEW_LOADTEST_CONNECTIONS")]
    pub connections: usize,

    /// Stop sending after this long (e.g. 30s, 2m, 500ms).
    #[arg(long, value_parser = parse_duration, env = "CROSSVIEW_LOADTEST_DURATION")]
    pub duration: Option<Duration>,

    /// Stop after this many frames per scene.
    #[arg(long, env = "CROSSVIEW_LOADTEST_FRAMES")]
    pub frames: Option<u64>,

    /// Frame ids on the wire: `fresh` shifts the recording's ids above any earlier run's
    /// (by the current Unix time in ms x 1000), so the server never sees them as late;
    /// `original` sends them unchanged (a fresh server only).
    #[arg(long, value_enum, default_value = "fresh")]
    pub frame_ids: FrameIds,

    /// Replay the recording again (with shifted frame ids) until --duration/--frames.
    #[arg(long = "loop")]
    pub repeat: bool,

    /// Most batches awaiting an answer; beyond it an open-loop send is skipped and counted
    /// as a `client_backlog` error, a closed-loop send waits.
    #[arg(long, default_value_t = 4096)]
    pub max_in_flight: usize,

    /// Closed loop (--rate 0): frames per scene allowed to await their result before the
    /// next frame is sent.
    #[arg(long, default_value_t = 8)]
    pub window: usize,

    /// After the last send, wait this long for outstanding results.
    #[arg(long, value_parser = parse_duration, default_value = "5s")]
    pub drain_timeout: Duration,

    /// Latency percentiles count only the frames sent this long after the run's first send
    /// (e.g. 2s: how the server answers once a run's first seconds are over, such as right
    /// after an overload). Everything else is counted as always.
    #[arg(long, value_parser = parse_duration, default_value = "0s")]
    pub latency_after: Duration,

    /// HTTP request timeout.
    #[arg(long, value_parser = parse_duration, default_value = "10s")]
    pub request_timeout: Duration,

    /// Use HTTP/1.1 for batch posts instead of HTTP/2 (h2c).
    #[arg(long)]
    pub http1: bool,

    /// Poll /readyz for up to this long before starting.
    #[arg(long, value_parser = parse_duration, env = "CROSSVIEW_LOADTEST_WAIT_READY")]
    pub wait_ready: Option<Duration>,

    /// Allow a non-loopback target host by name (repeatable), e.g. a compose service.
    #[arg(long, value_delimiter = ',', env = "CROSSVIEW_LOADTEST_ALLOW_HOST")]
    pub allow_host: Vec<String>,

    /// Soak mode: several scenes at a steady rate, cameras dropping out and reconnecting,
    /// random late and duplicate batches; compares counts with the server's /metrics.
    #[arg(long)]
    pub soak: bool,

    /// Soak: per camera and frame, chance a camera drops out (its connection closes).
    #[arg(long, default_value_t = 0.002)]
    pub dropout_prob: f64,

    /// Soak: how many frames a dropped camera stays away (uniform in 1..=N).
    #[arg(long, default_value_t = 30)]
    pub dropout_frames: u64,

    /// Soak: per batch, chance it is held back and sent late.
    #[arg(long, default_value_t = 0.005)]
    pub late_prob: f64,

    /// Soak: how long a late batch is held back.
    #[arg(long, value_parser = parse_duration, default_value = "1s")]
    pub late_delay: Duration,

    /// Soak: per batch, chance it is sent twice.
    #[arg(long, default_value_t = 0.005)]
    pub duplicate_prob: f64,

    /// Seed of the soak mode's random choices.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,

    /// Sample this process's resident memory (e.g. the server's pid) during the run.
    #[arg(long)]
    pub server_pid: Option<u32>,

    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,

    /// Kafka transport: bootstrap brokers `host:port[,...]` (loopback unless --allow-host).
    /// --target is then only used by --wait-ready (a replica's HTTP port).
    #[arg(long, env = "CROSSVIEW_LOADTEST_KAFKA_BROKERS")]
    pub kafka_brokers: Option<String>,

    /// Kafka transport: the topic the replicas consume batches from.
    #[arg(
        long,
        default_value = "batches",
        env = "CROSSVIEW_LOADTEST_KAFKA_INPUT_TOPIC"
    )]
    pub kafka_input_topic: String,

    /// Kafka transport: the topic the replicas produce results to.
    #[arg(
        long,
        default_value = "results",
        env = "CROSSVIEW_LOADTEST_KAFKA_OUTPUT_TOPIC"
    )]
    pub kafka_output_topic: String,

    /// Kafka transport: encoding of the produced batches, `json` (a batch line) or
    /// `protobuf` (`crossview.v1.Batch`), named by each record's `content-type` header.
    #[arg(long, default_value = "json", env = "CROSSVIEW_LOADTEST_KAFKA_FORMAT")]
    pub kafka_format: ValueFormat,

    /// Kafka transport: a librdkafka property `KEY=VALUE` for producer and consumer
    /// (repeatable; e.g. security.protocol, sasl.*).
    #[arg(long)]
    pub kafka_property: Vec<String>,
}

pub use crossview_api::duration::parse_duration;

impl Args {
    /// Checks option combinations that clap cannot.
    pub fn validate(&self) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.rate.is_finite() && self.rate >= 0.0,
            "--rate must be >= 0"
        );
        anyhow::ensure!(self.scenes >= 1, "--scenes must be >= 1");
        anyhow::ensure!(self.connections >= 1, "--connections must be >= 1");
        anyhow::ensure!(self.max_in_flight >= 1, "--max-in-flight must be >= 1");
        anyhow::ensure!(self.window >= 1, "--window must be >= 1");
        anyhow::ensure!(
            self.duration.is_some() || self.frames.is_some() || !self.repeat,
            "--loop needs --duration or --frames to stop"
        );
        if self.transport == Transport::Kafka {
            anyhow::ensure!(
                self.kafka_brokers.is_some(),
                "--transport kafka needs --kafka-brokers"
            );
            anyhow::ensure!(
                !self.soak,
                "--soak drops and reconnects camera connections: gRPC or HTTP only"
            );
        }
        if self.frame_ids == FrameIds::Times {
            anyhow::ensure!(
                self.rate > 0.0 && crossview_core::types::check_fps(self.rate).is_ok(),
                "--frame-ids times needs a fixed --rate of at most {} frames/s (the scene's)",
                crossview_core::types::MAX_FPS
            );
        }
        if self.soak {
            anyhow::ensure!(self.rate > 0.0, "--soak needs a fixed --rate");
            anyhow::ensure!(
                self.duration.is_some() || self.frames.is_some(),
                "--soak needs --duration or --frames"
            );
        }
        for (name, p) in [
            ("--dropout-prob", self.dropout_prob),
            ("--late-prob", self.late_prob),
            ("--duplicate-prob", self.duplicate_prob),
        ] {
            anyhow::ensure!((0.0..=1.0).contains(&p), "{name} must be within [0, 1]");
        }
        Ok(())
    }

    /// The scene names to drive, derived from the recording's scene name.
    pub fn scene_names(&self, recording_scene: &str) -> Vec<String> {
        if !self.scene_names.is_empty() {
            self.scene_names.clone()
        } else if self.scenes == 1 {
            vec![recording_scene.to_string()]
        } else {
            (0..self.scenes)
                .map(|i| format!("{recording_scene}-{i}"))
                .collect()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations() {
        assert_eq!(parse_duration("30s").unwrap(), Duration::from_secs(30));
        assert_eq!(parse_duration("250ms").unwrap(), Duration::from_millis(250));
        assert_eq!(parse_duration("2m").unwrap(), Duration::from_secs(120));
        assert!(parse_duration("1.5").is_err(), "a bare number needs a unit");
        assert!(parse_duration("-1s").is_err());
        assert!(parse_duration("3 parsecs").is_err());
    }

    #[test]
    fn scene_names_from_count_or_list() {
        let mut a = Args::parse_from(["x", "--recording", "r.jsonl", "--scenes", "3"]);
        assert_eq!(a.scene_names("lab"), vec!["lab-0", "lab-1", "lab-2"]);
        a.scenes = 1;
        assert_eq!(a.scene_names("lab"), vec!["lab"]);
        let a = Args::parse_from(["x", "--recording", "r", "--scene-names", "p,q"]);
        assert_eq!(a.scene_names("lab"), vec!["p", "q"]);
        let a = Args::parse_from(["x", "--recording", "r", "--loop"]);
        assert!(a.validate().is_err());
        let a = Args::parse_from(["x", "--recording", "r", "--transport", "kafka"]);
        assert!(a.validate().is_err(), "kafka needs brokers");
        let a = Args::parse_from([
            "x",
            "--recording",
            "r",
            "--transport",
            "kafka",
            "--kafka-brokers",
            "b:9092",
        ]);
        a.validate().unwrap();
    }
}

//! Server configuration: the library-side settings the CLI (`crossview serve`) fills from flags
//! and environment variables, and tests fill directly.
use std::path::PathBuf;
use std::time::Duration;

use crate::error::{Error, Result};
use crossview_core::memory::MemoryConfig;
use crossview_core::tracking::TrackerConfig;
use crossview_core::{CameraSpec, SceneSpec};

/// A model to serve: scene `name` from ONNX file `path`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModelSpec {
    /// Scene name (defaults to the file stem).
    pub name: String,
    /// The SPEC §8 ONNX model file.
    pub path: PathBuf,
}

impl ModelSpec {
    /// Parses `[NAME=]path.onnx`; the scene name defaults to the file stem.
    pub fn parse(s: &str) -> Result<Self> {
        let (name, path) = match s.split_once('=') {
            Some((n, p)) if !n.is_empty() && !n.contains('/') => (Some(n.to_string()), p),
            _ => (None, s),
        };
        let path = PathBuf::from(path);
        let name = match name {
            Some(n) => n,
            None => path
                .file_stem()
                .and_then(|s| s.to_str())
                .filter(|s| !s.is_empty())
                .ok_or_else(|| Error::invalid("--model", format!("no scene name in '{s}'")))?
                .to_string(),
        };
        validate_scene_name(&name)?;
        Ok(ModelSpec { name, path })
    }
}

/// A scene declared by its cameras alone (no model yet): batches are accepted, recorded and
/// published unassociated until a model for it is loaded (`--model NAME=path` naming a file
/// that appears later, picked up on reload).
#[derive(Debug, Clone, PartialEq)]
pub struct SceneDecl {
    /// Name and cameras (names and image sizes, in camera-index order).
    pub spec: SceneSpec,
    /// The scene's frame rate (`...@10fps`, a header's `"fps"`): what capture times are
    /// grouped by ([`crossview_core::capture`]); `None`: the model's training rate, if any.
    pub fps: Option<f64>,
}

impl SceneDecl {
    /// Parses `NAME=cam1:1920x1080,cam2:1280x720,...[@10fps]`, or the path of a JSON file
    /// holding a SPEC §7 scene header `{"scene": {"name", "cameras": [{"name", "width",
    /// "height"}]}, "fps": 10}` (a recording's first line is one).
    pub fn parse(s: &str) -> Result<Self> {
        let mut fps = None;
        let spec = match s.split_once('=') {
            Some((name, cams)) if !name.contains('/') => {
                let cams = match cams.rsplit_once('@') {
                    Some((rest, rate)) if rate.ends_with("fps") => {
                        fps = Some(parse_fps(rate)?);
                        rest
                    }
                    _ => cams,
                };
                let cameras = cams
                    .split(',')
                    .map(|c| parse_camera(c.trim()))
                    .collect::<Result<Vec<_>>>()?;
                SceneSpec {
                    name: name.to_string(),
                    cameras,
                }
            }
            _ => {
                // Only the first line: a recording may be gigabytes, a header is small.
                use std::io::{BufRead, Read};
                let io = |e| crossview_core::Error::Io {
                    path: s.into(),
                    source: e,
                };
                let mut first = String::new();
                std::io::BufReader::new(std::fs::File::open(s).map_err(io)?)
                    .take(MAX_HEADER_BYTES)
                    .read_line(&mut first)
                    .map_err(io)?;
                if first.len() as u64 >= MAX_HEADER_BYTES && !first.ends_with('\n') {
                    return Err(Error::invalid(
                        "--scene",
                        format!("{s}: the first line exceeds {MAX_HEADER_BYTES} bytes"),
                    ));
                }
                #[derive(serde::Deserialize)]
                struct Header {
                    scene: SceneSpec,
                    #[serde(default)]
                    fps: Option<f64>,
                }
                let h: Header = serde_json::from_str(&first).map_err(|e| {
                    Error::invalid("--scene", format!("{s}: not a scene header: {e}"))
                })?;
                if let Some(f) = h.fps {
                    crossview_core::types::check_fps(f)
                        .map_err(|e| Error::invalid("--scene", format!("{s}: {e}")))?;
                }
                fps = h.fps;
                h.scene
            }
        };
        validate_scene_name(&spec.name)?;
        for c in &spec.cameras {
            c.check().map_err(|e| Error::invalid("--scene", e))?;
        }
        if spec.cameras.is_empty() {
            return Err(Error::invalid("--scene", format!("'{s}' names no camera")));
        }
        let mut seen = std::collections::BTreeSet::new();
        for c in &spec.cameras {
            if !seen.insert(c.name.as_str()) {
                return Err(Error::invalid(
                    "--scene",
                    format!("camera '{}' appears twice", c.name),
                ));
            }
        }
        Ok(SceneDecl { spec, fps })
    }
}

/// `10fps`, `29.97fps`: a frame rate in (0, 1000].
fn parse_fps(s: &str) -> Result<f64> {
    let bad = |why: String| Error::invalid("--scene", format!("'@{s}': {why}"));
    let v: f64 = s
        .trim_end_matches("fps")
        .parse()
        .map_err(|_| bad("not a rate like @10fps".into()))?;
    crossview_core::types::check_fps(v).map_err(bad)?;
    Ok(v)
}

/// Longest scene header `--scene FILE` reads (a header of many cameras is a few KiB).
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// `name:WIDTHxHEIGHT`, optionally followed by the camera's clock offset: in frame ids,
/// `@+N` or `@-N` (what `crossview sync-check` reports), or in milliseconds, `@+120ms` (a
/// camera that sends capture times).
fn parse_camera(s: &str) -> Result<CameraSpec> {
    let bad = || {
        Error::invalid(
            "--scene",
            format!(
                "'{s}' is not CAMERA:WIDTHxHEIGHT, CAMERA:WIDTHxHEIGHT@OFFSET or \
                 CAMERA:WIDTHxHEIGHT@OFFSETms"
            ),
        )
    };
    let (body, offset, offset_ms) = match s.rsplit_once('@') {
        Some((body, o)) if !o.contains(':') => {
            let (o, ms) = match o.strip_suffix("ms") {
                Some(o) => (o, true),
                None => (o, false),
            };
            let o: i64 = o
                .strip_prefix('+')
                .unwrap_or(o)
                .parse()
                .map_err(|_| bad())?;
            if ms { (body, 0, o) } else { (body, o, 0) }
        }
        _ => (s, 0, 0),
    };
    let (name, size) = body.rsplit_once(':').ok_or_else(bad)?;
    let (w, h) = size.split_once('x').ok_or_else(bad)?;
    let (width, height): (u32, u32) =
        (w.parse().map_err(|_| bad())?, h.parse().map_err(|_| bad())?);
    let camera = CameraSpec {
        offset,
        offset_ms,
        ..CameraSpec::new(name, width, height)
    };
    camera.check().map_err(|e| Error::invalid("--scene", e))?;
    Ok(camera)
}

/// Scene names travel in URL paths: keep them to `[A-Za-z0-9._-]`, 1..=64 characters.
pub(crate) fn validate_scene_name(name: &str) -> Result<()> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
    if ok {
        Ok(())
    } else {
        Err(Error::invalid(
            "scene",
            format!("'{name}' must be 1-64 characters of [A-Za-z0-9._-]"),
        ))
    }
}

/// Settings of the live clock watch ([`crate::scene`]'s `clock` module, docs/clock-offsets.md).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ClockWatchConfig {
    /// Most recent frames an estimate uses (0: the watch is off).
    pub window: usize,
    /// At most one estimate per this interval.
    pub interval: Duration,
    /// Largest offset searched, in frame steps either way (bounds the work).
    pub max_offset: u32,
    /// Apply a camera's estimated offset once two estimates over full, successive windows
    /// agree on it (`--auto-align`); off by default.
    pub auto_align: bool,
    /// Leave a camera that does not fit the model out of association until it fits again
    /// (`--fence-moved-cameras`, docs/camera-fit.md); on by default.
    pub fence: bool,
}

impl Default for ClockWatchConfig {
    /// 300 frames (chosen on the simulator: BENCHMARKS.md, "Camera clock offsets"), one
    /// estimate per 10 s, ±10 frames searched, no auto-align.
    fn default() -> Self {
        ClockWatchConfig {
            window: 300,
            interval: Duration::from_secs(10),
            max_offset: 10,
            auto_align: false,
            fence: true,
        }
    }
}

/// Size and cost caps that keep one request from costing unbounded memory or time.
///
/// Association cost model ([`super::cost`]): a frame with `n_c` boxes in camera `c` costs
/// `Σ_{a<b} n_a · n_b · min(n_a, n_b)` units (one Hungarian assignment per camera pair);
/// one unit is about 2–3.5 ns of one core. `max_frame_cost` refuses the batch
/// (or unary request) that would push a frame over it, and `max_detections` is chosen so
/// that two full cameras fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Limits {
    /// Largest HTTP body or gRPC message in bytes.
    pub max_request_bytes: usize,
    /// Most cameras a scene (model) may have.
    pub max_cameras: usize,
    /// Most detections in one camera batch.
    pub max_detections: usize,
    /// Longest appearance vector.
    pub max_appearance_len: usize,
    /// Frames queued for the encoder per scene before new work is shed (RESOURCE_EXHAUSTED).
    pub queue_capacity: usize,
    /// Frame results buffered per subscriber before it is dropped as too slow.
    pub subscriber_buffer: usize,
    /// Most association cost units one frame may reach (see the cost model above).
    pub max_frame_cost: u64,
    /// The scene's queue budget: while its oldest queued job has waited longer, new frames
    /// are shed at intake (their batches refused with a retry-after), and a frame that waited
    /// longer anyway is shed from the queue; a unary request that waited longer is refused.
    /// Bounds the latency of the frames that are associated (Kafka mode waits instead).
    pub max_queue_delay: Duration,
    /// Frame-id window (see [`super::sync`]): batches further than this from the scene's
    /// current frame ids are refused as out of range.
    pub frame_window: u64,
    /// A JSON Lines body stops early once more than this many lines were rejected and
    /// rejected lines outnumber accepted ones.
    pub max_rejected_lines: usize,
    /// The live clock watch's window, interval and search range ([`crate::scene`]): bounds
    /// its work to one estimate per interval.
    pub clock_watch: ClockWatchConfig,
}

/// The default queue budget (`--max-queue-delay`; chosen by measurement, docs/serve.md
/// "Sizing").
pub const DEFAULT_MAX_QUEUE_DELAY: Duration = Duration::from_millis(500);

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_request_bytes: 4 << 20,
            max_cameras: 64,
            max_detections: 512,
            max_appearance_len: 4096,
            queue_capacity: 256,
            subscriber_buffer: 1024,
            max_frame_cost: 200_000_000,
            max_queue_delay: DEFAULT_MAX_QUEUE_DELAY,
            frame_window: super::sync::DEFAULT_FRAME_WINDOW,
            max_rejected_lines: 100,
            clock_watch: ClockWatchConfig::default(),
        }
    }
}

/// Connection limits and timeouts of the shared gRPC + HTTP port (HTTP/1 and HTTP/2 alike).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// Most open connections. At the cap a new connection closes the longest-idle one (no
    /// request in flight); when none is idle the new connection is refused (closed at once).
    pub max_connections: usize,
    /// A TLS handshake and a request head (HTTP/1) must complete within this time.
    pub header_read_timeout: Duration,
    /// A connection with no request in flight for this long is closed (covers slow or
    /// absent request heads on HTTP/2 too).
    pub idle_timeout: Duration,
    /// An HTTP request body, or one gRPC message once started, must arrive within this time.
    pub body_timeout: Duration,
    /// Most concurrent HTTP/2 streams (requests) per connection.
    pub http2_max_streams: u32,
    /// HTTP/2 keep-alive ping interval; a peer that does not answer within the same time is
    /// disconnected.
    pub http2_keepalive: Duration,
    /// A result subscriber (gRPC `Subscribe`/`Stream`, SSE) that has not taken a published
    /// result for this long while results wait for it is disconnected.
    pub subscriber_stall_timeout: Duration,
    /// Memory all result subscribers together may cost (bytes; each is charged a fixed
    /// worst case, see [`crate::subscribers`]). At the budget a new subscription displaces
    /// the subscriber furthest behind, or is refused when all keep up.
    pub subscriber_memory: usize,
    /// Most result subscriptions one connection may hold.
    pub max_subscriptions_per_connection: usize,
}

impl Default for ConnectionLimits {
    fn default() -> Self {
        ConnectionLimits {
            max_connections: 512,
            header_read_timeout: Duration::from_secs(10),
            idle_timeout: Duration::from_secs(60),
            body_timeout: Duration::from_secs(30),
            http2_max_streams: 100,
            http2_keepalive: Duration::from_secs(30),
            subscriber_stall_timeout: Duration::from_secs(30),
            subscriber_memory: 256 << 20,
            max_subscriptions_per_connection: 64,
        }
    }
}

/// TLS certificate chain and private key (PEM files).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsConfig {
    pub cert: PathBuf,
    pub key: PathBuf,
}

/// Everything [`super::Server`] needs. Its `Debug` output redacts the API keys.
#[derive(Clone)]
pub struct ServeConfig {
    /// Models to load, one scene each.
    pub models: Vec<ModelSpec>,
    /// Scenes declared by their cameras (no model yet). A model of `models` with the same
    /// name may name a file that does not exist yet: it is loaded on reload.
    pub scenes: Vec<SceneDecl>,
    /// How long a frame waits for missing cameras before it leaves as partial.
    pub sync_timeout: Duration,
    /// Pending frames per scene beyond which the oldest leaves as partial.
    pub max_pending_frames: usize,
    /// Accepted bearer tokens; empty = no authentication. A blank token is a start-up error.
    pub api_keys: Vec<String>,
    /// Serve without API keys on an address beyond loopback (otherwise a start-up error).
    pub allow_unauthenticated: bool,
    /// Serve TLS (rustls) when set.
    pub tls: Option<TlsConfig>,
    /// Size, cost and queue caps.
    pub limits: Limits,
    /// Connection cap and timeouts.
    pub connections: ConnectionLimits,
    /// How long graceful shutdown waits for open connections after flushing.
    pub shutdown_grace: Duration,
    /// Re-read every scene's model file on `SIGHUP` (the binary sets it; tests in one
    /// process use the admin route instead).
    pub reload_on_sighup: bool,
    /// How each scene links its identities over time into track ids; `None` tracks nothing
    /// (streamed identities then carry no `track_id`).
    pub tracker: Option<TrackerConfig>,
    /// How each scene's streamed identities remember the past frames
    /// ([`crossview_core::memory`]); `None`: each frame alone.
    pub memory: Option<MemoryConfig>,
    /// Record every accepted batch ([`super::record`]) when set.
    pub record: Option<super::record::RecordConfig>,
    /// Heal scenes whose camera stopped fitting ([`crate::heal`], needs `record`) when set.
    pub heal: Option<super::heal::config::HealConfig>,
    /// Kafka mode ([`crate::transport::kafka`]) beside gRPC and HTTP, when set.
    pub kafka: Option<crate::transport::kafka::config::KafkaConfig>,
    /// Threads of the inference pool every scene's work runs on (0: one per core).
    pub inference_threads: usize,
    /// How far a capture time may fall from its frame's tick (`--time-tolerance`; `None`:
    /// half the scene's period).
    pub time_tolerance: Option<Duration>,
}

impl std::fmt::Debug for ServeConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ServeConfig")
            .field("models", &self.models)
            .field("scenes", &self.scenes)
            .field("reload_on_sighup", &self.reload_on_sighup)
            .field("sync_timeout", &self.sync_timeout)
            .field("max_pending_frames", &self.max_pending_frames)
            .field(
                "api_keys",
                &format_args!("<{} redacted>", self.api_keys.len()),
            )
            .field("allow_unauthenticated", &self.allow_unauthenticated)
            .field("tls", &self.tls)
            .field("limits", &self.limits)
            .field("connections", &self.connections)
            .field("shutdown_grace", &self.shutdown_grace)
            .field("tracker", &self.tracker)
            .field("memory", &self.memory)
            .field("record", &self.record)
            .field("heal", &self.heal)
            .field("kafka", &self.kafka)
            .field("inference_threads", &self.inference_threads)
            .field("time_tolerance", &self.time_tolerance)
            .finish()
    }
}

impl Default for ServeConfig {
    fn default() -> Self {
        ServeConfig {
            models: Vec::new(),
            scenes: Vec::new(),
            reload_on_sighup: false,
            sync_timeout: Duration::from_millis(200),
            max_pending_frames: 64,
            api_keys: Vec::new(),
            allow_unauthenticated: false,
            tls: None,
            limits: Limits::default(),
            connections: ConnectionLimits::default(),
            shutdown_grace: Duration::from_secs(10),
            tracker: Some(TrackerConfig::default()),
            memory: Some(MemoryConfig::default()),
            record: None,
            heal: None,
            kafka: None,
            inference_threads: 0,
            time_tolerance: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_decl_reads_inline_cameras_or_a_header_line() {
        let d = SceneDecl::parse("lab=a:640x480,b:1920x1080").unwrap();
        assert_eq!(d.spec.name, "lab");
        assert_eq!(d.spec.cameras.len(), 2);
        assert!(SceneDecl::parse("lab=a:640x480,a:640x480").is_err());
        // Clock offsets: `@+N`, `@-N`, `@N`; a name may hold an '@'.
        let d = SceneDecl::parse("lab=a:640x480@+2,b:640x480@-5,c:640x480@3,d@x:8x6").unwrap();
        let offsets: Vec<i64> = d.spec.cameras.iter().map(|c| c.offset).collect();
        assert_eq!(offsets, [2, -5, 3, 0]);
        assert_eq!(d.spec.cameras[3].name, "d@x");
        for bad in [
            "lab=a:640x480@",
            "lab=a:640x480@+x",
            "lab=a:640x480@99999999999",
        ] {
            assert!(SceneDecl::parse(bad).is_err(), "{bad}");
        }
        let dir = tempfile::tempdir().unwrap();
        let rec = dir.path().join("rec.jsonl");
        let header =
            r#"{"scene": {"name": "hall", "cameras": [{"name": "c", "width": 8, "height": 6}]}}"#;
        std::fs::write(&rec, format!("{header}\n{{\"camera\": \"c\"}}\n")).unwrap();
        let d = SceneDecl::parse(rec.to_str().unwrap()).unwrap();
        assert_eq!((d.spec.name.as_str(), d.spec.cameras[0].width), ("hall", 8));
        // A first line that never ends is refused after a bounded read.
        let big = dir.path().join("big.jsonl");
        std::fs::write(&big, vec![b'x'; (MAX_HEADER_BYTES + 10) as usize]).unwrap();
        let e = SceneDecl::parse(big.to_str().unwrap()).unwrap_err();
        assert!(e.to_string().contains("exceeds"), "{e}");
        assert!(SceneDecl::parse("/no/such/file.jsonl").is_err());
        // A header holds the cameras to the same rule as the inline form.
        let bad_headers = [
            r#"{"width": 0, "height": 6, "name": "c"}"#.to_string(),
            r#"{"width": 4294967295, "height": 6, "name": "c"}"#.to_string(),
            r#"{"width": 8, "height": 4294967295, "name": "c"}"#.to_string(),
            r#"{"width": 8, "height": 6, "name": ""}"#.to_string(),
            r#"{"width": 8, "height": 6, "name": "a\u0000b"}"#.to_string(),
            format!(
                r#"{{"width": 8, "height": 6, "name": "{}"}}"#,
                "x".repeat(500_000)
            ),
        ];
        for cam in bad_headers {
            let p = dir.path().join("bad.json");
            std::fs::write(
                &p,
                format!(r#"{{"scene": {{"name": "hall", "cameras": [{cam}]}}}}"#),
            )
            .unwrap();
            let e = SceneDecl::parse(p.to_str().unwrap());
            assert!(e.is_err(), "{}", &cam[..cam.len().min(80)]);
        }
        assert!(SceneDecl::parse("lab=:640x480").is_err());
        assert!(SceneDecl::parse(&format!("lab={}:640x480", "y".repeat(200))).is_err());
    }

    #[test]
    fn model_spec_parses_name_and_stem() {
        let m = ModelSpec::parse("lab=/tmp/x/model.onnx").unwrap();
        assert_eq!(m.name, "lab");
        assert_eq!(m.path, PathBuf::from("/tmp/x/model.onnx"));
        let m = ModelSpec::parse("/tmp/x/wildtrack.onnx").unwrap();
        assert_eq!(m.name, "wildtrack");
        assert!(ModelSpec::parse("bad name=/x.onnx").is_err());
    }

    #[test]
    fn debug_output_redacts_api_keys() {
        let c = ServeConfig {
            api_keys: vec!["s3cret".into()],
            ..ServeConfig::default()
        };
        let text = format!("{c:?}");
        assert!(
            !text.contains("s3cret") && text.contains("<1 redacted>"),
            "{text}"
        );
    }
}

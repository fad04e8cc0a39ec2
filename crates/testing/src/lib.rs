//! The shared fixtures of the integration tests: a small random encoder exported with the
//! project's exporter (real ONNX file, real ONNX Runtime), a real server on 127.0.0.1:0, gRPC
//! and HTTP clients, hang guards (never timing assertions), the `crossview` binary runner, the
//! WILDTRACK data, [`skip`], which refuses to skip under `CI=true`, and a real headless
//! Chromium ([`browser`]).

pub mod browser;
pub mod h2client;
pub mod kafka;

use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use crossview_api::pb;
use crossview_api::pb::association_client::AssociationClient;
use crossview_core::CameraSpec;
use crossview_model::export::write_onnx;
use crossview_model::{EncoderConfig, EncoderWeights, ModelMetadata};
use crossview_serve::{ModelSpec, ServeConfig};
use tokio::sync::oneshot;
use tonic::transport::Channel;

/// Generous upper bound for anything a test waits on (a hang guard, not a timing assertion).
pub const HANG_GUARD: Duration = Duration::from_secs(60);

/// Awaits `f`, failing the test if it takes longer than [`HANG_GUARD`].
pub async fn guard<F: Future>(what: &str, f: F) -> F::Output {
    tokio::time::timeout(HANG_GUARD, f)
        .await
        .unwrap_or_else(|_| panic!("hang guard: {what} did not finish"))
}

/// Camera names of the test scene.
pub const CAMERAS: [&str; 3] = ["c0", "c1", "c2"];

/// The test scene's cameras (different image sizes on purpose).
pub fn cameras() -> Vec<CameraSpec> {
    vec![
        CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: "c0".into(),
            width: 1920,
            height: 1080,
        },
        CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: "c1".into(),
            width: 1280,
            height: 720,
        },
        CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: "c2".into(),
            width: 640,
            height: 480,
        },
    ]
}

/// Exports a small random encoder for [`cameras`] to `dir/<stem>.onnx` with the project's
/// exporter and returns its path.
pub fn export_model(dir: &Path, stem: &str) -> PathBuf {
    export_model_with(dir, stem, 11, cameras())
}

/// Like [`export_model`], with weights from `seed` for the scene `cameras` (another seed:
/// another file, another version).
pub fn export_model_with(dir: &Path, stem: &str, seed: u64, cameras: Vec<CameraSpec>) -> PathBuf {
    let config = EncoderConfig {
        fourier_features: 8,
        camera_dim: 16,
        width: 48,
        blocks: 2,
    };
    let weights = EncoderWeights::random(cameras.len(), config, seed).expect("random weights");
    let mut meta = ModelMetadata::new(cameras);
    meta.threshold = 0.1;
    meta.version = "test-1".into();
    let path = dir.join(format!("{stem}.onnx"));
    write_onnx(&path, &weights, &meta).expect("export ONNX");
    path
}

/// A server running in this process on 127.0.0.1:0 with one scene, `lab`.
pub struct TestServer {
    pub addr: SocketAddr,
    pub dir: tempfile::TempDir,
    stop: Option<oneshot::Sender<()>>,
    task: Option<tokio::task::JoinHandle<crossview_serve::Result<()>>>,
}

/// The queue budget (`--max-queue-delay`) of the fixtures' servers, in process and spawned:
/// tests of other guarantees push whole recordings at once on a busy 2-core machine and must
/// not see frames shed; the overload tests set their own.
pub const TEST_QUEUE_BUDGET: Duration = Duration::from_secs(60);

/// Starts a server with scene `lab` (3 cameras); `configure` adjusts the configuration.
pub async fn start(configure: impl FnOnce(&mut ServeConfig)) -> TestServer {
    let dir = tempfile::tempdir().expect("tempdir");
    let model = export_model(dir.path(), "lab");
    let models = vec![ModelSpec::parse(model.to_str().unwrap()).unwrap()];
    serve_in(dir, models, configure).await
}

/// Starts a server with the scenes of `models`; `configure` adjusts the configuration.
pub async fn start_with(
    models: Vec<ModelSpec>,
    configure: impl FnOnce(&mut ServeConfig),
) -> TestServer {
    serve_in(tempfile::tempdir().expect("tempdir"), models, configure).await
}

async fn serve_in(
    dir: tempfile::TempDir,
    models: Vec<ModelSpec>,
    configure: impl FnOnce(&mut ServeConfig),
) -> TestServer {
    let mut config = ServeConfig {
        models,
        ..ServeConfig::default()
    };
    config.limits.max_queue_delay = TEST_QUEUE_BUDGET;
    configure(&mut config);
    let server_uses_tls = config.tls.is_some();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind");
    let addr = listener.local_addr().unwrap();
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(crossview_serve::run(config, listener, async move {
        let _ = rx.await;
    }));
    let server = TestServer {
        addr,
        dir,
        stop: Some(tx),
        task: Some(task),
    };
    if server_uses_tls {
        // Connections wait in the listener's backlog until the server accepts them.
        return server;
    }
    let http = reqwest::Client::new();
    guard("server readiness", async {
        loop {
            if let Ok(r) = http.get(server.url("/readyz")).send().await
                && r.status().is_success()
            {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    server
}

impl TestServer {
    /// Pushes frames `frames` of all three cameras of `lab` over HTTP JSON, `n` boxes per
    /// camera; asserts each batch is accepted (202).
    pub async fn push_http(&self, frames: std::ops::RangeInclusive<u64>, n: usize) {
        let http = reqwest::Client::new();
        for f in frames {
            for c in 0..3 {
                let r = http
                    .post(self.url("/v1/scenes/lab/batches"))
                    .json(&batch_json(c, f, n))
                    .send()
                    .await
                    .expect("push");
                assert_eq!(r.status(), 202, "push of camera {c}, frame {f}");
            }
        }
    }

    /// `http://addr{path}`.
    pub fn url(&self, path: &str) -> String {
        format!("http://{}{}", self.addr, path)
    }

    /// A new gRPC connection (its own TCP connection).
    pub async fn grpc(&self) -> AssociationClient<Channel> {
        let ch = Channel::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .expect("gRPC connect");
        AssociationClient::new(ch)
    }

    /// `GET path` as JSON; panics when the answer is not JSON.
    pub async fn get_json(&self, path: &str) -> serde_json::Value {
        reqwest::get(self.url(path))
            .await
            .expect("GET")
            .json()
            .await
            .expect("a JSON answer")
    }

    /// `POST path` with the JSON `body` (over a new connection): the answer's status and its
    /// body as JSON (`Null` when it is not JSON).
    pub async fn post_json(
        &self,
        path: &str,
        body: &serde_json::Value,
    ) -> (reqwest::StatusCode, serde_json::Value) {
        let r = reqwest::Client::new()
            .post(self.url(path))
            .json(body)
            .send()
            .await
            .expect("POST");
        let status = r.status();
        let bytes = r.bytes().await.expect("the answer's body");
        (
            status,
            serde_json::from_slice(&bytes).unwrap_or(serde_json::Value::Null),
        )
    }

    /// `scene`'s description over gRPC `GetScene` (its own connection); panics on a refusal.
    pub async fn scene(&self, scene: &str) -> pb::Scene {
        self.grpc()
            .await
            .get_scene(pb::GetSceneRequest {
                scene: scene.into(),
            })
            .await
            .expect("GetScene")
            .into_inner()
    }

    /// Subscribes to `scene`'s results over gRPC (its own connection); panics on a refusal.
    pub async fn subscribe(&self, scene: &str) -> tonic::Streaming<pb::FrameResult> {
        self.grpc()
            .await
            .subscribe(pb::SubscribeRequest {
                scene: scene.into(),
            })
            .await
            .expect("subscribe")
            .into_inner()
    }

    /// `/metrics` text.
    pub async fn metrics(&self) -> String {
        reqwest::get(self.url("/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap()
    }

    /// Triggers graceful shutdown and waits for `run` to return.
    pub async fn shutdown(mut self) -> crossview_serve::Result<()> {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
        let task = self.task.take().unwrap();
        guard("server shutdown", task).await.expect("server task")
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        if let Some(tx) = self.stop.take() {
            let _ = tx.send(());
        }
    }
}

/// Value of the metric line starting with `prefix` (name plus labels), 0 when absent.
pub fn metric(text: &str, prefix: &str) -> f64 {
    text.lines()
        .find(|l| l.starts_with(prefix))
        .and_then(|l| l.rsplit(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.0)
}

/// A protobuf detection.
pub fn det(x1: f32, y1: f32, x2: f32, y2: f32) -> pb::Detection {
    pb::Detection {
        bbox: Some(pb::BoundingBox { x1, y1, x2, y2 }),
        score: None,
        appearance: vec![],
    }
}

/// `n` deterministic, valid detections that depend on camera and frame, inside the camera's
/// image (boxes wrap around it, so any `n` fits).
pub fn dets(camera: usize, frame: u64, n: usize) -> Vec<pb::Detection> {
    let cam = &cameras()[camera];
    let (w, h) = (cam.width as f32, cam.height as f32);
    (0..n)
        .map(|i| {
            let x =
                (10.0 + 50.0 * i as f32 + 3.0 * camera as f32 + (frame % 7) as f32) % (w - 40.0);
            let y = (20.0 + i as f32 + 7.0 * (i as f32 * 50.0 / w).floor()) % (h - 200.0);
            det(x, y, x + 30.0, y + 180.0)
        })
        .collect()
}

/// Peak resident memory of this process (VmHWM) in bytes.
pub fn vm_hwm_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .expect("VmHWM in /proc/self/status")
        * 1024
}

/// A protobuf batch of scene `lab`.
pub fn batch(camera: usize, frame: u64, n: usize) -> pb::Batch {
    pb::Batch {
        scene: "lab".into(),
        camera: CAMERAS[camera].into(),
        frame_id: frame,
        detections: dets(camera, frame, n),
        time: None,
    }
}

/// The same batch in its SPEC §7 JSON form.
pub fn batch_json(camera: usize, frame: u64, n: usize) -> serde_json::Value {
    let dets: Vec<serde_json::Value> = dets(camera, frame, n)
        .into_iter()
        .map(|d| {
            let b = d.bbox.unwrap();
            serde_json::json!({ "bbox": [b.x1, b.y1, b.x2, b.y2] })
        })
        .collect();
    serde_json::json!({ "camera": CAMERAS[camera], "frame_id": frame, "detections": dets })
}

/// The most boxes per camera (all three cameras alike) the default limits admit: the most
/// expensive frame a client can send (`--max-frame-cost`).
pub fn largest_uniform() -> usize {
    let l = crossview_serve::Limits::default();
    (1..=l.max_detections)
        .take_while(|&n| crossview_serve::cost::frame_cost(&[n; 3]) <= l.max_frame_cost)
        .last()
        .expect("the default limits admit a frame of one box per camera")
}

/// A unary `associate` body: frame 1 with 3 × `n` boxes.
pub fn associate_body(n: usize) -> serde_json::Value {
    let views: Vec<_> = (0..3)
        .map(|c| {
            let mut b = batch_json(c, 1, n);
            b.as_object_mut().unwrap().remove("frame_id");
            b
        })
        .collect();
    serde_json::json!({ "frame_id": 1, "views": views })
}

/// Checks a result's identities: members point at existing boxes, at most one per camera per
/// identity, and no box in two identities.
pub fn check_identities(r: &pb::FrameResult, boxes_per_camera: &[usize]) {
    let mut seen = std::collections::HashSet::new();
    for id in &r.identities {
        assert!((0.0..=1.0).contains(&id.confidence), "{id:?}");
        let mut cams = std::collections::HashSet::new();
        for m in &id.members {
            let c = m.camera_index as usize;
            assert_eq!(m.camera, CAMERAS[c]);
            assert!((m.index as usize) < boxes_per_camera[c], "{m:?}");
            assert!(cams.insert(c), "two members of one camera in {id:?}");
            assert!(seen.insert((c, m.index)), "box in two identities: {m:?}");
        }
    }
}

/// The shipped `models/demo.onnx` (scene `demo`: the simulator's `square4` cameras) as the
/// server's one model.
pub fn demo_model() -> Vec<ModelSpec> {
    let path = repo_root().join("models/demo.onnx");
    vec![ModelSpec::parse(path.to_str().unwrap()).unwrap()]
}

/// `models/demo.onnx` followed by an untrained member, as one ensemble file `dir/<stem>.onnx`
/// (scene `demo`): its leading block is demo's own encoder, the rest only widens it.
pub fn demo_with_untrained_member(dir: &Path, stem: &str) -> PathBuf {
    let (single, meta) = crossview_model::read_ensemble(repo_root().join("models/demo.onnx"))
        .expect("read models/demo.onnx");
    let first = single.members()[0].clone();
    let noise = EncoderWeights::random(first.num_cameras, first.config, 7).expect("random weights");
    let ensemble = crossview_model::Ensemble::new(vec![first, noise]).expect("one ensemble");
    let path = dir.join(format!("{stem}.onnx"));
    crossview_model::write_ensemble_onnx(&path, &ensemble, &meta).expect("export ONNX");
    path
}

/// The repository root (where `models/`, `scenes/`, `proto/` and `.cache/` live).
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Whether this is a CI run (`CI` set to anything but empty, `0` or `false`): there a test
/// must not skip for want of a dependency.
pub(crate) fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| !v.is_empty() && v != "0" && v != "false")
}

/// Reports that a test cannot run its real dependency (`reason` says which and how to get it):
/// a `SKIPPED` note on a developer's machine, a failure under `CI=true` — a skipped test must
/// never pass as green in CI. The caller returns after it.
pub fn skip(reason: &str) {
    assert!(!in_ci(), "CI=true, so this test may not skip: {reason}");
    eprintln!("SKIPPED: {reason}");
}

/// The WILDTRACK data: `$CROSSVIEW_WILDTRACK_DIR` if set, else `../shared/data/wildtrack`
/// beside the repository; `None` (after [`skip`]) when it is absent.
pub fn wildtrack_dir() -> Option<PathBuf> {
    let dir = std::env::var_os("CROSSVIEW_WILDTRACK_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join("../shared/data/wildtrack"));
    if dir.join("annotations_positions").is_dir() {
        Some(dir)
    } else {
        skip(&format!(
            "WILDTRACK data not found at {} (set CROSSVIEW_WILDTRACK_DIR)",
            dir.display()
        ));
        None
    }
}

/// Runs the `crossview` binary `bin` (the test's `env!("CARGO_BIN_EXE_crossview")`) with
/// `args` and extra environment `env` (`CROSSVIEW_WORKERS` cleared); asserts success and
/// returns its stdout.
pub fn run_crossview(bin: &str, args: &[&str], env: &[(&str, &str)]) -> String {
    let out = std::process::Command::new(bin)
        .args(args)
        .env_remove("CROSSVIEW_WORKERS")
        .envs(env.iter().copied())
        .output()
        .expect("run crossview");
    assert!(
        out.status.success(),
        "crossview {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("UTF-8 output")
}

/// A child process killed when dropped, so a failing test leaves no server behind.
pub struct ChildGuard(pub std::process::Child);

impl std::ops::Deref for ChildGuard {
    type Target = std::process::Child;
    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

impl std::ops::DerefMut for ChildGuard {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.0
    }
}

impl Drop for ChildGuard {
    fn drop(&mut self) {
        if let Ok(None) = self.0.try_wait() {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
}

/// A `crossview serve` child process on 127.0.0.1:0 with `args`; returns the child and its
/// base URL (from the "serving" log line; the log keeps draining to the test's stderr).
pub async fn spawn_serve(bin: &str, args: &[&str]) -> (ChildGuard, String) {
    use std::io::{BufRead, BufReader};
    let mut child = ChildGuard(
        std::process::Command::new(bin)
            .args(["serve", "--listen", "127.0.0.1:0"])
            .args(args)
            .env("RUST_LOG", "info")
            // A flag in `args` wins over it.
            .env("CROSSVIEW_MAX_QUEUE_DELAY", "60s")
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("start crossview serve"),
    );
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = oneshot::channel();
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("server: {line}");
            if let Some(i) = line.find("127.0.0.1:")
                && line.contains("serving")
                && let Some(tx) = tx.take()
            {
                let addr: String = line[i..]
                    .chars()
                    .take_while(|c| c.is_ascii_digit() || *c == '.' || *c == ':')
                    .collect();
                let _ = tx.send(addr);
            }
        }
    });
    let addr = guard("server start", rx).await.expect("serving log line");
    (child, format!("http://{addr}"))
}

/// Sends signal `name` (`HUP`, `TERM`, ...) to `child` with the system's `kill`.
pub fn signal(child: &std::process::Child, name: &str) {
    let ok = std::process::Command::new("kill")
        .args([format!("-{name}"), child.id().to_string()])
        .status()
        .expect("run kill")
        .success();
    assert!(ok, "kill -{name} {}", child.id());
}

/// Waits (bounded by [`guard`]) until the Prometheus metric `name` (with its labels, as
/// rendered) of the server at `base` reaches `at_least`.
pub async fn wait_for_metric(base: &str, name: &str, at_least: f64) {
    let http = reqwest::Client::new();
    guard(name, async {
        loop {
            let text = http
                .get(format!("{base}/metrics"))
                .send()
                .await
                .unwrap()
                .text()
                .await
                .unwrap();
            if metric(&text, name) >= at_least {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

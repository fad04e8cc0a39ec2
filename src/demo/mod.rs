//! The newcomer's demo: a simulated multi-camera scene streamed into a running server over
//! the real gRPC API, with the server's identities scored live against the simulator's ground
//! truth.
//!
//! [`stream_scene`] is the client: it checks the server's scene matches the simulated cameras,
//! opens one bidirectional `Stream` call, and per frame sends every camera's batch (ground-truth
//! ids stripped: the protobuf `Detection` has no id field), waits for that frame's result and
//! scores it with [`score`] (SPEC §5, via `crossview_eval::metrics`). [`start_local_server`]
//! starts the real server in-process on a loopback port for `crossview demo`.
pub mod score;

use std::future::Future;
use std::net::SocketAddr;
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::{mpsc, oneshot};
use tokio_stream::StreamExt;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

use crossview_api::convert::{detection_to_pb, identity_from_pb};
use crossview_api::pb;
use crossview_api::pb::association_client::AssociationClient;
use crossview_core::identity::Identity;
use crossview_core::{Frame, SceneSpec};
use crossview_data::sim::{SimConfig, Simulator};
use crossview_eval::metrics::Metrics;
use crossview_serve::{Error, Result, ServeConfig, Server};

pub use score::{RunningScore, TruthIds, pair_records};

/// What one demo run streams.
#[derive(Debug, Clone)]
pub struct DemoConfig {
    /// The simulated scene (its cameras must be the served scene's cameras).
    pub sim: SimConfig,
    /// Scene name on the server.
    pub scene: String,
    /// Pause between frames (`None`: as fast as the server answers).
    pub pace: Option<Duration>,
}

/// One streamed frame, as shown to the user.
#[derive(Debug, Clone)]
pub struct FrameReport {
    /// Frame id.
    pub frame_id: u64,
    /// Boxes sent (all cameras).
    pub boxes: usize,
    /// Identities the server returned.
    pub identities: usize,
    /// Identities seen by two or more cameras.
    pub multi_view: usize,
    /// Cross-view links (pairs of boxes put in one identity).
    pub links: usize,
    /// Whether every camera made it into the frame.
    pub complete: bool,
    /// Server-side latency (first batch to result), milliseconds.
    pub latency_ms: f64,
    /// SPEC §5 metrics of this frame alone.
    pub frame: Metrics,
    /// SPEC §5 metrics over all frames so far.
    pub running: Metrics,
    /// Cameras the server fenced in this frame (they no longer fit the model): left out of
    /// the score, as the server left them out of association.
    pub fenced: Vec<String>,
}

/// How a demo run ended.
#[derive(Debug, Clone)]
pub struct DemoSummary {
    /// Frames streamed and scored.
    pub frames: u64,
    /// True when stopped early (Ctrl-C) rather than after the last frame.
    pub interrupted: bool,
    /// SPEC §5 metrics over all scored frames.
    pub metrics: Metrics,
}

/// Maps a gRPC status from the server to the server's error (the client sees what it refused).
fn status_error(what: &str, s: tonic::Status) -> Error {
    let msg = format!("{what}: {}", s.message());
    match s.code() {
        tonic::Code::InvalidArgument | tonic::Code::NotFound => Error::invalid(what, s.message()),
        tonic::Code::ResourceExhausted => Error::ResourceExhausted(msg),
        tonic::Code::Unauthenticated => Error::Unauthenticated(msg),
        code => Error::Unavailable(format!("{msg} ({code:?})")),
    }
}

/// Checks that the served scene has the simulated cameras (names and image sizes, in order).
fn check_scene(served: &pb::Scene, spec: &SceneSpec) -> Result<()> {
    let same = served.cameras.len() == spec.cameras.len()
        && served
            .cameras
            .iter()
            .zip(&spec.cameras)
            .all(|(s, c)| s.name == c.name && s.width == c.width && s.height == c.height);
    if same {
        return Ok(());
    }
    let list = |v: Vec<String>| v.join(", ");
    Err(Error::invalid(
        "scene",
        format!(
            "served scene '{}' has cameras [{}] but the simulated scene '{}' has [{}]; \
             use the preset the model was trained on",
            served.name,
            list(
                served
                    .cameras
                    .iter()
                    .map(|c| format!("{} {}x{}", c.name, c.width, c.height))
                    .collect()
            ),
            spec.name,
            list(
                spec.cameras
                    .iter()
                    .map(|c| format!("{} {}x{}", c.name, c.width, c.height))
                    .collect()
            ),
        ),
    ))
}

/// Every camera's batch of `frame` (an empty list for a camera that saw nobody).
fn frame_batches(scene: &str, spec: &SceneSpec, frame: &Frame) -> Vec<pb::Batch> {
    spec.cameras
        .iter()
        .zip(&frame.views)
        .map(|(cam, view)| pb::Batch {
            scene: scene.to_string(),
            camera: cam.name.clone(),
            frame_id: frame.frame_id,
            time: None,
            detections: view
                .as_deref()
                .unwrap_or_default()
                .iter()
                .map(detection_to_pb)
                .collect(),
        })
        .collect()
}

/// Streams `cfg.sim` frames to the server at `endpoint` (e.g. `http://127.0.0.1:8080`) over
/// one gRPC `Stream` call, scoring each frame's identities against the simulator's ground
/// truth; `on_frame` sees every scored frame. Stops after the last frame or when `stop`
/// resolves (checked between frames).
pub async fn stream_scene(
    endpoint: &str,
    cfg: &DemoConfig,
    stop: impl Future<Output = ()>,
    mut on_frame: impl FnMut(&FrameReport),
) -> Result<DemoSummary> {
    let channel = Channel::from_shared(endpoint.to_string())
        .map_err(|e| Error::invalid("server", format!("'{endpoint}': {e}")))?
        .connect()
        .await
        .map_err(|e| Error::Unavailable(format!("cannot connect to {endpoint}: {e}")))?;
    let mut client = AssociationClient::new(channel);
    let served = client
        .get_scene(pb::GetSceneRequest {
            scene: cfg.scene.clone(),
        })
        .await
        .map_err(|s| status_error("GetScene", s))?
        .into_inner();
    let mut sim = Simulator::new(&cfg.sim)?;
    let spec = sim.scene().clone();
    check_scene(&served, &spec)?;
    let cameras: Vec<String> = spec.cameras.iter().map(|c| c.name.clone()).collect();

    let (tx, rx) = mpsc::channel::<pb::Batch>(spec.cameras.len().max(1) * 4);
    let mut responses = client
        .stream(ReceiverStream::new(rx))
        .await
        .map_err(|s| status_error("Stream", s))?
        .into_inner();

    let mut truth_ids = TruthIds::new();
    let mut score = RunningScore::new();
    let mut frames = 0u64;
    let mut interrupted = false;
    tokio::pin!(stop);
    while let Some(frame) = sim.next_frame() {
        let mut truth = truth_ids.of_frame(&frame);
        for batch in frame_batches(&cfg.scene, &spec, &frame) {
            tx.send(batch)
                .await
                .map_err(|_| Error::Unavailable("the server closed the stream".into()))?;
        }
        let result = tokio::select! {
            r = next_result(&mut responses, frame.frame_id) => r?,
            _ = &mut stop => { interrupted = true; break; }
        };
        if !result.error.is_empty() {
            return Err(Error::Unavailable(format!(
                "frame {}: the server could not associate it: {}",
                frame.frame_id, result.error
            )));
        }
        // A fenced camera is scored as the server treated it: as absent.
        for (t, name) in truth.iter_mut().zip(&cameras) {
            if result.fenced_cameras.contains(name) {
                *t = None;
            }
        }
        let identities: Vec<Identity> = result
            .identities
            .iter()
            .filter(|i| {
                !i.members
                    .iter()
                    .any(|m| result.fenced_cameras.contains(&m.camera))
            })
            .map(identity_from_pb)
            .collect();
        let records = pair_records(frame.frame_id, &cameras, &truth, &identities)?;
        let (frame_m, running) = score.add_frame(records);
        frames += 1;
        on_frame(&FrameReport {
            frame_id: frame.frame_id,
            boxes: frame.num_boxes(),
            identities: identities.len(),
            multi_view: identities.iter().filter(|i| i.members.len() > 1).count(),
            links: identities.iter().map(Identity::links).sum(),
            complete: result.complete,
            latency_ms: result.latency_ms,
            frame: frame_m,
            running,
            fenced: result.fenced_cameras.clone(),
        });
        if let Some(pace) = cfg.pace {
            tokio::select! {
                _ = tokio::time::sleep(pace) => {}
                _ = &mut stop => { interrupted = true; break; }
            }
        }
    }
    drop(tx);
    Ok(DemoSummary {
        frames,
        interrupted,
        metrics: score.total(),
    })
}

/// Reads the response stream until the result of `frame_id`; a rejected batch is an error.
async fn next_result(
    responses: &mut tonic::Streaming<pb::StreamResponse>,
    frame_id: u64,
) -> Result<pb::FrameResult> {
    use pb::stream_response::Event;
    loop {
        let msg = responses
            .next()
            .await
            .ok_or_else(|| Error::Unavailable("the server ended the stream".into()))?
            .map_err(|s| status_error("Stream", s))?;
        match msg.event {
            Some(Event::Ack(a)) if a.code != 0 => {
                return Err(Error::invalid(
                    format!("batch (camera '{}', frame {})", a.camera, a.frame_id),
                    format!("rejected by the server ({}): {}", a.kind, a.message),
                ));
            }
            Some(Event::Result(r)) if r.frame_id == frame_id => return Ok(r),
            // Acks, and results of frames other clients push to the same scene.
            _ => {}
        }
    }
}

/// A server started in this process (see [`start_local_server`]).
#[derive(Debug)]
pub struct LocalServer {
    /// The loopback address it listens on.
    pub addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<Result<()>>,
}

impl LocalServer {
    /// `http://addr`, the endpoint for [`stream_scene`].
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Graceful shutdown (flushes pending frames, closes connections); waits for it.
    pub async fn shutdown(mut self) -> Result<()> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        self.task
            .await
            .map_err(|e| Error::Unavailable(format!("server task failed: {e}")))?
    }
}

/// Loads `config`'s models (blocking work off the async threads) and serves them on `listen`
/// (e.g. `127.0.0.1:0`) in this process until [`LocalServer::shutdown`].
pub async fn start_local_server(config: ServeConfig, listen: &str) -> Result<LocalServer> {
    let server = tokio::task::spawn_blocking(move || Server::load(config))
        .await
        .map_err(|e| Error::Unavailable(format!("model loading task failed: {e}")))??;
    let listener = TcpListener::bind(listen)
        .await
        .map_err(|e| crossview_core::Error::io(listen, e))?;
    let addr = listener
        .local_addr()
        .map_err(|e| crossview_core::Error::io(listen, e))?;
    let (tx, rx) = oneshot::channel::<()>();
    let task = tokio::spawn(server.serve(listener, async move {
        let _ = rx.await;
    }));
    Ok(LocalServer {
        addr,
        stop: Some(tx),
        task,
    })
}

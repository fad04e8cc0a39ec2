//! The gRPC transport (tonic): the one `Error → Status` mapping and a thin `Association` implementation over [`Service`].
pub mod push;

use std::pin::Pin;
use std::sync::Arc;

use futures::{Stream, StreamExt};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::ReceiverStream;
use tonic::{Code, Request, Response, Status, Streaming};

use crossview_api::convert::{
    associate_from_pb, batch_from_pb, reload_to_pb, result_to_pb, scene_to_pb,
};
use crossview_api::pb;

use crate::error::Error;
use crate::service::Service;

/// The gRPC methods this server serves: the only gRPC label values besides `other`.
pub(crate) const METHODS: &[&str] = &[
    "/crossview.v1.Association/Associate",
    "/crossview.v1.Association/Push",
    "/crossview.v1.Association/Subscribe",
    "/crossview.v1.Association/Stream",
    "/crossview.v1.Association/ListScenes",
    "/crossview.v1.Association/GetScene",
    "/crossview.v1.Association/Reload",
    "/grpc.health.v1.Health/Check",
    "/grpc.health.v1.Health/Watch",
    "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
];

/// The one `Error → gRPC status` mapping; the message is the error's, truncated.
pub(crate) fn status(e: Error) -> Status {
    use crossview_core::Error as Core;
    let code = match &e {
        Error::Core(c) => match c {
            Core::InvalidArgument { .. } | Core::Format { .. } => Code::InvalidArgument,
            Core::UnknownScene(_) | Core::UnknownCamera { .. } => Code::NotFound,
            Core::DuplicateBatch { .. } => Code::AlreadyExists,
            Core::Io { .. }
            | Core::Model { .. }
            | Core::Runtime { .. }
            | Core::Encoder(_)
            | Core::Internal { .. }
            | Core::Training(_) => Code::Internal,
        },
        Error::LateBatch { .. } | Error::NoModel(_) => Code::FailedPrecondition,
        Error::FrameOutOfRange { .. } => Code::OutOfRange,
        Error::ResourceExhausted(_)
        | Error::Overloaded { .. }
        | Error::DeadlineExceeded(_)
        | Error::SubscriberStalled(_) => Code::ResourceExhausted,
        Error::Unauthenticated(_) => Code::Unauthenticated,
        Error::Unavailable(_) => Code::Unavailable,
    };
    let mut meta = tonic::metadata::MetadataMap::new();
    meta.insert(
        KIND_KEY,
        tonic::metadata::MetadataValue::from_static(e.kind()),
    );
    if let Error::Core(Core::InvalidArgument { field, .. }) = &e
        && let Ok(v) = crate::echo::truncate_echo(field).parse()
    {
        meta.insert(FIELD_KEY, v);
    }
    if let Some(ms) = retry_after_ms(&e) {
        meta.insert(RETRY_AFTER_KEY, ms.into());
    }
    Status::with_metadata(code, crate::echo::truncate_echo(&e.report()), meta)
}

/// Status metadata naming the error's kind (as the HTTP body's `error.kind` and a rejected
/// ack's `kind`), so a client tells kinds that share a code apart without reading messages.
pub(crate) const KIND_KEY: &str = "crossview-error-kind";
/// Status metadata naming the offending field of an `invalid_argument` (when ASCII).
pub(crate) const FIELD_KEY: &str = "crossview-error-field";
/// Status metadata of an `overloaded` refusal: milliseconds to wait before retrying (as the
/// HTTP `Retry-After`, and a rejected ack's `retry_after_ms`).
pub(crate) const RETRY_AFTER_KEY: &str = "crossview-retry-after-ms";

/// An `overloaded` refusal's retry-after in milliseconds (at least 1).
fn retry_after_ms(e: &Error) -> Option<u64> {
    match e {
        Error::Overloaded { retry_after, .. } => {
            Some((retry_after.as_millis().min(u128::from(u64::MAX)) as u64).max(1))
        }
        _ => None,
    }
}

/// Pushes one protobuf batch — or a message that did not decode as one (see [`super::push`])
/// — and turns the outcome into its acknowledgement. An undecodable message's ack has no
/// scene, camera or frame id: acks come in message order.
fn push_one(svc: &Service, b: crate::error::Result<pb::Batch>) -> pb::BatchAck {
    let (scene, camera, frame_id) = match &b {
        Ok(b) => (echo(&b.scene), echo(&b.camera), b.frame_id),
        Err(_) => (String::new(), String::new(), 0),
    };
    let outcome = b
        .and_then(|b| Ok(batch_from_pb(b)?))
        .inspect_err(|e| svc.metrics().error(e))
        .and_then(|(scene, batch)| svc.push(&scene, batch));
    match outcome {
        // The frame id the batch was placed at (a timestamped batch's tick).
        Ok(ack) => pb::BatchAck {
            scene,
            camera,
            frame_id: ack.frame_id,
            ..Default::default()
        },
        Err(e) => refusal(scene, camera, frame_id, e),
    }
}

pub(crate) type BoxStream<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// One item of what a `Push` or `Stream` call reads: a batch, or a message that is not one
/// (see [`super::push`]); or the status the transport ends the call with (the call's status).
pub(crate) type Incoming = Result<crate::error::Result<pb::Batch>, Status>;

/// Forwards a `Stream` call's scene results to its response until the call is over: the client
/// cancelled (the subscriber is dropped at once, not at the next frame), the scene's results
/// ended (shutdown), or the client half-closed and the result of the newest frame it had
/// accepted went out (at most `linger` after the half-close: sync timeout + frame deadline).
async fn forward_results(
    mut results: crate::service::ResultStream,
    tx: mpsc::Sender<Result<pb::StreamResponse, Status>>,
    mut half_closed: watch::Receiver<Option<Option<u64>>>,
    linger: std::time::Duration,
) {
    use pb::stream_response::Event;
    let mut newest_sent: Option<u64> = None;
    let mut deadline: Option<tokio::time::Instant> = None;
    let mut watching = true;
    loop {
        // Ends once the newest accepted frame's result is out (or nothing was accepted).
        if let Some(last) = *half_closed.borrow() {
            if last.is_none_or(|l| newest_sent.is_some_and(|s| s >= l)) {
                return;
            }
            deadline.get_or_insert_with(|| tokio::time::Instant::now() + linger);
        }
        let linger_over = async {
            match deadline {
                Some(t) => tokio::time::sleep_until(t).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            r = results.next() => {
                let Some(r) = r else { return };
                let item = r
                    .map(|r| {
                        let id = r.result.frame_id;
                        newest_sent = Some(newest_sent.map_or(id, |s| s.max(id)));
                        pb::StreamResponse {
                            event: Some(Event::Result(result_to_pb(&r.result))),
                        }
                    })
                    .map_err(status);
                if tx.send(item).await.is_err() {
                    return;
                }
            }
            changed = half_closed.changed(), if watching => {
                if changed.is_err() {
                    // The reader task is gone; what it said last (if anything) stands.
                    watching = false;
                    if half_closed.borrow().is_none() {
                        return;
                    }
                }
            }
            _ = tx.closed() => return,
            _ = linger_over => return,
        }
    }
}

/// The tonic service: a thin shell over [`Service`].
#[derive(Debug, Clone)]
pub(crate) struct GrpcService {
    svc: Arc<Service>,
    stall_timeout: std::time::Duration,
}

impl GrpcService {
    /// Wraps the shared domain service; result subscribers that stop reading for
    /// `stall_timeout` are disconnected.
    pub fn new(svc: Arc<Service>, stall_timeout: std::time::Duration) -> Self {
        GrpcService { svc, stall_timeout }
    }

    /// The acknowledgements of a `Push` call: one per message, in order, until the client
    /// half-closes, the server shuts down or the transport ends the call (its status is the
    /// call's: `messages` yields it and ends).
    pub(crate) fn push_acks<S>(&self, messages: S) -> BoxStream<pb::BatchAck>
    where
        S: Stream<Item = Incoming> + Send + 'static,
    {
        let svc = self.svc.clone();
        let stop = svc.shutting_down();
        Box::pin(
            messages
                .take_until(stop)
                .map(move |m| m.map(|b| push_one(&svc, b))),
        )
    }

    /// The responses of a `Stream` call: one ack per message, in order (a message that is not
    /// a batch gets an INVALID_ARGUMENT ack and fixes no scene), interleaved with the results
    /// of the scene fixed by the first accepted batch.
    pub(crate) fn stream_responses<S>(&self, request: Request<S>) -> BoxStream<pb::StreamResponse>
    where
        S: Stream<Item = Incoming> + Send + 'static,
    {
        use pb::stream_response::Event;
        let svc = self.svc.clone();
        let conn = request
            .extensions()
            .get::<crate::conn::ConnHandle>()
            .cloned();
        let stall = Some(self.stall_timeout);
        let input = request.into_inner();
        let (tx, rx) = mpsc::channel::<Result<pb::StreamResponse, Status>>(64);
        tokio::spawn(async move {
            tokio::pin!(input);
            let mut scene: Option<String> = None;
            // The newest frame id this call had accepted; sent to the result forwarder when the
            // client half-closes, so the call ends once that frame's result is out.
            let mut last_accepted: Option<u64> = None;
            let (half_closed, half_closed_rx) = watch::channel::<Option<Option<u64>>>(None);
            let stop = svc.shutting_down();
            tokio::pin!(stop);
            loop {
                let msg = tokio::select! {
                    m = input.next() => m,
                    _ = &mut stop => None,
                    // The client went away: stop reading (the forwarder notices too).
                    _ = tx.closed() => break,
                };
                let b = match msg {
                    None => break,
                    Some(Err(s)) => {
                        let _ = tx.send(Err(s)).await;
                        break;
                    }
                    Some(Ok(b)) => b,
                };
                let ack = match (&scene, b) {
                    // Not a batch: refused like one, the scene still to be fixed.
                    (_, Err(e)) => push_one(&svc, Err(e)),
                    (None, Ok(b)) => match svc.subscribe(&b.scene, conn.clone(), stall) {
                        Ok(results) => {
                            scene = Some(b.scene.clone());
                            let linger = svc
                                .scene(&b.scene)
                                .map(|s| {
                                    let d = s.describe();
                                    std::time::Duration::from_millis(d.sync_timeout_ms)
                                        + s.limits().max_queue_delay
                                })
                                .unwrap_or_default();
                            tokio::spawn(forward_results(
                                results,
                                tx.clone(),
                                half_closed_rx.clone(),
                                linger,
                            ));
                            push_one(&svc, Ok(b))
                        }
                        Err(e) => reject(&b, e),
                    },
                    (Some(s), Ok(b)) if *s != b.scene => reject(
                        &b,
                        Error::invalid(
                            "scene",
                            format!(
                                "this stream serves scene '{s}', got '{}'",
                                crate::echo::truncate_echo(&b.scene)
                            ),
                        ),
                    ),
                    (Some(_), Ok(b)) => push_one(&svc, Ok(b)),
                };
                if ack.code == 0 {
                    last_accepted =
                        Some(last_accepted.map_or(ack.frame_id, |l| l.max(ack.frame_id)));
                }
                let item = pb::StreamResponse {
                    event: Some(Event::Ack(ack)),
                };
                if tx.send(Ok(item)).await.is_err() {
                    break;
                }
            }
            let _ = half_closed.send(Some(last_accepted));
        });
        Box::pin(ReceiverStream::new(rx))
    }
}

#[tonic::async_trait]
impl pb::association_server::Association for GrpcService {
    async fn associate(
        &self,
        request: Request<pb::AssociateRequest>,
    ) -> Result<Response<pb::FrameResult>, Status> {
        let (scene, req) = associate_from_pb(request.into_inner())
            .map_err(Error::from)
            .inspect_err(|e| self.svc.metrics().error(e))
            .map_err(status)?;
        let r = self.svc.associate(&scene, req).await.map_err(status)?;
        Ok(Response::new(result_to_pb(&r)))
    }

    type PushStream = BoxStream<pb::BatchAck>;

    async fn push(
        &self,
        request: Request<Streaming<pb::Batch>>,
    ) -> Result<Response<Self::PushStream>, Status> {
        // The server routes Push and Stream to `super::push::Routes`, which keeps the call
        // open past a message that does not decode; these generated entry points (tonic's
        // framing: such a message ends the call) serve only direct users of
        // `AssociationServer`.
        let messages = request.into_inner().map(|m| m.map(Ok));
        Ok(Response::new(self.push_acks(messages)))
    }

    type SubscribeStream = BoxStream<pb::FrameResult>;

    async fn subscribe(
        &self,
        request: Request<pb::SubscribeRequest>,
    ) -> Result<Response<Self::SubscribeStream>, Status> {
        let conn = request
            .extensions()
            .get::<crate::conn::ConnHandle>()
            .cloned();
        let stall = Some(self.stall_timeout);
        let results = self
            .svc
            .subscribe(&request.into_inner().scene, conn, stall)
            .map_err(status)?;
        let out = results.map(|r| r.map(|r| result_to_pb(&r.result)).map_err(status));
        Ok(Response::new(Box::pin(out)))
    }

    type StreamStream = BoxStream<pb::StreamResponse>;

    async fn stream(
        &self,
        request: Request<Streaming<pb::Batch>>,
    ) -> Result<Response<Self::StreamStream>, Status> {
        // See `push` above.
        let request = request.map(|messages| messages.map(|m| m.map(Ok)));
        Ok(Response::new(self.stream_responses(request)))
    }

    async fn list_scenes(
        &self,
        _request: Request<pb::ListScenesRequest>,
    ) -> Result<Response<pb::ListScenesResponse>, Status> {
        Ok(Response::new(pb::ListScenesResponse {
            scenes: self.svc.scenes().into_iter().map(scene_to_pb).collect(),
        }))
    }

    async fn reload(
        &self,
        _request: Request<pb::ReloadRequest>,
    ) -> Result<Response<pb::ReloadResponse>, Status> {
        let reloads = self.svc.reload().await;
        Ok(Response::new(pb::ReloadResponse {
            reloads: reloads.into_iter().map(reload_to_pb).collect(),
        }))
    }

    async fn get_scene(
        &self,
        request: Request<pb::GetSceneRequest>,
    ) -> Result<Response<pb::Scene>, Status> {
        let s = self
            .svc
            .describe(&request.into_inner().scene)
            .map_err(status)?;
        Ok(Response::new(scene_to_pb(s)))
    }
}

/// A client-supplied name as echoed in an ack (bounded, see [`super::truncate_echo`]).
fn echo(s: &str) -> String {
    crate::echo::truncate_echo(s).into_owned()
}

fn reject(b: &pb::Batch, e: Error) -> pb::BatchAck {
    refusal(echo(&b.scene), echo(&b.camera), b.frame_id, e)
}

/// The ack of a refused batch: `e`'s code, message, kind and retry-after.
fn refusal(scene: String, camera: String, frame_id: u64, e: Error) -> pb::BatchAck {
    let kind = e.kind().to_string();
    let retry_after_ms = retry_after_ms(&e).unwrap_or(0);
    let status = status(e);
    pb::BatchAck {
        scene,
        camera,
        frame_id,
        code: status.code() as i32,
        message: status.message().to_string(),
        kind,
        retry_after_ms,
    }
}

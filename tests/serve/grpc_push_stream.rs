//! One bad message does not end a gRPC `Push` or `Stream` call: after [good, bad, good, good] —
//! bad being invalid UTF-8 in `camera`, a truncated field in a well-framed message, an 11-byte
//! varint or a message over `--max-request-bytes` — the bad one gets an INVALID_ARGUMENT ack and
//! the batches after it are accepted and delivered (their frame comes out complete, on
//! `Subscribe` and, for `Stream`, on the call itself). What the framing cannot get past (the
//! request ending inside a message) ends the call with INVALID_ARGUMENT, never INTERNAL. The
//! messages are framed by hand and sent over a real HTTP/2 gRPC channel, one chunk at a time,
//! the call open throughout.

use std::time::Duration;

use crossview_api::pb;
use crossview_api::pb::stream_response::Event;
use crossview_testing::*;
use futures::StreamExt;
use http_body::Frame;
use prost::Message;
use prost::bytes::Bytes;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Code;
use tonic::codec::Streaming;
use tonic::transport::Channel;
use tower::ServiceExt;

type Chunk = Result<Frame<Bytes>, std::convert::Infallible>;

/// The two calls that take a stream of batches.
#[derive(Debug, Clone, Copy)]
enum Method {
    Push,
    Stream,
}

/// What comes back on a call: `Push` acks, or `Stream` events.
enum Responses {
    Push(Streaming<pb::BatchAck>),
    Stream(Streaming<pb::StreamResponse>),
}

/// One open `Push` or `Stream` call whose request bytes the test writes itself.
struct RawCall {
    tx: Option<mpsc::Sender<Chunk>>,
    responses: Responses,
    /// Frame results that came on a `Stream` call while the test waited for an ack.
    results: Vec<pb::FrameResult>,
}

impl RawCall {
    async fn open(server: &TestServer, method: Method) -> RawCall {
        let ch = Channel::from_shared(server.url(""))
            .unwrap()
            .connect()
            .await
            .expect("gRPC connect");
        let (tx, rx) = mpsc::channel::<Chunk>(16);
        let body = tonic::body::Body::new(http_body_util::StreamBody::new(ReceiverStream::new(rx)));
        let req = http::Request::builder()
            .method("POST")
            .uri(server.url(&format!("/crossview.v1.Association/{method:?}")))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(body)
            .unwrap();
        let resp = guard("the call", ch.oneshot(req)).await.expect("the call");
        let (parts, body) = resp.into_parts();
        fn decode<M: Message + Default + 'static>(
            body: tonic::body::Body,
            status: http::StatusCode,
        ) -> Streaming<M> {
            Streaming::new_response(
                tonic_prost::ProstDecoder::default(),
                body,
                status,
                None,
                None,
            )
        }
        let responses = match method {
            Method::Push => Responses::Push(decode(body, parts.status)),
            Method::Stream => Responses::Stream(decode(body, parts.status)),
        };
        RawCall {
            tx: Some(tx),
            responses,
            results: Vec::new(),
        }
    }

    /// Sends raw request bytes (any part of any frame).
    async fn send(&mut self, bytes: &[u8]) {
        let tx = self.tx.as_ref().expect("request still open");
        tx.send(Ok(Frame::data(Bytes::copy_from_slice(bytes))))
            .await
            .expect("request body");
    }

    /// Sends one framed message in two chunks (split inside its payload).
    async fn send_message(&mut self, payload: &[u8]) {
        let f = frame(payload);
        let (a, b) = f.split_at(5 + payload.len() / 2);
        self.send(a).await;
        self.send(b).await;
    }

    /// The next response (a `Push` ack as an [`Event::Ack`]), or how the call ended.
    async fn next(&mut self) -> Result<Option<Event>, tonic::Status> {
        match &mut self.responses {
            Responses::Push(acks) => Ok(guard("ack", acks.message()).await?.map(Event::Ack)),
            Responses::Stream(events) => Ok(guard("event", events.message())
                .await?
                .map(|r| r.event.expect("a Stream response with an event"))),
        }
    }

    /// The next ack; frame results before it are kept for [`RawCall::result`].
    async fn ack(&mut self) -> pb::BatchAck {
        loop {
            match self.next().await.expect("an ack").expect("an ack") {
                Event::Ack(a) => return a,
                Event::Result(r) => self.results.push(r),
            }
        }
    }

    /// The next frame result of a `Stream` call.
    async fn result(&mut self) -> pb::FrameResult {
        if !self.results.is_empty() {
            return self.results.remove(0);
        }
        match self.next().await.expect("a result").expect("a result") {
            Event::Result(r) => r,
            Event::Ack(a) => panic!("a result, not {a:?}"),
        }
    }

    /// How the call ended (frame results before that are skipped).
    async fn status(&mut self) -> tonic::Status {
        loop {
            match self.next().await {
                Err(e) => return e,
                Ok(Some(Event::Result(_))) => {}
                other => panic!("the call ends with a status, not {other:?}"),
            }
        }
    }

    /// Half-closes the request.
    fn close(&mut self) {
        self.tx = None;
    }
}

/// One gRPC message frame: uncompressed flag, big-endian length, payload.
fn frame(payload: &[u8]) -> Vec<u8> {
    let mut f = vec![0];
    f.extend_from_slice(&(payload.len() as u32).to_be_bytes());
    f.extend_from_slice(payload);
    f
}

fn encode(b: &pb::Batch) -> Vec<u8> {
    b.encode_to_vec()
}

/// Starts a server whose frames wait (almost) forever for missing cameras, so a frame only
/// comes out complete, and subscribes to its results.
async fn setup(
    configure: impl FnOnce(&mut crossview_serve::ServeConfig),
) -> (TestServer, Streaming<pb::FrameResult>) {
    let server = start(|c| {
        c.sync_timeout = Duration::from_secs(120);
        configure(c);
    })
    .await;
    let mut client = server.grpc().await;
    let results = client
        .subscribe(pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();
    (server, results)
}

/// The frame's result came out complete with every box of [`good_bad_good`] in an identity.
fn check_complete(r: &pb::FrameResult, frame_id: u64) {
    assert_eq!((r.frame_id, r.complete), (frame_id, true), "{r:?}");
    assert!(r.missing_cameras.is_empty() && r.error.is_empty(), "{r:?}");
    check_identities(r, &[2, 2, 2]);
    let members: usize = r.identities.iter().map(|i| i.members.len()).sum();
    assert_eq!(members, 6, "{r:?}");
}

/// [good c0, bad, good c1, good c2] of one frame on one open call, first of `Push` (frame 7),
/// then of `Stream` (frame 8): the bad message gets its own INVALID_ARGUMENT ack (message
/// containing `expect`), the others are accepted, the frame comes out complete with every box
/// in an identity (on `Subscribe`, and on the call itself for `Stream`), and the call ends
/// cleanly at the half-close.
async fn good_bad_good(
    bad: &[u8],
    expect: &str,
    server: TestServer,
    mut results: Streaming<pb::FrameResult>,
) {
    for (method, frame_id) in [(Method::Push, 7), (Method::Stream, 8)] {
        let before = metric(
            &server.metrics().await,
            "crossview_errors_total{kind=\"invalid_argument\"}",
        );
        let mut call = RawCall::open(&server, method).await;
        call.send_message(&encode(&batch(0, frame_id, 2))).await;
        let a = call.ack().await;
        assert_eq!(
            (a.code, a.camera.as_str(), a.frame_id),
            (0, "c0", frame_id),
            "{method:?}: {a:?}"
        );

        call.send_message(bad).await;
        let a = call.ack().await;
        assert_eq!(a.code, Code::InvalidArgument as i32, "{method:?}: {a:?}");
        assert_eq!(a.kind, "invalid_argument", "{method:?}: {a:?}");
        assert!(a.message.contains(expect), "{method:?}: {a:?}");

        call.send_message(&encode(&batch(1, frame_id, 2))).await;
        let a = call.ack().await;
        assert_eq!((a.code, a.camera.as_str()), (0, "c1"), "{method:?}: {a:?}");
        call.send_message(&encode(&batch(2, frame_id, 2))).await;
        let a = call.ack().await;
        assert_eq!((a.code, a.camera.as_str()), (0, "c2"), "{method:?}: {a:?}");

        let r = guard("the frame", results.next()).await.unwrap().unwrap();
        check_complete(&r, frame_id);
        if let Method::Stream = method {
            check_complete(&call.result().await, frame_id);
        }

        call.close();
        assert!(
            matches!(call.next().await, Ok(None)),
            "{method:?}: the call ends cleanly"
        );
        let after = metric(
            &server.metrics().await,
            "crossview_errors_total{kind=\"invalid_argument\"}",
        );
        assert_eq!(after, before + 1.0, "{method:?}");
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_utf8_in_camera_is_refused_alone() {
    let (server, results) = setup(|_| {}).await;
    let mut b = batch(1, 7, 1);
    b.camera = "XX".into();
    let mut bad = encode(&b);
    let at = bad.windows(2).position(|w| w == b"XX").unwrap();
    bad[at..at + 2].copy_from_slice(&[0xff, 0xfe]);
    assert!(pb::Batch::decode(bad.as_slice()).is_err());
    good_bad_good(&bad, "Batch.camera", server, results).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_field_in_a_well_framed_message_is_refused_alone() {
    let (server, results) = setup(|_| {}).await;
    // The last detection's length prefix promises more bytes than the message has.
    let mut bad = encode(&batch(1, 7, 3));
    bad.truncate(bad.len() - 4);
    assert!(pb::Batch::decode(bad.as_slice()).is_err());
    good_bad_good(&bad, "not a crossview.v1.Batch message", server, results).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_11_byte_varint_is_refused_alone() {
    let (server, results) = setup(|_| {}).await;
    let mut bad = encode(&pb::Batch {
        scene: "lab".into(),
        camera: "c1".into(),
        frame_id: 0,
        time: None,
        detections: vec![],
    });
    // Field 3 (frame_id, varint) with 11 bytes: ten continuation bytes, then a last one.
    bad.push(3 << 3);
    bad.extend_from_slice(&[0xff; 10]);
    bad.push(0x01);
    assert!(pb::Batch::decode(bad.as_slice()).is_err());
    good_bad_good(&bad, "varint", server, results).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_message_over_the_limit_is_skipped_and_refused_alone() {
    let (server, results) = setup(|c| c.limits.max_request_bytes = 4096).await;
    let mut b = batch(1, 7, 20);
    for d in &mut b.detections {
        d.appearance = vec![0.5; 64];
    }
    let bad = encode(&b);
    assert!(bad.len() > 4096, "{}", bad.len());
    good_bad_good(
        &bad,
        &format!("{} bytes is over the limit of 4096", bad.len()),
        server,
        results,
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_request_ending_inside_a_message_ends_either_call_with_invalid_argument() {
    let server = start(|c| c.limits.max_request_bytes = 4096).await;
    let good = frame(&encode(&batch(0, 7, 1)));
    // Ending inside a payload, inside a header, and inside an over-limit message being skipped
    // (declared 1 GiB: nothing of that size is ever held).
    let mut big_header = vec![0];
    big_header.extend_from_slice(&(1u32 << 30).to_be_bytes());
    let cases: [(&[u8], &str); 3] = [
        (&good[..good.len() - 3], "ended inside a message"),
        (&good[..3], "ended inside a message header (3 of 5 bytes)"),
        (&big_header, "(0 of 1073741824 bytes)"),
    ];
    let calls = [Method::Push, Method::Stream]
        .into_iter()
        .flat_map(|m| cases.map(|c| (m, c)));
    for (frame_id, (method, (tail, expect))) in (10u64..).zip(calls) {
        let mut call = RawCall::open(&server, method).await;
        call.send_message(&encode(&batch(0, frame_id, 1))).await;
        assert_eq!(call.ack().await.code, 0, "{method:?}");
        call.send(tail).await;
        call.close();
        let e = call.status().await;
        assert_eq!(e.code(), Code::InvalidArgument, "{method:?}: {e:?}");
        assert!(e.message().contains(expect), "{method:?}: {e:?}");
    }
    server.shutdown().await.unwrap();
}

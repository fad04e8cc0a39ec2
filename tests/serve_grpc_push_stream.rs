//! One bad message does not end a gRPC `Push` stream: after [good, bad, good, good] — bad being
//! invalid UTF-8 in `camera`, a truncated field in a well-framed message, an 11-byte varint or
//! a message over `--max-request-bytes` — the bad one gets an INVALID_ARGUMENT ack and the
//! batches after it are accepted and delivered (their frame comes out complete). What the
//! framing cannot get past (the request ending inside a message) ends the call with
//! INVALID_ARGUMENT, never INTERNAL. The messages are framed by hand and sent over a real
//! HTTP/2 gRPC channel, one chunk at a time, the call open throughout.
mod common;

use std::time::Duration;

use common::*;
use crossview::serve::pb;
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

/// One open `Push` call whose request bytes the test writes itself.
struct RawPush {
    tx: Option<mpsc::Sender<Chunk>>,
    acks: Streaming<pb::BatchAck>,
}

impl RawPush {
    async fn open(server: &TestServer) -> RawPush {
        let ch = Channel::from_shared(server.url(""))
            .unwrap()
            .connect()
            .await
            .expect("gRPC connect");
        let (tx, rx) = mpsc::channel::<Chunk>(16);
        let body = tonic::body::Body::new(http_body_util::StreamBody::new(ReceiverStream::new(rx)));
        let req = http::Request::builder()
            .method("POST")
            .uri(server.url("/crossview.v1.Association/Push"))
            .header("content-type", "application/grpc")
            .header("te", "trailers")
            .body(body)
            .unwrap();
        let resp = guard("Push call", ch.oneshot(req))
            .await
            .expect("Push call");
        let (parts, body) = resp.into_parts();
        let decoder = tonic_prost::ProstDecoder::<pb::BatchAck>::default();
        RawPush {
            tx: Some(tx),
            acks: Streaming::new_response(decoder, body, parts.status, None, None),
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

    /// The next ack, or how the call ended.
    async fn next(&mut self) -> Result<Option<pb::BatchAck>, tonic::Status> {
        guard("ack", self.acks.message()).await
    }

    async fn ack(&mut self) -> pb::BatchAck {
        self.next().await.expect("an ack").expect("an ack")
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
    configure: impl FnOnce(&mut crossview::serve::ServeConfig),
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

/// [good c0, bad, good c1, good c2] of frame 7 on one open call: the bad message gets its own
/// INVALID_ARGUMENT ack (message containing `expect`), the others are accepted, frame 7 comes
/// out complete with every box in an identity, and the call ends cleanly at the half-close.
async fn good_bad_good(
    bad: &[u8],
    expect: &str,
    server: TestServer,
    mut results: Streaming<pb::FrameResult>,
) {
    let before = metric(
        &server.metrics().await,
        "crossview_errors_total{kind=\"invalid_argument\"}",
    );
    let mut push = RawPush::open(&server).await;
    push.send_message(&encode(&batch(0, 7, 2))).await;
    let a = push.ack().await;
    assert_eq!(
        (a.code, a.camera.as_str(), a.frame_id),
        (0, "c0", 7),
        "{a:?}"
    );

    push.send_message(bad).await;
    let a = push.ack().await;
    assert_eq!(a.code, Code::InvalidArgument as i32, "{a:?}");
    assert_eq!(a.kind, "invalid_argument", "{a:?}");
    assert!(a.message.contains(expect), "{a:?}");

    push.send_message(&encode(&batch(1, 7, 2))).await;
    let a = push.ack().await;
    assert_eq!((a.code, a.camera.as_str()), (0, "c1"), "{a:?}");
    push.send_message(&encode(&batch(2, 7, 2))).await;
    let a = push.ack().await;
    assert_eq!((a.code, a.camera.as_str()), (0, "c2"), "{a:?}");

    let r = guard("frame 7", results.next()).await.unwrap().unwrap();
    assert_eq!((r.frame_id, r.complete), (7, true), "{r:?}");
    assert!(r.missing_cameras.is_empty() && r.error.is_empty(), "{r:?}");
    check_identities(&r, &[2, 2, 2]);
    let members: usize = r.identities.iter().map(|i| i.members.len()).sum();
    assert_eq!(members, 6, "{r:?}");

    push.close();
    assert!(
        matches!(push.next().await, Ok(None)),
        "the call ends cleanly"
    );
    let after = metric(
        &server.metrics().await,
        "crossview_errors_total{kind=\"invalid_argument\"}",
    );
    assert_eq!(after, before + 1.0);
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
async fn a_request_ending_inside_a_message_ends_the_call_with_invalid_argument() {
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
    for (frame_id, (tail, expect)) in (10u64..).zip(cases) {
        let mut push = RawPush::open(&server).await;
        push.send_message(&encode(&batch(0, frame_id, 1))).await;
        assert_eq!(push.ack().await.code, 0);
        push.send(tail).await;
        push.close();
        let e = push.next().await.expect_err("the call ends with a status");
        assert_eq!(e.code(), Code::InvalidArgument, "{e:?}");
        assert!(e.message().contains(expect), "{e:?}");
    }
    server.shutdown().await.unwrap();
}

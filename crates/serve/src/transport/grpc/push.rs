//! The request framing of the gRPC calls that take a stream of batches, `Push` and `Stream`,
//! so that one bad message costs one acknowledgement, not the call.
//!
//! tonic decodes a request stream with one codec and ends the call at the first message that
//! fails: INTERNAL when it does not parse, OUT_OF_RANGE when it is over the size limit. But a
//! gRPC message is a frame — a 1-byte compressed flag, a 4-byte big-endian length, the payload —
//! so where each message ends is known before its bytes are parsed, and the next one can be read
//! whatever this one holds. Here:
//! - [`Reframe`] wraps the request body and re-frames every message behind a one-byte tag: the
//!   payload as it came, or, for a message over the limit, only its declared length, once its
//!   bytes have all arrived and been discarded (constant memory; the time is the client's own
//!   upload, and `--body-timeout` still bounds each message);
//! - [`Decoder`] never fails a well-framed message: it yields the batch, or the error
//!   (INVALID_ARGUMENT, with prost's account of the offending field) that
//!   [`GrpcService::push_acks`] and [`GrpcService::stream_responses`] acknowledge like any
//!   other refused batch;
//! - only what the framing itself cannot get past ends the call: the request ending inside a
//!   message (INVALID_ARGUMENT), a compressed flag of 1 (these calls accept no compression; the
//!   gRPC compression spec requires INTERNAL there) or any other flag but 0 (INVALID_ARGUMENT).
//!
//! [`Routes`] serves `Push` and `Stream` this way and hands every other method to the generated
//! server.
use std::convert::Infallible;
use std::marker::PhantomData;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use http_body::Frame;
use prost::Message;
use prost::bytes::{Buf, BufMut, Bytes, BytesMut};
use tonic::codec::{BufferSettings, Codec, DecodeBuf};
use tonic::codegen::BoxFuture;
use tonic::server::NamedService;
use tonic::{Request, Response, Status, Streaming};

use super::{BoxStream, GrpcService};
use crate::error::Error;
use crossview_api::pb;
use crossview_api::pb::association_server::AssociationServer;

/// The paths of the methods served here.
pub(crate) const PUSH_PATH: &str = "/crossview.v1.Association/Push";
pub(crate) const STREAM_PATH: &str = "/crossview.v1.Association/Stream";

/// Tag of a re-framed message: the original payload follows.
const TAG_MESSAGE: u8 = 0;
/// Tag of a re-framed message: it was over the limit; its declared length (u32) follows.
const TAG_TOO_LARGE: u8 = 1;

/// What one `Push` or `Stream` message decodes to: a batch, or why it is not one.
pub type Item = crate::error::Result<pb::Batch>;

/// The association service's routes: `Push` and `Stream` with the framing of this module, the
/// rest by the generated server.
#[derive(Debug, Clone)]
pub(crate) struct Routes {
    generated: AssociationServer<GrpcService>,
    grpc: GrpcService,
    limit: usize,
}

impl Routes {
    /// `generated` for every method but `Push` and `Stream`, which `grpc` serves; their messages
    /// larger than `limit` bytes are acknowledged as refused and skipped.
    pub fn new(generated: AssociationServer<GrpcService>, grpc: GrpcService, limit: usize) -> Self {
        Routes {
            generated,
            grpc,
            limit,
        }
    }
}

impl NamedService for Routes {
    const NAME: &'static str = <AssociationServer<GrpcService> as NamedService>::NAME;
}

impl tower::Service<http::Request<tonic::body::Body>> for Routes {
    type Response = http::Response<tonic::body::Body>;
    type Error = Infallible;
    type Future = BoxFuture<Self::Response, Infallible>;

    fn poll_ready(&mut self, _cx: &mut Context<'_>) -> Poll<Result<(), Infallible>> {
        Poll::Ready(Ok(()))
    }

    fn call(&mut self, req: http::Request<tonic::body::Body>) -> Self::Future {
        let grpc = self.grpc.clone();
        match req.uri().path() {
            PUSH_PATH => serve(req, self.limit, move |r| grpc.push_acks(r.into_inner())),
            STREAM_PATH => serve(req, self.limit, move |r| grpc.stream_responses(r)),
            _ => self.generated.call(req),
        }
    }
}

/// Serves one call whose request messages are framed by this module: `respond` turns the
/// decoded request into the response stream.
fn serve<E, F>(
    req: http::Request<tonic::body::Body>,
    limit: usize,
    mut respond: F,
) -> BoxFuture<http::Response<tonic::body::Body>, Infallible>
where
    E: Message + Send + 'static,
    F: FnMut(Request<Streaming<Item>>) -> BoxStream<E> + Send + 'static,
{
    Box::pin(async move {
        let call = tower::service_fn(move |r: Request<Streaming<Item>>| {
            let responses = respond(r);
            async move { Ok::<_, Status>(Response::new(responses)) }
        });
        // Reframe has already bounded every message; tonic's own limit must not interfere.
        let mut grpc = tonic::server::Grpc::new(PushCodec::<E>::new(limit))
            .max_decoding_message_size(usize::MAX)
            .max_encoding_message_size(usize::MAX);
        let req = req.map(|b| Reframe::new(b, limit));
        Ok(grpc.streaming(call, req).await)
    })
}

/// Encodes responses with prost; decodes requests re-framed by [`Reframe`] with [`Decoder`].
#[derive(Debug)]
struct PushCodec<E> {
    limit: usize,
    _encode: PhantomData<fn() -> E>,
}

impl<E> PushCodec<E> {
    fn new(limit: usize) -> Self {
        PushCodec {
            limit,
            _encode: PhantomData,
        }
    }
}

impl<E: Message + Send + 'static> Codec for PushCodec<E> {
    type Encode = E;
    type Decode = Item;
    type Encoder = tonic_prost::ProstEncoder<E>;
    type Decoder = Decoder;

    fn encoder(&mut self) -> Self::Encoder {
        tonic_prost::ProstEncoder::new(BufferSettings::default())
    }

    fn decoder(&mut self) -> Self::Decoder {
        Decoder { limit: self.limit }
    }
}

/// Decodes one re-framed message into an [`Item`]; fails only on frames [`Reframe`] cannot
/// have made (a bug, hence INTERNAL).
#[derive(Debug)]
pub struct Decoder {
    limit: usize,
}

impl tonic::codec::Decoder for Decoder {
    type Item = Item;
    type Error = Status;

    fn decode(&mut self, buf: &mut DecodeBuf<'_>) -> Result<Option<Item>, Status> {
        if !buf.has_remaining() {
            return Err(Status::internal(
                "request re-framing: a message without its tag",
            ));
        }
        let item = match buf.get_u8() {
            TAG_MESSAGE => pb::Batch::decode(&mut *buf).map_err(|e| {
                Error::invalid("batch", format!("not a crossview.v1.Batch message: {e}"))
            }),
            TAG_TOO_LARGE if buf.remaining() >= 4 => Err(Error::invalid(
                "batch",
                format!(
                    "message of {} bytes is over the limit of {} bytes (--max-request-bytes); \
                     it was skipped",
                    buf.get_u32(),
                    self.limit
                ),
            )),
            _ => {
                return Err(Status::internal(
                    "request re-framing: a message with a bad tag",
                ));
            }
        };
        // A payload prost gave up on part way: the rest is this message's too.
        buf.advance(buf.remaining());
        Ok(Some(item))
    }
}

/// Where the request body is in its framing.
#[derive(Debug, Clone, Copy)]
enum At {
    /// Reading a frame header; `have` bytes of it so far.
    Header { have: usize },
    /// Passing on a payload of `len` bytes, `left` still to come.
    Payload { len: u32, left: u32 },
    /// Discarding an over-limit payload of `len` bytes, `left` still to come.
    Skip { len: u32, left: u32 },
}

/// A `Push` or `Stream` request body re-framed for [`Decoder`] (see the module docs).
pub(crate) struct Reframe {
    inner: tonic::body::Body,
    /// Largest payload passed on (at most `u32::MAX - 1`, so a tagged length fits).
    limit: u32,
    header: [u8; 5],
    at: At,
    /// An error to report once the bytes before it have gone out.
    error: Option<Status>,
    done: bool,
}

impl Reframe {
    /// Wraps a request body; payloads over `limit` bytes are skipped.
    pub fn new(inner: tonic::body::Body, limit: usize) -> Self {
        Reframe {
            inner,
            limit: u32::try_from(limit).unwrap_or(u32::MAX).min(u32::MAX - 1),
            header: [0; 5],
            at: At::Header { have: 0 },
            error: None,
            done: false,
        }
    }

    /// Re-frames `data` into `out`; an error ends the framing (what is in `out` still stands).
    fn advance(&mut self, mut data: Bytes, out: &mut BytesMut) -> Result<(), Status> {
        while data.has_remaining() {
            match self.at {
                At::Payload { len, left } | At::Skip { len, left } => {
                    let n = (left as usize).min(data.len());
                    let chunk = data.split_to(n);
                    if matches!(self.at, At::Payload { .. }) {
                        out.extend_from_slice(&chunk);
                    }
                    let left = left - n as u32;
                    self.at = match self.at {
                        At::Skip { .. } if left == 0 => {
                            // Skipped whole: its stand-in goes on, like a message read whole.
                            out.put_u8(0);
                            out.put_u32(5);
                            out.put_u8(TAG_TOO_LARGE);
                            out.put_u32(len);
                            At::Header { have: 0 }
                        }
                        _ if left == 0 => At::Header { have: 0 },
                        At::Payload { .. } => At::Payload { len, left },
                        _ => At::Skip { len, left },
                    };
                }
                At::Header { have } => {
                    let n = (5 - have).min(data.len());
                    self.header[have..have + n].copy_from_slice(&data.split_to(n));
                    if have + n < 5 {
                        self.at = At::Header { have: have + n };
                        continue;
                    }
                    let [flag, l @ ..] = self.header;
                    match flag {
                        0 => {}
                        1 => {
                            return Err(Status::internal(
                                "message with the compressed flag set, but this call accepts \
                                 no grpc-encoding",
                            ));
                        }
                        f => {
                            return Err(Status::invalid_argument(format!(
                                "message with compressed flag {f} (only 0 and 1 exist); the \
                                 request framing is lost"
                            )));
                        }
                    }
                    let len = u32::from_be_bytes(l);
                    self.at = if len > self.limit {
                        At::Skip { len, left: len }
                    } else {
                        out.put_u8(0);
                        out.put_u32(len + 1);
                        out.put_u8(TAG_MESSAGE);
                        match len {
                            0 => At::Header { have: 0 },
                            _ => At::Payload { len, left: len },
                        }
                    };
                }
            }
        }
        Ok(())
    }

    /// The error for a request that ended here, if that is inside a message.
    fn ended_inside(&self) -> Option<Status> {
        let what = match self.at {
            At::Header { have: 0 } => return None,
            At::Header { have } => format!("a message header ({have} of 5 bytes)"),
            At::Payload { len, left } | At::Skip { len, left } => {
                format!("a message ({} of {len} bytes)", len - left)
            }
        };
        Some(Status::invalid_argument(format!(
            "the request stream ended inside {what}"
        )))
    }
}

impl http_body::Body for Reframe {
    type Data = Bytes;
    type Error = Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, Status>>> {
        let this = &mut *self;
        loop {
            if let Some(e) = this.error.take() {
                this.done = true;
                return Poll::Ready(Some(Err(e)));
            }
            if this.done {
                return Poll::Ready(None);
            }
            match ready!(Pin::new(&mut this.inner).poll_frame(cx)) {
                Some(Ok(frame)) => match frame.into_data() {
                    Ok(data) => {
                        let mut out = BytesMut::with_capacity(data.len() + 16);
                        if let Err(e) = this.advance(data, &mut out) {
                            this.error = Some(e);
                        }
                        if !out.is_empty() {
                            return Poll::Ready(Some(Ok(Frame::data(out.freeze()))));
                        }
                    }
                    // Trailers end the request.
                    Err(trailers) => match this.ended_inside() {
                        Some(e) => this.error = Some(e),
                        None => return Poll::Ready(Some(Ok(trailers))),
                    },
                },
                Some(Err(e)) => {
                    this.done = true;
                    return Poll::Ready(Some(Err(e)));
                }
                None => match this.ended_inside() {
                    Some(e) => this.error = Some(e),
                    None => this.done = true,
                },
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(flag: u8, payload: &[u8]) -> Vec<u8> {
        let mut f = vec![flag];
        f.extend_from_slice(&(payload.len() as u32).to_be_bytes());
        f.extend_from_slice(payload);
        f
    }

    fn reframe(limit: usize, chunks: &[&[u8]]) -> (Vec<u8>, Result<(), Status>) {
        let mut r = Reframe::new(tonic::body::Body::empty(), limit);
        let mut out = BytesMut::new();
        for c in chunks {
            if let Err(e) = r.advance(Bytes::copy_from_slice(c), &mut out) {
                return (out.to_vec(), Err(e));
            }
        }
        match r.ended_inside() {
            Some(e) => (out.to_vec(), Err(e)),
            None => (out.to_vec(), Ok(())),
        }
    }

    #[test]
    fn messages_are_tagged_and_over_limit_ones_skipped_across_chunks() {
        let mut input = frame(0, b"abc");
        input.extend(frame(0, &[7; 10]));
        input.extend(frame(0, b""));
        input.extend(frame(0, b"de"));
        // Every split of the input gives the same output.
        let mut want = frame(0, b"\0abc");
        want.extend(frame(0, &[TAG_TOO_LARGE, 0, 0, 0, 10]));
        want.extend(frame(0, b"\0"));
        want.extend(frame(0, b"\0de"));
        for cut in 0..input.len() {
            let (a, b) = input.split_at(cut);
            let (out, end) = reframe(4, &[a, b]);
            assert!(end.is_ok(), "cut {cut}: {end:?}");
            assert_eq!(out, want, "cut {cut}");
        }
    }

    #[test]
    fn the_framing_errors_end_it_with_their_codes() {
        let (out, end) = reframe(8, &[&frame(0, b"ok"), &frame(0, b"abcdef")[..4]]);
        assert_eq!(out, frame(0, b"\0ok"));
        let e = end.unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument, "{e:?}");
        assert!(e.message().contains("header (4 of 5 bytes)"), "{e:?}");
        let (_, end) = reframe(8, &[&frame(0, b"abcdef")[..8]]);
        assert!(end.unwrap_err().message().contains("(3 of 6 bytes)"));
        // Skipping an over-limit message that never completes.
        let (_, end) = reframe(2, &[&frame(0, b"abcdef")[..8]]);
        assert!(end.unwrap_err().message().contains("(3 of 6 bytes)"));
        let (_, end) = reframe(8, &[&frame(1, b"x")]);
        assert_eq!(end.unwrap_err().code(), tonic::Code::Internal);
        let (_, end) = reframe(8, &[&frame(9, b"x")]);
        assert_eq!(end.unwrap_err().code(), tonic::Code::InvalidArgument);
    }
}

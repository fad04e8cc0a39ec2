//! A raw HTTP/2 client (the `h2` crate) for subscribers that misbehave the way real ones can:
//! flow-control windows of the test's choosing, and a socket it stops reading altogether.
//! It is what a client that subscribes and never reads looks like to the server.
use std::net::SocketAddr;
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::task::{Context, Poll};

use bytes::Bytes;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;

/// A TCP stream whose reads stop (stay pending) once `paused` is set: the peer's data then
/// piles up in the kernel and, past that, in the server.
struct Pausable {
    inner: TcpStream,
    paused: Arc<AtomicBool>,
}

impl AsyncRead for Pausable {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        if self.paused.load(Ordering::Acquire) {
            return Poll::Pending;
        }
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl AsyncWrite for Pausable {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// One HTTP/2 connection holding event streams that are never read.
pub struct NeverRead {
    paused: Arc<AtomicBool>,
    /// Response bodies kept open (dropping one would cancel its stream).
    bodies: Vec<h2::RecvStream>,
    /// Status codes of the subscriptions this connection asked for.
    pub statuses: Vec<u16>,
    task: tokio::task::JoinHandle<()>,
}

impl NeverRead {
    /// Opens one HTTP/2 connection to `addr` with stream and connection windows `window`
    /// (bytes; 0 lets the server send nothing), asks for `path` `streams` times (with
    /// `authorization` when given), waits for every response head, then stops reading the
    /// socket when `stop_reading`. Requests the server refuses keep their status.
    pub async fn open(
        addr: SocketAddr,
        path: &str,
        streams: usize,
        window: u32,
        authorization: Option<&str>,
        stop_reading: bool,
    ) -> std::io::Result<NeverRead> {
        let tcp = TcpStream::connect(addr).await?;
        let paused = Arc::new(AtomicBool::new(false));
        let io = Pausable {
            inner: tcp,
            paused: paused.clone(),
        };
        let (mut client, conn) = h2::client::Builder::new()
            .initial_window_size(window)
            .initial_connection_window_size(window.max(65_535))
            .handshake::<_, Bytes>(io)
            .await
            .map_err(std::io::Error::other)?;
        let task = tokio::spawn(async move {
            let _ = conn.await;
        });
        let mut pending = Vec::with_capacity(streams);
        for _ in 0..streams {
            client = client.ready().await.map_err(std::io::Error::other)?;
            let mut req = http::Request::builder()
                .method("GET")
                .uri(format!("http://{addr}{path}"));
            if let Some(a) = authorization {
                req = req.header("authorization", a);
            }
            let (resp, _) = client
                .send_request(req.body(()).expect("request"), true)
                .map_err(std::io::Error::other)?;
            pending.push(resp);
        }
        let mut bodies = Vec::new();
        let mut statuses = Vec::new();
        for resp in pending {
            match resp.await {
                Ok(r) => {
                    statuses.push(r.status().as_u16());
                    bodies.push(r.into_body());
                }
                // The server reset or refused this stream (e.g. beyond its stream cap).
                Err(_) => statuses.push(0),
            }
        }
        if stop_reading {
            paused.store(true, Ordering::Release);
        }
        Ok(NeverRead {
            paused,
            bodies,
            statuses,
            task,
        })
    }

    /// Subscriptions the server accepted (200).
    pub fn accepted(&self) -> usize {
        self.statuses.iter().filter(|s| **s == 200).count()
    }

    /// True once the server closed the connection (the connection task saw it end; only
    /// while the client still reads its socket).
    pub fn closed(&self) -> bool {
        self.task.is_finished()
    }

    /// True once the client stopped reading its socket.
    pub fn paused(&self) -> bool {
        self.paused.load(Ordering::Acquire)
    }

    /// Open response bodies.
    pub fn open_streams(&self) -> usize {
        self.bodies.len()
    }
}

impl Drop for NeverRead {
    fn drop(&mut self) {
        self.task.abort();
    }
}

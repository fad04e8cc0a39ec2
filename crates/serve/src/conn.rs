//! Connections of the shared port: a cap with eviction of idle connections, idle and
//! first-request timeouts, and hard closing (stalled subscribers, end of the shutdown grace).
//!
//! Rules ([`ConnectionLimits`]), the same for HTTP/1, HTTP/2 and gRPC:
//! - at most `max_connections` connections are open. At the cap, a new connection closes the
//!   longest-idle one (no request in flight) to take its place; when every connection has a
//!   request in flight, the new one is refused (closed at once, counted in
//!   `crossview_connections_refused_total`). Idle floods therefore cannot lock anyone out;
//! - a connection must start its first request within `header_read_timeout` of being accepted
//!   (TLS handshake included), and one with no request in flight for `idle_timeout` is closed
//!   (HTTP/1 additionally bounds each request head by `header_read_timeout` in hyper, which
//!   also bounds the keep-alive gap between two requests);
//! - closing is graceful first (HTTP/2 GOAWAY, HTTP/1 close after the current response) and
//!   hard one second later.
//!
//! A request counts as in flight from its head until its response body is finished or
//! dropped, so long-lived streams (Subscribe, Stream, SSE) keep their connection open; bodies
//! themselves are bounded by `body_timeout` elsewhere ([`super::body`]).
use std::collections::HashMap;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes, HttpBody};
use hyper_util::server::graceful::GracefulConnection;
use tokio::sync::{Notify, watch};

use super::config::ConnectionLimits;
use super::metrics::Metrics;

/// How long a connection asked to close gracefully may take before it is dropped.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

/// The state of one open connection, shared with its requests.
#[derive(Debug)]
pub(crate) struct ConnState {
    /// Unique among the server's connections.
    id: u64,
    accepted: Instant,
    /// Requests in flight (head received, response body not yet finished or dropped).
    active: AtomicUsize,
    /// Requests started so far.
    started: AtomicU64,
    /// When `active` last dropped to 0 (or the accept time).
    idle_since: Mutex<Instant>,
    /// Set once the connection was asked to close.
    closing: AtomicBool,
    /// Graceful close request (eviction).
    close: Notify,
    /// Hard close request.
    kill: Notify,
    /// Notified when `active` drops to 0 (the idle timer starts).
    became_idle: Notify,
}

impl ConnState {
    fn new(id: u64, now: Instant) -> Self {
        ConnState {
            id,
            accepted: now,
            active: AtomicUsize::new(0),
            started: AtomicU64::new(0),
            idle_since: Mutex::new(now),
            closing: AtomicBool::new(false),
            close: Notify::new(),
            kill: Notify::new(),
            became_idle: Notify::new(),
        }
    }

    fn idle_since(&self) -> Instant {
        *crate::locks::lock(&self.idle_since)
    }

    /// Marks a request in flight until the returned guard drops.
    pub(crate) fn begin(self: &Arc<Self>) -> ActiveGuard {
        self.active.fetch_add(1, Ordering::AcqRel);
        self.started.fetch_add(1, Ordering::AcqRel);
        ActiveGuard(self.clone())
    }

    /// When this connection becomes closable for idleness, if it is idle now.
    fn idle_deadline(&self, limits: &ConnectionLimits) -> Option<Instant> {
        if self.active.load(Ordering::Acquire) > 0 {
            return None;
        }
        Some(if self.started.load(Ordering::Acquire) == 0 {
            self.accepted + limits.header_read_timeout
        } else {
            self.idle_since() + limits.idle_timeout
        })
    }
}

/// Keeps one request counted as in flight on its connection.
#[derive(Debug)]
pub(crate) struct ActiveGuard(Arc<ConnState>);

impl Drop for ActiveGuard {
    fn drop(&mut self) {
        if self.0.active.fetch_sub(1, Ordering::AcqRel) == 1 {
            *crate::locks::lock(&self.0.idle_since) = Instant::now();
            self.0.became_idle.notify_one();
        }
    }
}

/// A request's handle on its connection (in the request extensions): lets a handler close the
/// connection, e.g. when its subscriber stopped reading.
#[derive(Debug, Clone)]
pub struct ConnHandle(pub(crate) Arc<ConnState>);

impl ConnHandle {
    /// The connection's id (unique among the server's connections).
    pub(crate) fn id(&self) -> u64 {
        self.0.id
    }

    /// Drops the connection at once (every request on it ends).
    pub fn kill(&self) {
        self.0.closing.store(true, Ordering::Release);
        self.0.kill.notify_one();
    }
}

/// The open connections of one server.
#[derive(Debug)]
pub struct Connections {
    limits: ConnectionLimits,
    metrics: Metrics,
    open: Mutex<HashMap<u64, Arc<ConnState>>>,
    next_id: AtomicU64,
    /// Notified whenever a connection ends.
    ended: Notify,
}

/// A registered connection; unregisters on drop.
#[derive(Debug)]
pub(crate) struct ConnGuard {
    connections: Arc<Connections>,
    id: u64,
    /// The connection's shared state.
    pub state: Arc<ConnState>,
}

impl Drop for ConnGuard {
    fn drop(&mut self) {
        let n = {
            let mut open = self.connections.lock();
            open.remove(&self.id);
            open.len()
        };
        self.connections.metrics.connections(n);
        self.connections.ended.notify_waiters();
    }
}

impl Connections {
    /// No connections yet, under `limits`.
    pub fn new(limits: ConnectionLimits, metrics: Metrics) -> Arc<Self> {
        Arc::new(Connections {
            limits,
            metrics,
            open: Mutex::new(HashMap::new()),
            next_id: AtomicU64::new(0),
            ended: Notify::new(),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u64, Arc<ConnState>>> {
        crate::locks::lock(&self.open)
    }

    /// Registers a new connection, evicting the longest-idle one at the cap; `None` when the
    /// connection must be refused (at the cap and no connection is idle).
    pub fn admit(self: &Arc<Self>) -> Option<ConnGuard> {
        let now = Instant::now();
        let mut open = self.lock();
        let live = open
            .values()
            .filter(|c| !c.closing.load(Ordering::Acquire))
            .count();
        // Connections asked to close still hold a descriptor for up to CLOSE_GRACE; bound them.
        if live >= self.limits.max_connections.max(1)
            || open.len() >= 2 * self.limits.max_connections.max(1)
        {
            let victim = open
                .values()
                .filter(|c| {
                    !c.closing.load(Ordering::Acquire) && c.active.load(Ordering::Acquire) == 0
                })
                .min_by_key(|c| c.idle_since())
                .cloned();
            match victim {
                Some(v) if open.len() < 2 * self.limits.max_connections.max(1) => {
                    v.closing.store(true, Ordering::Release);
                    v.close.notify_one();
                    self.metrics.connection_evicted();
                }
                _ => {
                    drop(open);
                    self.metrics.connection_refused();
                    return None;
                }
            }
        }
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let state = Arc::new(ConnState::new(id, now));
        open.insert(id, state.clone());
        let n = open.len();
        drop(open);
        self.metrics.connections(n);
        Some(ConnGuard {
            connections: self.clone(),
            id,
            state,
        })
    }

    /// Number of open connections.
    pub fn len(&self) -> usize {
        self.lock().len()
    }

    /// True when no connection is open.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Waits until every connection has ended.
    pub(crate) async fn drained(&self) {
        loop {
            let ended = self.ended.notified();
            if self.is_empty() {
                return;
            }
            ended.await;
        }
    }

    /// Drops every open connection at once (the shutdown grace is over).
    pub(crate) fn kill_all(&self) {
        for c in self.lock().values() {
            c.closing.store(true, Ordering::Release);
            c.kill.notify_one();
        }
    }
}

/// Drives one connection to its end under the connection rules (see the module docs): closes
/// it gracefully when idle too long, when evicted or at server shutdown, and drops it when
/// killed or when a graceful close takes longer than [`CLOSE_GRACE`] (except at shutdown,
/// whose grace the server enforces).
pub async fn drive<C>(
    conn: C,
    state: Arc<ConnState>,
    limits: ConnectionLimits,
    mut shutdown: watch::Receiver<bool>,
) -> Result<(), C::Error>
where
    C: GracefulConnection,
{
    tokio::pin!(conn);
    let mut hard_deadline: Option<tokio::time::Instant> = None;
    let mut graceful = false;
    loop {
        let idle = if graceful {
            None
        } else {
            state.idle_deadline(&limits)
        };
        let idle_sleep = async {
            match idle {
                Some(t) => tokio::time::sleep_until(t.into()).await,
                None => std::future::pending().await,
            }
        };
        let hard_sleep = async {
            match hard_deadline {
                Some(t) => tokio::time::sleep_until(t).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            r = conn.as_mut() => return r,
            _ = state.kill.notified() => return Ok(()),
            _ = state.became_idle.notified() => {}
            _ = hard_sleep => return Ok(()),
            _ = idle_sleep => {
                // Re-check: a request may have started or ended since the deadline was taken.
                if state.idle_deadline(&limits).is_some_and(|t| t <= Instant::now()) {
                    tracing::debug!("closing idle connection");
                    state.closing.store(true, Ordering::Release);
                    conn.as_mut().graceful_shutdown();
                    graceful = true;
                    hard_deadline = Some(tokio::time::Instant::now() + CLOSE_GRACE);
                }
            }
            _ = state.close.notified(), if !graceful => {
                tracing::debug!("closing evicted idle connection");
                conn.as_mut().graceful_shutdown();
                graceful = true;
                hard_deadline = Some(tokio::time::Instant::now() + CLOSE_GRACE);
            }
            r = shutdown.wait_for(|v| *v), if !graceful => {
                if r.is_ok() {
                    conn.as_mut().graceful_shutdown();
                    graceful = true;
                }
            }
        }
    }
}

/// A response body that keeps its request counted as in flight until it ends or drops.
pub(crate) struct Tracked {
    inner: Body,
    _guard: ActiveGuard,
}

impl Tracked {
    /// Wraps `inner`, holding `guard` for its lifetime.
    pub fn new(inner: Body, guard: ActiveGuard) -> Self {
        Tracked {
            inner,
            _guard: guard,
        }
    }
}

impl HttpBody for Tracked {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

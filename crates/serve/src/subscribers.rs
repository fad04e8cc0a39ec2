//! The one budget for result subscribers (gRPC `Subscribe` / `Stream`, SSE over HTTP/1.1 and
//! HTTP/2), so that clients that subscribe and never read cannot exhaust the server's memory
//! or its connection slots.
//!
//! **Memory.** What a subscriber costs the server is bounded per stream: the scene's results
//! are shared (one broadcast ring per scene), and the transport holds at most
//! [`TRANSPORT_BUFFER`] bytes of encoded results per stream (HTTP/2 send buffer, HTTP/1 write
//! buffer) before it stops taking more. Each subscriber is therefore charged a fixed
//! [`SUBSCRIBER_CHARGE`], and the subscribers together stay within `subscriber_memory`
//! ([`ConnectionLimits`]): `subscriber_memory / SUBSCRIBER_CHARGE` subscribers at most, and
//! `max_subscriptions_per_connection` on one connection.
//!
//! **At the budget** a new subscription first displaces the subscriber furthest behind (results
//! published that it has not taken; its connection is closed, as a stalled subscriber's is) and
//! is refused (`RESOURCE_EXHAUSTED` / 429) when every subscriber is keeping up. Both are counted
//! (`crossview_subscribers_dropped_total{reason="budget"}`, `crossview_errors_total`).
//!
//! **Connection slots.** Connections holding subscriptions may take at most three quarters of
//! `max_connections`: the last quarter is kept for health checks, metrics scrapes and pushes,
//! which therefore always get a connection (idle connections are evicted for them). A
//! subscription that would make a further connection a subscriber's beyond that share is
//! refused (or displaces one that is behind) and its connection becomes idle, so evictable.
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, Weak};

use crate::config::ConnectionLimits;
use crate::conn::ConnHandle;
use crate::error::{Error, Result};
use crate::metrics::Metrics;
use crate::scene::Scene;

/// Bytes of encoded results the transport may hold for one stream that is not read (the
/// HTTP/2 send buffer and the HTTP/1 write buffer are set to it).
pub(crate) const TRANSPORT_BUFFER: usize = 64 << 10;

/// What one subscriber is charged against `subscriber_memory`: its transport buffer, one
/// encoded result beyond it, the stream's own state and the allocator's slack. Measured: a
/// never-read HTTP/2 stream whose buffer is full costs the server about 133 KiB with
/// results of ~6 KiB (BENCHMARKS.md, "Subscriber budget"); results much larger than 64 KiB
/// cost a stream more.
pub(crate) const SUBSCRIBER_CHARGE: usize = TRANSPORT_BUFFER + (96 << 10);

/// One live subscriber.
#[derive(Debug)]
struct Entry {
    scene: Arc<Scene>,
    /// `scene.published()` when it subscribed.
    start: u64,
    /// Results it has taken (the stream's own counter; gone once the stream is dropped).
    taken: Weak<AtomicU64>,
    conn: Option<ConnHandle>,
}

impl Entry {
    /// Results published since it subscribed that it has not taken.
    fn behind(&self) -> u64 {
        let taken = self
            .taken
            .upgrade()
            .map_or(0, |t| t.load(Ordering::Acquire));
        self.scene
            .published()
            .saturating_sub(self.start)
            .saturating_sub(taken)
    }
}

#[derive(Debug, Default)]
struct Registry {
    next_id: u64,
    entries: HashMap<u64, Entry>,
    /// Subscriptions per connection id.
    per_conn: HashMap<u64, usize>,
}

impl Registry {
    fn remove(&mut self, id: u64) {
        if let Some(e) = self.entries.remove(&id)
            && let Some(c) = &e.conn
        {
            let key = c.id();
            if let Some(n) = self.per_conn.get_mut(&key) {
                *n -= 1;
                if *n == 0 {
                    self.per_conn.remove(&key);
                }
            }
        }
    }

    /// The subscriber furthest behind among those `eligible`, if any is behind at all and
    /// can be disconnected (has a connection).
    fn slowest(&self, eligible: impl Fn(&Entry) -> bool) -> Option<(u64, u64)> {
        self.entries
            .iter()
            .filter(|(_, e)| e.conn.is_some() && eligible(e))
            .map(|(id, e)| (e.behind(), *id))
            .filter(|(behind, _)| *behind > 0)
            .max()
            .map(|(behind, id)| (id, behind))
    }

    /// Disconnects subscriber `id`'s connection and forgets every subscription on it now
    /// (their streams end as the connection closes).
    fn evict(&mut self, id: u64) -> usize {
        let Some(conn) = self.entries.get(&id).and_then(|e| e.conn.clone()) else {
            return 0;
        };
        let ids: Vec<u64> = self
            .entries
            .iter()
            .filter(|(_, e)| e.conn.as_ref().is_some_and(|c| c.id() == conn.id()))
            .map(|(id, _)| *id)
            .collect();
        for id in &ids {
            self.remove(*id);
        }
        conn.kill();
        ids.len()
    }
}

/// The subscriber budget of one server (see the module docs).
#[derive(Debug)]
pub(crate) struct Subscribers {
    max_total: usize,
    max_per_conn: usize,
    max_conns: usize,
    registry: Mutex<Registry>,
    metrics: Metrics,
}

/// Keeps one subscriber registered until dropped (its stream owns it).
#[derive(Debug)]
pub(crate) struct Ticket {
    owner: Arc<Subscribers>,
    id: u64,
}

impl Drop for Ticket {
    fn drop(&mut self) {
        self.owner.lock().remove(self.id);
    }
}

impl Subscribers {
    /// A budget under `limits`.
    pub(crate) fn new(limits: &ConnectionLimits, metrics: Metrics) -> Arc<Self> {
        Arc::new(Subscribers {
            max_total: (limits.subscriber_memory / SUBSCRIBER_CHARGE).max(1),
            max_per_conn: limits.max_subscriptions_per_connection.max(1),
            max_conns: (limits.max_connections - limits.max_connections / 4).max(1),
            registry: Mutex::default(),
            metrics,
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Registry> {
        crate::locks::lock(&self.registry)
    }

    /// Admits a subscriber of `scene` on `conn` (whose stream counts taken results in
    /// `taken`), displacing the subscriber furthest behind when a bound is reached, or
    /// refusing with `ResourceExhausted` when every subscriber keeps up.
    pub(crate) fn admit(
        self: &Arc<Self>,
        scene: &Arc<Scene>,
        conn: Option<&ConnHandle>,
        taken: &Arc<AtomicU64>,
    ) -> Result<Ticket> {
        let mut reg = self.lock();
        if let Some(c) = conn {
            let on_conn = reg.per_conn.get(&c.id()).copied().unwrap_or(0);
            if on_conn >= self.max_per_conn {
                return Err(self.refuse(format!(
                    "this connection already holds {on_conn} subscriptions (--max-subscriptions-per-connection)"
                )));
            }
            if on_conn == 0 && reg.per_conn.len() >= self.max_conns {
                self.displace(&mut reg, "subscriber connections", |e| {
                    e.conn.as_ref().is_some_and(|o| o.id() != c.id())
                })?;
            }
        }
        if reg.entries.len() >= self.max_total {
            self.displace(&mut reg, "subscriber memory budget", |_| true)?;
        }
        let id = reg.next_id;
        reg.next_id += 1;
        if let Some(c) = conn {
            *reg.per_conn.entry(c.id()).or_default() += 1;
        }
        reg.entries.insert(
            id,
            Entry {
                scene: scene.clone(),
                start: scene.published(),
                taken: Arc::downgrade(taken),
                conn: conn.cloned(),
            },
        );
        Ok(Ticket {
            owner: self.clone(),
            id,
        })
    }

    /// Frees room by disconnecting the slowest `eligible` subscriber that is behind, or
    /// returns the refusal.
    fn displace(
        &self,
        reg: &mut Registry,
        what: &str,
        eligible: impl Fn(&Entry) -> bool,
    ) -> Result<()> {
        match reg.slowest(eligible) {
            Some((id, behind)) => {
                let n = reg.evict(id);
                tracing::info!(
                    behind,
                    subscriptions = n,
                    "{what} full: disconnecting the subscriber furthest behind"
                );
                self.metrics.subscribers_dropped("budget", n as u64);
                Ok(())
            }
            None => Err(self.refuse(format!(
                "{what} full and every subscriber keeps up; try again later (docs/serve.md, \"Limits and budgets\")"
            ))),
        }
    }

    /// The refusal (counted once, by the service that returns it).
    fn refuse(&self, why: String) -> Error {
        Error::ResourceExhausted(why)
    }
}

//! Bookkeeping shared by senders and subscribers: which batches were sent and accepted, which
//! frames came back, push-to-result latency, and errors by kind.
use std::collections::{BTreeMap, HashMap};
use std::sync::Mutex;

use std::time::Instant;

use hdrhistogram::Histogram;
use tokio::sync::Notify;

/// Identifies a frame of one scene: `(scene index, frame id)`.
pub type FrameKey = (usize, u64);

/// What a frame result says became of the frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Every camera's batch in it.
    Complete,
    /// Cameras missing.
    Partial,
    /// Shed whole under overload (status `shed`): not associated.
    Shed,
}

impl Outcome {
    /// From a result's `complete` flag and whether its status is `shed`.
    pub fn of(complete: bool, shed: bool) -> Self {
        match (shed, complete) {
            (true, _) => Outcome::Shed,
            (false, true) => Outcome::Complete,
            (false, false) => Outcome::Partial,
        }
    }
}

#[derive(Debug, Default)]
struct FrameState {
    /// When the most recent batch of this frame was handed to the transport.
    last_send: Option<Instant>,
    sent: u32,
    /// Batches the server answered (accepted or rejected) or that failed client-side.
    answered: u32,
    accepted: u32,
    /// Batches refused as `overloaded` (the server shed the frame, or was over budget).
    overloaded: u32,
    result: bool,
}

impl FrameState {
    /// Still waiting for something: an answer to a batch, or the result of an accepted frame.
    fn in_flight(&self) -> bool {
        !self.result && (self.accepted > 0 || self.answered < self.sent)
    }
}

/// Counts and latencies of one run; cheap to share behind an `Arc`.
pub struct Tracker {
    inner: Mutex<Inner>,
    /// Latencies count only for frames sent this long after the first send.
    latency_after: std::time::Duration,
    /// Woken whenever a frame stops being in flight.
    progress: Notify,
}

struct Inner {
    frames: HashMap<FrameKey, FrameState>,
    /// Frames for which `FrameState::in_flight` holds.
    in_flight: usize,
    sent: u64,
    accepted: u64,
    rejected_by_kind: BTreeMap<String, u64>,
    errors_by_kind: BTreeMap<String, u64>,
    results: u64,
    results_complete: u64,
    results_shed: u64,
    /// Partial results of frames whose every batch was accepted (a camera was cut on the way).
    partial_all_accepted: u64,
    unexpected_results: u64,
    duplicate_results: u64,
    missed_live: u64,
    latency_complete: Histogram<u64>,
    latency_partial: Histogram<u64>,
    first_send: Option<Instant>,
    last_result: Option<Instant>,
}

/// Latency histogram bounds: 1 µs to 10 min, 3 significant digits.
fn histogram() -> Histogram<u64> {
    Histogram::new_with_bounds(1, 600_000_000, 3).expect("static histogram bounds are valid")
}

impl Default for Tracker {
    fn default() -> Self {
        Self::new()
    }
}

impl Tracker {
    /// An empty tracker.
    pub fn new() -> Self {
        Tracker {
            inner: Mutex::new(Inner {
                frames: HashMap::new(),
                in_flight: 0,
                sent: 0,
                accepted: 0,
                rejected_by_kind: BTreeMap::new(),
                errors_by_kind: BTreeMap::new(),
                results: 0,
                results_complete: 0,
                results_shed: 0,
                partial_all_accepted: 0,
                unexpected_results: 0,
                duplicate_results: 0,
                missed_live: 0,
                latency_complete: histogram(),
                latency_partial: histogram(),
                first_send: None,
                last_result: None,
            }),
            progress: Notify::new(),
            latency_after: std::time::Duration::ZERO,
        }
    }

    /// Counts latencies only of frames whose last batch was sent `d` or more after the run's
    /// first send.
    pub fn latency_after(mut self, d: std::time::Duration) -> Self {
        self.latency_after = d;
        self
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Applies `f` to the state of frame `key`, keeping the in-flight count right.
    fn update<T>(&self, key: FrameKey, f: impl FnOnce(&mut Inner, &mut FrameState) -> T) -> T {
        let mut g = self.lock();
        let mut st = g.frames.remove(&key).unwrap_or_default();
        let before = st.in_flight();
        let out = f(&mut g, &mut st);
        let after = st.in_flight();
        g.frames.insert(key, st);
        match (before, after) {
            (false, true) => g.in_flight += 1,
            (true, false) => {
                g.in_flight -= 1;
                drop(g);
                self.progress.notify_waiters();
            }
            _ => {}
        }
        out
    }

    /// A batch of `key` is about to be sent at `at`.
    pub fn sent(&self, key: FrameKey, at: Instant) {
        self.update(key, |g, st| {
            g.sent += 1;
            g.first_send.get_or_insert(at);
            st.sent += 1;
            st.last_send = Some(st.last_send.map_or(at, |t| t.max(at)));
        })
    }

    /// The server accepted a batch of `key`.
    pub fn accepted(&self, key: FrameKey) {
        self.update(key, |g, st| {
            g.accepted += 1;
            st.accepted += 1;
            st.answered += 1;
        })
    }

    /// The server rejected a batch of `key` with kind `kind` (e.g. `late`, `duplicate`).
    pub fn rejected(&self, key: FrameKey, kind: &str) {
        self.update(key, |g, st| {
            *g.rejected_by_kind.entry(kind.to_string()).or_default() += 1;
            st.answered += 1;
            if kind == "overloaded" {
                st.overloaded += 1;
            }
        })
    }

    /// A batch of `key` failed client-side or in transport, with kind `kind` (e.g. `timeout`).
    pub fn failed(&self, key: FrameKey, kind: &str) {
        self.update(key, |g, st| {
            *g.errors_by_kind.entry(kind.to_string()).or_default() += 1;
            st.answered += 1;
        })
    }

    /// A failure not tied to one batch, of kind `kind` (e.g. `subscribe_closed`).
    pub fn error(&self, kind: &str) {
        *self
            .lock()
            .errors_by_kind
            .entry(kind.to_string())
            .or_default() += 1;
    }

    /// A frame result arrived at `at`.
    pub fn result(&self, key: FrameKey, outcome: Outcome, at: Instant) {
        let known = {
            let mut g = self.lock();
            g.results += 1;
            g.last_result = Some(at);
            match outcome {
                Outcome::Complete => g.results_complete += 1,
                Outcome::Shed => g.results_shed += 1,
                Outcome::Partial => {}
            }
            if !g.frames.contains_key(&key) {
                g.unexpected_results += 1;
            }
            g.frames.contains_key(&key)
        };
        if !known {
            return;
        }
        self.update(key, |g, st| {
            if st.result {
                g.duplicate_results += 1;
                return;
            }
            st.result = true;
            if outcome == Outcome::Partial && st.accepted == st.sent && st.answered == st.sent {
                g.partial_all_accepted += 1;
            }
            let Some(sent) = st.last_send else { return };
            if g.first_send
                .is_some_and(|t0| sent.saturating_duration_since(t0) < self.latency_after)
            {
                return;
            }
            let micros = at.saturating_duration_since(sent).as_micros().max(1) as u64;
            let h = match outcome {
                Outcome::Complete => &mut g.latency_complete,
                Outcome::Partial => &mut g.latency_partial,
                Outcome::Shed => return,
            };
            h.saturating_record(micros);
        })
    }

    /// A result the live subscription never delivered but a later re-read of the output
    /// found (Kafka: the broker's live reads skipped it): the frame is not lost, its latency
    /// unknown.
    pub fn found_on_reread(&self, key: FrameKey) {
        self.update(key, |g, st| {
            if !st.result {
                st.result = true;
                g.missed_live += 1;
            }
        })
    }

    /// Frames still waiting for a batch answer or, once accepted, for their result.
    pub fn in_flight(&self) -> usize {
        self.lock().in_flight
    }

    /// Waits until fewer than `limit` frames are in flight (closed-loop pacing). Re-checks
    /// at least every 50 ms so a missed wake-up cannot stall the run.
    pub async fn wait_in_flight_below(&self, limit: usize) {
        loop {
            let notified = self.progress.notified();
            if self.in_flight() < limit {
                return;
            }
            let _ = tokio::time::timeout(std::time::Duration::from_millis(50), notified).await;
        }
    }

    /// A snapshot of everything counted so far.
    pub fn snapshot(&self) -> Snapshot {
        let g = self.lock();
        let lost: Vec<FrameKey> = {
            let mut v: Vec<FrameKey> = g
                .frames
                .iter()
                .filter(|(_, f)| f.accepted > 0 && !f.result)
                .map(|(k, _)| *k)
                .collect();
            v.sort_unstable();
            v
        };
        Snapshot {
            sent: g.sent,
            accepted: g.accepted,
            rejected_by_kind: g.rejected_by_kind.clone(),
            errors_by_kind: g.errors_by_kind.clone(),
            results: g.results,
            results_complete: g.results_complete,
            results_shed: g.results_shed,
            partial_all_accepted: g.partial_all_accepted,
            frames_cut_by_overload: g
                .frames
                .values()
                .filter(|f| f.overloaded > 0 && f.accepted > 0)
                .count() as u64,
            unexpected_results: g.unexpected_results,
            duplicate_results: g.duplicate_results,
            missed_live: g.missed_live,
            frames_accepted: g.frames.values().filter(|f| f.accepted > 0).count() as u64,
            lost,
            latency_complete: g.latency_complete.clone(),
            latency_partial: g.latency_partial.clone(),
            active: match (g.first_send, g.last_result) {
                (Some(a), Some(b)) => b.saturating_duration_since(a),
                _ => std::time::Duration::ZERO,
            },
        }
    }
}

/// Point-in-time copy of a [`Tracker`].
#[derive(Debug, Clone)]
pub struct Snapshot {
    pub sent: u64,
    pub accepted: u64,
    pub rejected_by_kind: BTreeMap<String, u64>,
    pub errors_by_kind: BTreeMap<String, u64>,
    pub results: u64,
    pub results_complete: u64,
    /// Results with status `shed`.
    pub results_shed: u64,
    /// Partial results of frames whose every batch was accepted.
    pub partial_all_accepted: u64,
    /// Frames with both accepted batches and batches refused as `overloaded` (the server
    /// promises a frame is either taken whole or shed whole).
    pub frames_cut_by_overload: u64,
    pub unexpected_results: u64,
    pub duplicate_results: u64,
    /// Results found only by re-reading the output (see [`Tracker::found_on_reread`]).
    pub missed_live: u64,
    pub frames_accepted: u64,
    pub lost: Vec<FrameKey>,
    pub latency_complete: Histogram<u64>,
    pub latency_partial: Histogram<u64>,
    /// First send to last result.
    pub active: std::time::Duration,
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn shed_and_overload_are_told_apart_and_early_latencies_can_be_left_out() {
        let t = Tracker::new().latency_after(Duration::from_secs(2));
        let t0 = Instant::now();
        // Frame 0 early, frame 1 after 2 s: only frame 1's latency counts.
        for (f, at) in [(0, t0), (1, t0 + Duration::from_secs(3))] {
            for _ in 0..3 {
                t.sent((0, f), at);
                t.accepted((0, f));
            }
            t.result((0, f), Outcome::Complete, at + Duration::from_millis(7));
        }
        // Frame 2 shed whole; frame 3 cut: one batch taken, one refused as overloaded.
        t.sent((0, 2), t0);
        t.rejected((0, 2), "overloaded");
        t.result((0, 2), Outcome::Shed, t0);
        t.sent((0, 3), t0);
        t.sent((0, 3), t0);
        t.accepted((0, 3));
        t.rejected((0, 3), "overloaded");
        t.result((0, 3), Outcome::Partial, t0);
        let s = t.snapshot();
        assert_eq!(s.latency_complete.len(), 1);
        assert_eq!((s.results, s.results_complete, s.results_shed), (4, 2, 1));
        assert_eq!(s.frames_cut_by_overload, 1);
        assert_eq!(s.partial_all_accepted, 0);
    }

    #[test]
    fn matches_results_to_sends_and_finds_lost_frames() {
        let t = Tracker::new();
        let t0 = Instant::now();
        for f in 0..3 {
            t.sent((0, f), t0);
            t.accepted((0, f));
        }
        t.sent((0, 9), t0);
        assert_eq!(t.in_flight(), 4);
        t.rejected((0, 9), "late");
        assert_eq!(t.in_flight(), 3);
        t.result((0, 0), Outcome::Complete, t0 + Duration::from_millis(5));
        t.result((0, 1), Outcome::Partial, t0 + Duration::from_millis(300));
        t.result((0, 1), Outcome::Partial, t0 + Duration::from_millis(301));
        t.result((1, 0), Outcome::Complete, t0);
        let s = t.snapshot();
        assert_eq!((s.sent, s.accepted, s.results), (4, 3, 4));
        assert_eq!(s.lost, vec![(0, 2)]);
        assert_eq!(s.unexpected_results, 1);
        assert_eq!(s.duplicate_results, 1);
        assert_eq!(s.rejected_by_kind["late"], 1);
        assert_eq!(s.latency_complete.len(), 1);
        let p50 = s.latency_complete.value_at_quantile(0.5);
        assert!((4_990..=5_010).contains(&p50), "{p50}");
        assert_eq!(s.latency_partial.len(), 1);
        assert_eq!(t.in_flight(), 1);
        t.found_on_reread((0, 2));
        t.found_on_reread((0, 2));
        let s = t.snapshot();
        assert!(s.lost.is_empty());
        assert_eq!((s.missed_live, s.latency_partial.len()), (1, 1));
        t.sent((0, 5), t0);
        t.failed((0, 5), "timeout");
        assert_eq!(t.in_flight(), 0);
        assert_eq!(t.snapshot().errors_by_kind["timeout"], 1);
    }
}

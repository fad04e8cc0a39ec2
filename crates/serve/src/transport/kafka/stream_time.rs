//! The stream time of one owned input partition (docs/kafka.md, "Stream time"): how far, by
//! the times the producers stamped their records, the partition has been delivered here. Its
//! scenes' sync timeouts run on it ([`crate::scene::Scene::follow_stream`]), the way stream
//! processors close windows on event time rather than on the reader's clock: a frame is cut
//! once the partition has delivered records at least `--sync-timeout` later than the frame's
//! first batch, or — only while the partition is caught up (nothing unread, no rebalance under
//! way) — once it has been quiet that long by the wall clock. While delivery is held, no frame
//! is cut.
use std::time::{Duration, Instant};

use crate::scene::StreamClock;

/// See the module docs.
#[derive(Debug, Default)]
pub(super) struct PartitionTime {
    /// What the partition's scenes read.
    clock: StreamClock,
    /// The latest record time delivered (ms since the Unix epoch; 0: none yet).
    stream_ms: u64,
    /// When (wall) the last record was delivered.
    delivered_at: Option<Instant>,
    /// The emission of the first report that found the partition caught up, with nothing
    /// delivered since: the quiet began then.
    idle_since: Option<Instant>,
    /// Reports emitted before this are not believed (a rebalance ended then).
    trust_from: Option<Instant>,
    /// A rebalance is under way.
    held: bool,
}

impl PartitionTime {
    /// The clock the partition's scenes follow.
    pub(super) fn clock(&self) -> StreamClock {
        self.clock.clone()
    }

    /// The stream time (ms since the Unix epoch; 0: nothing delivered yet).
    pub(super) fn millis(&self) -> u64 {
        self.clock.millis()
    }

    /// A record stamped `ts` (ms since the Unix epoch; `None` or not positive: no usable
    /// stamp, its arrival stands in) was delivered at wall time `now` (`now_ms`). The stream
    /// moves to its stamp, never beyond the wall clock: a producer whose clock runs ahead
    /// counts as now. Returns whether the stamp was usable.
    pub(super) fn deliver(&mut self, ts: Option<i64>, now: Instant, now_ms: u64) -> bool {
        let stamp = ts.filter(|t| *t > 0).map(|t| t as u64);
        self.stream_ms = self.stream_ms.max(stamp.unwrap_or(now_ms).min(now_ms));
        self.delivered_at = Some(now);
        self.idle_since = None;
        self.clock.advance_to(self.stream_ms);
        stamp.is_some()
    }

    /// A statistics report emitted at `at` found everything the broker holds read
    /// (`caught_up`) or not. Caught up, believed (no rebalance under way or since, nothing
    /// delivered since) and quiet since an earlier such report, the clock runs on by the quiet
    /// time. Returns whether it moved.
    pub(super) fn report(&mut self, caught_up: bool, at: Instant) -> bool {
        let stale =
            self.delivered_at.is_some_and(|d| at < d) || self.trust_from.is_some_and(|t| at < t);
        if self.held || stale {
            return false;
        }
        if !caught_up {
            self.idle_since = None;
            return false;
        }
        let since = *self.idle_since.get_or_insert(at);
        self.run_on(at.saturating_duration_since(since))
    }

    /// Consumption has been stuck since the last delivery (no room for frames in flight), so
    /// nothing unread can complete a waiting frame: the clock runs on by the wall time since
    /// that delivery. Returns whether it moved.
    pub(super) fn stuck(&mut self, now: Instant) -> bool {
        let quiet = self
            .delivered_at
            .map_or(Duration::ZERO, |d| now.saturating_duration_since(d));
        self.run_on(quiet)
    }

    /// A rebalance began: delivery is held, the quiet does not count.
    pub(super) fn hold(&mut self) {
        self.held = true;
        self.idle_since = None;
    }

    /// The rebalance ended at `now`: reports emitted before are not believed.
    pub(super) fn release(&mut self, now: Instant) {
        self.held = false;
        self.idle_since = None;
        self.trust_from = Some(now);
    }

    fn run_on(&mut self, quiet: Duration) -> bool {
        if self.stream_ms == 0 {
            return false;
        }
        let before = self.clock.millis();
        let quiet = u64::try_from(quiet.as_millis()).unwrap_or(u64::MAX);
        self.clock.advance_to(self.stream_ms.saturating_add(quiet));
        self.clock.millis() > before
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: Duration = Duration::from_millis(1);

    /// Records move the stream by their stamps (never past the wall clock, never back; no
    /// stamp: the arrival); wall time alone moves nothing.
    #[test]
    fn records_move_the_stream_by_their_stamps() {
        let (t0, w0) = (Instant::now(), 1_000_000u64);
        let mut p = PartitionTime::default();
        assert!(p.deliver(Some(999_000), t0, w0));
        assert_eq!(p.millis(), 999_000, "a backlog's old stamp");
        assert!(p.deliver(Some(999_500), t0 + 5 * MS, w0 + 5));
        assert_eq!(p.millis(), 999_500);
        p.deliver(Some(999_100), t0 + 6 * MS, w0 + 6);
        assert_eq!(p.millis(), 999_500, "an older stamp: never back");
        p.deliver(Some(1_005_000), t0 + 7 * MS, w0 + 7);
        assert_eq!(
            p.millis(),
            w0 + 7,
            "a stamp ahead of the wall clock counts as now"
        );
        assert!(!p.deliver(None, t0 + 8 * MS, w0 + 8));
        assert!(!p.deliver(Some(-1), t0 + 9 * MS, w0 + 9));
        assert_eq!(p.millis(), w0 + 9, "no usable stamp: the arrival");
    }

    /// Caught up and quiet, the stream runs on from the first report that found it so; a
    /// report not caught up, a delivery, or a rebalance starts the quiet over, and reports
    /// emitted before a delivery or during a rebalance are not believed.
    #[test]
    fn a_quiet_caught_up_partition_runs_on_wall_time() {
        let (t0, w0) = (Instant::now(), 1_000_000u64);
        let mut p = PartitionTime::default();
        assert!(
            !p.report(true, t0),
            "nothing delivered: no stream to run on"
        );
        p.deliver(Some(w0 as i64), t0, w0);
        assert!(!p.report(true, t0 + 100 * MS), "the quiet begins");
        assert!(p.report(true, t0 + 300 * MS));
        assert_eq!(p.millis(), w0 + 200);
        assert!(!p.report(false, t0 + 400 * MS), "records wait unread");
        assert!(!p.report(true, t0 + 500 * MS), "the quiet begins again");
        assert!(p.report(true, t0 + 800 * MS));
        assert_eq!(p.millis(), w0 + 300);
        // A rebalance: nothing counts while it lasts, nor what was emitted before its end.
        p.hold();
        assert!(!p.report(true, t0 + 900 * MS));
        assert!(!p.report(true, t0 + 2_000 * MS));
        p.release(t0 + 2_100 * MS);
        assert!(
            !p.report(true, t0 + 2_050 * MS),
            "emitted during the rebalance"
        );
        assert!(!p.report(true, t0 + 2_200 * MS));
        assert!(
            !p.report(true, t0 + 2_400 * MS),
            "only 200 ms of quiet: w0 + 200 < w0 + 300"
        );
        assert!(p.report(true, t0 + 2_600 * MS));
        assert_eq!(p.millis(), w0 + 400);
        // A delivery: reports emitted before it are stale.
        p.deliver(Some(w0 as i64 + 3_000), t0 + 3_000 * MS, w0 + 3_000);
        assert!(!p.report(true, t0 + 2_900 * MS));
        assert_eq!(p.millis(), w0 + 3_000);
    }

    /// Stuck consumption runs the stream on by the wall time since the last delivery.
    #[test]
    fn stuck_consumption_runs_on_wall_time() {
        let (t0, w0) = (Instant::now(), 1_000_000u64);
        let mut p = PartitionTime::default();
        p.deliver(Some(w0 as i64), t0, w0);
        assert!(p.stuck(t0 + 1_000 * MS));
        assert_eq!(p.millis(), w0 + 1_000);
    }
}

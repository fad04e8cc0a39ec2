//! The clock a scene's sync timeouts run on. Over gRPC and HTTP it is the wall clock: arrival
//! is the truth there. In Kafka mode it is the *stream time* of the scene's input partition
//! ([`StreamClock`], kept by the transport): how far, by the times the cameras' producers
//! stamped their records, the partition has delivered — so a frame waits as long as delivery
//! is held (a rebalance, a pause, a backlog) and is cut only once the stream has moved on
//! past its timeout, or the partition has been caught up and quiet that long.
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

/// A partition's stream time, shared by the transport (which moves it) and the partition's
/// scenes (which read it): milliseconds since the Unix epoch, 0 before the first record.
/// Read as an [`Instant`] of its own domain (see [`StreamClock::now`]): never compared with
/// wall instants, never slept on.
#[derive(Debug, Clone, Default)]
pub struct StreamClock(Arc<AtomicU64>);

/// The origin of stream instants: a stream time of `ms` reads as `origin + ms`.
fn origin() -> Instant {
    static ORIGIN: OnceLock<Instant> = OnceLock::new();
    *ORIGIN.get_or_init(Instant::now)
}

impl StreamClock {
    /// Moves the clock to `ms` (ms since the Unix epoch) if that is later; never back.
    pub fn advance_to(&self, ms: u64) {
        self.0.fetch_max(ms, Ordering::AcqRel);
    }

    /// The stream time in ms since the Unix epoch (0: nothing delivered yet).
    pub fn millis(&self) -> u64 {
        self.0.load(Ordering::Acquire)
    }

    /// The stream time as an instant of the stream domain.
    pub fn now(&self) -> Instant {
        origin() + Duration::from_millis(self.millis())
    }
}

/// A scene's timebase (see the module docs).
#[derive(Debug, Default)]
pub(super) enum Timebase {
    /// Wall time.
    #[default]
    Wall,
    /// The stream time of the scene's input partition.
    Stream(StreamClock),
}

impl Timebase {
    /// The synchronizer's clock at wall time `now`.
    pub(super) fn at(&self, now: Instant) -> Instant {
        match self {
            Timebase::Wall => now,
            Timebase::Stream(c) => c.now(),
        }
    }

    /// When the timer should look again for a frame due at clock `deadline`: on wall time at
    /// the deadline; on stream time when the transport moves the clock (it wakes the timer).
    pub(super) fn wake_at(&self, deadline: Instant) -> Option<Instant> {
        match self {
            Timebase::Wall => Some(deadline),
            Timebase::Stream(_) => None,
        }
    }

    /// Whether timeouts run on stream time.
    pub(super) fn is_stream(&self) -> bool {
        matches!(self, Timebase::Stream(_))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Wall time reads the wall clock and wakes at deadlines; stream time reads its clock,
    /// which never moves back, and waits to be woken.
    #[test]
    fn wall_and_stream_time() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let wall = Timebase::Wall;
        assert_eq!(wall.at(t0 + ms(50)), t0 + ms(50));
        assert_eq!(wall.wake_at(t0), Some(t0));
        let c = StreamClock::default();
        let stream = Timebase::Stream(c.clone());
        c.advance_to(1_000);
        let at = stream.at(t0);
        assert_eq!(stream.at(t0 + ms(5_000)), at, "wall time does not move it");
        c.advance_to(1_250);
        assert_eq!(stream.at(t0), at + ms(250));
        c.advance_to(1_100);
        assert_eq!(c.millis(), 1_250, "never back");
        assert_eq!(stream.wake_at(at), None);
    }
}

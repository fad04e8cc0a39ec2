//! A scene's input watermark: the time up to which a transport knows it has read every input
//! record that was written. Frames are stamped with their wall-clock arrival, but their
//! `--sync-timeout` is measured against the watermark, so a frame never times out while the
//! rest of its cameras may still be unread (Kafka mode, while a replica reads a backlog or
//! falls behind). Transports without one (gRPC, HTTP) leave it unset: wall time.
use std::time::Instant;

/// See the module docs.
#[derive(Debug, Default)]
pub(super) struct Watermark {
    /// Everything written before this instant has been read (`None`: no transport keeps a
    /// watermark, wall time rules).
    read_until: Option<Instant>,
}

impl Watermark {
    /// The synchronizer's clock at wall time `now`: the watermark, never ahead of `now`.
    pub(super) fn at(&self, now: Instant) -> Instant {
        self.read_until.map_or(now, |w| w.min(now))
    }

    /// When the timer should look again for a frame whose timeout falls at `deadline` (wall
    /// time `now`): at the deadline, or, when the watermark has yet to reach a deadline that
    /// is already past, never (the next [`set`](Self::set) wakes it).
    pub(super) fn wake_at(&self, deadline: Instant, now: Instant) -> Option<Instant> {
        match self.read_until {
            Some(w) if deadline <= now && w < deadline => None,
            _ => Some(deadline),
        }
    }

    /// Moves the watermark: `Some` never moves it back; `None` returns to wall time.
    pub(super) fn set(&mut self, read_until: Option<Instant>) {
        self.read_until = match (self.read_until, read_until) {
            (Some(old), Some(new)) => Some(old.max(new)),
            (_, new) => new,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    const MS: Duration = Duration::from_millis(1);

    /// Wall time without a watermark; with one, the clock stops at it, never moves back, and
    /// a past deadline the watermark has not reached waits for the next move.
    #[test]
    fn the_clock_never_passes_what_was_read() {
        let t0 = Instant::now();
        let mut w = Watermark::default();
        assert_eq!(w.at(t0 + 50 * MS), t0 + 50 * MS);
        assert_eq!(w.wake_at(t0, t0 + 50 * MS), Some(t0));
        w.set(Some(t0 + 10 * MS));
        assert_eq!(w.at(t0 + 50 * MS), t0 + 10 * MS);
        assert_eq!(w.at(t0 + 5 * MS), t0 + 5 * MS, "never ahead of now");
        w.set(Some(t0));
        assert_eq!(w.at(t0 + 50 * MS), t0 + 10 * MS, "never moves back");
        assert_eq!(
            w.wake_at(t0 + 20 * MS, t0 + 50 * MS),
            None,
            "past, not reached"
        );
        assert_eq!(w.wake_at(t0 + 60 * MS, t0 + 50 * MS), Some(t0 + 60 * MS));
        assert_eq!(w.wake_at(t0 + 5 * MS, t0 + 50 * MS), Some(t0 + 5 * MS));
        w.set(None);
        assert_eq!(w.at(t0 + 50 * MS), t0 + 50 * MS);
    }
}

//! The per-scene frame synchronizer: a pure state machine, driven by explicit time, that lines
//! up per-camera batches by frame id and decides when a frame leaves.
//!
//! Rules (SPEC §7, service issue):
//! - a frame is emitted as soon as every camera has reported it, but frames leave strictly in
//!   frame-id order, so a complete frame waits for older pending frames;
//! - a frame whose first batch arrived `timeout` ago is emitted (partial if cameras are
//!   missing), together with every older pending frame, so no frame waits longer than `timeout`;
//! - when more than `max_pending` frames are pending, the oldest leave first;
//! - a batch for a frame id at or below the last emitted one is *late*; a second batch of the
//!   same camera for a pending frame is a *duplicate*; both are rejected and change nothing;
//! - [`Synchronizer::flush`] emits everything pending (graceful shutdown).
//!
//! Every accepted batch therefore ends up in exactly one emitted frame.
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use crate::core::{Detection, Frame};

/// Why a batch was refused by the synchronizer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Rejection {
    /// The frame was already emitted (or an older one is being waited on no longer).
    Late,
    /// This camera already reported this frame.
    Duplicate,
}

/// Why a frame left the synchronizer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EmitReason {
    /// Every camera reported.
    Complete,
    /// It (or a newer frame) waited `timeout`.
    Timeout,
    /// Too many frames were pending; the oldest left.
    Overflow,
    /// The synchronizer was flushed (shutdown).
    Flush,
}

/// A frame that left the synchronizer.
#[derive(Debug, Clone, PartialEq)]
pub struct Emitted {
    /// The frame; `views[c]` is `None` for cameras that did not report.
    pub frame: Frame,
    /// When its first batch arrived (for latency).
    pub first_seen: Instant,
    /// Why it left now.
    pub reason: EmitReason,
}

impl Emitted {
    /// True when every camera reported.
    pub fn complete(&self) -> bool {
        self.frame.is_complete()
    }
}

#[derive(Debug)]
struct Pending {
    frame: Frame,
    first_seen: Instant,
    reported: usize,
}

/// Lines up batches of `num_cameras` cameras by frame id (see the module docs for the rules).
#[derive(Debug)]
pub struct Synchronizer {
    num_cameras: usize,
    timeout: Duration,
    max_pending: usize,
    pending: BTreeMap<u64, Pending>,
    /// The highest emitted frame id; batches at or below it are late.
    last_emitted: Option<u64>,
}

impl Synchronizer {
    /// A synchronizer for `num_cameras` cameras; `max_pending` is at least 1.
    pub fn new(num_cameras: usize, timeout: Duration, max_pending: usize) -> Self {
        Synchronizer {
            num_cameras,
            timeout,
            max_pending: max_pending.max(1),
            pending: BTreeMap::new(),
            last_emitted: None,
        }
    }

    /// Number of frames waiting.
    pub fn pending_frames(&self) -> usize {
        self.pending.len()
    }

    /// The highest emitted frame id so far.
    pub fn last_emitted(&self) -> Option<u64> {
        self.last_emitted
    }

    /// Accepts camera `camera`'s batch for `frame_id` at time `now` and returns the frames that
    /// leave because of it (in frame-id order), or why the batch was rejected.
    ///
    /// `camera` must be `< num_cameras` (the caller resolved the camera name).
    pub fn push(
        &mut self,
        camera: usize,
        frame_id: u64,
        detections: Vec<Detection>,
        now: Instant,
    ) -> Result<Vec<Emitted>, Rejection> {
        assert!(camera < self.num_cameras, "camera index out of range");
        if self.last_emitted.is_some_and(|last| frame_id <= last) {
            return Err(Rejection::Late);
        }
        let n = self.num_cameras;
        let entry = self.pending.entry(frame_id).or_insert_with(|| Pending {
            frame: Frame::new(frame_id, n),
            first_seen: now,
            reported: 0,
        });
        if entry.frame.views[camera].is_some() {
            return Err(Rejection::Duplicate);
        }
        entry.frame.views[camera] = Some(detections);
        entry.reported += 1;
        Ok(self.poll(now))
    }

    /// Emits, in frame-id order, every frame that may leave at time `now`.
    pub fn poll(&mut self, now: Instant) -> Vec<Emitted> {
        let mut out = Vec::new();
        // Timeout: the newest expired frame takes every older one with it.
        let expired = self
            .pending
            .iter()
            .filter(|(_, p)| now.saturating_duration_since(p.first_seen) >= self.timeout)
            .map(|(&id, _)| id)
            .next_back();
        if let Some(limit) = expired {
            while let Some((&id, _)) = self.pending.first_key_value() {
                if id > limit {
                    break;
                }
                out.push(self.pop_first(EmitReason::Timeout));
            }
        }
        while let Some((_, head)) = self.pending.first_key_value() {
            let reason = if head.reported == self.num_cameras {
                EmitReason::Complete
            } else if self.pending.len() > self.max_pending {
                EmitReason::Overflow
            } else {
                break;
            };
            out.push(self.pop_first(reason));
        }
        out
    }

    /// The earliest time at which [`poll`](Self::poll) may emit something, if anything waits.
    pub fn next_deadline(&self) -> Option<Instant> {
        self.pending
            .values()
            .map(|p| p.first_seen + self.timeout)
            .min()
    }

    /// Emits every pending frame in frame-id order (graceful shutdown).
    pub fn flush(&mut self) -> Vec<Emitted> {
        let mut out = Vec::with_capacity(self.pending.len());
        while !self.pending.is_empty() {
            out.push(self.pop_first(EmitReason::Flush));
        }
        out
    }

    fn pop_first(&mut self, reason: EmitReason) -> Emitted {
        let (id, p) = self.pending.pop_first().expect("caller checked non-empty");
        self.last_emitted = Some(id);
        Emitted {
            frame: p.frame,
            first_seen: p.first_seen,
            reason,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn det() -> Vec<Detection> {
        vec![Detection::new([1.0, 2.0, 3.0, 4.0])]
    }

    fn ids(e: &[Emitted]) -> Vec<u64> {
        e.iter().map(|e| e.frame.frame_id).collect()
    }

    const T: Duration = Duration::from_millis(200);

    #[test]
    fn complete_frame_leaves_at_once() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, 16);
        assert!(s.push(0, 7, det(), t0).unwrap().is_empty());
        assert!(s.push(2, 7, vec![], t0).unwrap().is_empty());
        let out = s.push(1, 7, det(), t0).unwrap();
        assert_eq!(ids(&out), vec![7]);
        assert!(out[0].complete());
        assert_eq!(out[0].reason, EmitReason::Complete);
        assert_eq!(out[0].frame.views[2], Some(vec![]));
        assert_eq!(s.pending_frames(), 0);
    }

    #[test]
    fn complete_frame_waits_for_older_then_leaves_in_order() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(2, T, 16);
        s.push(0, 1, det(), t0).unwrap();
        s.push(0, 2, det(), t0).unwrap();
        assert!(s.push(1, 2, det(), t0).unwrap().is_empty(), "2 waits for 1");
        let out = s.push(1, 1, det(), t0).unwrap();
        assert_eq!(ids(&out), vec![1, 2]);
        assert!(out.iter().all(Emitted::complete));
    }

    #[test]
    fn missing_camera_gives_partial_after_timeout() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, 16);
        s.push(0, 5, det(), t0).unwrap();
        s.push(1, 5, det(), t0 + Duration::from_millis(50)).unwrap();
        assert_eq!(s.next_deadline(), Some(t0 + T));
        assert!(s.poll(t0 + T - Duration::from_millis(1)).is_empty());
        let out = s.poll(t0 + T);
        assert_eq!(ids(&out), vec![5]);
        assert!(!out[0].complete());
        assert_eq!(out[0].reason, EmitReason::Timeout);
        assert_eq!(out[0].frame.views[2], None);
        assert_eq!(s.next_deadline(), None);
    }

    #[test]
    fn expired_newer_frame_takes_older_ones_with_it() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(2, T, 16);
        s.push(0, 10, det(), t0).unwrap();
        s.push(0, 9, det(), t0 + Duration::from_millis(100))
            .unwrap();
        let out = s.poll(t0 + T);
        assert_eq!(ids(&out), vec![9, 10]);
        assert_eq!(s.push(1, 9, det(), t0 + T), Err(Rejection::Late));
    }

    #[test]
    fn late_and_duplicate_are_rejected_without_effect() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(2, T, 16);
        s.push(0, 3, det(), t0).unwrap();
        assert_eq!(s.push(0, 3, det(), t0), Err(Rejection::Duplicate));
        s.push(1, 3, det(), t0).unwrap();
        assert_eq!(s.push(1, 3, det(), t0), Err(Rejection::Late));
        assert_eq!(s.push(0, 2, det(), t0), Err(Rejection::Late));
        assert_eq!(s.pending_frames(), 0);
        assert_eq!(s.last_emitted(), Some(3));
    }

    #[test]
    fn overflow_emits_oldest_first() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(2, T, 2);
        s.push(0, 1, det(), t0).unwrap();
        s.push(0, 2, det(), t0).unwrap();
        let out = s.push(0, 3, det(), t0).unwrap();
        assert_eq!(ids(&out), vec![1]);
        assert_eq!(out[0].reason, EmitReason::Overflow);
        assert_eq!(s.pending_frames(), 2);
    }

    #[test]
    fn flush_emits_everything_in_order() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, 16);
        for f in [4, 2, 9] {
            s.push(1, f, det(), t0).unwrap();
        }
        let out = s.flush();
        assert_eq!(ids(&out), vec![2, 4, 9]);
        assert!(out.iter().all(|e| e.reason == EmitReason::Flush));
        assert_eq!(s.pending_frames(), 0);
    }

    proptest! {
        /// Any interleaving of pushes and polls: accepted batches appear in exactly one emitted
        /// frame, frames leave in strictly increasing order, and rejections are exactly the
        /// late and duplicate batches.
        #[test]
        fn every_accepted_batch_is_emitted_once_in_order(
            ops in proptest::collection::vec((0usize..3, 0u64..12, 0u64..400, any::<bool>()), 0..80),
            max_pending in 1usize..6,
        ) {
            let t0 = Instant::now();
            let mut s = Synchronizer::new(3, T, max_pending);
            let mut emitted: Vec<Emitted> = Vec::new();
            let mut accepted = std::collections::HashSet::new();
            let mut clock = 0u64;
            for (cam, frame, dt, poll) in ops {
                clock += dt;
                let now = t0 + Duration::from_millis(clock);
                if poll {
                    emitted.extend(s.poll(now));
                    continue;
                }
                let was_emitted = emitted.iter().any(|e| e.frame.frame_id >= frame);
                match s.push(cam, frame, vec![], now) {
                    Ok(out) => {
                        prop_assert!(!was_emitted);
                        prop_assert!(accepted.insert((cam, frame)));
                        emitted.extend(out);
                    }
                    Err(Rejection::Late) => prop_assert!(was_emitted),
                    Err(Rejection::Duplicate) => prop_assert!(accepted.contains(&(cam, frame))),
                }
                prop_assert!(s.pending_frames() <= max_pending);
            }
            emitted.extend(s.flush());
            let order: Vec<u64> = ids(&emitted);
            prop_assert!(order.windows(2).all(|w| w[0] < w[1]));
            let mut seen = std::collections::HashSet::new();
            for e in &emitted {
                for (c, v) in e.frame.views.iter().enumerate() {
                    if v.is_some() {
                        prop_assert!(seen.insert((c, e.frame.frame_id)));
                    }
                }
            }
            prop_assert_eq!(seen, accepted);
        }
    }
}

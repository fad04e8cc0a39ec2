//! The per-scene frame synchronizer: a pure state machine, driven by explicit time, that lines
//! up per-camera batches by frame id and decides when a frame leaves.
//!
//! Rules (SPEC §7, service issue):
//! - a frame is emitted as soon as every camera has reported it, but frames leave strictly in
//!   frame-id order, so a complete frame waits for older pending frames;
//! - a frame whose first batch arrived `timeout` ago is emitted (partial if cameras are
//!   missing), together with every older pending frame, so no frame waits longer than `timeout`;
//! - when more than `max_pending` frames are pending, the oldest leave first;
//! - a batch for a frame id at or below the last emitted one (but within the window below) is
//!   *late*; a second batch of the same camera for a pending frame is a *duplicate*; both are
//!   rejected and change nothing;
//! - **window**: frame ids must stay within `window` of the last emitted frame id (before
//!   anything was emitted: of the oldest pending frame). A batch further ahead or further
//!   behind is *out of range*: rejected, changing nothing, so no single batch (a frame id of
//!   2^64−1, a jump to 10^9, far-future junk filling the pending slots) can make every later
//!   frame late;
//! - **restart**: camera ids restart, wrap and jump after long outages. Out-of-range batches
//!   are remembered per camera until the next accepted batch; once the out-of-range batches of
//!   a majority of the cameras (and at least two batches) lie within `window` of each other,
//!   the synchronizer *re-anchors*: every pending frame leaves (reason
//!   [`EmitReason::Restart`]), the last emitted id is forgotten and the batch that completed
//!   the majority is accepted as the first of the new range. The other cameras' earlier
//!   out-of-range batches stay rejected (their senders were told so);
//! - [`Synchronizer::flush`] emits everything pending (graceful shutdown).
//!
//! Every accepted batch therefore ends up in exactly one emitted frame.
use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use crossview_core::{Detection, Frame};

/// Why a batch was refused by the synchronizer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Rejection {
    /// The frame was already emitted (or an older one is being waited on no longer).
    Late,
    /// This camera already reported this frame.
    Duplicate,
    /// The frame id is more than the window away from the scene's current frame ids.
    OutOfRange,
}

/// Why a frame left the synchronizer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EmitReason {
    /// Every camera reported.
    Complete,
    /// It (or a newer frame) waited `timeout`.
    Timeout,
    /// Too many frames were pending; the oldest left.
    Overflow,
    /// The synchronizer was flushed (shutdown).
    Flush,
    /// A majority of cameras moved to frame ids outside the window (a restart).
    Restart,
}

/// A frame that left the synchronizer.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Emitted {
    /// The frame; `views[c]` is `None` for cameras that did not report.
    pub frame: Frame,
    /// When its first batch arrived (for latency).
    pub first_seen: Instant,
    /// How long it waited by the clock its timeout is measured on (from its first batch to
    /// the clock at which it left; zero when flushed).
    pub waited: Duration,
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
    /// The clock when its first batch came: its timeout runs from here.
    due_from: Instant,
    reported: usize,
}

/// Lines up batches of `num_cameras` cameras by frame id (see the module docs for the rules).
#[derive(Debug)]
pub(crate) struct Synchronizer {
    num_cameras: usize,
    timeout: Duration,
    max_pending: usize,
    pending: BTreeMap<u64, Pending>,
    /// The highest emitted frame id; batches at or below it are late.
    last_emitted: Option<u64>,
    /// How far (in frame ids) a batch may be from the current frame ids.
    window: u64,
    /// Per camera, its latest out-of-range frame id since the last accepted batch.
    strays: Vec<Option<u64>>,
    /// Out-of-range batches since the last accepted batch.
    stray_batches: usize,
    /// Re-anchors so far.
    restarts: u64,
}

/// The default frame-id window (see the module docs).
pub(crate) const DEFAULT_FRAME_WINDOW: u64 = 100_000;

impl Synchronizer {
    /// A synchronizer for `num_cameras` cameras; `max_pending` is at least 1.
    pub fn new(num_cameras: usize, timeout: Duration, max_pending: usize) -> Self {
        Synchronizer {
            num_cameras,
            timeout,
            max_pending: max_pending.max(1),
            pending: BTreeMap::new(),
            last_emitted: None,
            window: DEFAULT_FRAME_WINDOW,
            strays: vec![None; num_cameras],
            stray_batches: 0,
            restarts: 0,
        }
    }

    /// How many times the frame ids restarted (re-anchors) so far (the model test's oracle).
    #[cfg(test)]
    pub(crate) fn restarts(&self) -> u64 {
        self.restarts
    }

    /// Sets the frame-id window (at least 1; see the module docs).
    pub(crate) fn with_window(mut self, window: u64) -> Self {
        self.window = window.max(1);
        self
    }

    /// The frame-id window.
    pub fn window(&self) -> u64 {
        self.window
    }

    /// Where `frame_id` lies relative to the current frame ids: `None` when it is accepted
    /// (pending or new), otherwise why not.
    fn classify(&self, frame_id: u64) -> Option<Rejection> {
        let w = self.window;
        match (self.last_emitted, self.pending.keys().next()) {
            (Some(last), _) if frame_id <= last => (last - frame_id > w)
                .then_some(Rejection::OutOfRange)
                .or(Some(Rejection::Late)),
            (Some(last), _) => (frame_id - last > w).then_some(Rejection::OutOfRange),
            (None, Some(&oldest)) => {
                (frame_id.abs_diff(oldest) > w).then_some(Rejection::OutOfRange)
            }
            (None, None) => None,
        }
    }

    /// Records an out-of-range batch; true when the cameras' out-of-range batches now agree
    /// enough to re-anchor on `frame_id` (see the module docs).
    fn record_stray(&mut self, camera: usize, frame_id: u64) -> bool {
        self.strays[camera] = Some(frame_id);
        self.stray_batches += 1;
        let agree = self
            .strays
            .iter()
            .flatten()
            .filter(|&&s| s.abs_diff(frame_id) <= self.window)
            .count();
        agree > self.num_cameras / 2 && self.stray_batches >= 2
    }

    /// Emits every pending frame and forgets the frame-id range (a restart of the ids).
    fn reanchor(&mut self) -> Vec<Emitted> {
        let mut out = Vec::with_capacity(self.pending.len());
        while !self.pending.is_empty() {
            out.push(self.pop_first(EmitReason::Restart, None));
        }
        self.last_emitted = None;
        self.restarts += 1;
        out
    }

    /// Number of frames waiting.
    pub(crate) fn pending_frames(&self) -> usize {
        self.pending.len()
    }

    /// The pending frame `frame_id`, if it is waiting.
    pub(crate) fn pending_frame(&self, frame_id: u64) -> Option<&Frame> {
        self.pending.get(&frame_id).map(|p| &p.frame)
    }

    /// The highest emitted frame id so far.
    pub(crate) fn last_emitted(&self) -> Option<u64> {
        self.last_emitted
    }

    /// Accepts camera `camera`'s batch for `frame_id` at time `now` and returns the frames that
    /// leave because of it (in frame-id order), or why the batch was rejected.
    ///
    /// `camera` must be `< num_cameras` (the caller resolved the camera name).
    #[cfg(test)]
    pub fn push(
        &mut self,
        camera: usize,
        frame_id: u64,
        detections: Vec<Detection>,
        now: Instant,
    ) -> Result<Vec<Emitted>, Rejection> {
        self.push_at(camera, frame_id, detections, now, now)
    }

    /// Accepts camera `camera`'s batch for `frame_id` and returns the frames that leave because
    /// of it, or why it was rejected, with two clocks: a new frame is stamped `arrived` (wall
    /// time, for latency), and timeouts are measured on the clock `now`, which need not be
    /// the wall clock (Kafka mode: the stream time of the scene's partition, so a frame never
    /// times out while delivery is held). `camera` must be `< num_cameras`.
    pub fn push_at(
        &mut self,
        camera: usize,
        frame_id: u64,
        detections: Vec<Detection>,
        arrived: Instant,
        now: Instant,
    ) -> Result<Vec<Emitted>, Rejection> {
        assert!(camera < self.num_cameras, "camera index out of range");
        let mut out = Vec::new();
        match self.classify(frame_id) {
            None => {}
            Some(Rejection::OutOfRange) => {
                if !self.record_stray(camera, frame_id) {
                    return Err(Rejection::OutOfRange);
                }
                out = self.reanchor();
            }
            Some(r) => return Err(r),
        }
        let n = self.num_cameras;
        let entry = self.pending.entry(frame_id).or_insert_with(|| Pending {
            frame: Frame::new(frame_id, n),
            first_seen: arrived,
            due_from: now,
            reported: 0,
        });
        if entry.frame.views[camera].is_some() {
            return Err(Rejection::Duplicate);
        }
        entry.frame.views[camera] = Some(detections);
        entry.reported += 1;
        self.strays.iter_mut().for_each(|s| *s = None);
        self.stray_batches = 0;
        out.extend(self.poll(now));
        Ok(out)
    }

    /// Emits, in frame-id order, every frame that may leave at time `now`.
    pub fn poll(&mut self, now: Instant) -> Vec<Emitted> {
        let mut out = Vec::new();
        // Timeout: the newest expired frame takes every older one with it.
        let expired = self
            .pending
            .iter()
            .filter(|(_, p)| now.saturating_duration_since(p.due_from) >= self.timeout)
            .map(|(&id, _)| id)
            .next_back();
        if let Some(limit) = expired {
            while let Some((&id, _)) = self.pending.first_key_value() {
                if id > limit {
                    break;
                }
                out.push(self.pop_first(EmitReason::Timeout, Some(now)));
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
            out.push(self.pop_first(reason, Some(now)));
        }
        out
    }

    /// The earliest clock at which [`poll`](Self::poll) may emit something, if anything waits.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        self.pending
            .values()
            .map(|p| p.due_from + self.timeout)
            .min()
    }

    /// Emits every pending frame in frame-id order (graceful shutdown).
    pub fn flush(&mut self) -> Vec<Emitted> {
        let mut out = Vec::with_capacity(self.pending.len());
        while !self.pending.is_empty() {
            out.push(self.pop_first(EmitReason::Flush, None));
        }
        out
    }

    /// Drops every pending frame (never emitted) and starts over as if `last_emitted` were the
    /// last frame emitted (`None`: nothing yet); returns how many frames were dropped. For a
    /// scene whose input moved to another consumer (Kafka mode's revocation), or came back.
    pub(crate) fn restart(&mut self, last_emitted: Option<u64>) -> usize {
        let n = self.pending.len();
        self.pending.clear();
        self.last_emitted = last_emitted;
        self.strays.iter_mut().for_each(|s| *s = None);
        self.stray_batches = 0;
        n
    }

    /// The oldest pending frame, leaving for `reason` at clock `now` (`None`: flushed).
    fn pop_first(&mut self, reason: EmitReason, now: Option<Instant>) -> Emitted {
        let (id, p) = self.pending.pop_first().expect("caller checked non-empty");
        self.last_emitted = Some(id);
        Emitted {
            frame: p.frame,
            first_seen: p.first_seen,
            waited: now.map_or(Duration::ZERO, |n| n.saturating_duration_since(p.due_from)),
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

    /// Timeouts run on the second clock, from its reading at the frame's first batch, however
    /// far wall time moves meanwhile; the arrival stamp is kept for latency, the wait on the
    /// second clock is reported; complete frames still leave at once.
    #[test]
    fn timeouts_run_on_the_clock_they_are_given() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        // The second clock (a stream's time) reads s0 while wall time reads t0 + ...
        let s0 = t0 + Duration::from_secs(3600);
        let mut s = Synchronizer::new(2, T, 16);
        assert!(s.push_at(0, 5, det(), t0 + ms(300), s0).unwrap().is_empty());
        assert_eq!(s.next_deadline(), Some(s0 + T));
        assert!(
            s.poll(s0 + T - ms(1)).is_empty(),
            "the clock has not moved on by the timeout"
        );
        // Another frame starts while the clock has moved 100 ms.
        assert!(
            s.push_at(0, 6, det(), t0 + ms(400), s0 + ms(100))
                .unwrap()
                .is_empty()
        );
        let out = s.push_at(1, 6, det(), t0 + ms(2400), s0 + ms(150)).unwrap();
        assert!(out.is_empty(), "6 is complete but 5, older, still waits");
        let out = s.poll(s0 + T);
        assert_eq!(ids(&out), vec![5, 6], "5 times out, complete 6 follows");
        assert_eq!(out[0].first_seen, t0 + ms(300));
        assert_eq!(out[0].waited, T);
        assert_eq!(out[1].waited, T - ms(100));
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
    fn huge_frame_id_is_out_of_range_and_changes_nothing() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, 16).with_window(1000);
        for c in 0..3 {
            s.push(c, 10, det(), t0).unwrap();
        }
        assert_eq!(s.last_emitted(), Some(10));
        for id in [u64::MAX, 1_000_000_000, 1011] {
            assert_eq!(s.push(0, id, det(), t0), Err(Rejection::OutOfRange));
        }
        assert_eq!(s.pending_frames(), 0);
        // The window edge itself is in range, and normal frames go on.
        assert!(s.push(1, 1010, det(), t0).is_ok());
        let out = s.push(0, 11, det(), t0).unwrap();
        assert!(out.is_empty());
        assert_eq!(s.pending_frames(), 2);
    }

    #[test]
    fn window_applies_before_anything_was_emitted() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(2, T, 16).with_window(100);
        s.push(0, 500, det(), t0).unwrap();
        assert!(s.push(1, 450, det(), t0).is_ok(), "slightly older is fine");
        assert_eq!(s.push(1, u64::MAX, det(), t0), Err(Rejection::OutOfRange));
        assert_eq!(s.push(0, 0, det(), t0), Err(Rejection::OutOfRange));
    }

    #[test]
    fn majority_of_cameras_restarting_their_ids_reanchors() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, 16).with_window(1000);
        for c in 0..3 {
            s.push(c, 50_000, det(), t0).unwrap();
        }
        s.push(2, 50_001, det(), t0).unwrap();
        // Camera 0 restarts at 0: one camera is not a majority.
        assert_eq!(s.push(0, 0, det(), t0), Err(Rejection::OutOfRange));
        // Camera 1 follows: two of three agree; the pending frame leaves, frame 1 is accepted.
        let out = s.push(1, 1, det(), t0).unwrap();
        assert_eq!(ids(&out), vec![50_001]);
        assert_eq!(out[0].reason, EmitReason::Restart);
        assert_eq!(s.last_emitted(), None);
        assert!(s.push(0, 1, det(), t0).is_ok());
        // Camera 2, still on the old ids, is now out of range on its own.
        assert_eq!(s.push(2, 50_002, det(), t0), Err(Rejection::OutOfRange));
        let out = s.push(2, 1, det(), t0).unwrap();
        assert_eq!(ids(&out), vec![1]);
        assert!(out[0].complete());
    }

    #[test]
    fn one_camera_scene_needs_two_out_of_range_batches_to_restart() {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(1, T, 16).with_window(10);
        s.push(0, 100, det(), t0).unwrap();
        assert_eq!(s.push(0, u64::MAX, det(), t0), Err(Rejection::OutOfRange));
        // An accepted batch in between forgets the stray.
        s.push(0, 101, det(), t0).unwrap();
        assert_eq!(s.push(0, 0, det(), t0), Err(Rejection::OutOfRange));
        assert_eq!(ids(&s.push(0, 1, det(), t0).unwrap()), vec![1]);
        assert_eq!(s.last_emitted(), Some(1));
    }

    #[test]
    fn restart_drops_pending_frames_and_resumes_past_the_given_frame() {
        let mut s = Synchronizer::new(2, Duration::from_secs(1), 8);
        let t = Instant::now();
        s.push(0, 1, det(), t).unwrap();
        s.push(1, 1, det(), t).unwrap();
        s.push(0, 2, det(), t).unwrap();
        assert_eq!(s.restart(Some(1)), 1, "frame 2 dropped");
        assert_eq!(s.pending_frames(), 0);
        assert_eq!(s.push(1, 1, det(), t), Err(Rejection::Late));
        let out = s.push(0, 2, det(), t).unwrap();
        assert!(out.is_empty(), "frame 2 forms afresh");
        assert_eq!(ids(&s.push(1, 2, det(), t).unwrap()), vec![2]);
        assert_eq!(s.restart(None), 0);
        assert!(s.push(0, 1, det(), t).is_ok(), "nothing emitted any more");
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
                    Err(Rejection::OutOfRange) => prop_assert!(false, "ids stay within the window"),
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

        /// With a small window and restarts: accepted batches still appear in exactly one
        /// emitted frame, pending frames stay bounded, and between two re-anchors frames leave
        /// in strictly increasing order.
        #[test]
        fn window_and_restarts_lose_nothing(
            ops in proptest::collection::vec((0usize..3, 0u64..60, 0u64..300, any::<bool>()), 0..120),
            window in 1u64..20,
        ) {
            let t0 = Instant::now();
            let mut s = Synchronizer::new(3, T, 4).with_window(window);
            // Emission order per epoch (the number of re-anchors before the frame's batches).
            let mut order: BTreeMap<u64, Vec<u64>> = BTreeMap::new();
            let mut accepted = std::collections::HashSet::new();
            let mut seen = std::collections::HashSet::new();
            let mut clock = 0u64;
            let mut take = |out: Vec<Emitted>, epoch: u64| {
                for e in out {
                    let epoch = if e.reason == EmitReason::Restart { epoch - 1 } else { epoch };
                    order.entry(epoch).or_default().push(e.frame.frame_id);
                    for (c, v) in e.frame.views.iter().enumerate() {
                        if v.is_some() {
                            assert!(seen.insert((c, e.frame.frame_id, epoch)));
                        }
                    }
                }
            };
            for (cam, frame, dt, poll) in ops {
                clock += dt;
                let now = t0 + Duration::from_millis(clock);
                if poll {
                    take(s.poll(now), s.restarts());
                    continue;
                }
                if let Ok(out) = s.push(cam, frame, vec![], now) {
                    accepted.insert((cam, frame, s.restarts()));
                    take(out, s.restarts());
                }
                prop_assert!(s.pending_frames() <= 4);
            }
            take(s.flush(), s.restarts());
            for ids in order.values() {
                prop_assert!(ids.windows(2).all(|w| w[0] < w[1]), "{:?}", order);
            }
            prop_assert_eq!(seen, accepted);
        }
    }
}

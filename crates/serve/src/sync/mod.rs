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
//! - **shed**: under overload the scene sheds a *new* frame whole ([`Synchronizer::shed`]):
//!   it holds no batch, leaves as soon as every older frame has (never holding newer ones
//!   back), and every batch of it is refused ([`Rejection::Shed`]) — before and after it
//!   left, as long as the last [`SHED_MEMORY`] shed frames are remembered — so a frame is
//!   either whole or shed, never cut by the overload;
//! - [`Synchronizer::flush`] emits everything pending (graceful shutdown).
//!
//! Every accepted batch therefore ends up in exactly one emitted frame.
use std::collections::{BTreeMap, BTreeSet};
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
    /// The frame was shed (overload): none of its batches is taken.
    Shed,
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
    /// It was shed, and every older frame has left.
    Shed,
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
    /// Shed under overload: it holds no batch and is published as shed, never associated.
    pub shed: bool,
}

impl Emitted {
    /// True when every camera reported.
    pub fn complete(&self) -> bool {
        self.frame.is_complete()
    }
}

/// Shed frames remembered (their late batches are refused as shed, not late).
pub(crate) const SHED_MEMORY: usize = 1024;

#[derive(Debug)]
struct Pending {
    frame: Frame,
    first_seen: Instant,
    /// The clock when its first batch came: its timeout runs from here.
    due_from: Instant,
    reported: usize,
    /// Shed: it takes no batch and leaves as soon as it is the oldest.
    shed: bool,
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
    /// The newest shed frames (at most [`SHED_MEMORY`]).
    shed: BTreeSet<u64>,
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
            shed: BTreeSet::new(),
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
        // The ids start over: an old shed id may come back as a new frame.
        self.shed.clear();
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
        if self.shed.contains(&frame_id) {
            return Err(Rejection::Shed);
        }
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
            shed: false,
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

    /// Sheds frame `frame_id`, which has no batch yet (see the module docs): refuses its
    /// batches from now on and returns the frames that leave (itself, once it is the
    /// oldest). A frame id that a batch could not take (late, out of range) is refused the
    /// same way; one already pending is left as it is (nothing leaves).
    pub fn shed(
        &mut self,
        frame_id: u64,
        arrived: Instant,
        now: Instant,
    ) -> Result<Vec<Emitted>, Rejection> {
        if self.shed.contains(&frame_id) || self.pending.contains_key(&frame_id) {
            return Ok(Vec::new());
        }
        if let Some(r) = self.classify(frame_id) {
            return Err(r);
        }
        self.pending.insert(
            frame_id,
            Pending {
                frame: Frame::new(frame_id, self.num_cameras),
                first_seen: arrived,
                due_from: now,
                reported: 0,
                shed: true,
            },
        );
        self.shed.insert(frame_id);
        while self.shed.len() > SHED_MEMORY {
            self.shed.pop_first();
        }
        Ok(self.poll(now))
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
            let reason = if head.shed {
                EmitReason::Shed
            } else if head.reported == self.num_cameras {
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
        self.shed.clear();
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
            shed: p.shed,
        }
    }
}

#[cfg(test)]
mod tests;

//! What a replica owns and what it consumed but has not committed: the bookkeeping behind
//! "ownership decides everything" (docs/kafka.md).
//!
//! * Per owned partition, the consumed offsets still open (their batch is in no produced
//!   result yet) and a *generation*, new at every assignment of the partition.
//! * Per frame with consumed batches, its records and the generation they were read in: a
//!   frame whose partition was revoked since (or revoked and assigned again) is *stale* and is
//!   never produced here; the owner re-reads its batches from the committed offset.
//! * Per scene, the partition and generation it was last (re)started in and the last frame
//!   produced for it: the first record of a scene in a new generation restarts the scene's
//!   synchronizer just past that frame, so re-read batches re-form their frames and those of
//!   frames already produced are recognised as re-deliveries.
//! * Per partition ever owned, one past the highest offset consumed: a record below it was
//!   read before (a re-delivery after a rebalance).
//! * Per owned partition, its *stream time* ([`PartitionTime`]): its scenes' sync timeouts
//!   run on it, so a frame never times out while delivery is held.
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::time::Instant;

use super::stream_time::PartitionTime;
use crate::scene::StreamClock;

/// The offsets of one owned input partition.
#[derive(Debug, Default)]
struct Part {
    /// Consumed offsets whose batch is not yet in a produced result (nor refused).
    open: BTreeSet<i64>,
    /// One past the highest consumed offset.
    next: Option<i64>,
    /// The last offset committed (or handed to the commit).
    committed: Option<i64>,
    /// Which assignment of the partition this is.
    generation: u64,
    /// Its stream time.
    time: PartitionTime,
}

impl Part {
    fn committable(&self) -> Option<i64> {
        self.open.first().copied().or(self.next)
    }
}

/// The input records of one frame not yet in a produced result.
#[derive(Debug, Clone, PartialEq)]
pub(super) struct Held {
    partition: i32,
    generation: u64,
    offsets: Vec<i64>,
}

/// Where a scene was last (re)started and what was last produced for it.
#[derive(Debug)]
struct SceneState {
    partition: i32,
    generation: u64,
    produced: Option<u64>,
}

/// What to do with a result the scene published.
#[derive(Debug, PartialEq)]
pub(super) enum Publish {
    /// Its batches came from a partition owned since they were read: produce it, then close
    /// them ([`Ownership::produced`]).
    Owned(Held),
    /// Its batches came from a partition revoked since: never produced here.
    Stale,
    /// Not fed from Kafka (a scene no record has named): produced, nothing to close.
    Unheld,
}

/// The ownership state of one replica (see the module docs).
#[derive(Debug, Default)]
pub(super) struct Ownership {
    parts: BTreeMap<i32, Part>,
    frames: HashMap<(String, u64), Held>,
    scenes: HashMap<String, SceneState>,
    /// Per partition ever owned here: one past the highest offset consumed.
    seen: HashMap<i32, i64>,
    generations: u64,
    /// When the current assignment began (ms since the Unix epoch): the results' epoch.
    pub(super) epoch: u64,
}

impl Ownership {
    /// `partition` is now owned (a new generation; already owned: unchanged).
    pub(super) fn assign(&mut self, partition: i32) {
        if !self.parts.contains_key(&partition) {
            self.generations += 1;
            let generation = self.generations;
            self.parts.insert(
                partition,
                Part {
                    generation,
                    ..Part::default()
                },
            );
        }
    }

    /// `partition` is no longer owned: forgets its open offsets and its frames; returns the
    /// scenes last started on it (their pending frames must be dropped) and how many frames
    /// with consumed batches were forgotten.
    pub(super) fn revoke(&mut self, partition: i32) -> (Vec<String>, usize) {
        if let Some(p) = self.parts.remove(&partition)
            && let Some(n) = p.next
        {
            let seen = self.seen.entry(partition).or_insert(n);
            *seen = (*seen).max(n);
        }
        let before = self.frames.len();
        self.frames.retain(|_, h| h.partition != partition);
        (
            self.scenes_on(|q| q == partition),
            before - self.frames.len(),
        )
    }

    /// The stream clock of owned `partition` (see the module docs).
    pub(super) fn clock(&self, partition: i32) -> Option<StreamClock> {
        self.parts.get(&partition).map(|p| p.time.clock())
    }

    /// A record stamped `ts` of owned `partition` was delivered at wall time `now` (`now_ms`):
    /// see [`PartitionTime::deliver`]. `None` when the partition is not owned.
    pub(super) fn deliver(
        &mut self,
        partition: i32,
        ts: Option<i64>,
        now: Instant,
        now_ms: u64,
    ) -> Option<bool> {
        Some(
            self.parts
                .get_mut(&partition)?
                .time
                .deliver(ts, now, now_ms),
        )
    }

    /// The consumer's statistics for owned `partition`, emitted at `at`: the broker's high
    /// watermark `high` (negative: unknown, or not to be trusted now) and where librdkafka
    /// has the consumer (its committed or application offset, whichever is further;
    /// negative: unknown). Caught up when everything below `high` was read
    /// ([`PartitionTime::report`]). Returns the stream time, and the scenes on
    /// the partition when it moved; `None` when not owned.
    pub(super) fn report(
        &mut self,
        partition: i32,
        high: i64,
        position: i64,
        at: Instant,
    ) -> Option<(u64, Vec<String>)> {
        let p = self.parts.get_mut(&partition)?;
        let read = p.next.unwrap_or(i64::MIN).max(position);
        let moved = p.time.report(high >= 0 && read >= high, at);
        let ms = p.time.millis();
        let scenes = if moved {
            self.scenes_on(|q| q == partition)
        } else {
            Vec::new()
        };
        Some((ms, scenes))
    }

    /// Consumption is stuck ([`PartitionTime::stuck`]): returns the scenes whose stream time
    /// moved.
    pub(super) fn stuck(&mut self, now: Instant) -> Vec<String> {
        let moved: Vec<i32> = self
            .parts
            .iter_mut()
            .filter_map(|(&q, p)| p.time.stuck(now).then_some(q))
            .collect();
        self.scenes_on(|q| moved.contains(&q))
    }

    /// A rebalance began: every owned partition's delivery is held.
    pub(super) fn hold_all(&mut self) {
        self.parts.values_mut().for_each(|p| p.time.hold());
    }

    /// The rebalance ended at `now`.
    pub(super) fn release_all(&mut self, now: Instant) {
        self.parts.values_mut().for_each(|p| p.time.release(now));
    }

    /// The scenes last started on a partition `on` accepts.
    fn scenes_on(&self, on: impl Fn(i32) -> bool) -> Vec<String> {
        self.scenes
            .iter()
            .filter(|(_, s)| on(s.partition))
            .map(|(name, _)| name.clone())
            .collect()
    }

    /// Whether `partition` is owned now.
    pub(super) fn owns(&self, partition: i32) -> bool {
        self.parts.contains_key(&partition)
    }

    /// Record `offset` of `partition` was consumed and stays open until
    /// [`done`](Self::done). `None` when the partition is not owned (the record is left to
    /// its owner); else whether it was read here before (a re-delivery).
    pub(super) fn consumed(&mut self, partition: i32, offset: i64) -> Option<bool> {
        let p = self.parts.get_mut(&partition)?;
        p.open.insert(offset);
        p.next = Some(p.next.map_or(offset + 1, |n| n.max(offset + 1)));
        Some(self.seen.get(&partition).is_some_and(|&n| offset < n))
    }

    /// The record at `offset` needs no result (refused, or a re-delivery).
    pub(super) fn done(&mut self, partition: i32, offset: i64) {
        if let Some(p) = self.parts.get_mut(&partition) {
            p.open.remove(&offset);
        }
    }

    /// A record of `scene` was read from owned `partition`: `Some(last produced frame)` when
    /// the scene (re)starts here now (first record in this generation), `None` when it
    /// already runs here.
    pub(super) fn enter_scene(&mut self, scene: &str, partition: i32) -> Option<Option<u64>> {
        let generation = self.parts.get(&partition)?.generation;
        match self.scenes.get_mut(scene) {
            Some(s) if s.partition == partition && s.generation == generation => None,
            Some(s) => {
                s.partition = partition;
                s.generation = generation;
                Some(s.produced)
            }
            None => {
                self.scenes.insert(
                    scene.to_string(),
                    SceneState {
                        partition,
                        generation,
                        produced: None,
                    },
                );
                Some(None)
            }
        }
    }

    /// Record `offset` holds a batch of `frame` of `scene`; true when it is the frame's first.
    pub(super) fn hold(&mut self, scene: &str, frame: u64, partition: i32, offset: i64) -> bool {
        let generation = self.parts.get(&partition).map_or(0, |p| p.generation);
        let held = self
            .frames
            .entry((scene.to_string(), frame))
            .or_insert_with(|| Held {
                partition,
                generation,
                offsets: Vec::new(),
            });
        held.offsets.push(offset);
        held.offsets.len() == 1
    }

    /// Undoes [`hold`](Self::hold) for a refused batch that created its frame, and closes it.
    pub(super) fn unhold(&mut self, scene: &str, frame: u64, partition: i32, offset: i64) {
        let key = (scene.to_string(), frame);
        if let Some(h) = self.frames.get_mut(&key) {
            h.offsets.retain(|o| *o != offset);
            if h.offsets.is_empty() {
                self.frames.remove(&key);
            }
        }
        self.done(partition, offset);
    }

    /// Frames with consumed batches not yet in a produced result.
    pub(super) fn in_flight(&self) -> usize {
        self.frames.len()
    }

    /// What to do with the published result of `frame` of `scene`.
    pub(super) fn take_frame(&mut self, scene: &str, frame: u64) -> Publish {
        match self.frames.remove(&(scene.to_string(), frame)) {
            Some(h) if self.current(&h) => Publish::Owned(h),
            Some(_) => Publish::Stale,
            None if self.scenes.contains_key(scene) => Publish::Stale,
            None => Publish::Unheld,
        }
    }

    fn current(&self, h: &Held) -> bool {
        self.parts
            .get(&h.partition)
            .is_some_and(|p| p.generation == h.generation)
    }

    /// `frame` of `scene` was produced (acknowledged): it is the scene's last produced frame,
    /// and its records close (unless their partition was revoked since).
    pub(super) fn produced(&mut self, scene: &str, frame: u64, held: Option<Held>) {
        if let Some(s) = self.scenes.get_mut(scene) {
            s.produced = Some(frame);
        }
        if let Some(h) = held
            && self.current(&h)
        {
            for o in h.offsets {
                self.done(h.partition, o);
            }
        }
    }

    /// The owned partitions whose committable offset moved, marked as committed.
    pub(super) fn take_commits(&mut self) -> Vec<(i32, i64)> {
        let mut out = Vec::new();
        for (k, p) in &mut self.parts {
            if let Some(c) = p.committable()
                && p.committed.is_none_or(|done| c > done)
            {
                p.committed = Some(c);
                out.push((*k, c));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committable_offset_waits_for_the_lowest_open_batch() {
        let mut o = Ownership::default();
        o.assign(0);
        for off in 10..14 {
            assert_eq!(o.consumed(0, off), Some(false));
        }
        assert!(o.take_commits().iter().all(|(_, c)| *c == 10));
        o.done(0, 11);
        o.done(0, 12);
        assert!(o.take_commits().is_empty(), "10 still open");
        o.done(0, 10);
        assert_eq!(o.take_commits(), vec![(0, 13)]);
        o.done(0, 13);
        assert_eq!(o.take_commits(), vec![(0, 14)]);
        assert!(o.take_commits().is_empty());
    }

    #[test]
    fn records_of_a_partition_not_owned_are_left_alone() {
        let mut o = Ownership::default();
        assert_eq!(o.consumed(3, 0), None);
        assert_eq!(o.enter_scene("lab", 3), None);
        assert!(o.take_commits().is_empty());
    }

    /// A frame half read when its partition is revoked is never produced by this replica;
    /// when the partition comes back, the scene restarts past its last produced frame and the
    /// records read before are re-deliveries.
    #[test]
    fn revocation_makes_pending_frames_stale_and_a_returning_scene_restarts() {
        let mut o = Ownership::default();
        o.assign(0);
        assert_eq!(
            o.enter_scene("lab", 0),
            Some(None),
            "first record starts it"
        );
        assert_eq!(o.enter_scene("lab", 0), None, "then it runs");
        // Frame 1 (offsets 0, 1) produced; frame 2 (offset 2) still pending.
        for off in 0..3 {
            o.consumed(0, off);
        }
        assert!(o.hold("lab", 1, 0, 0));
        assert!(!o.hold("lab", 1, 0, 1));
        assert!(o.hold("lab", 2, 0, 2));
        let Publish::Owned(h) = o.take_frame("lab", 1) else {
            panic!("frame 1 is owned")
        };
        o.produced("lab", 1, Some(h));
        assert_eq!(o.take_commits(), vec![(0, 2)]);
        // Revoked mid-frame 2: the scene's pending frames must go, frame 2 is stale.
        let (scenes, forgotten) = o.revoke(0);
        assert_eq!((scenes, forgotten), (vec!["lab".to_string()], 1));
        assert!(!o.owns(0));
        assert_eq!(o.take_frame("lab", 2), Publish::Stale);
        // Back again: a new generation; the scene restarts past frame 1; offsets 2 (frame 2,
        // re-read from the committed offset) is a re-delivery.
        o.assign(0);
        assert_eq!(o.consumed(0, 2), Some(true));
        assert_eq!(o.enter_scene("lab", 0), Some(Some(1)));
        assert!(o.hold("lab", 2, 0, 2));
        assert_eq!(o.consumed(0, 3), Some(false), "a new record");
        assert!(!o.hold("lab", 2, 0, 3));
        let Publish::Owned(h) = o.take_frame("lab", 2) else {
            panic!("frame 2 is owned again")
        };
        assert_eq!(h.offsets, vec![2, 3]);
        o.produced("lab", 2, Some(h));
        assert_eq!(o.take_commits(), vec![(0, 4)]);
        assert_eq!(o.in_flight(), 0);
    }

    /// A result produced after its partition was revoked and assigned again does not close
    /// the new generation's records of the same offsets.
    #[test]
    fn a_late_acknowledgement_never_closes_a_newer_generation() {
        let mut o = Ownership::default();
        o.assign(0);
        o.enter_scene("lab", 0);
        o.consumed(0, 0);
        o.hold("lab", 5, 0, 0);
        let Publish::Owned(old) = o.take_frame("lab", 5) else {
            panic!("owned")
        };
        o.revoke(0);
        o.assign(0);
        o.consumed(0, 0);
        o.produced("lab", 5, Some(old));
        assert_eq!(o.take_commits(), vec![(0, 0)], "offset 0 stays open");
        assert_eq!(o.enter_scene("lab", 0), Some(Some(5)), "but 5 was produced");
    }

    #[test]
    fn scenes_no_record_named_are_produced_without_offsets() {
        let mut o = Ownership::default();
        assert_eq!(o.take_frame("grpc-only", 1), Publish::Unheld);
    }

    /// Stream time per owned partition: records move it, a statistics report moves it on
    /// only when everything below the high watermark was read (or committed), and it reaches
    /// the scenes started on the partition; stuck consumption moves every partition on.
    #[test]
    fn stream_time_moves_by_records_and_by_caught_up_quiet() {
        use std::time::Duration;
        let ms = Duration::from_millis;
        let (t0, w0) = (Instant::now(), 1_000_000u64);
        let stamp = |ms: u64| Some(ms as i64);
        let mut o = Ownership::default();
        assert!(o.clock(0).is_none(), "not owned");
        assert_eq!(o.report(9, 5, 0, t0), None, "not owned");
        assert_eq!(o.deliver(9, stamp(w0), t0, w0), None, "not owned");
        o.assign(0);
        o.assign(1);
        o.enter_scene("a", 0);
        o.enter_scene("b", 0);
        o.enter_scene("c", 1);
        let clock = o.clock(0).unwrap();
        o.consumed(0, 8);
        assert_eq!(o.deliver(0, stamp(w0), t0, w0), Some(true));
        assert_eq!(clock.millis(), w0);
        // 10 records on the broker, 9 read: not caught up.
        assert_eq!(o.report(0, 10, -1001, t0 + ms(100)), Some((w0, vec![])));
        o.consumed(0, 9);
        o.deliver(0, stamp(w0 + 10), t0 + ms(110), w0 + 110);
        // Caught up from 200 ms on; 300 ms later the stream has run on by 300 ms.
        assert_eq!(
            o.report(0, 10, -1001, t0 + ms(200)).unwrap().1,
            Vec::<String>::new()
        );
        let (at, mut scenes) = o.report(0, 10, -1001, t0 + ms(500)).unwrap();
        scenes.sort();
        assert_eq!((at, scenes), (w0 + 310, vec!["a".into(), "b".into()]));
        assert_eq!(clock.millis(), w0 + 310);
        // Unknown high watermark (-1): not caught up.
        assert_eq!(o.report(1, -1, -1, t0 + ms(600)), Some((0, vec![])));
        o.deliver(1, stamp(w0), t0, w0);
        let mut moved = o.stuck(t0 + ms(1_000));
        moved.sort();
        assert_eq!(moved, ["a", "b", "c"]);
        assert_eq!(o.clock(1).unwrap().millis(), w0 + 1_000);
        assert_eq!(
            clock.millis(),
            w0 + 10 + 890,
            "by the quiet since the last delivery"
        );
        // Revoked and assigned again: a new stream time.
        o.revoke(1);
        o.assign(1);
        assert_eq!(o.clock(1).unwrap().millis(), 0);
    }
}

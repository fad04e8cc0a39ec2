//! The synchronizer's rules, one test each, and two property tests over random interleavings.
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

#[test]
fn a_shed_frame_takes_no_batch_and_leaves_in_order() {
    let t0 = Instant::now();
    let mut s = Synchronizer::new(3, T, 16);
    s.push(0, 5, det(), t0).unwrap();
    // Frame 6 is shed behind frame 5, which still waits for cameras: nothing leaves yet.
    assert!(s.shed(6, t0, t0).unwrap().is_empty());
    assert_eq!(s.push(1, 6, det(), t0), Err(Rejection::Shed));
    s.push(1, 5, det(), t0).unwrap();
    let out = s.push(2, 5, det(), t0).unwrap();
    assert_eq!(ids(&out), vec![5, 6]);
    assert!(!out[0].shed && out[0].complete());
    assert!(out[1].shed && out[1].reason == EmitReason::Shed);
    assert!(out[1].frame.views.iter().all(Option::is_none));
    // After it left, its batches are still refused as shed, not as late.
    assert_eq!(s.push(2, 6, det(), t0), Err(Rejection::Shed));
    assert_eq!(s.push(2, 5, det(), t0), Err(Rejection::Late));
}

#[test]
fn a_shed_frame_never_holds_newer_frames_back() {
    let t0 = Instant::now();
    let mut s = Synchronizer::new(2, T, 16);
    assert_eq!(ids(&s.shed(3, t0, t0).unwrap()), vec![3]);
    assert!(s.push(0, 4, det(), t0).unwrap().is_empty());
    assert_eq!(ids(&s.push(1, 4, det(), t0).unwrap()), vec![4]);
    // Shedding a frame that already has a batch changes nothing; a late id is refused.
    s.push(0, 7, det(), t0).unwrap();
    assert!(s.shed(7, t0, t0).unwrap().is_empty());
    assert_eq!(ids(&s.push(1, 7, det(), t0).unwrap()), vec![7]);
    assert_eq!(s.shed(2, t0, t0), Err(Rejection::Late));
}

#[test]
fn shed_frames_are_remembered_within_a_bound() {
    let t0 = Instant::now();
    let mut s = Synchronizer::new(1, T, 16);
    for f in 0..(SHED_MEMORY as u64 + 10) {
        s.shed(f, t0, t0).unwrap();
    }
    assert_eq!(s.shed.len(), SHED_MEMORY);
    assert_eq!(s.push(0, 9, det(), t0), Err(Rejection::Late));
    assert_eq!(
        s.push(0, SHED_MEMORY as u64 + 9, det(), t0),
        Err(Rejection::Shed)
    );
}

proptest! {
    /// Any interleaving of pushes, polls and sheds: accepted batches appear in exactly one
    /// emitted frame, frames leave in strictly increasing order, a shed frame takes no batch
    /// and leaves once, and rejections are exactly the late, duplicate and shed batches.
    #[test]
    fn every_accepted_batch_is_emitted_once_in_order(
        ops in proptest::collection::vec((0usize..3, 0u64..12, 0u64..400, 0u8..6), 0..80),
        max_pending in 1usize..6,
    ) {
        let t0 = Instant::now();
        let mut s = Synchronizer::new(3, T, max_pending);
        let mut emitted: Vec<Emitted> = Vec::new();
        let mut accepted = std::collections::HashSet::new();
        let mut shed = std::collections::HashSet::new();
        let mut clock = 0u64;
        for (cam, frame, dt, op) in ops {
            clock += dt;
            let now = t0 + Duration::from_millis(clock);
            let was_emitted = emitted.iter().any(|e| e.frame.frame_id >= frame);
            match op {
                0 => {
                    emitted.extend(s.poll(now));
                    continue;
                }
                1 => {
                    let begun = accepted.iter().any(|&(_, f)| f == frame);
                    match s.shed(frame, now, now) {
                        Ok(out) => {
                            if !begun && !was_emitted {
                                shed.insert(frame);
                            }
                            emitted.extend(out);
                        }
                        Err(Rejection::Late) => prop_assert!(was_emitted),
                        Err(r) => prop_assert!(false, "shed refused with {:?}", r),
                    }
                    continue;
                }
                _ => {}
            }
            match s.push(cam, frame, vec![], now) {
                Ok(out) => {
                    prop_assert!(!was_emitted && !shed.contains(&frame));
                    prop_assert!(accepted.insert((cam, frame)));
                    emitted.extend(out);
                }
                Err(Rejection::Late) => prop_assert!(was_emitted && !shed.contains(&frame)),
                Err(Rejection::Duplicate) => prop_assert!(accepted.contains(&(cam, frame))),
                Err(Rejection::Shed) => prop_assert!(shed.contains(&frame)),
                Err(Rejection::OutOfRange) => prop_assert!(false, "ids stay within the window"),
            }
            prop_assert!(s.pending_frames() <= max_pending);
        }
        emitted.extend(s.flush());
        let order: Vec<u64> = ids(&emitted);
        prop_assert!(order.windows(2).all(|w| w[0] < w[1]));
        let mut seen = std::collections::HashSet::new();
        for e in &emitted {
            if e.shed {
                prop_assert!(shed.contains(&e.frame.frame_id));
                prop_assert!(e.frame.views.iter().all(Option::is_none));
            }
            for (c, v) in e.frame.views.iter().enumerate() {
                if v.is_some() {
                    prop_assert!(seen.insert((c, e.frame.frame_id)));
                }
            }
        }
        let left_shed: std::collections::HashSet<u64> =
            emitted.iter().filter(|e| e.shed).map(|e| e.frame.frame_id).collect();
        prop_assert_eq!(left_shed, shed);
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

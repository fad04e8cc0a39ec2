//! The memory's guarantees: a transient mistake is repaired, strong present evidence is never
//! overridden, what no longer applies is dropped, and the state stays bounded.
use std::sync::Arc;

use ndarray::Array2;

use super::{Memory, MemoryConfig};
use crate::association::{AssociationConfig, frame_identities_with};
use crate::calibration::Calibration;
use crate::identity::Identity;
use crate::{Detection, Frame, FrameEmbeddings};

/// `P(same | d)`: 1 up to 0.3, 0 from 1.0 on, linear between.
fn config() -> AssociationConfig {
    let mut cfg = AssociationConfig::default();
    cfg.identity.calibration = Some(Arc::new(Calibration {
        distances: vec![0.3, 1.0],
        probabilities: vec![1.0, 0.0],
        false_share: 0.0,
        samples: [100, 100],
    }));
    cfg
}

/// A person at ground position `(x, y)`: the box a camera sees (pixels, 100 px per metre
/// along x) and the embedding a perfect encoder gives (the position).
#[derive(Clone, Copy)]
struct Seen {
    x: f32,
    y: f32,
}

/// What each camera sees: the people, each with an embedding offset; `None` for a camera that
/// did not report.
type Views = [View];

/// One camera's view: the people it sees with their embedding offsets, if it reported.
type View = Option<Vec<(Seen, [f32; 2])>>;

/// One frame: `views[c]` the people camera `c` sees, each with an optional embedding offset
/// (a transient encoder mistake); `None` for a camera that did not report.
fn frame(id: u64, views: &Views) -> (Frame, FrameEmbeddings) {
    let mut frame = Frame::new(id, views.len());
    let mut embs = Vec::new();
    for (c, v) in views.iter().enumerate() {
        let Some(v) = v else {
            embs.push(None);
            continue;
        };
        let dets = v
            .iter()
            .map(|(p, _)| Detection::new([100.0 * p.x, 100.0, 100.0 * p.x + 50.0, 250.0]))
            .collect();
        frame.views[c] = Some(dets);
        let e = Array2::from_shape_fn((v.len(), 2), |(i, k)| {
            let (p, off) = v[i];
            [p.x, p.y][k] + off[k]
        });
        embs.push(Some(e));
    }
    (frame, FrameEmbeddings::from_views(&embs).unwrap())
}

/// The identities as sorted lists of `(camera, box)`.
fn groups(ids: &[Identity]) -> Vec<Vec<(usize, usize)>> {
    let mut g: Vec<Vec<(usize, usize)>> = ids.iter().map(|i| i.members.clone()).collect();
    g.sort();
    g
}

fn two_people(t: f32, offset: [f32; 2]) -> Vec<View> {
    let a = Seen {
        x: 1.0 + 0.05 * t,
        y: 0.0,
    };
    let b = Seen {
        x: 6.0 - 0.05 * t,
        y: 0.0,
    };
    vec![
        Some(vec![(a, [0.0; 2]), (b, [0.0; 2])]),
        Some(vec![(a, offset), (b, [0.0; 2])]),
    ]
}

#[test]
fn a_transient_mistake_is_repaired_by_the_past() {
    let cfg = config();
    let mut memory = Memory::new(MemoryConfig::default());
    for t in 0..6u64 {
        let (f, e) = frame(10 * t, &two_people(t as f32, [0.0; 2]));
        let ids = frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
        assert_eq!(
            groups(&ids),
            vec![vec![(0, 0), (1, 0)], vec![(0, 1), (1, 1)]]
        );
    }
    // Frame 6: camera 1's encoder is off by 5 m for person a (an occluded box).
    let (f, e) = frame(60, &two_people(6.0, [0.0, 5.0]));
    let alone = frame_identities_with(&f, &e, &cfg, &[], None);
    assert_eq!(groups(&alone).len(), 3, "alone, the frame splits person a");
    let remembered = frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    assert_eq!(
        groups(&remembered),
        vec![vec![(0, 0), (1, 0)], vec![(0, 1), (1, 1)]],
        "the past keeps person a whole"
    );
}

#[test]
fn strong_present_evidence_is_never_overridden() {
    let cfg = config();
    let mut memory = Memory::new(MemoryConfig::default());
    // For twenty frames camera 1 sees person a 8 m off (two people, as far as the pair knows)
    // ...
    for t in 0..20u64 {
        let (f, e) = frame(t, &two_people(t as f32 / 4.0, [0.0, 8.0]));
        let ids = frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
        assert_eq!(groups(&ids).len(), 3);
    }
    // ... then exactly where camera 0 sees them (the box still continues its track): P = 1
    // ≥ hold, taken as it is, where the remembered mean alone would still split them.
    let (f, e) = frame(20, &two_people(5.0, [0.0; 2]));
    let ids = frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    assert_eq!(memory.links()[1], vec![Some(0), Some(1)]);
    assert_eq!(
        groups(&ids),
        vec![vec![(0, 0), (1, 0)], vec![(0, 1), (1, 1)]]
    );
}

#[test]
fn boxes_keep_their_links_in_any_order_and_newcomers_start_fresh() {
    let cfg = config();
    let mut memory = Memory::new(MemoryConfig::default());
    let p = |x: f32| (Seen { x, y: 0.0 }, [0.0; 2]);
    let (f, e) = frame(0, &[Some(vec![p(1.0), p(4.0)]), Some(vec![p(1.0)])]);
    frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    // Next frame: camera 0's boxes come in the other order, plus a newcomer far away.
    let (f, e) = frame(1, &[Some(vec![p(4.1), p(9.0), p(1.1)]), None]);
    frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    let links = memory.links();
    assert_eq!(links[0], vec![Some(1), None, Some(0)]);
    assert!(
        links[1].is_empty(),
        "a camera that did not report has no links this frame"
    );
}

#[test]
fn memory_is_dropped_when_it_no_longer_applies() {
    let cfg = config();
    let cfg_mem = MemoryConfig::default();
    let feed = |memory: &mut Memory, id: u64, t: f32| {
        let (f, e) = frame(id, &two_people(t, [0.0; 2]));
        frame_identities_with(&f, &e, &cfg, &[], Some(memory));
    };
    let linked = |memory: &Memory| memory.links().iter().flatten().flatten().count();
    let mut memory = Memory::new(cfg_mem.clone());
    feed(&mut memory, 100, 0.0);
    feed(&mut memory, 105, 1.0);
    assert_eq!(linked(&memory), 4, "ids stepping by 5 link every box");
    // Ids that go back (a restart, an out-of-order frame) and ids that jump beyond the gap
    // start over: no box continues anything.
    feed(&mut memory, 105, 2.0);
    assert_eq!(linked(&memory), 0, "a repeated id");
    feed(&mut memory, 110, 3.0);
    assert_eq!(linked(&memory), 4);
    feed(&mut memory, 110 + 5 * (cfg_mem.max_gap + 1), 4.0);
    assert_eq!(linked(&memory), 0, "a gap of more than max_gap frames");
    // A fenced camera is forgotten and not linked; it starts fresh when the fence lifts.
    feed(&mut memory, 200, 5.0);
    let (f, e) = frame(205, &two_people(6.0, [0.0; 2]));
    frame_identities_with(&f, &e, &cfg, &[false, true], Some(&mut memory));
    assert!(memory.links()[1].is_empty());
    assert_eq!(
        memory.remembered(),
        0,
        "no pair with the fenced camera is kept"
    );
    feed(&mut memory, 210, 7.0);
    assert_eq!(memory.links()[1], vec![None, None]);
    // A camera silent for longer than the gap is forgotten.
    for k in 1..=cfg_mem.max_gap + 1 {
        let (f, e) = frame(210 + 5 * k, &[two_people(8.0, [0.0; 2])[0].clone(), None]);
        frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    }
    feed(&mut memory, 210 + 5 * (cfg_mem.max_gap + 2), 9.0);
    assert_eq!(
        memory.links()[1],
        vec![None, None],
        "camera 1 came back fresh"
    );
    // Another camera count (a new scene layout) and a clear start over.
    let (f, e) = frame(1000, &[two_people(0.0, [0.0; 2])[0].clone()]);
    frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    assert_eq!(memory.remembered(), 0);
    memory.clear();
    assert!(memory.links().is_empty());
}

#[test]
fn state_stays_bounded_in_an_endless_stream() {
    let cfg = config();
    let mut memory = Memory::new(MemoryConfig::default());
    for t in 0..300u64 {
        // A crowd whose size swings between 1 and 40, people coming and going.
        let n = 1 + (t * 7 % 40) as usize;
        let view: Vec<(Seen, [f32; 2])> = (0..n)
            .map(|i| {
                (
                    Seen {
                        x: i as f32 * 0.8 + 0.01 * t as f32,
                        y: 0.0,
                    },
                    [0.0; 2],
                )
            })
            .collect();
        let (f, e) = frame(t, &[Some(view.clone()), Some(view.clone()), Some(view)]);
        frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
        // One distance per pair of boxes of the last frame, as the frame itself holds.
        assert!(
            memory.remembered() <= 3 * n * n,
            "frame {t}: {}",
            memory.remembered()
        );
    }
}

#[test]
fn bad_input_is_harmless() {
    let cfg = config();
    let mut memory = Memory::new(MemoryConfig::default());
    let p = |x: f32, off: f32| (Seen { x, y: 0.0 }, [off, 0.0]);
    for (t, off) in [
        (0u64, 0.0),
        (1, f32::NAN),
        (2, f32::INFINITY),
        (3, 1e30),
        (4, 0.0),
    ] {
        let (f, e) = frame(
            t,
            &[
                Some(vec![p(1.0, off), p(3.0, 0.0)]),
                Some(vec![p(1.0, 0.0)]),
            ],
        );
        let ids = frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
        assert_eq!(ids.iter().map(|i| i.members.len()).sum::<usize>(), 3);
    }
    // Ids at the ends of the range.
    for id in [u64::MAX, 0, u64::MAX - 1, u64::MAX] {
        let (f, e) = frame(id, &two_people(0.0, [0.0; 2]));
        frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory));
    }
    // Empty views and views without embeddings for their boxes.
    let (f, e) = frame(7, &[Some(vec![]), Some(vec![])]);
    assert!(frame_identities_with(&f, &e, &cfg, &[], Some(&mut memory)).is_empty());
    for carry in [f32::NAN, -0.1, 1.0, f32::INFINITY] {
        assert!(MemoryConfig::with_carry(carry).is_err(), "{carry}");
    }
    assert_eq!(MemoryConfig::with_carry(0.0).unwrap(), None);
}

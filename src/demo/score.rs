//! Scoring the server's identities against the simulator's ground truth, client-side.
//!
//! A frame result lists global identities (members = camera index + box index). For every
//! camera pair `i < j` that both have boxes, the pairwise matches implied by the identities
//! (two members of one identity in cameras `i` and `j`) become one [`PairRecord`], and the
//! project's SPEC §5 code ([`compute_metrics`]) scores them: per frame and running over all
//! frames so far. Ground-truth ids never leave the client.
use crossview_core::identity::Identity;
use crossview_core::{Error, Result};
use crossview_eval::metrics::{Metrics, PairRecord, compute_metrics};

/// Ground-truth ids of every box of a frame, per camera (`None` = camera did not report).
///
/// A box without an id (a simulated false positive) gets a fresh id of its own, unique over
/// the run: a "person" seen by that one box only, so leaving it unmatched is a true negative
/// and matching it is an error.
#[derive(Debug, Clone, Default)]
pub struct TruthIds {
    next_unlabelled: u64,
}

/// First id handed to unlabelled boxes (far above any simulated person id).
const UNLABELLED_BASE: u64 = 1 << 62;

impl TruthIds {
    /// A fresh id source.
    pub fn new() -> Self {
        TruthIds {
            next_unlabelled: UNLABELLED_BASE,
        }
    }

    /// The ids of `frame`'s boxes, camera by camera.
    pub fn of_frame(&mut self, frame: &crossview_core::Frame) -> Vec<Option<Vec<u64>>> {
        frame
            .views
            .iter()
            .map(|v| {
                v.as_ref().map(|dets| {
                    dets.iter()
                        .map(|d| {
                            d.id.unwrap_or_else(|| {
                                self.next_unlabelled += 1;
                                self.next_unlabelled
                            })
                        })
                        .collect()
                })
            })
            .collect()
    }
}

/// The SPEC §5 image-pair records implied by a frame's identities.
///
/// `truth[c]` holds the ids of camera `c`'s boxes; pairs are all `i < j` with boxes on both
/// sides. The confidence matrix holds the identity confidence on matched entries and 0
/// elsewhere (the server returns identities, not the full S matrices, so AP is not meaningful
/// here; P, R, ACC and IPAA are). Members pointing outside the batches are an error.
pub fn pair_records(
    frame_id: u64,
    cameras: &[String],
    truth: &[Option<Vec<u64>>],
    identities: &[Identity],
) -> Result<Vec<PairRecord>> {
    let len = |c: usize| truth.get(c).and_then(Option::as_ref).map_or(0, Vec::len);
    for (k, ident) in identities.iter().enumerate() {
        for &(c, i) in &ident.members {
            if c >= truth.len() || i >= len(c) {
                return Err(Error::invalid(
                    format!("frame {frame_id} identities[{k}]"),
                    format!("member (camera {c}, box {i}) outside the frame that was sent"),
                ));
            }
        }
    }
    let name = |c: usize| cameras.get(c).cloned().unwrap_or_else(|| c.to_string());
    let mut records = Vec::new();
    for a in 0..truth.len() {
        for b in a + 1..truth.len() {
            let (Some(ids_a), Some(ids_b)) = (&truth[a], &truth[b]) else {
                continue;
            };
            if ids_a.is_empty() || ids_b.is_empty() {
                continue;
            }
            let m = ids_b.len();
            let mut scores = vec![0.0f32; ids_a.len() * m];
            let mut matches = Vec::new();
            for ident in identities {
                let in_a = ident.members.iter().find(|&&(c, _)| c == a);
                let in_b = ident.members.iter().find(|&&(c, _)| c == b);
                if let (Some(&(_, i)), Some(&(_, j))) = (in_a, in_b) {
                    let s = if ident.confidence.is_finite() {
                        ident.confidence
                    } else {
                        0.0
                    };
                    scores[i * m + j] = s;
                    matches.push((i, j, s));
                }
            }
            let record = PairRecord {
                frame_id,
                camera_a: name(a),
                camera_b: name(b),
                ids_a: ids_a.clone(),
                ids_b: ids_b.clone(),
                scores,
                matches,
                identity_matches: None,
            };
            record.validate()?;
            records.push(record);
        }
    }
    Ok(records)
}

/// Running SPEC §5 scores over the frames seen so far.
#[derive(Debug, Clone, Default)]
pub struct RunningScore {
    records: Vec<PairRecord>,
}

impl RunningScore {
    /// No frames yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds one frame's records; returns `(this frame's metrics, running metrics)`.
    pub fn add_frame(&mut self, records: Vec<PairRecord>) -> (Metrics, Metrics) {
        let frame = compute_metrics(&records);
        self.records.extend(records);
        (frame, self.total())
    }

    /// Metrics over every frame added so far.
    pub fn total(&self) -> Metrics {
        compute_metrics(&self.records)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::{Detection, Frame};

    fn names() -> Vec<String> {
        vec!["a".into(), "b".into(), "c".into()]
    }

    #[test]
    fn identities_become_pairwise_matches_scored_by_spec_metrics() {
        // a: persons 1, 2; b: persons 2, 1; c: person 1 only.
        let truth = vec![Some(vec![1, 2]), Some(vec![2, 1]), Some(vec![1])];
        let ids = vec![
            Identity {
                id: 0,
                confidence: 0.9,
                members: vec![(0, 0), (1, 1), (2, 0)],
            },
            Identity {
                id: 0,
                confidence: 0.8,
                members: vec![(0, 1), (1, 0)],
            },
        ];
        let recs = pair_records(5, &names(), &truth, &ids).unwrap();
        assert_eq!(recs.len(), 3);
        assert_eq!(recs[0].matches, vec![(0, 1, 0.9), (1, 0, 0.8)]);
        let mut score = RunningScore::new();
        let (frame, total) = score.add_frame(recs);
        assert_eq!(frame.acc, 1.0);
        assert_eq!(frame.precision, 1.0);
        assert_eq!(total.pairs, 3);
        assert_eq!(identities_links(&ids), 3 + 1);
    }

    fn identities_links(ids: &[Identity]) -> usize {
        ids.iter().map(Identity::links).sum()
    }

    #[test]
    fn a_wrong_identity_lowers_the_running_accuracy() {
        let truth = vec![Some(vec![1, 2]), Some(vec![1, 2]), None];
        let right = vec![
            Identity {
                id: 0,
                confidence: 1.0,
                members: vec![(0, 0), (1, 0)],
            },
            Identity {
                id: 0,
                confidence: 1.0,
                members: vec![(0, 1), (1, 1)],
            },
        ];
        let wrong = vec![Identity {
            id: 0,
            confidence: 1.0,
            members: vec![(0, 0), (1, 1)],
        }];
        let mut score = RunningScore::new();
        let (_, t1) = score.add_frame(pair_records(0, &names(), &truth, &right).unwrap());
        assert_eq!(t1.acc, 1.0);
        let (f2, t2) = score.add_frame(pair_records(1, &names(), &truth, &wrong).unwrap());
        assert_eq!(f2.acc, 0.0);
        assert!(t2.acc > 0.0 && t2.acc < 1.0);
        assert_eq!(t2.frames, 2);
    }

    #[test]
    fn members_outside_the_frame_are_an_error_not_a_panic() {
        let truth = vec![Some(vec![1]), Some(vec![1]), Some(vec![])];
        let bad = vec![Identity {
            id: 0,
            confidence: 1.0,
            members: vec![(0, 0), (2, 3)],
        }];
        let err = pair_records(0, &names(), &truth, &bad).unwrap_err();
        assert!(err.to_string().contains("outside"), "{err}");
        let bad_cam = vec![Identity {
            id: 0,
            confidence: 1.0,
            members: vec![(7, 0)],
        }];
        assert!(pair_records(0, &names(), &truth, &bad_cam).is_err());
    }

    #[test]
    fn unlabelled_boxes_get_unique_ids() {
        let mut frame = Frame::new(0, 2);
        let mut with_id = Detection::new([0.0, 0.0, 1.0, 1.0]);
        with_id.id = Some(3);
        let fp = Detection::new([0.0, 0.0, 1.0, 1.0]);
        frame.views[0] = Some(vec![with_id, fp.clone()]);
        frame.views[1] = Some(vec![fp]);
        let ids = TruthIds::new().of_frame(&frame);
        let (a, b) = (ids[0].as_ref().unwrap(), ids[1].as_ref().unwrap());
        assert_eq!(a[0], 3);
        assert_ne!(a[1], b[0]);
        assert!(a[1] > UNLABELLED_BASE && b[0] > UNLABELLED_BASE);
    }
}

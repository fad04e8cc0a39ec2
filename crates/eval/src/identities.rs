//! **[ours]** Scores of whole identities against ground truth, beside the SPEC §5 pair
//! metrics: how many frames come out exactly right, and how often an identity is right at
//! each level of its confidence (the confidence should mean what it says).
use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use crossview_core::identity::Identity;

/// Identities of one confidence decile: how many, and how many were right.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Decile {
    pub identities: usize,
    pub correct: usize,
}

/// Whole-identity scores over the frames of an evaluation.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct IdentityStats {
    /// Frames scored.
    pub frames: usize,
    /// Frames whose identities are all right.
    pub frames_exact: usize,
    /// Identities scored.
    pub identities: usize,
    /// Identities that are right: every member has one ground-truth id, and every box of
    /// that id in the frame is a member.
    pub correct: usize,
    /// By confidence: decile `k` holds confidences in `[k/10, (k+1)/10)` (1.0 in the last).
    pub deciles: [Decile; 10],
}

impl IdentityStats {
    /// Adds one frame: its identities and the ground-truth ids of its boxes (`ids[c][i]` for
    /// box `i` of camera `c`; `None` for cameras that did not report).
    pub fn add_frame(&mut self, identities: &[Identity], ids: &[Option<Vec<u64>>]) {
        let id_of = |c: usize, i: usize| ids.get(c)?.as_ref()?.get(i).copied();
        let mut boxes: HashMap<u64, usize> = HashMap::new();
        for &gt in ids.iter().flatten().flatten() {
            *boxes.entry(gt).or_default() += 1;
        }
        let boxes_of = |gt: u64| boxes.get(&gt).copied().unwrap_or(0);
        let mut exact = true;
        for ident in identities {
            let first = ident.members.first().and_then(|&(c, i)| id_of(c, i));
            let right = first.is_some_and(|gt| {
                ident.members.iter().all(|&(c, i)| id_of(c, i) == Some(gt))
                    && boxes_of(gt) == ident.members.len()
            });
            exact &= right;
            self.identities += 1;
            self.correct += usize::from(right);
            let k = ((ident.confidence.clamp(0.0, 1.0) * 10.0) as usize).min(9);
            self.deciles[k].identities += 1;
            self.deciles[k].correct += usize::from(right);
        }
        self.frames += 1;
        self.frames_exact += usize::from(exact);
    }

    /// Adds the counts of `other` (scores of other frames): the same as having added its frames
    /// here (every field is a count).
    pub fn merge(&mut self, other: &IdentityStats) {
        self.frames += other.frames;
        self.frames_exact += other.frames_exact;
        self.identities += other.identities;
        self.correct += other.correct;
        for (d, o) in self.deciles.iter_mut().zip(&other.deciles) {
            d.identities += o.identities;
            d.correct += o.correct;
        }
    }

    /// Whether precision rises with confidence: every non-empty decile's precision is at
    /// least the next lower non-empty decile's minus `tolerance` (in percentage points).
    pub fn monotone(&self, tolerance: f64) -> bool {
        let precisions: Vec<f64> = self
            .deciles
            .iter()
            .filter(|d| d.identities > 0)
            .map(|d| 100.0 * d.correct as f64 / d.identities as f64)
            .collect();
        precisions.windows(2).all(|w| w[1] >= w[0] - tolerance)
    }

    /// The text block `crossview eval` prints under the table.
    pub fn format(&self) -> String {
        let pct = |a: usize, b: usize| {
            if b == 0 {
                "-".to_string()
            } else {
                format!("{:.1}", 100.0 * a as f64 / b as f64)
            }
        };
        let mut out = format!(
            "identities: {} in {} frames, {}% right; frames with every identity right: {}% ({} of {})\n",
            self.identities,
            self.frames,
            pct(self.correct, self.identities),
            pct(self.frames_exact, self.frames),
            self.frames_exact,
            self.frames
        );
        out.push_str("identity precision by confidence:");
        for (k, d) in self.deciles.iter().enumerate() {
            if d.identities > 0 {
                out.push_str(&format!(
                    " [{:.1},{:.1}) {}% of {};",
                    k as f64 / 10.0,
                    (k + 1) as f64 / 10.0,
                    pct(d.correct, d.identities),
                    d.identities
                ));
            }
        }
        out.push('\n');
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn right_wrong_and_incomplete_identities() {
        let ids = vec![Some(vec![1, 2]), Some(vec![2, 1]), None];
        let ident = |confidence: f32, members: Vec<(usize, usize)>| Identity {
            id: 0,
            confidence,
            members,
        };
        let mut s = IdentityStats::default();
        s.add_frame(
            &[
                ident(0.95, vec![(0, 0), (1, 1)]),
                ident(0.9, vec![(0, 1), (1, 0)]),
            ],
            &ids,
        );
        assert_eq!((s.frames_exact, s.correct), (1, 2));
        // Person 2 split in two: both halves are incomplete, the frame is not exact.
        s.add_frame(
            &[
                ident(0.95, vec![(0, 0), (1, 1)]),
                ident(0.35, vec![(0, 1)]),
                ident(0.3, vec![(1, 0)]),
            ],
            &ids,
        );
        assert_eq!(
            (s.frames, s.frames_exact, s.identities, s.correct),
            (2, 1, 5, 3)
        );
        assert_eq!(
            s.deciles[9],
            Decile {
                identities: 3,
                correct: 3
            }
        );
        assert_eq!(
            s.deciles[3],
            Decile {
                identities: 2,
                correct: 0
            }
        );
        assert_eq!(s.frames_exact as f64 / s.frames as f64, 0.5);
        assert!(s.format().contains("50.0% (1 of 2)"), "{}", s.format());
        // Frames scored separately and merged count the same as frames added in turn.
        let (mut a, mut b) = (IdentityStats::default(), IdentityStats::default());
        a.add_frame(&[ident(0.95, vec![(0, 0), (1, 1)])], &ids);
        b.add_frame(&[ident(0.35, vec![(0, 1)]), ident(0.3, vec![(1, 0)])], &ids);
        let mut both = a;
        both.add_frame(&[ident(0.35, vec![(0, 1)]), ident(0.3, vec![(1, 0)])], &ids);
        a.merge(&b);
        assert_eq!(a, both);
    }

    #[test]
    fn monotone_within_a_tolerance_and_empty_deciles_skipped() {
        let mut s = IdentityStats::default();
        s.deciles[2] = Decile {
            identities: 10,
            correct: 5,
        };
        s.deciles[7] = Decile {
            identities: 100,
            correct: 48,
        };
        assert!(s.monotone(3.0), "48 % after 50 %: within 3 points");
        assert!(!s.monotone(1.0));
        s.deciles[9] = Decile {
            identities: 10,
            correct: 4,
        };
        assert!(!s.monotone(3.0), "40 % after 48 %");
        assert!(IdentityStats::default().monotone(0.0));
    }
}

//! The paper's association metrics (SPEC §5) over per-image-pair records.
//!
//! All rates are **fractions in [0, 1]** (the CLI prints them as percentages). A rate whose
//! denominator is zero (e.g. precision with no kept match, AP with no positive score) is 0;
//! the counts in [`Metrics`] show when that happened.
use std::collections::HashSet;

use serde::{Deserialize, Serialize};

use crossview_core::{Error, Result};

/// Everything needed to score one image pair (camera `a` < camera `b` of one frame); also the
/// line format of `crossview eval --dump-pairs`:
/// `{"frame_id","camera_a","camera_b","ids_a":[...],"ids_b":[...],"scores":[...],"matches":[[i,j,s],...],"identity_matches":[[i,j,s],...]}`
/// (`identity_matches` optional: the matches implied by the frame's identities).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PairRecord {
    pub frame_id: u64,
    /// Camera name of the first view.
    pub camera_a: String,
    /// Camera name of the second view.
    pub camera_b: String,
    /// Ground-truth ids of the first view's boxes (n).
    pub ids_a: Vec<u64>,
    /// Ground-truth ids of the second view's boxes (m).
    pub ids_b: Vec<u64>,
    /// Confidence matrix `S`, row-major `n × m`.
    pub scores: Vec<f32>,
    /// Kept matches `(i, j, s)`: box `i` of view a with box `j` of view b, confidence `s`.
    pub matches: Vec<(usize, usize, f32)>,
    /// **[ours]** The matches implied by the frame's identities, same form (absent in dumps
    /// written before identities were reported).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity_matches: Option<Vec<(usize, usize, f32)>>,
}

impl PairRecord {
    /// Checks the record's internal consistency: `scores` has `n·m` finite values, matches
    /// index existing boxes, use each box at most once and carry finite scores.
    pub fn validate(&self) -> Result<()> {
        let field = |f: &str| {
            format!(
                "pair record (frame {}, {}–{}).{f}",
                self.frame_id, self.camera_a, self.camera_b
            )
        };
        let (n, m) = (self.ids_a.len(), self.ids_b.len());
        if self.scores.len() != n * m {
            return Err(Error::invalid(
                field("scores"),
                format!(
                    "expected {n}×{m} = {} values, got {}",
                    n * m,
                    self.scores.len()
                ),
            ));
        }
        if let Some(k) = self.scores.iter().position(|v| !v.is_finite()) {
            return Err(Error::invalid(
                field(&format!("scores[{k}]")),
                "must be finite",
            ));
        }
        check_matches(&self.matches, n, m, |k| field(&format!("matches[{k}]")))?;
        if let Some(im) = &self.identity_matches {
            check_matches(im, n, m, |k| field(&format!("identity_matches[{k}]")))?;
        }
        Ok(())
    }

    /// This record with its identity matches as the scored matches (`None` when it has
    /// none), so identities are scored exactly like pairwise matching.
    pub fn as_identities(&self) -> Option<PairRecord> {
        Some(PairRecord {
            matches: self.identity_matches.clone()?,
            identity_matches: None,
            ..self.clone()
        })
    }
}

/// Matches index existing boxes, use each box at most once and carry finite scores.
fn check_matches(
    matches: &[(usize, usize, f32)],
    n: usize,
    m: usize,
    field: impl Fn(usize) -> String,
) -> Result<()> {
    let mut used_a = vec![false; n];
    let mut used_b = vec![false; m];
    for (k, &(i, j, s)) in matches.iter().enumerate() {
        if i >= n || j >= m {
            return Err(Error::invalid(
                field(k),
                format!("index ({i}, {j}) outside {n}×{m}"),
            ));
        }
        if used_a[i] || used_b[j] {
            return Err(Error::invalid(
                field(k),
                format!("box {i} or {j} matched twice"),
            ));
        }
        if !s.is_finite() {
            return Err(Error::invalid(field(k), "score must be finite"));
        }
        used_a[i] = true;
        used_b[j] = true;
    }
    Ok(())
}

/// SPEC §5 metrics (fractions in [0, 1]) and the counts behind them.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Metrics {
    /// Average precision of all pooled S entries (scikit-learn's `average_precision_score`).
    pub ap: f64,
    /// False-positive rate at 95% recall of the pooled S ranking.
    pub fpr95: f64,
    /// Correct matches / kept matches.
    pub precision: f64,
    /// Correct matches / persons seen by both views.
    pub recall: f64,
    /// (TN + correct) / persons seen by either view.
    pub acc: f64,
    /// Fraction of image pairs associated perfectly.
    pub ipaa_100: f64,
    /// Fraction of image pairs with pair accuracy ≥ 90%.
    pub ipaa_90: f64,
    /// Fraction of image pairs with pair accuracy ≥ 80%.
    pub ipaa_80: f64,
    /// Number of image pairs scored.
    pub pairs: usize,
    /// Number of distinct frames among them.
    pub frames: usize,
    /// Kept matches.
    pub kept: usize,
    /// Correct kept matches.
    pub correct: usize,
    /// Σ |L1 ∩ L2|: persons visible in both views.
    pub common: usize,
    /// Σ |L1 ∪ L2|: persons visible in either view.
    pub union: usize,
    /// Unmatched boxes whose person is absent from the other view.
    pub true_negatives: usize,
    /// Pooled S entries whose two boxes share an id.
    pub positives: usize,
    /// Pooled S entries whose two boxes differ.
    pub negatives: usize,
}

/// Per-pair counts for ACC / IPAA.
struct PairCounts {
    kept: usize,
    correct: usize,
    common: usize,
    union: usize,
    tn: usize,
}

fn pair_counts(r: &PairRecord) -> PairCounts {
    let (n, m) = (r.ids_a.len(), r.ids_b.len());
    let l1: HashSet<u64> = r.ids_a.iter().copied().collect();
    let l2: HashSet<u64> = r.ids_b.iter().copied().collect();
    let common = l1.intersection(&l2).count();
    let union = l1.len() + l2.len() - common;
    let mut matched_a = vec![false; n];
    let mut matched_b = vec![false; m];
    let mut kept = 0;
    let mut correct = 0;
    for &(i, j, _) in &r.matches {
        // Records are validated on read; skip anything out of range instead of panicking.
        if i >= n || j >= m {
            continue;
        }
        kept += 1;
        matched_a[i] = true;
        matched_b[j] = true;
        if r.ids_a[i] == r.ids_b[j] {
            correct += 1;
        }
    }
    let tn_a = (0..n)
        .filter(|&i| !matched_a[i] && !l2.contains(&r.ids_a[i]))
        .count();
    let tn_b = (0..m)
        .filter(|&j| !matched_b[j] && !l1.contains(&r.ids_b[j]))
        .count();
    PairCounts {
        kept,
        correct,
        common,
        union,
        tn: tn_a + tn_b,
    }
}

fn ratio(num: usize, den: usize) -> f64 {
    if den == 0 {
        0.0
    } else {
        num as f64 / den as f64
    }
}

/// Sorts `(score, is_positive)` by score, descending, and yields the cumulative
/// `(true positives, false positives)` after each group of tied scores — one entry per distinct
/// threshold, the walk both [`average_precision`] and [`fpr_at_95_recall`] are built on.
fn cumulative_counts(scored: &mut [(f32, bool)]) -> impl Iterator<Item = (usize, usize)> + '_ {
    scored.sort_unstable_by(|x, y| y.0.total_cmp(&x.0));
    let (mut tp, mut fp) = (0usize, 0usize);
    scored.chunk_by(|x, y| x.0 == y.0).map(move |group| {
        let pos = group.iter().filter(|s| s.1).count();
        tp += pos;
        fp += group.len() - pos;
        (tp, fp)
    })
}

/// Average precision exactly as scikit-learn's `average_precision_score`: with the scores
/// sorted descending and tied scores grouped into one threshold,
/// `AP = Σ_k (R_k − R_{k−1}) · P_k`. `scored` holds `(score, is_positive)`; 0 without positives.
pub(crate) fn average_precision(scored: &mut [(f32, bool)]) -> f64 {
    let total_pos = scored.iter().filter(|s| s.1).count();
    if total_pos == 0 {
        return 0.0;
    }
    let mut prev_recall = 0.0;
    let mut ap = 0.0;
    for (tp, fp) in cumulative_counts(scored) {
        let recall = tp as f64 / total_pos as f64;
        let precision = tp as f64 / (tp + fp) as f64;
        ap += (recall - prev_recall) * precision;
        prev_recall = recall;
    }
    ap
}

/// FPR at 95% recall (SPEC §5): scores sorted descending, tied scores taken together; at the
/// first score where the cumulative positives reach 95% of all positives, the fraction of
/// all negatives whose score is at or above it. 0 without positives or negatives.
pub(crate) fn fpr_at_95_recall(scored: &mut [(f32, bool)]) -> f64 {
    let total_pos = scored.iter().filter(|s| s.1).count();
    let total_neg = scored.len() - total_pos;
    if total_pos == 0 || total_neg == 0 {
        return 0.0;
    }
    for (tp, fp) in cumulative_counts(scored) {
        // tp / total_pos >= 0.95, in integers.
        if tp * 100 >= 95 * total_pos {
            return fp as f64 / total_neg as f64;
        }
    }
    1.0
}

/// Computes every SPEC §5 metric over all image pairs. Records are expected to be valid
/// ([`PairRecord::validate`]); out-of-range entries are skipped rather than panicking.
pub fn compute_metrics(records: &[PairRecord]) -> Metrics {
    let mut m = Metrics {
        pairs: records.len(),
        ..Default::default()
    };
    let (mut ok100, mut ok90, mut ok80) = (0usize, 0usize, 0usize);
    let mut scored: Vec<(f32, bool)> = Vec::new();
    let mut frames = HashSet::new();
    for r in records {
        frames.insert(r.frame_id);
        let c = pair_counts(r);
        m.kept += c.kept;
        m.correct += c.correct;
        m.common += c.common;
        m.union += c.union;
        m.true_negatives += c.tn;
        let good = c.tn + c.correct;
        // good / union >= X%, in integers (exact at the boundaries).
        ok100 += usize::from(good * 100 >= 100 * c.union);
        ok90 += usize::from(good * 100 >= 90 * c.union);
        ok80 += usize::from(good * 100 >= 80 * c.union);
        let nb = r.ids_b.len();
        for (k, &s) in r.scores.iter().enumerate() {
            let (i, j) = (k / nb.max(1), k % nb.max(1));
            if i < r.ids_a.len() && j < nb {
                scored.push((s, r.ids_a[i] == r.ids_b[j]));
            }
        }
    }
    m.frames = frames.len();
    m.positives = scored.iter().filter(|s| s.1).count();
    m.negatives = scored.len() - m.positives;
    m.precision = ratio(m.correct, m.kept);
    m.recall = ratio(m.correct, m.common);
    m.acc = ratio(m.true_negatives + m.correct, m.union);
    m.ipaa_100 = ratio(ok100, m.pairs);
    m.ipaa_90 = ratio(ok90, m.pairs);
    m.ipaa_80 = ratio(ok80, m.pairs);
    m.ap = average_precision(&mut scored);
    m.fpr95 = fpr_at_95_recall(&mut scored);
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(
        ids_a: Vec<u64>,
        ids_b: Vec<u64>,
        scores: Vec<f32>,
        matches: Vec<(usize, usize, f32)>,
    ) -> PairRecord {
        PairRecord {
            frame_id: 0,
            camera_a: "a".into(),
            camera_b: "b".into(),
            ids_a,
            ids_b,
            scores,
            matches,
            identity_matches: None,
        }
    }

    fn close(x: f64, y: f64) -> bool {
        (x - y).abs() < 1e-9
    }

    #[test]
    fn all_unmatched_persons_are_true_negatives() {
        // Nobody is seen by both views and nothing is matched: a perfect pair.
        let r = rec(vec![1, 2], vec![3], vec![0.1, 0.2], vec![]);
        let m = compute_metrics(&[r]);
        assert_eq!(m.true_negatives, 3);
        assert_eq!(m.union, 3);
        assert!(close(m.acc, 1.0));
        assert!(close(m.ipaa_100, 1.0));
        assert_eq!((m.kept, m.common), (0, 0));
        assert!(close(m.precision, 0.0) && close(m.recall, 0.0));
        assert_eq!(m.positives, 0);
        assert!(close(m.ap, 0.0));
    }

    #[test]
    fn a_wrong_match_is_an_error_on_both_sides() {
        // Views share person 1; 2 is only in a, 3 only in b. The matcher pairs 2 with 1 (wrong).
        // ids_a = [1, 2], ids_b = [1, 3].
        let r = rec(
            vec![1, 2],
            vec![1, 3],
            vec![0.5, 0.1, 0.9, 0.2],
            vec![(1, 0, 0.9)],
        );
        let m = compute_metrics(std::slice::from_ref(&r));
        // a0 (id 1) unmatched but present in b: error. a1 wrongly matched: error.
        // b0 wrongly matched: error. b1 (id 3) unmatched and absent from a: TN.
        assert_eq!((m.kept, m.correct, m.true_negatives), (1, 0, 1));
        assert_eq!((m.common, m.union), (1, 3));
        assert!(close(m.precision, 0.0));
        assert!(close(m.recall, 0.0));
        assert!(close(m.acc, 1.0 / 3.0));
        assert!(close(m.ipaa_80, 0.0));
        // A second, perfect pair: IPAA-100 = 1/2, ACC pooled = (1 + 1 + 2) / (3 + 3)... computed.
        let good = rec(
            vec![1, 2],
            vec![1, 3],
            vec![0.9, 0.1, 0.2, 0.1],
            vec![(0, 0, 0.9)],
        );
        let m = compute_metrics(&[r, good]);
        assert!(close(m.ipaa_100, 0.5));
        assert!(close(m.precision, 0.5));
        assert!(close(m.recall, 0.5));
        // good: correct 1 + TN 2 (a1, b1) over union 3.
        assert!(close(m.acc, (1.0 + 3.0) / 6.0));
        assert_eq!(m.frames, 1);
    }

    #[test]
    fn ipaa_thresholds_are_exact_at_boundaries() {
        // 10 persons in both views, 9 matched correctly, 1 unmatched: accuracy exactly 90%.
        let ids: Vec<u64> = (0..10).collect();
        let matches = (0..9).map(|i| (i, i, 1.0)).collect();
        let r = rec(ids.clone(), ids, vec![0.5; 100], matches);
        let m = compute_metrics(&[r]);
        assert!(close(m.acc, 0.9));
        assert!(close(m.ipaa_90, 1.0) && close(m.ipaa_100, 0.0) && close(m.ipaa_80, 1.0));
    }

    #[test]
    fn ap_and_fpr95_on_a_tiny_ranked_list() {
        // Ranked: + + - + - - -   (P = 3, N = 4)
        let mut s = vec![
            (0.9, true),
            (0.8, true),
            (0.7, false),
            (0.6, true),
            (0.5, false),
            (0.4, false),
            (0.3, false),
        ];
        // sklearn: (1 + 1 + 3/4) / 3
        assert!(close(average_precision(&mut s), 2.75 / 3.0));
        // 95% of 3 positives needs all 3, reached at 0.6; 1 of 4 negatives at or above.
        assert!(close(fpr_at_95_recall(&mut s), 0.25));
        // Ties form one threshold: [0.8+, 0.8-, 0.3+] -> 0.5*0.5 + 0.5*(2/3).
        let mut t = vec![(0.8, true), (0.8, false), (0.3, true)];
        assert!(close(average_precision(&mut t), 0.25 + 1.0 / 3.0));
        assert!(close(fpr_at_95_recall(&mut t), 1.0));
        // Perfect ranking.
        let mut p = vec![(0.9, true), (0.1, false)];
        assert!(close(average_precision(&mut p), 1.0));
        assert!(close(fpr_at_95_recall(&mut p), 0.0));
    }

    #[test]
    fn pooled_scores_are_labelled_by_id() {
        // ids_a = [1, 2], ids_b = [2, 1]: positives at (0,1) and (1,0).
        let r = rec(vec![1, 2], vec![2, 1], vec![0.1, 0.9, 0.8, 0.2], vec![]);
        let m = compute_metrics(&[r]);
        assert_eq!((m.positives, m.negatives), (2, 2));
        assert!(close(m.ap, 1.0));
        assert!(close(m.fpr95, 0.0));
    }

    #[test]
    fn validation_rejects_inconsistent_records() {
        assert!(
            rec(vec![1], vec![2], vec![0.5], vec![(0, 0, 0.5)])
                .validate()
                .is_ok()
        );
        assert!(
            rec(vec![1], vec![2], vec![0.5, 0.1], vec![])
                .validate()
                .is_err()
        );
        assert!(
            rec(vec![1], vec![2], vec![f32::NAN], vec![])
                .validate()
                .is_err()
        );
        assert!(
            rec(vec![1], vec![2], vec![0.5], vec![(1, 0, 0.5)])
                .validate()
                .is_err()
        );
        let dup = rec(
            vec![1, 2],
            vec![2],
            vec![0.5, 0.5],
            vec![(0, 0, 0.5), (1, 0, 0.5)],
        );
        assert!(dup.validate().is_err());
    }

    #[test]
    fn serde_line_format() {
        let r = rec(vec![1], vec![2, 3], vec![0.5, 0.25], vec![(0, 1, 0.25)]);
        let line = serde_json::to_string(&r).unwrap();
        assert_eq!(
            line,
            r#"{"frame_id":0,"camera_a":"a","camera_b":"b","ids_a":[1],"ids_b":[2,3],"scores":[0.5,0.25],"matches":[[0,1,0.25]]}"#
        );
        assert_eq!(serde_json::from_str::<PairRecord>(&line).unwrap(), r);
    }
}

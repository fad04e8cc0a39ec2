//! Matching two views (SPEC §3): from the distances ([`crate::distances`]) to the Hungarian
//! assignment and the pairs kept by the confidence threshold.
//!
//! Written for the hot path of the server (21 camera pairs per frame for 7 cameras): the
//! assignment step is a shortest-augmenting-path solver ([`crate::lsa`]) that keeps its
//! buffers between calls. BENCHMARKS.md has the timings.
use ndarray::{Array2, ArrayView1, ArrayView2};

use crate::distances::{
    euclidean_distances, euclidean_distances_with_norms, normalize_in_place, row_sq_norms,
};

/// One kept match between box `a` of the first view and box `b` of the second, with its
/// confidence `score = 1 - D[a, b]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub a: usize,
    pub b: usize,
    pub score: f32,
}

impl Match {
    /// `(a, b, score)`: the form the dumps and the associate output write.
    pub fn triple(&self) -> (usize, usize, f32) {
        (self.a, self.b, self.score)
    }
}

/// One Hungarian pair, kept or not: box `a` of the first view with box `b` of the second,
/// its SPEC §3 confidence `score = 1 - D[a, b]` and its raw geometric embedding distance
/// `distance = Dg[a, b]` (what a [`crate::calibration::Calibration`] reads: unlike `S` it
/// does not depend on the other boxes of the pair).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Assigned {
    pub a: usize,
    pub b: usize,
    pub score: f32,
    pub distance: f32,
}

/// The association of one camera pair within a frame: the pair's cameras and its matching.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewPair {
    pub cam_a: usize,
    pub cam_b: usize,
    pub matching: PairMatching,
}

/// The result of matching two views.
#[derive(Debug, Clone, PartialEq)]
pub struct PairMatching {
    /// Confidence matrix `S = 1 - D`, shape `[n, m]`.
    pub scores: Array2<f32>,
    /// Every Hungarian pair (`min(n, m)` of them), sorted by `a`: the evidence the identities
    /// are built from.
    pub assignment: Vec<Assigned>,
    /// Hungarian pairs with `score >= threshold`, sorted by `a` (SPEC §3 pairwise matching).
    pub matches: Vec<Match>,
    /// The raw geometric distance of any entry is `(1 − scores[(a, b)]) · distance_scale`
    /// (so the identities can read a calibrated `P` off every entry, not only the assigned
    /// ones); NaN when appearance was fused into `D` and the raw distances cannot be read back.
    pub distance_scale: f32,
}

impl PairMatching {
    /// Raw geometric distance of entry `(a, b)` (see [`Self::distance_scale`]); NaN when it
    /// cannot be read back or `(a, b)` is out of range.
    pub fn distance(&self, a: usize, b: usize) -> f32 {
        self.scores
            .get((a, b))
            .map_or(f32::NAN, |s| (1.0 - s) * self.distance_scale)
    }
}

/// SPEC §3's kept matches: the Hungarian pairs with `S ≥ threshold`, in assignment order.
pub(crate) fn kept_matches(assignment: &[Assigned], threshold: f32) -> Vec<Match> {
    assignment
        .iter()
        .filter(|p| p.score >= threshold)
        .map(|p| Match {
            a: p.a,
            b: p.b,
            score: p.score,
        })
        .collect()
}

/// Minimum-cost one-to-one assignment: `min(n, m)` pairs `(row, col)`, sorted by row
/// ([`crate::lsa::assign`], on this thread's reusable solver). An empty side gives
/// no pairs. Non-finite entries never hang or panic: NaN and `+inf` are treated as worse
/// than every finite cost and `-inf` as better; callers validate their inputs before this
/// point anyway.
pub fn hungarian(cost: ArrayView2<f32>) -> Vec<(usize, usize)> {
    crate::lsa::assign(cost)
}

/// Full SPEC §3 matching of two views from their embeddings (and optional appearance
/// vectors, used only when both sides have them).
///
/// `S = 1 − D`; the Hungarian pairs on `D` with `S ≥ threshold` are kept (every pair may be
/// dropped, unlike the reference code which always keeps the last one).
pub fn match_views(
    emb_a: ArrayView2<f32>,
    emb_b: ArrayView2<f32>,
    app_a: Option<ArrayView2<f32>>,
    app_b: Option<ArrayView2<f32>>,
    alpha: f32,
    threshold: f32,
) -> PairMatching {
    let na = row_sq_norms(emb_a);
    let nb = row_sq_norms(emb_b);
    let apps = match (app_a, app_b) {
        (Some(x), Some(y)) => Some((x, y)),
        _ => None,
    };
    match_views_with_norms(emb_a, emb_b, na.view(), nb.view(), apps, alpha, threshold)
}

/// [`match_views`] with precomputed squared row norms of the embeddings. Appearance is used
/// when given with consistent shapes (rows equal to the embeddings', equal widths);
/// otherwise it is ignored with a warning.
pub(crate) fn match_views_with_norms(
    emb_a: ArrayView2<f32>,
    emb_b: ArrayView2<f32>,
    norms_a: ArrayView1<f32>,
    norms_b: ArrayView1<f32>,
    appearance: Option<(ArrayView2<f32>, ArrayView2<f32>)>,
    alpha: f32,
    threshold: f32,
) -> PairMatching {
    let d = euclidean_distances_with_norms(emb_a, emb_b, norms_a, norms_b);
    let da = appearance.and_then(|(x, y)| {
        if x.nrows() == emb_a.nrows() && y.nrows() == emb_b.nrows() && x.ncols() == y.ncols() {
            Some(euclidean_distances(x, y))
        } else {
            tracing::warn!("appearance shapes inconsistent with embeddings; using geometry only");
            None
        }
    });
    match_from_distances(d, da.as_ref(), alpha, threshold)
}

/// The SPEC §3 steps after the distances: normalise `dg` (fusing `da` when given, same
/// shape), Hungarian on `D`, `S = 1 − D`, keep pairs with `S ≥ threshold`. `dg` is reused
/// as the score matrix (no extra allocation).
pub fn match_from_distances(
    mut dg: Array2<f32>,
    da: Option<&Array2<f32>>,
    alpha: f32,
    threshold: f32,
) -> PairMatching {
    // With appearance, D no longer scales back to Dg: keep the raw geometric values of the
    // (rare) fused case; without it, Dg = D · scale.
    let raw = da.map(|_| dg.clone());
    let scale = normalize_in_place(&mut dg, da, alpha);
    let pairs = hungarian(dg.view());
    let assignment: Vec<Assigned> = pairs
        .into_iter()
        .map(|(a, b)| {
            let d = dg[(a, b)];
            let distance = match &raw {
                Some(g) => g[(a, b)],
                None => d * scale,
            };
            Assigned {
                a,
                b,
                score: 1.0 - d,
                distance,
            }
        })
        .collect();
    // S = 1 - D, in place.
    dg.mapv_inplace(|v| 1.0 - v);
    let matches = kept_matches(&assignment, threshold);
    PairMatching {
        scores: dg,
        assignment,
        matches,
        distance_scale: if raw.is_some() { f32::NAN } else { scale },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::is_valid_assignment;
    use ndarray::{Array2, array};
    use proptest::prelude::*;

    fn brute_force_min(cost: &Array2<f32>) -> f64 {
        // Assign every row of the smaller side; enumerate injective maps.
        let (n, m) = cost.dim();
        let (small, large, t) = if n <= m { (n, m, false) } else { (m, n, true) };
        let at = |i: usize, j: usize| -> f64 {
            if t {
                cost[(j, i)] as f64
            } else {
                cost[(i, j)] as f64
            }
        };
        fn rec(
            i: usize,
            small: usize,
            large: usize,
            used: &mut Vec<bool>,
            acc: f64,
            best: &mut f64,
            at: &dyn Fn(usize, usize) -> f64,
        ) {
            if i == small {
                *best = best.min(acc);
                return;
            }
            for j in 0..large {
                if !used[j] {
                    used[j] = true;
                    rec(i + 1, small, large, used, acc + at(i, j), best, at);
                    used[j] = false;
                }
            }
        }
        let mut best = f64::INFINITY;
        rec(
            0,
            small,
            large,
            &mut vec![false; large],
            0.0,
            &mut best,
            &at,
        );
        if small == 0 { 0.0 } else { best }
    }

    fn matrix(n: usize, m: usize) -> impl Strategy<Value = Array2<f32>> {
        proptest::collection::vec(0.0f32..1.0, n * m)
            .prop_map(move |v| Array2::from_shape_vec((n, m), v).unwrap())
    }

    fn sized_matrix(max: usize) -> impl Strategy<Value = Array2<f32>> {
        (0..=max, 0..=max).prop_flat_map(|(n, m)| matrix(n, m))
    }

    #[test]
    fn hungarian_small_known_case() {
        let c = array![[4.0f32, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]];
        assert_eq!(hungarian(c.view()), vec![(0, 1), (1, 0), (2, 2)]);
        // More rows than columns: transposed internally.
        let c = array![[1.0f32, 9.0], [9.0, 1.0], [0.0, 0.5]];
        let p = hungarian(c.view());
        assert_eq!(p, vec![(1, 1), (2, 0)]);
    }

    #[test]
    fn hungarian_empty_sides_give_no_pairs() {
        assert!(hungarian(Array2::<f32>::zeros((0, 3)).view()).is_empty());
        assert!(hungarian(Array2::<f32>::zeros((3, 0)).view()).is_empty());
        assert!(hungarian(Array2::<f32>::zeros((0, 0)).view()).is_empty());
    }

    #[test]
    fn hungarian_non_finite_is_deterministic_and_terminates() {
        let c = array![
            [f32::NAN, 0.5, 0.25],
            [0.2, f32::NEG_INFINITY, 0.3],
            [0.3, 0.4, f32::INFINITY]
        ];
        let p1 = hungarian(c.view());
        assert_eq!(p1, hungarian(c.view()));
        // -inf is the most attractive entry; NaN/inf are avoided.
        assert_eq!(p1, vec![(0, 2), (1, 1), (2, 0)]);
        let all_nan = Array2::from_elem((4, 2), f32::NAN);
        assert!(is_valid_assignment(&hungarian(all_nan.view()), 4, 2));
        // Huge but finite magnitudes do not overflow.
        let huge = array![[f32::MAX, -f32::MAX], [0.0, f32::MAX]];
        assert_eq!(hungarian(huge.view()), vec![(0, 1), (1, 0)]);
    }

    #[test]
    fn match_views_drops_pairs_below_threshold_including_the_last() {
        // Two identical points and one far away: the far pair has S ~ 0.
        let a = array![[0.0f32, 0.0], [10.0, 0.0]];
        let b = array![[0.0f32, 0.1], [0.0, 10.0]];
        let pm = match_views(a.view(), b.view(), None, None, 0.1, 0.4);
        assert_eq!(pm.scores.dim(), (2, 2));
        assert_eq!(pm.matches.len(), 1);
        assert_eq!((pm.matches[0].a, pm.matches[0].b), (0, 0));
        // A single pair with S = 0 is dropped too (no "keep the last pair" quirk).
        let a1 = array![[0.0f32, 0.0]];
        let b1 = array![[5.0f32, 0.0]];
        let pm = match_views(a1.view(), b1.view(), None, None, 0.1, 0.1);
        assert!(pm.matches.is_empty());
        // Empty view.
        let e = Array2::<f32>::zeros((0, 2));
        let pm = match_views(e.view(), b.view(), None, None, 0.1, 0.0);
        assert_eq!(pm.scores.dim(), (0, 2));
        assert!(pm.matches.is_empty());
    }

    #[test]
    fn appearance_changes_the_assignment() {
        // Geometry is ambiguous; appearance decides.
        let a = array![[0.0f32], [1.0]];
        let b = array![[0.5f32], [0.5001]];
        let app_a = array![[1.0f32, 0.0], [0.0, 1.0]];
        let app_b = array![[0.0f32, 1.0], [1.0, 0.0]];
        let pm = match_views(
            a.view(),
            b.view(),
            Some(app_a.view()),
            Some(app_b.view()),
            0.5,
            0.0,
        );
        let pairs: Vec<_> = pm.matches.iter().map(|m| (m.a, m.b)).collect();
        assert_eq!(pairs, vec![(0, 1), (1, 0)]);
    }

    proptest! {
        #[test]
        fn hungarian_is_valid_and_optimal(cost in sized_matrix(6)) {
            let (n, m) = cost.dim();
            let pairs = hungarian(cost.view());
            prop_assert!(is_valid_assignment(&pairs, n, m));
            let total: f64 = pairs.iter().map(|&(r, c)| cost[(r, c)] as f64).sum();
            let best = brute_force_min(&cost);
            prop_assert!(total <= best + 1e-6, "total {total} > best {best}");
        }

        #[test]
        fn hungarian_valid_on_larger_matrices(cost in sized_matrix(40)) {
            let (n, m) = cost.dim();
            prop_assert!(is_valid_assignment(&hungarian(cost.view()), n, m));
        }

        #[test]
        fn raising_threshold_only_removes_pairs(
            a in matrix(5, 3), b in matrix(4, 3), t1 in 0.0f32..1.0, t2 in 0.0f32..1.0
        ) {
            let (lo, hi) = if t1 <= t2 { (t1, t2) } else { (t2, t1) };
            let low = match_views(a.view(), b.view(), None, None, 0.1, lo);
            let high = match_views(a.view(), b.view(), None, None, 0.1, hi);
            prop_assert!(high.matches.iter().all(|m| low.matches.contains(m)));
            prop_assert!(high.matches.iter().all(|m| m.score >= hi));
            prop_assert!(low.matches.iter().all(|m| m.score >= lo));
            // With threshold 0 (S >= 0 always), all min(n, m) Hungarian pairs are kept.
            let all = match_views(a.view(), b.view(), None, None, 0.1, 0.0);
            prop_assert_eq!(all.matches.len(), 4);
        }
    }
}

//! Pairwise distances, max-normalisation with optional appearance fusion, Hungarian
//! assignment and the confidence threshold (SPEC §3).
//!
//! The functions are written for the hot path of the server (one call per camera pair per
//! frame): distances use one matrix product (`‖a‖² + ‖b‖² − 2ab`), normalisation works in
//! place, and the Hungarian step scales costs to integers once and runs
//! `pathfinding::kuhn_munkres` on a borrowed buffer.
use ndarray::{Array1, Array2, ArrayView1, ArrayView2, Zip};
use pathfinding::kuhn_munkres::{Weights, kuhn_munkres};

/// Added to every normalising maximum so that an all-zero matrix stays finite (SPEC §3).
pub const NORM_EPS: f32 = 1e-6;

/// Resolution of the integer costs handed to Kuhn–Munkres: the finite cost range is mapped
/// onto `0..=COST_SCALE`, i.e. about 1e-9 of the range, finer than an `f32` ulp near 1.
const COST_SCALE: f64 = (1u64 << 30) as f64;

/// One kept match between box `a` of the first view and box `b` of the second, with its
/// confidence `score = 1 - D[a, b]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Match {
    pub a: usize,
    pub b: usize,
    pub score: f32,
}

/// The result of matching two views.
#[derive(Debug, Clone, PartialEq)]
pub struct PairMatching {
    /// Confidence matrix `S = 1 - D`, shape `[n, m]`.
    pub scores: Array2<f32>,
    /// Hungarian pairs with `score >= threshold`, sorted by `a`.
    pub matches: Vec<Match>,
}

/// Squared L2 norm of every row of `x`.
pub fn row_sq_norms(x: ArrayView2<f32>) -> Array1<f32> {
    x.rows().into_iter().map(|r| r.dot(&r)).collect()
}

/// Euclidean distances between the rows of `a` `[n, d]` and `b` `[m, d]`: `[n, m]`.
///
/// Computed as `sqrt(max(0, ‖a‖² + ‖b‖² − 2 a·b))` with one matrix product; the clamp
/// removes the tiny negative values cancellation produces for identical rows.
///
/// # Panics
/// When `a` and `b` have different widths (a programming error: both come from one encoder).
pub fn euclidean_distances(a: ArrayView2<f32>, b: ArrayView2<f32>) -> Array2<f32> {
    let na = row_sq_norms(a);
    let nb = row_sq_norms(b);
    euclidean_distances_with_norms(a, b, na.view(), nb.view())
}

/// [`euclidean_distances`] with the squared row norms already known (the frame-level
/// association computes each view's norms once instead of once per camera pair).
///
/// # Panics
/// When widths or norm lengths disagree with the matrices (a programming error).
pub fn euclidean_distances_with_norms(
    a: ArrayView2<f32>,
    b: ArrayView2<f32>,
    norms_a: ArrayView1<f32>,
    norms_b: ArrayView1<f32>,
) -> Array2<f32> {
    assert_eq!(
        a.ncols(),
        b.ncols(),
        "euclidean_distances: embedding widths differ"
    );
    assert_eq!(
        norms_a.len(),
        a.nrows(),
        "euclidean_distances: norms_a length"
    );
    assert_eq!(
        norms_b.len(),
        b.nrows(),
        "euclidean_distances: norms_b length"
    );
    let mut d = a.dot(&b.t());
    Zip::from(d.rows_mut())
        .and(&norms_a)
        .for_each(|mut row, &na| {
            Zip::from(&mut row).and(&norms_b).for_each(|v, &nb| {
                *v = (na + nb - 2.0 * *v).max(0.0).sqrt();
            });
        });
    d
}

/// Geometric distances of every view pair `a < b` of a frame, in the order
/// `(0,1), (0,2), …, (1,2), …`: `views[k]` is `[n_k, d]` (every view with at least one box).
///
/// Faster than one [`euclidean_distances`] per pair: the later views are copied once into one
/// contiguous matrix, so each view needs a single matrix product against all views after it
/// (k − 1 larger products instead of k(k−1)/2 small ones).
///
/// # Panics
/// When the views have different widths (a programming error: one encoder made them all).
pub fn all_pairs_distances(views: &[ArrayView2<f32>]) -> Vec<Array2<f32>> {
    let k = views.len();
    if k < 2 {
        return Vec::new();
    }
    let dim = views[0].ncols();
    assert!(
        views.iter().all(|v| v.ncols() == dim),
        "all_pairs_distances: embedding widths differ"
    );
    let norms: Vec<Array1<f32>> = views.iter().map(|v| row_sq_norms(*v)).collect();
    // Row offset of view b (b >= 1) inside `rest` = concat(views[1..]).
    let mut offsets = vec![0usize; k + 1];
    for b in 1..k {
        offsets[b + 1] = offsets[b] + views[b].nrows();
    }
    let mut data = Vec::with_capacity(offsets[k] * dim);
    for v in &views[1..] {
        match v.as_slice() {
            Some(sl) => data.extend_from_slice(sl),
            None => v.rows().into_iter().for_each(|r| data.extend(r.iter())),
        }
    }
    let rest = ArrayView2::from_shape((offsets[k], dim), &data).expect("sized above");
    let mut out = Vec::with_capacity(k * (k - 1) / 2);
    for a in 0..k - 1 {
        let start = offsets[a + 1];
        let gram = views[a].dot(&rest.slice(ndarray::s![start.., ..]).t());
        let na = &norms[a];
        for (b, nb) in norms.iter().enumerate().skip(a + 1) {
            let col = offsets[b] - start;
            out.push(Array2::from_shape_fn((na.len(), nb.len()), |(i, j)| {
                (na[i] + nb[j] - 2.0 * gram[(i, col + j)]).max(0.0).sqrt()
            }));
        }
    }
    out
}

/// Largest finite value of `m` (0 when there is none). NaN and infinities are skipped so
/// that one bad entry cannot turn the whole matrix into NaN.
fn finite_max(m: &Array2<f32>) -> f32 {
    m.iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(0.0f32, f32::max)
}

/// In place: `dg ← Dg/max(Dg)` or, with appearance, `(1-alpha) Dg/max(Dg) + alpha Da/max(Da)`.
/// An appearance matrix of a different shape is ignored (geometry only) with a warning.
fn normalize_in_place(dg: &mut Array2<f32>, da: Option<&Array2<f32>>, alpha: f32) {
    let da = match da {
        Some(da) if da.dim() != dg.dim() => {
            tracing::warn!(
                geometric = ?dg.dim(),
                appearance = ?da.dim(),
                "appearance distance shape differs from geometric; using geometry only"
            );
            None
        }
        other => other,
    };
    let inv_g = 1.0 / (finite_max(dg) + NORM_EPS);
    match da {
        None => dg.mapv_inplace(|v| v * inv_g),
        Some(da) => {
            let inv_a = 1.0 / (finite_max(da) + NORM_EPS);
            let (wg, wa) = ((1.0 - alpha) * inv_g, alpha * inv_a);
            Zip::from(dg)
                .and(da)
                .for_each(|g, &a| *g = wg * *g + wa * a);
        }
    }
}

/// `D = Dg/max(Dg)` or, with appearance, `(1-alpha) Dg/max(Dg) + alpha Da/max(Da)` (SPEC §3).
/// Each matrix is divided by its own largest finite value plus [`NORM_EPS`]. `alpha` is used
/// only when `da` is given (and has the same shape as `dg`).
pub fn normalized_distance(dg: &Array2<f32>, da: Option<&Array2<f32>>, alpha: f32) -> Array2<f32> {
    let mut d = dg.clone();
    normalize_in_place(&mut d, da, alpha);
    d
}

/// Integer weights for Kuhn–Munkres (which maximises): `-scaled cost`, stored row-major in
/// the orientation the solver needs (rows ≤ columns).
struct IntWeights {
    rows: usize,
    cols: usize,
    data: Vec<i64>,
}

impl Weights<i64> for IntWeights {
    fn rows(&self) -> usize {
        self.rows
    }
    fn columns(&self) -> usize {
        self.cols
    }
    fn at(&self, row: usize, col: usize) -> i64 {
        self.data[row * self.cols + col]
    }
    fn neg(&self) -> Self {
        IntWeights {
            rows: self.rows,
            cols: self.cols,
            data: self.data.iter().map(|v| -v).collect(),
        }
    }
}

/// Converts `cost` to integer weights (negated, so maximising weight = minimising cost).
///
/// Finite costs map linearly onto `0..=COST_SCALE` (min → 0). Non-finite entries get a
/// fixed, deterministic place: NaN and `+inf` cost `2·COST_SCALE` (worse than every finite
/// entry), `-inf` costs `-COST_SCALE` (better than every finite entry). The integer matrix
/// is always finite and bounded, so the solver can neither loop nor overflow.
fn int_weights(cost: ArrayView2<f32>, transpose: bool) -> IntWeights {
    let (lo, hi) = cost
        .iter()
        .filter(|v| v.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let (lo, range) = if lo <= hi {
        (lo as f64, (hi as f64 - lo as f64))
    } else {
        (0.0, 0.0)
    };
    let scale = if range > 0.0 { COST_SCALE / range } else { 0.0 };
    let to_int = |v: f32| -> i64 {
        let c = if v.is_finite() {
            ((v as f64 - lo) * scale).round()
        } else if v == f32::NEG_INFINITY {
            -COST_SCALE
        } else {
            2.0 * COST_SCALE
        };
        -(c as i64)
    };
    let (n, m) = cost.dim();
    let (rows, cols) = if transpose { (m, n) } else { (n, m) };
    let mut data = Vec::with_capacity(n * m);
    if transpose {
        for c in 0..m {
            data.extend(cost.column(c).iter().map(|&v| to_int(v)));
        }
    } else {
        for r in cost.rows() {
            data.extend(r.iter().map(|&v| to_int(v)));
        }
    }
    IntWeights { rows, cols, data }
}

/// Minimum-cost one-to-one assignment on a finite cost matrix: `min(n, m)` pairs `(row, col)`,
/// sorted by row.
///
/// Costs are scaled to integers (resolution ~1e-9 of the finite cost range) for
/// `pathfinding::kuhn_munkres`; the matrix is transposed when it has more rows than
/// columns. An empty side gives no pairs. Non-finite entries never hang or panic: NaN and
/// `+inf` are treated as worse than every finite cost and `-inf` as better (see
/// `int_weights`); callers validate their inputs before this point anyway.
pub fn hungarian(cost: ArrayView2<f32>) -> Vec<(usize, usize)> {
    let (n, m) = cost.dim();
    if n == 0 || m == 0 {
        return Vec::new();
    }
    let transpose = n > m;
    let weights = int_weights(cost, transpose);
    let (_, assign) = kuhn_munkres(&weights);
    if transpose {
        // assign[col] = row; rebuild sorted by row.
        let mut pairs: Vec<(usize, usize)> = assign
            .into_iter()
            .enumerate()
            .map(|(c, r)| (r, c))
            .collect();
        pairs.sort_unstable();
        pairs
    } else {
        assign.into_iter().enumerate().collect()
    }
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
pub fn match_views_with_norms(
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
    normalize_in_place(&mut dg, da, alpha);
    let pairs = hungarian(dg.view());
    // S = 1 - D, in place.
    dg.mapv_inplace(|v| 1.0 - v);
    let matches = pairs
        .into_iter()
        .filter_map(|(a, b)| {
            let score = dg[(a, b)];
            (score >= threshold).then_some(Match { a, b, score })
        })
        .collect();
    PairMatching {
        scores: dg,
        matches,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
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

    fn is_valid_assignment(pairs: &[(usize, usize)], n: usize, m: usize) -> bool {
        let mut rows = vec![false; n];
        let mut cols = vec![false; m];
        for &(r, c) in pairs {
            if r >= n || c >= m || rows[r] || cols[c] {
                return false;
            }
            rows[r] = true;
            cols[c] = true;
        }
        pairs.len() == n.min(m) && pairs.windows(2).all(|w| w[0].0 < w[1].0)
    }

    fn matrix(n: usize, m: usize) -> impl Strategy<Value = Array2<f32>> {
        proptest::collection::vec(0.0f32..1.0, n * m)
            .prop_map(move |v| Array2::from_shape_vec((n, m), v).unwrap())
    }

    fn sized_matrix(max: usize) -> impl Strategy<Value = Array2<f32>> {
        (0..=max, 0..=max).prop_flat_map(|(n, m)| matrix(n, m))
    }

    #[test]
    fn distances_match_direct_formula() {
        let a = array![[0.0f32, 0.0], [3.0, 4.0]];
        let b = array![[0.0f32, 0.0], [6.0, 8.0], [3.0, 4.0]];
        let d = euclidean_distances(a.view(), b.view());
        let want = array![[0.0f32, 10.0, 5.0], [5.0, 5.0, 0.0]];
        for (x, y) in d.iter().zip(want.iter()) {
            assert!((x - y).abs() < 1e-5, "{d:?}");
        }
    }

    #[test]
    fn all_pairs_distances_equal_per_pair_distances() {
        let v0 = array![[0.0f32, 1.0], [2.0, 3.0]];
        let v1 = array![[1.0f32, 1.0]];
        let v2 = array![[5.0f32, 0.0], [0.0, 5.0], [1.0, 2.0]];
        // A non-contiguous view (a transposed array) is handled too.
        let v3t = array![[1.0f32, 2.0], [3.0, 4.0]];
        let v3 = v3t.t();
        let views = [v0.view(), v1.view(), v2.view(), v3];
        let all = all_pairs_distances(&views);
        let mut k = 0;
        for a in 0..4 {
            for b in a + 1..4 {
                let want = euclidean_distances(views[a], views[b]);
                assert_eq!(all[k].dim(), want.dim());
                for (x, y) in all[k].iter().zip(want.iter()) {
                    assert!((x - y).abs() < 1e-5);
                }
                k += 1;
            }
        }
        assert_eq!(k, all.len());
        assert!(all_pairs_distances(&views[..1]).is_empty());
    }

    #[test]
    fn normalization_divides_by_own_max_and_fuses_appearance() {
        let dg = array![[1.0f32, 2.0], [4.0, 0.0]];
        let d = normalized_distance(&dg, None, 0.1);
        assert!((d[(1, 0)] - 4.0 / (4.0 + NORM_EPS)).abs() < 1e-7);
        assert!((d[(0, 1)] - 0.5).abs() < 1e-5);
        let da = array![[10.0f32, 0.0], [0.0, 5.0]];
        let d = normalized_distance(&dg, Some(&da), 0.1);
        assert!((d[(0, 0)] - (0.9 * 0.25 + 0.1 * 1.0)).abs() < 1e-5);
        assert!((d[(1, 1)] - (0.1 * 0.5)).abs() < 1e-5);
        // All-zero matrix stays finite.
        let z = normalized_distance(&Array2::zeros((2, 2)), None, 0.0);
        assert!(z.iter().all(|v| *v == 0.0));
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

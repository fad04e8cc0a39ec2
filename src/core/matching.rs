//! Pairwise distances, max-normalisation with optional appearance fusion, Hungarian
//! assignment and the confidence threshold (SPEC §3).
//!
//! The functions are written for the hot path of the server (21 camera pairs per frame for 7
//! cameras): the distances of all pairs of a frame come from a few large matrix products
//! (`‖a‖² + ‖b‖² − 2ab`, [`all_pairs_distances`], through the `gemm` crate), normalisation
//! works in place, and the assignment step is a shortest-augmenting-path solver
//! ([`crate::core::lsa`]) that keeps its buffers between calls. BENCHMARKS.md has the timings.
use std::ops::Range;

use ndarray::{Array1, Array2, ArrayView1, ArrayView2, Zip};

/// Added to every normalising maximum so that an all-zero matrix stays finite (SPEC §3).
pub const NORM_EPS: f32 = 1e-6;

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
/// `distance = Dg[a, b]` (what a [`crate::core::calibration::Calibration`] reads: unlike `S` it
/// does not depend on the other boxes of the pair).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Assigned {
    pub a: usize,
    pub b: usize,
    pub score: f32,
    pub distance: f32,
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
}

/// Squared L2 norm of every row of `x`.
pub fn row_sq_norms(x: ArrayView2<f32>) -> Array1<f32> {
    x.rows()
        .into_iter()
        .map(|r| match r.as_slice() {
            Some(r) => sq_norm(r),
            None => r.dot(&r),
        })
        .collect()
}

/// `Σ v²` in sixteen independent lanes, so that it compiles to vector code (a plain sum is
/// one serial chain of additions).
fn sq_norm(v: &[f32]) -> f32 {
    let mut lanes = [0f32; 16];
    let mut chunks = v.chunks_exact(16);
    for c in &mut chunks {
        for k in 0..16 {
            lanes[k] += c[k] * c[k];
        }
    }
    let tail: f32 = chunks.remainder().iter().map(|x| x * x).sum();
    lanes.iter().sum::<f32>() + tail
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
/// `(0,1), (0,2), …, (1,2), …`: view `k` is the row range `views[k]` of the one embedding
/// matrix `x` `[N, d]` (ranges ascending and non-overlapping, empty ones allowed; rows
/// between ranges are ignored).
///
/// Much faster than one [`euclidean_distances`] per pair: the views are split into two
/// halves, all rows of the first half are multiplied by all rows of the second in ONE matrix
/// product, and each half is split again. For 7 views that is 6 products (the largest
/// 105 × 140 rows for 35 boxes per view) instead of 21 small ones, computing exactly the
/// needed dot products, large enough for the `gemm` kernels to run near their peak, and
/// with no copy of the embeddings.
///
/// # Panics
/// When the ranges are not ascending or exceed `x` (a programming error:
/// [`crate::core::FrameEmbeddings`] guarantees both).
pub fn all_pairs_distances(x: ArrayView2<f32>, views: &[Range<usize>]) -> Vec<Array2<f32>> {
    let k = views.len();
    if k < 2 {
        return Vec::new();
    }
    assert!(
        views
            .windows(2)
            .all(|w| w[0].start <= w[0].end && w[0].end <= w[1].start)
            && views[k - 1].start <= views[k - 1].end
            && views[k - 1].end <= x.nrows(),
        "all_pairs_distances: view ranges must be ascending and inside the matrix"
    );
    let x = x.as_standard_layout();
    let flat = x.as_slice().expect("standard layout is contiguous");
    let dim = x.ncols();
    // Gram entries of the used rows, indexed from `base`, filled above the diagonal blocks.
    let base = views[0].start;
    let span = views[k - 1].end - base;
    let mut gram = vec![0f32; span * span];
    gram_halves(flat, dim, views, base, &mut gram, span);
    let norms = row_sq_norms(x.slice(ndarray::s![base..base + span, ..]));
    let norms = norms.as_slice().expect("freshly collected");
    let mut out = Vec::with_capacity(k * (k - 1) / 2);
    for (a, ra) in views.iter().enumerate() {
        for rb in &views[a + 1..] {
            let nb = &norms[rb.start - base..rb.end - base];
            let mut d = Vec::with_capacity(ra.len() * rb.len());
            for i in ra.clone() {
                let row = (i - base) * span + rb.start - base;
                let na = norms[i - base];
                d.extend(
                    gram[row..row + rb.len()]
                        .iter()
                        .zip(nb)
                        .map(|(&g, &nb)| (na + nb - 2.0 * g).max(0.0).sqrt()),
                );
            }
            out.push(Array2::from_shape_vec((ra.len(), rb.len()), d).expect("sized above"));
        }
    }
    out
}

/// Fills the Gram blocks of all view pairs of `views` (rows counted from `base`, `gram`
/// row-major with row stride `ld`): one product of the first half's rows by the second
/// half's, then each half recursively.
fn gram_halves(
    flat: &[f32],
    dim: usize,
    views: &[Range<usize>],
    base: usize,
    gram: &mut [f32],
    ld: usize,
) {
    if views.len() < 2 {
        return;
    }
    let (first, second) = views.split_at(views.len() / 2);
    let rows_a = first[0].start..first[first.len() - 1].end;
    let rows_b = second[0].start..second[second.len() - 1].end;
    if !rows_a.is_empty() && !rows_b.is_empty() {
        let at = (rows_a.start - base) * ld + rows_b.start - base;
        gram_block(flat, dim, rows_a, rows_b, &mut gram[at..], ld);
    }
    gram_halves(flat, dim, first, base, gram, ld);
    gram_halves(flat, dim, second, base, gram, ld);
}

/// `out[i * ld + j] = x[a.start + i] · x[b.start + j]` for the rows of the row-major
/// `[rows, dim]` matrix `flat`: one single-threaded `gemm` call (its kernels pick the
/// widest SIMD the CPU has at run time).
///
/// # Panics
/// When a range exceeds `flat` or the block exceeds `out` (a programming error).
fn gram_block(
    flat: &[f32],
    dim: usize,
    a: Range<usize>,
    b: Range<usize>,
    out: &mut [f32],
    ld: usize,
) {
    let (m, n) = (a.len(), b.len());
    if m == 0 || n == 0 {
        return;
    }
    assert!(a.end * dim <= flat.len() && b.end * dim <= flat.len() && n <= ld);
    assert!((m - 1) * ld + n <= out.len());
    if dim == 0 {
        out.chunks_mut(ld).take(m).for_each(|r| r[..n].fill(0.0));
        return;
    }
    // SAFETY: with the asserts above, every element gemm reads (rows `a` and `b` of `flat`,
    // `dim` values each) and writes (`m` rows of `n` values, row stride `ld`, in `out`) is in
    // bounds; `out` is borrowed mutably, so it aliases neither input.
    unsafe {
        gemm::gemm(
            m,
            n,
            dim,
            out.as_mut_ptr(),
            1,
            ld as isize,
            false,
            flat[a.start * dim..].as_ptr(),
            1,
            dim as isize,
            flat[b.start * dim..].as_ptr(),
            dim as isize,
            1,
            0.0f32,
            1.0f32,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Largest finite value of `m` (0 when there is none). NaN and infinities are skipped so
/// that one bad entry cannot turn the whole matrix into NaN.
fn finite_max(m: &Array2<f32>) -> f32 {
    let m = m.as_standard_layout();
    let flat = m.as_slice().expect("standard layout is contiguous");
    finite_range(flat).map_or(0.0, |(_, hi)| hi.max(0.0))
}

/// Smallest and largest finite values of `values` (`None` when there is none).
///
/// The common case takes one pass in eight independent lanes (vector code): `f32::min` and
/// `f32::max` already skip NaN, and only when an infinity shows up does a second, exact
/// pass filter the non-finite values out.
fn finite_range(values: &[f32]) -> Option<(f32, f32)> {
    let mut lo = [f32::INFINITY; 8];
    let mut hi = [f32::NEG_INFINITY; 8];
    let mut chunks = values.chunks_exact(8);
    for c in &mut chunks {
        for k in 0..8 {
            lo[k] = lo[k].min(c[k]);
            hi[k] = hi[k].max(c[k]);
        }
    }
    for &v in chunks.remainder() {
        lo[0] = lo[0].min(v);
        hi[0] = hi[0].max(v);
    }
    let lo = lo.into_iter().fold(f32::INFINITY, f32::min);
    let hi = hi.into_iter().fold(f32::NEG_INFINITY, f32::max);
    if lo.is_finite() && hi.is_finite() {
        return Some((lo, hi));
    }
    values
        .iter()
        .filter(|v| v.is_finite())
        .fold(None, |r, &v| match r {
            None => Some((v, v)),
            Some((lo, hi)) => Some((v.min(lo), v.max(hi))),
        })
}

/// In place: `dg ← Dg/max(Dg)` or, with appearance, `(1-alpha) Dg/max(Dg) + alpha Da/max(Da)`.
/// An appearance matrix of a different shape is ignored (geometry only) with a warning.
/// Returns the geometric divisor `max(Dg) + NORM_EPS`.
fn normalize_in_place(dg: &mut Array2<f32>, da: Option<&Array2<f32>>, alpha: f32) -> f32 {
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
    let scale = finite_max(dg) + NORM_EPS;
    let inv_g = 1.0 / scale;
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
    scale
}

/// `D = Dg/max(Dg)` or, with appearance, `(1-alpha) Dg/max(Dg) + alpha Da/max(Da)` (SPEC §3).
/// Each matrix is divided by its own largest finite value plus [`NORM_EPS`]. `alpha` is used
/// only when `da` is given (and has the same shape as `dg`).
pub fn normalized_distance(dg: &Array2<f32>, da: Option<&Array2<f32>>, alpha: f32) -> Array2<f32> {
    let mut d = dg.clone();
    let _ = normalize_in_place(&mut d, da, alpha);
    d
}

/// Minimum-cost one-to-one assignment: `min(n, m)` pairs `(row, col)`, sorted by row
/// ([`crate::core::lsa::assign`], on this thread's reusable solver). An empty side gives
/// no pairs. Non-finite entries never hang or panic: NaN and `+inf` are treated as worse
/// than every finite cost and `-inf` as better; callers validate their inputs before this
/// point anyway.
pub fn hungarian(cost: ArrayView2<f32>) -> Vec<(usize, usize)> {
    crate::core::lsa::assign(cost)
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
    let matches = assignment
        .iter()
        .filter(|p| p.score >= threshold)
        .map(|p| Match {
            a: p.a,
            b: p.b,
            score: p.score,
        })
        .collect();
    PairMatching {
        scores: dg,
        assignment,
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
        // Views as row ranges of one matrix, with an empty view and an unused row between.
        let x = array![
            [0.0f32, 1.0],
            [2.0, 3.0],
            [1.0, 1.0],
            [9.0, 9.0],
            [5.0, 0.0],
            [0.0, 5.0],
            [1.0, 2.0],
            [1.0, 3.0],
            [2.0, 4.0]
        ];
        let ranges = [0..2, 2..3, 3..3, 4..7, 7..9];
        // The same through a non-standard layout (a transposed copy viewed back).
        let xt = x.t().to_owned();
        for m in [x.view(), xt.t()] {
            let all = all_pairs_distances(m, &ranges);
            let mut k = 0;
            for a in 0..ranges.len() {
                for b in a + 1..ranges.len() {
                    let want = euclidean_distances(
                        x.slice(ndarray::s![ranges[a].clone(), ..]),
                        x.slice(ndarray::s![ranges[b].clone(), ..]),
                    );
                    assert_eq!(all[k].dim(), want.dim());
                    for (p, q) in all[k].iter().zip(want.iter()) {
                        assert!((p - q).abs() < 1e-5, "{a}-{b}: {p} vs {q}");
                    }
                    k += 1;
                }
            }
            assert_eq!(k, all.len());
        }
        assert!(all_pairs_distances(x.view(), &ranges[..1]).is_empty());
        // Zero-width embeddings: all distances are 0.
        let z = Array2::<f32>::zeros((3, 0));
        let d = all_pairs_distances(z.view(), &[0..1, 1..3]);
        assert_eq!(d[0], Array2::<f32>::zeros((1, 2)));
    }

    proptest! {
        #[test]
        fn all_pairs_distances_match_the_direct_formula(
            sizes in proptest::collection::vec(0usize..9, 2..9),
            dim in 1usize..40,
            seed in 0u64..1000,
        ) {
            let total: usize = sizes.iter().sum();
            let x = Array2::from_shape_fn((total, dim), |(i, j)| {
                (((i * 31 + j * 17) as u64 + seed) % 23) as f32 / 7.0 - 1.5
            });
            let mut ranges = Vec::new();
            let mut start = 0;
            for &n in &sizes {
                ranges.push(start..start + n);
                start += n;
            }
            let all = all_pairs_distances(x.view(), &ranges);
            let mut k = 0;
            for a in 0..ranges.len() {
                for b in a + 1..ranges.len() {
                    for (i, ri) in ranges[a].clone().enumerate() {
                        for (j, rj) in ranges[b].clone().enumerate() {
                            // Squared distances: the Gram form cancels near zero, so
                            // compare at the scale of the squared norms.
                            let direct: f32 = x.row(ri).iter().zip(x.row(rj))
                                .map(|(p, q)| (p - q) * (p - q)).sum();
                            let scale = 1.0 + x.row(ri).dot(&x.row(ri)) + x.row(rj).dot(&x.row(rj));
                            let got = all[k][(i, j)];
                            prop_assert!((got * got - direct).abs() < 1e-5 * scale, "{} vs {}", got * got, direct);
                        }
                    }
                    k += 1;
                }
            }
            prop_assert_eq!(k, all.len());
        }
    }

    #[test]
    fn finite_range_skips_nan_and_infinities() {
        let mut v: Vec<f32> = (0..20).map(|i| i as f32 - 5.0).collect();
        assert_eq!(finite_range(&v), Some((-5.0, 14.0)));
        v[3] = f32::NAN;
        v[17] = f32::INFINITY;
        v[19] = f32::NEG_INFINITY;
        assert_eq!(finite_range(&v), Some((-5.0, 13.0)));
        assert_eq!(finite_range(&[f32::NAN, f32::INFINITY]), None);
        assert_eq!(finite_range(&[]), None);
        assert_eq!(finite_range(&[f32::NAN, 2.0]), Some((2.0, 2.0)));
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

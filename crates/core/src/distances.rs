//! Pairwise distances (SPEC §3): Euclidean distances between two views' embeddings, all
//! camera pairs of a frame at once from a few large matrix products (`‖a‖² + ‖b‖² − 2ab`,
//! [`all_pairs_distances`], through the `gemm` crate), and max-normalisation with optional
//! appearance fusion, in place. [`crate::matching`] turns them into assignments.
use std::ops::Range;

use ndarray::{Array1, Array2, ArrayView1, ArrayView2, Zip};

/// Added to every normalising maximum so that an all-zero matrix stays finite (SPEC §3).
pub(crate) const NORM_EPS: f32 = 1e-6;

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
    let mut d = dot_t(a, b);
    Zip::from(d.rows_mut())
        .and(&norms_a)
        .for_each(|mut row, &na| {
            Zip::from(&mut row).and(&norms_b).for_each(|v, &nb| {
                *v = (na + nb - 2.0 * *v).max(0.0).sqrt();
            });
        });
    d
}

/// `a · bᵀ` through the `gemm` crate (the kernels [`all_pairs_distances`] uses; for the small
/// products of one camera or one pair, tens of rows, a few per cent faster than ndarray's
/// `dot`). Views in standard layout are read in place; others are copied first.
///
/// # Panics
/// When the widths differ (a programming error).
pub(crate) fn dot_t(a: ArrayView2<f32>, b: ArrayView2<f32>) -> Array2<f32> {
    assert_eq!(a.ncols(), b.ncols(), "dot_t: widths differ");
    let (m, n, dim) = (a.nrows(), b.nrows(), a.ncols());
    let (a, b) = (a.as_standard_layout(), b.as_standard_layout());
    let mut out = Array2::<f32>::zeros((m, n));
    let (a, b) = (
        a.as_slice().expect("standard layout is contiguous"),
        b.as_slice().expect("standard layout is contiguous"),
    );
    let out_flat = out.as_slice_mut().expect("freshly made");
    gram_block((a, m), (b, n), dim, out_flat, n);
    out
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
/// [`crate::FrameEmbeddings`] guarantees both).
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
        let rows = |r: Range<usize>| (&flat[r.start * dim..r.end * dim], r.len());
        gram_block(rows(rows_a), rows(rows_b), dim, &mut gram[at..], ld);
    }
    gram_halves(flat, dim, first, base, gram, ld);
    gram_halves(flat, dim, second, base, gram, ld);
}

/// `out[i * ld + j] = a[i] · b[j]` for the `m` rows of `a` and the `n` rows of `b` (`(rows,
/// count)`, row-major, `dim` values a row): one single-threaded `gemm` call (its kernels pick
/// the widest SIMD the CPU has at run time).
///
/// # Panics
/// When a matrix is shorter than its rows or the block exceeds `out` (a programming error).
fn gram_block(
    (a, m): (&[f32], usize),
    (b, n): (&[f32], usize),
    dim: usize,
    out: &mut [f32],
    ld: usize,
) {
    if m == 0 || n == 0 {
        return;
    }
    assert!(m * dim <= a.len() && n * dim <= b.len() && n <= ld);
    assert!((m - 1) * ld + n <= out.len());
    if dim == 0 {
        out.chunks_mut(ld).take(m).for_each(|r| r[..n].fill(0.0));
        return;
    }
    // SAFETY: with the asserts above, every element gemm reads (`m` rows of `a` and `n` of
    // `b`, `dim` values each) and writes (`m` rows of `n` values, row stride `ld`, in `out`)
    // is in bounds; `out` is borrowed mutably, so it aliases neither input.
    #[allow(unsafe_code)]
    unsafe {
        gemm::gemm(
            m,
            n,
            dim,
            out.as_mut_ptr(),
            1,
            ld as isize,
            false,
            a.as_ptr(),
            1,
            dim as isize,
            b.as_ptr(),
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
    finite_max_of(m.as_slice().expect("standard layout is contiguous"))
}

/// [`finite_max`] of values already flat (the memory reads the divisor of a pair's `S`).
pub(crate) fn finite_max_of(flat: &[f32]) -> f32 {
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
pub(crate) fn normalize_in_place(
    dg: &mut Array2<f32>,
    da: Option<&Array2<f32>>,
    alpha: f32,
) -> f32 {
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

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::{Array2, array};
    use proptest::prelude::*;

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

    #[test]
    fn dot_t_reads_views_of_any_layout() {
        let x = Array2::from_shape_fn((7, 5), |(i, j)| (i * 5 + j) as f32 * 0.25 - 3.0);
        let xt = x.t().to_owned();
        // Standard, transposed (column-major) and every-other-row views, against ndarray.
        for (a, b) in [
            (x.view(), x.view()),
            (xt.t(), x.slice(ndarray::s![1..4, ..])),
            (
                x.slice(ndarray::s![..;2, 1..]),
                xt.t().slice_move(ndarray::s![2.., 1..]),
            ),
        ] {
            let want = a.dot(&b.t());
            let got = dot_t(a, b);
            assert_eq!(got.dim(), want.dim());
            for (p, q) in got.iter().zip(want.iter()) {
                assert!((p - q).abs() < 1e-4, "{p} vs {q}");
            }
        }
        let none = Array2::<f32>::zeros((0, 5));
        assert_eq!(dot_t(none.view(), x.view()).dim(), (0, 7));
        let flat = Array2::<f32>::zeros((3, 0));
        assert_eq!(
            dot_t(flat.view(), flat.view()),
            Array2::<f32>::zeros((3, 3))
        );
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
}

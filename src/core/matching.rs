//! Pairwise distances, max-normalisation with optional appearance fusion, Hungarian
//! assignment and the confidence threshold (SPEC §3).
use ndarray::{Array2, ArrayView2};

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

/// Euclidean distances between the rows of `a` `[n, d]` and `b` `[m, d]`: `[n, m]`.
pub fn euclidean_distances(a: ArrayView2<f32>, b: ArrayView2<f32>) -> Array2<f32> {
    let _ = (a, b);
    todo!("foundation: core::matching")
}

/// `D = Dg/max(Dg)` or, with appearance, `(1-alpha) Dg/max(Dg) + alpha Da/max(Da)` (SPEC §3).
pub fn normalized_distance(dg: &Array2<f32>, da: Option<&Array2<f32>>, alpha: f32) -> Array2<f32> {
    let _ = (dg, da, alpha);
    todo!("foundation: core::matching")
}

/// Minimum-cost one-to-one assignment on a finite cost matrix: `min(n, m)` pairs `(row, col)`,
/// sorted by row.
pub fn hungarian(cost: ArrayView2<f32>) -> Vec<(usize, usize)> {
    let _ = cost;
    todo!("foundation: core::matching")
}

/// Full SPEC §3 matching of two views from their embeddings (and optional appearance
/// vectors, used only when both sides have them).
pub fn match_views(
    emb_a: ArrayView2<f32>,
    emb_b: ArrayView2<f32>,
    app_a: Option<ArrayView2<f32>>,
    app_b: Option<ArrayView2<f32>>,
    alpha: f32,
    threshold: f32,
) -> PairMatching {
    let _ = (emb_a, emb_b, app_a, app_b, alpha, threshold);
    todo!("foundation: core::matching")
}

//! One camera pair's shift profile: for every shift `δ` within the search range, the mean
//! Hungarian-matched embedding distance between camera `a` at frame `t` and camera `b` at
//! frame `t + δ`, over every `t` both have; its minimum, refined below one frame step, and
//! how clearly the minimum stands out.
use ndarray::{Array2, ArrayView2};

use super::{CameraSeries, OffsetConfig};
use crate::distances::euclidean_distances_with_norms;

/// A pair's profile and what it says.
#[derive(Debug, Clone, PartialEq)]
pub struct PairProfile {
    /// The shifts searched, in frame ids (multiples of the step, ascending).
    pub shifts: Vec<i64>,
    /// Mean matched distance at each shift (`NaN` where too few frames).
    pub costs: Vec<f32>,
    /// Frames scored at each shift.
    pub counts: Vec<usize>,
    /// Index into `shifts` of the minimum (`None`: no shift had enough frames).
    pub best: Option<usize>,
    /// Sub-step position of the minimum in frame ids (parabola through it and its neighbours).
    pub refined: Option<f32>,
    /// Paired z-score of the minimum against every shift at least two steps away (the
    /// smallest of them; 0 when there is none to compare with).
    pub z: f32,
    /// The frame ids of camera `a` profiled, ascending: the rows of `values`.
    pub frames: Vec<i64>,
    /// Per frame of `a` (rows) and shift (columns), the mean matched distance (`NaN` where
    /// `b` has no frame): what the costs average, kept so that a later look at the newest
    /// frames alone ([`crate::fit`]) costs no matching.
    pub values: Array2<f32>,
}

impl PairProfile {
    /// The shift at the minimum, in frame ids.
    pub fn delta(&self) -> Option<i64> {
        self.best.map(|i| self.shifts[i])
    }
}

/// Caps a z-score (a noiseless profile would give an infinite one).
const Z_CAP: f32 = 1_000.0;

/// The profile of cameras `a` and `b` on frame step `step` (see the module docs).
pub fn profile(a: &CameraSeries, b: &CameraSeries, step: i64, cfg: &OffsetConfig) -> PairProfile {
    let step = step.max(1);
    let m = i64::from(cfg.max_offset);
    let shifts: Vec<i64> = (-m..=m).filter_map(|k| k.checked_mul(step)).collect();
    // Per frame of `a` (rows) and shift (columns): the mean matched distance, NaN if `b` has
    // no frame there.
    let ts: Vec<i64> = a.frame_ids().collect();
    let mut values = Array2::from_elem((ts.len(), shifts.len()), f32::NAN);
    for (i, &t) in ts.iter().enumerate() {
        let Some((ea, na)) = a.get(t) else { continue };
        for (j, &s) in shifts.iter().enumerate() {
            let Some(frame) = t.checked_add(s) else {
                continue;
            };
            let Some((eb, nb)) = b.get(frame) else {
                continue;
            };
            let d = euclidean_distances_with_norms(ea.view(), eb.view(), na.view(), nb.view());
            let pairs = crate::lsa::assign(d.view());
            if pairs.is_empty() {
                continue;
            }
            let sum: f32 = pairs.iter().map(|&(r, c)| d[(r, c)]).sum();
            values[(i, j)] = sum / pairs.len() as f32;
        }
    }
    summarise(shifts, ts, values, step, cfg)
}

/// The profile's costs, minimum, refinement and z-score from the per-frame values.
fn summarise(
    shifts: Vec<i64>,
    frames: Vec<i64>,
    values: Array2<f32>,
    step: i64,
    cfg: &OffsetConfig,
) -> PairProfile {
    let (costs, counts): (Vec<f32>, Vec<usize>) = column_means(values.view(), cfg.min_frames)
        .into_iter()
        .map(|(mean, n)| (mean.unwrap_or(f32::NAN), n))
        .unzip();
    let best = costs
        .iter()
        .enumerate()
        .filter(|(_, c)| c.is_finite())
        .min_by(|x, y| x.1.total_cmp(y.1))
        .map(|(i, _)| i);
    let (refined, z) = match best {
        None => (None, 0.0),
        Some(b) => (
            Some(refine(&costs, b, shifts[b], step)),
            min_z(&values, b, cfg.min_frames),
        ),
    };
    PairProfile {
        shifts,
        costs,
        counts,
        best,
        refined,
        z,
        frames,
        values,
    }
}

/// Per column (shift) of `values`, the mean of its finite entries (`None` when fewer than
/// `min_frames`, at least one) and how many there are: a profile's cost at each shift.
pub(crate) fn column_means(
    values: ArrayView2<f32>,
    min_frames: usize,
) -> Vec<(Option<f32>, usize)> {
    values
        .columns()
        .into_iter()
        .map(|column| {
            let (n, sum) = column
                .iter()
                .filter(|v| v.is_finite())
                .fold((0usize, 0f64), |(n, s), &v| (n + 1, s + f64::from(v)));
            let mean = (n >= min_frames.max(1)).then(|| (sum / n as f64) as f32);
            (mean, n)
        })
        .collect()
}

/// The minimum's position below one step: the vertex of the parabola through the costs at
/// `best − 1`, `best`, `best + 1` (within half a step either way), or `best` itself at the
/// edge of the range or on a flat bottom.
fn refine(costs: &[f32], best: usize, shift: i64, step: i64) -> f32 {
    let at = shift as f32;
    if best == 0 || best + 1 >= costs.len() {
        return at;
    }
    let (l, c, r) = (costs[best - 1], costs[best], costs[best + 1]);
    let curvature = l - 2.0 * c + r;
    if !(l.is_finite() && r.is_finite()) || curvature <= f32::EPSILON {
        return at;
    }
    let vertex = (0.5 * (l - r) / curvature).clamp(-0.5, 0.5);
    at + vertex * step as f32
}

/// The smallest paired z-score of column `best` against every column at least two steps
/// away: per frame, the difference of their values; `mean / (sd / √n)` over the frames both
/// have (at least `min_frames`). 0 when no column qualifies or a difference is never positive.
fn min_z(values: &Array2<f32>, best: usize, min_frames: usize) -> f32 {
    let mut z_min = f32::INFINITY;
    for j in 0..values.ncols() {
        if j.abs_diff(best) < 2 {
            continue;
        }
        let diffs: Vec<f64> = values
            .rows()
            .into_iter()
            .filter_map(|row| {
                let (x, y) = (row[j], row[best]);
                (x.is_finite() && y.is_finite()).then(|| f64::from(x - y))
            })
            .collect();
        if diffs.len() < min_frames.max(2) {
            continue;
        }
        z_min = z_min.min(paired_z(&diffs));
    }
    if z_min.is_finite() {
        z_min.max(0.0)
    } else {
        0.0
    }
}

/// `mean / (sd / √n)` of `diffs`, capped; 0 for a zero or negative mean.
fn paired_z(diffs: &[f64]) -> f32 {
    let n = diffs.len() as f64;
    let mean = diffs.iter().sum::<f64>() / n;
    if mean <= 0.0 {
        return 0.0;
    }
    let var = diffs.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / (n - 1.0);
    let se = (var / n).sqrt();
    if se <= 0.0 {
        return Z_CAP;
    }
    ((mean / se) as f32).min(Z_CAP)
}

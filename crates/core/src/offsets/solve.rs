//! The joint fit: every confident pair measures `o_b − o_a`; weighted least squares over the
//! pairs linked to the reference gives each camera's offset, the pair that disagrees most is
//! dropped while it disagrees by more than [`OffsetConfig::outlier_steps`], and cameras no
//! confident pair reaches stay unknown.
use nalgebra::{DMatrix, DVector};

use super::{CameraOffset, OffsetConfig, OffsetEstimate, PairProfile, PairSummary, Unknown};

/// A z-score above this adds no more weight (the deepest pairs would otherwise drown the rest).
const WEIGHT_CAP: f32 = 50.0;

/// One measurement of the fit, in frame steps.
#[derive(Debug, Clone, Copy)]
struct Edge {
    pair: usize,
    a: usize,
    b: usize,
    delta: f64,
    weight: f64,
}

/// Offsets for `num_cameras` cameras from the pairs' profiles (`(a, b, profile)` with
/// `a ≠ b`), each camera's frame count, the frame step, and an optional reference camera
/// (default: the camera whose offset is the median of the known ones, so that the cameras
/// that disagree with the majority are the ones shown as shifted).
pub fn solve(
    num_cameras: usize,
    pairs: &[(usize, usize, PairProfile)],
    frames_per_camera: &[usize],
    step: i64,
    reference: Option<usize>,
    cfg: &OffsetConfig,
) -> OffsetEstimate {
    let step = step.max(1);
    let mut edges: Vec<Edge> = pairs
        .iter()
        .enumerate()
        .filter(|(_, (a, b, p))| a != b && *a < num_cameras && *b < num_cameras && p.z >= cfg.min_z)
        .filter_map(|(i, (a, b, p))| {
            Some(Edge {
                pair: i,
                a: *a,
                b: *b,
                delta: f64::from(p.refined?) / step as f64,
                weight: f64::from(p.z.min(WEIGHT_CAP)),
            })
        })
        .collect();
    let anchor = reference.unwrap_or_else(|| strongest(num_cameras, &edges));
    let offsets = loop {
        let member = component(num_cameras, anchor, &edges);
        let offsets = least_squares(num_cameras, anchor, &member, &edges);
        let worst = edges
            .iter()
            .enumerate()
            .filter(|(_, e)| member[e.a])
            .map(|(k, e)| (k, (offsets[e.b] - offsets[e.a] - e.delta).abs()))
            .max_by(|x, y| x.1.total_cmp(&y.1));
        match worst {
            Some((k, r)) if r > f64::from(cfg.outlier_steps) => {
                edges.remove(k);
            }
            _ => {
                break member
                    .iter()
                    .zip(&offsets)
                    .map(|(m, o)| m.then_some(*o))
                    .collect();
            }
        }
    };
    let (reference, offsets) = rebase(reference.unwrap_or(anchor), reference.is_some(), offsets);
    let cameras = (0..num_cameras)
        .map(|c| camera(c, &offsets, &edges, frames_per_camera, step, cfg))
        .collect();
    let used: Vec<usize> = edges.iter().map(|e| e.pair).collect();
    let pairs = pairs
        .iter()
        .enumerate()
        .map(|(i, (a, b, p))| PairSummary {
            a: *a,
            b: *b,
            delta: p.delta(),
            refined: p.refined,
            z: p.z,
            frames: p.best.map_or(0, |k| p.counts[k]),
            used: used.contains(&i),
        })
        .collect();
    OffsetEstimate {
        reference,
        step,
        cameras,
        pairs,
    }
}

/// The camera with the largest total weight of confident pairs (the lowest index on a tie).
fn strongest(num_cameras: usize, edges: &[Edge]) -> usize {
    let mut total = vec![0.0f64; num_cameras];
    for e in edges {
        total[e.a] += e.weight;
        total[e.b] += e.weight;
    }
    (0..num_cameras)
        .max_by(|&x, &y| total[x].total_cmp(&total[y]).then(y.cmp(&x)))
        .unwrap_or(0)
}

/// Which cameras the edges link to `anchor`.
fn component(num_cameras: usize, anchor: usize, edges: &[Edge]) -> Vec<bool> {
    let mut member = vec![false; num_cameras];
    if anchor >= num_cameras {
        return member;
    }
    member[anchor] = true;
    let mut grew = true;
    while grew {
        grew = false;
        for e in edges {
            if member[e.a] != member[e.b] {
                member[e.a] = true;
                member[e.b] = true;
                grew = true;
            }
        }
    }
    member
}

/// Weighted least squares `min Σ w (o_b − o_a − δ)²` with `o_anchor = 0`, over the cameras in
/// `member` (others stay 0): the normal equations (a weighted graph Laplacian with the anchor's
/// row and column removed, positive definite for a connected component) solved by Cholesky.
fn least_squares(num_cameras: usize, anchor: usize, member: &[bool], edges: &[Edge]) -> Vec<f64> {
    let unknowns: Vec<usize> = (0..num_cameras)
        .filter(|&c| member[c] && c != anchor)
        .collect();
    let index = |c: usize| unknowns.iter().position(|&u| u == c);
    let k = unknowns.len();
    let mut lhs = DMatrix::<f64>::zeros(k, k);
    let mut rhs = DVector::<f64>::zeros(k);
    for e in edges.iter().filter(|e| member[e.a] && member[e.b]) {
        let (ia, ib) = (index(e.a), index(e.b));
        for (i, sign) in [(ia, -1.0), (ib, 1.0)] {
            let Some(i) = i else { continue };
            lhs[(i, i)] += e.weight;
            rhs[i] += sign * e.weight * e.delta;
        }
        if let (Some(ia), Some(ib)) = (ia, ib) {
            lhs[(ia, ib)] -= e.weight;
            lhs[(ib, ia)] -= e.weight;
        }
    }
    // Not positive definite cannot happen for a connected component; all 0 keeps it total.
    let x = lhs
        .cholesky()
        .map_or_else(|| DVector::zeros(k), |c| c.solve(&rhs));
    let mut offsets = vec![0.0; num_cameras];
    for (u, &c) in unknowns.iter().enumerate() {
        offsets[c] = x[u];
    }
    offsets
}

/// Moves the zero: onto `reference` when one was asked for, else onto the known camera whose
/// rounded offset is the (lower) median of the known ones. Returns the reference and the
/// offsets relative to it.
fn rebase(anchor: usize, fixed: bool, offsets: Vec<Option<f64>>) -> (usize, Vec<Option<f64>>) {
    let reference = if fixed {
        anchor
    } else {
        let mut known: Vec<(i64, usize)> = offsets
            .iter()
            .enumerate()
            .filter_map(|(c, o)| o.map(|o| (o.round() as i64, c)))
            .collect();
        known.sort_unstable();
        match known.get(known.len().saturating_sub(1) / 2) {
            Some(&(_, c)) => c,
            None => anchor,
        }
    };
    let zero = offsets.get(reference).copied().flatten().unwrap_or(0.0);
    let offsets = offsets.into_iter().map(|o| o.map(|o| o - zero)).collect();
    (reference, offsets)
}

/// One camera's entry: its offset in ids, its pairs' support and agreement.
fn camera(
    c: usize,
    offsets: &[Option<f64>],
    edges: &[Edge],
    frames_per_camera: &[usize],
    step: i64,
    cfg: &OffsetConfig,
) -> CameraOffset {
    let mine: Vec<&Edge> = edges.iter().filter(|e| e.a == c || e.b == c).collect();
    let few = frames_per_camera.get(c).copied().unwrap_or(0) < cfg.min_frames;
    let Some(o) = offsets[c].filter(|_| !few && !mine.is_empty()) else {
        return CameraOffset {
            camera: c,
            frames: None,
            refined: None,
            pairs: 0,
            z: 0.0,
            residual: 0.0,
            confidence: 0.0,
            unknown: Some(if few {
                Unknown::TooFewFrames
            } else {
                Unknown::NoConfidentPair
            }),
        };
    };
    let residuals: Vec<f64> = mine
        .iter()
        .filter_map(|e| Some(offsets[e.b]? - offsets[e.a]? - e.delta))
        .collect();
    let residual =
        (residuals.iter().map(|r| r * r).sum::<f64>() / residuals.len().max(1) as f64).sqrt();
    let z = mine.iter().map(|e| e.weight).fold(0.0f64, f64::max) as f32;
    let agreement = (1.0 - residual / f64::from(cfg.outlier_steps)).clamp(0.0, 1.0) as f32;
    CameraOffset {
        camera: c,
        frames: Some(o.round() as i64 * step),
        refined: Some((o * step as f64) as f32),
        pairs: mine.len(),
        z,
        residual: residual as f32,
        confidence: (1.0 - (-z / 8.0).exp()) * agreement,
        unknown: None,
    }
}

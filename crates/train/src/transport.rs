//! **[ours, after SuperGlue's `log_optimal_transport`]** The soft counterpart of the Hungarian
//! matching for the synchronization loss early in the first stage: entropy-regularised optimal
//! transport between two images' boxes, with a dustbin on each side so that images with
//! different box counts balance.
//!
//! With random early embeddings the Hungarian matching of two images is decided by ties, and
//! which tie the solver breaks shapes the whole run. The transport plan instead spreads each
//! box's mass over the boxes it is nearly as close to; as the temperature falls towards 0 the
//! plan becomes the Hungarian assignment (every real box matched while the dustbin costs more
//! than any real pair). The plan is computed on detached distances and used as fixed weights,
//! so the loss's gradient is the plan itself: no differentiation through the iterations.
use ndarray::{Array2, ArrayView2};

/// Cost of sending a box to the other side's dustbin, in units of the max-normalised distance
/// (every real pair costs at most 1, so in the cold limit every box of the smaller side is
/// matched, as with the Hungarian).
const BIN_COST: f32 = 1.0;

/// Sinkhorn iterations: enough for the plan's marginals to settle at the temperatures used,
/// down to [`MIN_TEMPERATURE`] (the tests check them).
const ITERATIONS: usize = 100;

/// Below this temperature the plan is the Hungarian assignment in all but name (and Sinkhorn
/// would need many more iterations to show it): [`temperature`] hands over to the Hungarian.
const MIN_TEMPERATURE: f32 = 0.02;

/// Plan entries below this share of a box's unit mass are dropped (they weigh nothing in the
/// loss and would only add pairs to it).
const MIN_MASS: f32 = 1e-3;

/// `log Σ exp(x)` over an iterator, stable for large negative values.
fn log_sum_exp(xs: impl Iterator<Item = f32> + Clone) -> f32 {
    let m = xs.clone().fold(f32::NEG_INFINITY, f32::max);
    if m == f32::NEG_INFINITY {
        return m;
    }
    m + xs.map(|x| (x - m).exp()).sum::<f32>().ln()
}

/// The transport plan between the rows and columns of `cost` (max-normalised distances, within
/// [0, 1]) at temperature `eps > 0`: `(row, column, mass)` for every real pair carrying at least
/// [`MIN_MASS`] of a box's unit mass. Empty when either side has no box or `eps` is not a
/// positive finite number.
pub(crate) fn soft_assignment(cost: ArrayView2<f32>, eps: f32) -> Vec<(usize, usize, f32)> {
    let (n, m) = cost.dim();
    if n == 0 || m == 0 || !(eps.is_finite() && eps > 0.0) {
        return Vec::new();
    }
    // Scores of the (n + 1) × (m + 1) coupling; the last row and column are the dustbins, whose
    // own crossing costs nothing.
    let z = Array2::from_shape_fn((n + 1, m + 1), |(i, j)| match (i < n, j < m) {
        (true, true) => {
            let c = cost[(i, j)];
            -(if c.is_finite() { c } else { 1.0 }) / eps
        }
        (false, false) => 0.0,
        _ => -BIN_COST / eps,
    });
    let norm = -((n + m) as f32).ln();
    let log_mu: Vec<f32> = (0..=n)
        .map(|i| if i < n { norm } else { (m as f32).ln() + norm })
        .collect();
    let log_nu: Vec<f32> = (0..=m)
        .map(|j| if j < m { norm } else { (n as f32).ln() + norm })
        .collect();
    let (mut u, mut v) = (vec![0f32; n + 1], vec![0f32; m + 1]);
    for _ in 0..ITERATIONS {
        for i in 0..=n {
            u[i] = log_mu[i] - log_sum_exp((0..=m).map(|j| z[(i, j)] + v[j]));
        }
        for j in 0..=m {
            v[j] = log_nu[j] - log_sum_exp((0..=n).map(|i| z[(i, j)] + u[i]));
        }
    }
    let scale = (n + m) as f32;
    let mut out = Vec::new();
    for i in 0..n {
        for j in 0..m {
            let mass = (z[(i, j)] + u[i] + v[j]).exp() * scale;
            if mass >= MIN_MASS {
                out.push((i, j, mass));
            }
        }
    }
    out
}

/// The temperature of the soft assignment at `epoch` (1-based) of a first stage of `epochs`:
/// `start` falling linearly to 0 over the first `fraction` of the stage, `None` (the Hungarian)
/// once it is below [`MIN_TEMPERATURE`], or when `fraction` or `start` is 0.
pub(crate) fn temperature(epoch: usize, epochs: usize, fraction: f64, start: f32) -> Option<f32> {
    let soft_epochs = (fraction * epochs as f64).round();
    if soft_epochs < 1.0 || start <= 0.0 || epoch as f64 > soft_epochs {
        return None;
    }
    let left = 1.0 - (epoch as f64 - 1.0) / soft_epochs;
    Some(start * left as f32).filter(|&t| t >= MIN_TEMPERATURE)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::matching::hungarian;
    use ndarray::array;

    fn row_mass(plan: &[(usize, usize, f32)], i: usize) -> f32 {
        plan.iter().filter(|p| p.0 == i).map(|p| p.2).sum()
    }

    #[test]
    fn a_cold_plan_is_the_hungarian_assignment() {
        // Greedy would take (0, 0); the optimum is (0, 1), (1, 0).
        let c = array![[0.1f32, 0.2], [0.15, 0.9]];
        let plan = soft_assignment(c.view(), MIN_TEMPERATURE);
        let hard: Vec<(usize, usize)> = plan
            .iter()
            .filter(|p| p.2 > 0.5)
            .map(|p| (p.0, p.1))
            .collect();
        assert_eq!(hard, hungarian(c.view()));
        for i in 0..2 {
            assert!((row_mass(&plan, i) - 1.0).abs() < 0.02, "{plan:?}");
        }
    }

    #[test]
    fn a_warm_plan_spreads_mass_over_near_ties_and_keeps_the_marginals() {
        // Rows 0 and 1 are equally close to both columns: a tie the Hungarian breaks arbitrarily.
        let c = array![[0.3f32, 0.3, 1.0], [0.3, 0.3, 1.0]];
        let plan = soft_assignment(c.view(), 0.1);
        let m = |i, j| {
            plan.iter()
                .find(|p| p.0 == i && p.1 == j)
                .map_or(0.0, |p| p.2)
        };
        assert!(
            (m(0, 0) - m(0, 1)).abs() < 1e-3 && m(0, 0) > 0.3,
            "{plan:?}"
        );
        assert!(m(0, 2) < m(0, 0));
        // Each real box carries at most its unit mass; the smaller side is (nearly) all matched.
        for i in 0..2 {
            let r = row_mass(&plan, i);
            assert!(r <= 1.0 + 1e-2 && r > 0.9, "row {i}: {r}");
        }
    }

    #[test]
    fn rectangular_and_degenerate_inputs_are_bounded() {
        let c = array![[0.0f32], [1.0], [0.5]];
        let plan = soft_assignment(c.view(), MIN_TEMPERATURE);
        assert!(plan.iter().all(|p| p.2.is_finite() && p.2 <= 1.0 + 1e-2));
        assert!(row_mass(&plan, 0) > 0.9, "{plan:?}");
        let empty = Array2::<f32>::zeros((0, 3));
        assert!(soft_assignment(empty.view(), 0.1).is_empty());
        assert!(soft_assignment(c.view(), 0.0).is_empty());
        assert!(soft_assignment(c.view(), f32::NAN).is_empty());
        let bad = array![[f32::NAN, 0.2], [0.1, f32::INFINITY]];
        assert!(
            soft_assignment(bad.view(), 0.1)
                .iter()
                .all(|p| p.2.is_finite())
        );
    }

    #[test]
    fn the_temperature_falls_to_the_hungarian() {
        assert_eq!(temperature(1, 100, 0.25, 0.2), Some(0.2));
        let mid = temperature(13, 100, 0.25, 0.2).unwrap();
        assert!(mid > 0.0 && mid < 0.2);
        assert!(temperature(23, 100, 0.25, 0.2).unwrap() > MIN_TEMPERATURE);
        assert_eq!(temperature(24, 100, 0.25, 0.2), None, "below the minimum");
        assert_eq!(temperature(26, 100, 0.25, 0.2), None);
        // Past the first stage (self-training) even a whole-stage fraction hands over.
        assert_eq!(temperature(101, 100, 1.0, 0.2), None);
        assert_eq!(temperature(1, 100, 0.0, 0.2), None);
        assert_eq!(temperature(1, 100, 0.25, 0.0), None);
    }
}

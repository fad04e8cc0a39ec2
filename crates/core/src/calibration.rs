//! **[ours]** A match confidence that means the same thing in every camera pair and every
//! scene density: `P(same person | d)`, the probability that a Hungarian pair at raw geometric
//! embedding distance `d` is one person, estimated with no labels.
//!
//! SPEC §3's `S = 1 − D/max D` is relative to the other boxes of the pair: with one person per
//! view `S ≈ 0` even for a perfect match, and the same `S` means different things in a crowd
//! and in a corridor. The raw distance `d` does not depend on the other boxes. Its meaning is
//! learned from the one free signal of the method (SPEC §4):
//! - Hungarian pairs between **synchronized** images of two cameras are a mixture of true
//!   matches and false ones (people seen by one camera only, mismatches);
//! - Hungarian pairs between **time-shifted** images (5–20 frames apart) are all false.
//!
//! So `f_sync(d) = π f_true(d) + (1 − π) f_false(d)` with `f_false ≈ f_shift`, and
//! `P(true | d) = 1 − (1 − π) f_shift(d) / f_sync(d)`. The false share `1 − π` is read where
//! true matches are rare: beyond the median shifted distance. Densities are histograms on
//! quantile bins of the pooled samples; the estimate is made non-increasing in `d` (pool
//! adjacent violators, weighted by bin counts) and stored as a piecewise-linear table in the
//! model file (`crossview.calibration`, SPEC §8).
use serde::{Deserialize, Serialize};

use crate::{Error, Result};

/// Quantile bins of the pooled distances used by [`Calibration::fit`].
const BINS: usize = 32;
/// Fewest samples of each kind [`Calibration::fit`] accepts.
pub(crate) const MIN_SAMPLES: usize = 50;

/// `P(same person | raw geometric distance)` of a Hungarian pair, as a piecewise-linear,
/// non-increasing table (constant beyond the first and last knots).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// Knot distances, strictly increasing.
    pub distances: Vec<f32>,
    /// `P(same person)` at each knot, in [0, 1], non-increasing.
    pub probabilities: Vec<f32>,
    /// Estimated share of synchronized Hungarian pairs that are not one person.
    pub false_share: f32,
    /// Number of synchronized and of time-shifted pairs the table was fitted on.
    pub samples: [usize; 2],
}

impl Calibration {
    /// Fits the table from the raw distances of Hungarian pairs between synchronized images
    /// (`synchronized`) and between time-shifted images (`shifted`). Non-finite values are
    /// ignored; fewer than [`MIN_SAMPLES`] finite values of either kind is an error.
    pub fn fit(synchronized: &[f32], shifted: &[f32]) -> Result<Calibration> {
        let finite = |v: &[f32]| -> Vec<f32> {
            let mut v: Vec<f32> = v.iter().copied().filter(|x| x.is_finite()).collect();
            v.sort_unstable_by(f32::total_cmp);
            v
        };
        let (sync, shift) = (finite(synchronized), finite(shifted));
        if sync.len() < MIN_SAMPLES || shift.len() < MIN_SAMPLES {
            return Err(Error::invalid(
                "calibration",
                format!(
                    "needs at least {MIN_SAMPLES} synchronized and {MIN_SAMPLES} time-shifted pairs, got {} and {}",
                    sync.len(),
                    shift.len()
                ),
            ));
        }
        let mut pooled: Vec<f32> = sync.iter().chain(&shift).copied().collect();
        pooled.sort_unstable_by(f32::total_cmp);
        let mut edges: Vec<f32> = (0..=BINS)
            .map(|k| quantile(&pooled, k as f64 / BINS as f64))
            .collect();
        edges.dedup();
        if edges.len() < 2 {
            // Every distance is the same: nothing separates true from false.
            let d = pooled[0];
            return Ok(Calibration {
                distances: vec![d],
                probabilities: vec![0.0],
                false_share: 1.0,
                samples: [sync.len(), shift.len()],
            });
        }
        let hist = |v: &[f32]| -> Vec<f64> {
            let mut h = vec![0f64; edges.len() - 1];
            for &x in v {
                // Bin k holds [edges[k], edges[k+1]); the last bin also holds its upper edge.
                let k = edges.partition_point(|&e| e <= x).saturating_sub(1);
                let last = h.len() - 1;
                h[k.min(last)] += 1.0;
            }
            h
        };
        let (hs, hf) = (hist(&sync), hist(&shift));
        let median_shift = quantile(&shift, 0.5);
        let above = |v: &[f32]| v.len() - v.partition_point(|&x| x <= median_shift);
        let tail_shift = above(&shift) as f64 / shift.len() as f64;
        let false_share = if tail_shift > 0.0 {
            (above(&sync) as f64 / sync.len() as f64 / tail_shift).min(1.0)
        } else {
            1.0
        };
        let (ns, nf) = (sync.len() as f64, shift.len() as f64);
        let raw: Vec<f64> = hs
            .iter()
            .zip(&hf)
            .map(|(&s, &f)| {
                if s == 0.0 {
                    0.0
                } else {
                    (1.0 - false_share * (f / nf) / (s / ns)).clamp(0.0, 1.0)
                }
            })
            .collect();
        let weights: Vec<f64> = hs.iter().zip(&hf).map(|(s, f)| s + f).collect();
        let probabilities = non_increasing(&raw, &weights)
            .into_iter()
            .map(|p| p as f32)
            .collect();
        let distances = edges.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect();
        let cal = Calibration {
            distances,
            probabilities,
            false_share: false_share as f32,
            samples: [sync.len(), shift.len()],
        };
        cal.validate()?;
        Ok(cal)
    }

    /// `P(same person)` at distance `d`: linear between knots, constant outside them.
    /// A non-finite `d` gets the probability of the farthest knot.
    pub fn probability(&self, d: f32) -> f32 {
        let (xs, ps) = (&self.distances, &self.probabilities);
        let Some(&last) = ps.last() else { return 0.0 };
        if !d.is_finite() || d >= xs[xs.len() - 1] {
            return last;
        }
        if d <= xs[0] {
            return ps[0];
        }
        let k = xs.partition_point(|&x| x <= d);
        let (x0, x1, p0, p1) = (xs[k - 1], xs[k], ps[k - 1], ps[k]);
        p0 + (p1 - p0) * (d - x0) / (x1 - x0)
    }

    /// The largest distance whose probability is at least `p` (the table is non-increasing,
    /// so `probability(d) ≥ p` exactly when `d ≤ reach(p)`): `+∞` when even the farthest knot
    /// reaches `p`, `−∞` when not even the nearest does (or `p` is NaN).
    pub fn reach(&self, p: f32) -> f32 {
        let (xs, ps) = (&self.distances, &self.probabilities);
        match (ps.first(), ps.last()) {
            (Some(_), Some(&last)) if last >= p => f32::INFINITY,
            (Some(&first), _) if first >= p => {
                let k = ps.partition_point(|&q| q >= p);
                let (x0, x1, p0, p1) = (xs[k - 1], xs[k], ps[k - 1], ps[k]);
                x0 + (x1 - x0) * (p0 - p) / (p0 - p1)
            }
            _ => f32::NEG_INFINITY,
        }
    }

    /// Checks the table's invariants (what a model file must hold to be trusted).
    pub fn validate(&self) -> Result<()> {
        let bad = |why: String| Error::invalid("calibration", why);
        if self.distances.is_empty() || self.distances.len() != self.probabilities.len() {
            return Err(bad(format!(
                "needs as many probabilities as distances (at least one), got {} and {}",
                self.probabilities.len(),
                self.distances.len()
            )));
        }
        if self.distances.iter().any(|d| !d.is_finite())
            || self.distances.windows(2).any(|w| w[1] <= w[0])
        {
            return Err(bad(
                "distances must be finite and strictly increasing".into()
            ));
        }
        if self.probabilities.iter().any(|p| !(0.0..=1.0).contains(p))
            || self.probabilities.windows(2).any(|w| w[1] > w[0])
        {
            return Err(bad(
                "probabilities must lie in [0, 1] and not increase with distance".into(),
            ));
        }
        if !(0.0..=1.0).contains(&self.false_share) {
            return Err(bad(format!(
                "false_share must lie in [0, 1], got {}",
                self.false_share
            )));
        }
        Ok(())
    }
}

/// The `q`-quantile of sorted `v` (linear interpolation).
fn quantile(v: &[f32], q: f64) -> f32 {
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    let t = (pos - lo as f64) as f32;
    v[lo] + (v[hi] - v[lo]) * t
}

/// The weighted least-squares non-increasing fit of `y` (pool adjacent violators).
fn non_increasing(y: &[f64], w: &[f64]) -> Vec<f64> {
    // (mean, weight, count) blocks; a block that rises above its predecessor is pooled.
    let mut blocks: Vec<(f64, f64, usize)> = Vec::with_capacity(y.len());
    for (&v, &wt) in y.iter().zip(w) {
        blocks.push((v, wt.max(1e-12), 1));
        while blocks.len() > 1 {
            let (b, a) = (blocks[blocks.len() - 1], blocks[blocks.len() - 2]);
            if b.0 <= a.0 {
                break;
            }
            blocks.truncate(blocks.len() - 2);
            let wt = a.1 + b.1;
            blocks.push(((a.0 * a.1 + b.0 * b.1) / wt, wt, a.2 + b.2));
        }
    }
    blocks
        .into_iter()
        .flat_map(|(v, _, n)| std::iter::repeat_n(v, n))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::{Distribution, Normal};

    /// Synchronized pairs: 60 % true (near 1), 40 % false (near 5); shifted: all false.
    fn samples(seed: u64) -> (Vec<f32>, Vec<f32>) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let t = Normal::new(1.0f32, 0.4).unwrap();
        let f = Normal::new(5.0f32, 1.0).unwrap();
        let sync = (0..4000)
            .map(|_| {
                if rng.random::<f32>() < 0.6 {
                    t.sample(&mut rng).abs()
                } else {
                    f.sample(&mut rng).abs()
                }
            })
            .collect();
        let shift = (0..4000).map(|_| f.sample(&mut rng).abs()).collect();
        (sync, shift)
    }

    #[test]
    fn separates_true_from_false_distances() {
        let (sync, shift) = samples(1);
        let cal = Calibration::fit(&sync, &shift).unwrap();
        assert!(cal.probability(0.8) > 0.9, "{cal:?}");
        assert!(cal.probability(6.0) < 0.1, "{cal:?}");
        assert!((cal.false_share - 0.4).abs() < 0.1, "{}", cal.false_share);
        // Non-increasing everywhere, bounded, finite for any input.
        let mut last = 1.0f32;
        for k in 0..200 {
            let p = cal.probability(k as f32 * 0.05);
            assert!((0.0..=1.0).contains(&p) && p <= last + 1e-6);
            last = p;
        }
        for d in [f32::NAN, f32::INFINITY, -1.0, 1e30] {
            assert!((0.0..=1.0).contains(&cal.probability(d)));
        }
    }

    #[test]
    fn reach_is_where_the_probability_falls_below() {
        let (s, f) = samples(3);
        let cal = Calibration::fit(&s, &f).unwrap();
        for p in [0.0f32, 0.05, 0.3, 0.5, 0.9, 0.99, 1.0, 1.5] {
            let r = cal.reach(p);
            for k in 0..400 {
                let d = k as f32 * 0.01;
                assert_eq!(cal.probability(d) >= p, d <= r, "p {p} d {d} reach {r}");
            }
        }
        assert_eq!(cal.reach(f32::NAN), f32::NEG_INFINITY);
    }

    #[test]
    fn serde_round_trip_and_validation() {
        let (sync, shift) = samples(2);
        let cal = Calibration::fit(&sync, &shift).unwrap();
        let back: Calibration =
            serde_json::from_str(&serde_json::to_string(&cal).unwrap()).unwrap();
        assert_eq!(back, cal);
        let mut bad = cal.clone();
        bad.probabilities[0] = 1.5;
        assert!(bad.validate().is_err());
        let mut bad = cal.clone();
        bad.distances.reverse();
        assert!(bad.validate().is_err());
        let mut bad = cal;
        bad.probabilities.pop();
        assert!(bad.validate().is_err());
    }

    #[test]
    fn too_few_or_degenerate_samples() {
        assert!(Calibration::fit(&[1.0; 10], &[2.0; 100]).is_err());
        assert!(Calibration::fit(&[f32::NAN; 100], &[2.0; 100]).is_err());
        let flat = Calibration::fit(&[3.0; 100], &[3.0; 100]).unwrap();
        assert_eq!(flat.probability(3.0), 0.0);
    }

    #[test]
    fn pool_adjacent_violators() {
        assert_eq!(
            non_increasing(&[1.0, 0.5, 0.7, 0.2], &[1.0; 4]),
            vec![1.0, 0.6, 0.6, 0.2]
        );
    }
}

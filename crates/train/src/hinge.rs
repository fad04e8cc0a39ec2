//! The triplet hinge of SPEC §4's synchronization and edge losses, batched: each triplet's two
//! sides are (weighted) means of pair distances, computed in one pass over every pair.
use candle_core::{D, Tensor};

use crate::model::ce;
use crossview_core::Result;

/// Triplet margin (SPEC §4).
pub(crate) const MARGIN: f32 = 1.0;

/// Pairs of embedding rows whose mean distance forms one side of a triplet hinge:
/// `delta[t] = mean_pos d - mean_neg d`, `loss = Σ_t mask[t] · relu(delta[t] + margin) / T`.
#[derive(Debug, Clone, Default)]
pub(crate) struct HingeSet {
    left: Vec<u32>,
    right: Vec<u32>,
    /// `(triplet, coefficient)` per pair.
    coef: Vec<(usize, f32)>,
    /// Triplets with both a positive and a negative side.
    valid: Vec<bool>,
}

impl HingeSet {
    /// An empty set for `triplets` triplets.
    pub fn new(triplets: usize) -> Self {
        HingeSet {
            valid: vec![false; triplets],
            ..Default::default()
        }
    }

    /// Adds triplet `t`'s positive pairs and negative pairs (row indices into one
    /// embedding matrix). A triplet counts only when both lists are non-empty.
    pub fn add(&mut self, t: usize, pos: &[(u32, u32)], neg: &[(u32, u32)]) {
        let unit = |l: &[(u32, u32)]| l.iter().map(|&(a, b)| (a, b, 1.0)).collect::<Vec<_>>();
        self.add_weighted(t, &unit(pos), &unit(neg));
    }

    /// Adds triplet `t` with weighted pairs `(left, right, weight)`: each side's distance is
    /// the weighted mean of its pairs' (a transport plan's soft assignment). A triplet counts
    /// only when both sides carry positive weight.
    pub fn add_weighted(&mut self, t: usize, pos: &[(u32, u32, f32)], neg: &[(u32, u32, f32)]) {
        let total = |l: &[(u32, u32, f32)]| l.iter().map(|p| p.2).sum::<f32>();
        let (wp, wn) = (total(pos), total(neg));
        if !(wp > 0.0 && wn > 0.0 && wp.is_finite() && wn.is_finite()) {
            return;
        }
        self.valid[t] = true;
        for (list, sign) in [(pos, 1.0 / wp), (neg, -1.0 / wn)] {
            for &(l, r, w) in list {
                self.left.push(l);
                self.right.push(r);
                self.coef.push((t, sign * w));
            }
        }
    }

    /// True when no triplet contributes.
    pub fn is_empty(&self) -> bool {
        self.left.is_empty()
    }

    /// The hinge loss summed over valid triplets and divided by `divisor` (the batch size).
    pub fn loss(&self, emb: &Tensor, divisor: usize) -> Result<Tensor> {
        let dev = emb.device();
        let t = self.valid.len();
        if self.is_empty() {
            return Tensor::zeros((), candle_core::DType::F32, dev).map_err(ce);
        }
        let p = self.left.len();
        let mut m = vec![0f32; t * p];
        for (i, &(tri, c)) in self.coef.iter().enumerate() {
            m[tri * p + i] = c;
        }
        let mask: Vec<f32> = self.valid.iter().map(|&v| f32::from(u8::from(v))).collect();
        let run = || -> candle_core::Result<Tensor> {
            let l = Tensor::from_slice(&self.left, p, dev)?;
            let r = Tensor::from_slice(&self.right, p, dev)?;
            let diff = (emb.index_select(&l, 0)? - emb.index_select(&r, 0)?)?;
            let d = (diff.sqr()?.sum_keepdim(D::Minus1)? + 1e-12)?.sqrt()?; // [P, 1]
            let m = Tensor::from_vec(m, (t, p), dev)?;
            let delta = m.matmul(&d)?.squeeze(1)?; // [T]
            let hinge = (delta + MARGIN as f64)?.relu()?;
            let mask = Tensor::from_vec(mask, t, dev)?;
            (hinge * mask)?.sum_all()? / divisor as f64
        };
        run().map_err(ce)
    }
}

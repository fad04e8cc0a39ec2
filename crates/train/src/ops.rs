//! The encoder's steps as few candle operations with one-pass gradients (a training step's time
//! was mostly element-wise passes and the graph's gradient bookkeeping, not matrix products):
//! - [`residual_block`]: a whole block, `ReLU(LayerNorm(x @ w + b + x))`, as one node of the
//!   graph. The LayerNorm + ReLU composed from candle's operations took eight tensors forward
//!   and about twice that backward; and candle's backward pass adds every gradient an
//!   operation hands back to a freshly zeroed buffer, so a block as four nodes (product, bias,
//!   residual, normalisation) paid for five such buffers of the activations' size, as one node
//!   for one. It keeps its normalised pre-activation, so its gradient redoes neither the
//!   product nor the rows' statistics.
//! - [`add_bias`]: `x + b` for each row, whose gradient for `b` sums the rows in one
//!   contiguous pass (candle's reduction over the first axis, which `broadcast_add`'s gradient
//!   uses, took about 50× its reduction over the last on a `[500, 64]` gradient).
use std::sync::{Arc, OnceLock};

use candle_core::backend::BackendStorage;
use candle_core::{CpuStorage, CustomOp1, CustomOp2, CustomOp3, Layout, Shape, Tensor};

/// One residual block of the encoder, `ReLU(LayerNorm(x @ w + b + x))` over the last axis (no
/// scale or shift: SPEC §2's block), as one operation: `x` `[N, G]`, `w` `[G, G]`, `b` `[G]`,
/// float32.
pub(crate) fn residual_block(
    x: &Tensor,
    w: &Tensor,
    b: &Tensor,
    eps: f32,
) -> candle_core::Result<Tensor> {
    let op = ResidualBlock {
        eps,
        saved: OnceLock::new(),
    };
    x.contiguous()?
        .apply_op3(&w.contiguous()?, &b.contiguous()?, op)
}

/// `x + b` for every row of `x` (`[N, G]`, float32) and `b` (`[G]`).
pub(crate) fn add_bias(x: &Tensor, b: &Tensor) -> candle_core::Result<Tensor> {
    x.contiguous()?.apply_op2(&b.contiguous()?, AddBias)
}

/// The forward operation of [`add_bias`]; the gradient of `b` is [`SumRows`].
struct AddBias;

/// The sum of the rows of `[N, G]`: `[G]`; not differentiable itself.
struct SumRows;

impl CustomOp2 for AddBias {
    fn name(&self) -> &'static str {
        "add-bias"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, width) = rows(s1, l1)?;
        let (b, _) = rows(s2, l2)?;
        if b.len() != width {
            return Err(candle_core::Error::Msg("add_bias: bias length".into()));
        }
        let mut out = x.to_vec();
        for row in out.chunks_exact_mut(width) {
            for (y, b) in row.iter_mut().zip(b) {
                *y += b;
            }
        }
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    fn bwd(
        &self,
        _x: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>)> {
        let db = grad.contiguous()?.apply_op1_no_bwd(&SumRows)?;
        Ok((Some(grad.clone()), Some(db)))
    }
}

impl CustomOp1 for SumRows {
    fn name(&self) -> &'static str {
        "sum-rows"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, width) = rows(storage, layout)?;
        let mut sum = vec![0f32; width];
        for row in x.chunks_exact(width) {
            for (s, v) in sum.iter_mut().zip(row) {
                *s += v;
            }
        }
        Ok((CpuStorage::F32(sum), Shape::from(width)))
    }
}

/// The forward operation of [`residual_block`]. It keeps what its gradient needs, so the
/// gradient neither redoes the product nor the rows' statistics.
struct ResidualBlock {
    eps: f32,
    saved: OnceLock<Arc<Normalised>>,
}

/// The block's pre-activation normalised, `x̂ = (pre − mean) · inv`, and each row's `inv =
/// 1 / sqrt(variance + eps)`.
struct Normalised {
    xhat: Vec<f32>,
    inv: Vec<f32>,
}

/// The gradient of the block's pre-activation given its output's; not differentiable itself.
struct NormaliseReluGrad(Arc<Normalised>);

/// The row-major float32 values of a contiguous layout, and the length of its last axis.
fn rows<'a>(storage: &'a CpuStorage, layout: &Layout) -> candle_core::Result<(&'a [f32], usize)> {
    let (start, end) = layout
        .contiguous_offsets()
        .ok_or_else(|| candle_core::Error::Msg("a strided input to a fused operation".into()))?;
    let values = &storage.as_slice::<f32>()?[start..end];
    let width = layout.dims().last().copied().unwrap_or(1).max(1);
    Ok((values, width))
}

/// Lanes of the sums below: eight independent accumulators, which the compiler keeps in one
/// vector register (a single running sum is one long chain of dependent additions).
const LANES: usize = 8;

/// `Σ f(a_i, b_i)` over two rows of equal length, summed in [`LANES`] lanes.
fn lane_sum(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> f32) -> f32 {
    let mut acc = [0f32; LANES];
    let (ca, cb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
    let tail: f32 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(&x, &y)| f(x, y))
        .sum();
    for (x, y) in ca.zip(cb) {
        for k in 0..LANES {
            acc[k] += f(x[k], y[k]);
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// The mean and `1 / sqrt(variance + eps)` of one row (two passes, as LayerNorm defines it).
fn moments(row: &[f32], eps: f32) -> (f32, f32) {
    let n = row.len() as f32;
    let mean = lane_sum(row, row, |v, _| v) / n;
    let var = lane_sum(row, row, |v, _| (v - mean) * (v - mean)) / n;
    (mean, 1.0 / (var + eps).sqrt())
}

impl CustomOp3 for ResidualBlock {
    fn name(&self) -> &'static str {
        "residual-block"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, width) = rows(s1, l1)?;
        let (b, _) = rows(s3, l3)?;
        if l2.dims() != [width, width] || b.len() != width || l1.dims().len() != 2 {
            return Err(candle_core::Error::Msg("residual_block: shapes".into()));
        }
        let n = x.len() / width;
        let CpuStorage::F32(mut pre) = s1.matmul(s2, (1, n, width, width), l1, l2)? else {
            return Err(candle_core::Error::Msg(
                "residual_block: float32 only".into(),
            ));
        };
        let mut out = vec![0f32; pre.len()];
        let mut inv = Vec::with_capacity(n);
        for ((pre, x), y) in pre
            .chunks_exact_mut(width)
            .zip(x.chunks_exact(width))
            .zip(out.chunks_exact_mut(width))
        {
            for ((p, x), b) in pre.iter_mut().zip(x).zip(b) {
                *p = *p + b + x;
            }
            let (mean, inv_row) = moments(pre, self.eps);
            for (p, y) in pre.iter_mut().zip(y.iter_mut()) {
                *p = (*p - mean) * inv_row;
                *y = p.max(0.0);
            }
            inv.push(inv_row);
        }
        let _ = self.saved.set(Arc::new(Normalised { xhat: pre, inv }));
        Ok((CpuStorage::F32(out), l1.shape().clone()))
    }

    /// `d pre` from the saved normalisation, then `dx = d pre @ wᵀ + d pre` (the product and
    /// the residual), `dw = xᵀ @ d pre`, `db = Σ_rows d pre`.
    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let saved = self.saved.get().ok_or_else(|| {
            candle_core::Error::Msg("residual_block: a gradient before the forward".into())
        })?;
        let dpre = grad
            .contiguous()?
            .apply_op1_no_bwd(&NormaliseReluGrad(Arc::clone(saved)))?;
        let dx = (dpre.matmul(&w.detach().t()?)? + &dpre)?;
        let dw = x.detach().t()?.matmul(&dpre)?;
        let db = dpre.apply_op1_no_bwd(&SumRows)?;
        Ok((Some(dx), Some(dw), Some(db)))
    }
}

impl CustomOp1 for NormaliseReluGrad {
    fn name(&self) -> &'static str {
        "normalise-relu-grad"
    }

    /// With `g = dy` where `x̂ ≥ 0` (else 0): `d pre = inv · (g − mean(g) − x̂ · mean(g·x̂))`.
    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (dy, width) = rows(storage, layout)?;
        let Normalised { xhat, inv } = &*self.0;
        if dy.len() != xhat.len() {
            return Err(candle_core::Error::Msg(
                "residual_block: gradient shape".into(),
            ));
        }
        let mut dx = vec![0f32; dy.len()];
        let n = width as f32;
        for (((dy, xhat), dx), &inv) in dy
            .chunks_exact(width)
            .zip(xhat.chunks_exact(width))
            .zip(dx.chunks_exact_mut(width))
            .zip(inv)
        {
            for ((&d, &v), out) in dy.iter().zip(xhat).zip(dx.iter_mut()) {
                *out = if v >= 0.0 { d } else { 0.0 };
            }
            let mean_g = lane_sum(dx, dx, |g, _| g) / n;
            let mean_gx = lane_sum(dx, xhat, |g, v| g * v) / n;
            for (out, &v) in dx.iter_mut().zip(xhat) {
                *out = inv * (*out - mean_g - v * mean_gx);
            }
        }
        Ok((CpuStorage::F32(dx), layout.shape().clone()))
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use candle_core::{D, Device, Var};

    /// The composed reference the fused op replaces.
    fn reference(x: &Tensor, eps: f32) -> candle_core::Result<Tensor> {
        let mean = x.mean_keepdim(D::Minus1)?;
        let xc = x.broadcast_sub(&mean)?;
        let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
        xc.broadcast_div(&(var + eps as f64)?.sqrt()?)?.relu()
    }

    #[test]
    fn add_bias_and_its_gradients_match_broadcast_add() {
        let dev = Device::Cpu;
        for (rows, width) in [(7, 5), (300, 64), (1, 1)] {
            let x =
                Var::from_tensor(&Tensor::randn(0f32, 1.0, (rows, width), &dev).unwrap()).unwrap();
            let b = Var::from_tensor(&Tensor::randn(0f32, 1.0, width, &dev).unwrap()).unwrap();
            let w = Tensor::randn(0f32, 1.0, (rows, width), &dev).unwrap();
            let fused = add_bias(x.as_tensor(), b.as_tensor()).unwrap();
            let plain = x.as_tensor().broadcast_add(b.as_tensor()).unwrap();
            assert_eq!(max_diff(&fused, &plain), 0.0);
            let gf = (fused * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let gp = (plain * &w).unwrap().sum_all().unwrap().backward().unwrap();
            for v in [&x, &b] {
                let (f, p) = (
                    gf.get(v.as_tensor()).unwrap(),
                    gp.get(v.as_tensor()).unwrap(),
                );
                assert!(max_diff(f, p) < 1e-5, "{rows}x{width}: {}", max_diff(f, p));
            }
        }
        let x = Tensor::zeros((2, 3), candle_core::DType::F32, &dev).unwrap();
        assert!(
            add_bias(
                &x,
                &Tensor::zeros(4, candle_core::DType::F32, &dev).unwrap()
            )
            .is_err()
        );
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        let d = (a - b).unwrap().abs().unwrap().flatten_all().unwrap();
        d.max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// A block composed from candle's operations, as the encoder was before [`residual_block`]
    /// (also the reference of `model`'s whole-encoder test).
    pub(crate) fn composed_block(
        x: &Tensor,
        w: &Tensor,
        b: &Tensor,
        eps: f32,
    ) -> candle_core::Result<Tensor> {
        reference(&(x.matmul(w)?.broadcast_add(b)? + x)?, eps)
    }

    /// Asserts that every element of `got` is within `share` of `want`'s largest absolute value
    /// (taken as at least 1) of `want`'s: rounding, not a different computation.
    pub(crate) fn assert_within_share(got: &Tensor, want: &Tensor, share: f32, what: &str) {
        let scale = want.abs().unwrap().max_all().unwrap();
        let scale = scale.to_scalar::<f32>().unwrap();
        let diff = max_diff(got, want);
        assert!(diff <= share * scale.max(1.0), "{what}: {diff} of {scale}");
    }

    #[test]
    fn a_block_and_its_gradients_match_the_composed_ops() {
        let dev = Device::Cpu;
        let var = |shape: (usize, usize), sd: f32| {
            Var::from_tensor(&Tensor::randn(0.1f32, sd, shape, &dev).unwrap()).unwrap()
        };
        for (rows, width) in [(5, 7), (33, 96), (1, 1), (250, 64)] {
            let x = var((rows, width), 2.0);
            let w = var((width, width), 0.3);
            let b = Var::from_tensor(&Tensor::randn(0f32, 1.0, width, &dev).unwrap()).unwrap();
            let up = Tensor::randn(0f32, 1.0, (rows, width), &dev).unwrap();
            let fused = residual_block(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
            let plain = composed_block(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
            assert!(max_diff(&fused, &plain) < 1e-5, "{rows}x{width} forward");
            let gf = (fused * &up)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            let gp = (plain * &up)
                .unwrap()
                .sum_all()
                .unwrap()
                .backward()
                .unwrap();
            for (name, v) in [("x", &x), ("w", &w), ("b", &b)] {
                let (f, p) = (
                    gf.get(v.as_tensor()).unwrap(),
                    gp.get(v.as_tensor()).unwrap(),
                );
                assert_within_share(f, p, 1e-5, &format!("{rows}x{width} d{name}"));
            }
        }
    }

    #[test]
    fn a_block_rejects_shapes_that_do_not_fit() {
        let dev = Device::Cpu;
        let z = |shape: &[usize]| Tensor::zeros(shape, candle_core::DType::F32, &dev).unwrap();
        assert!(residual_block(&z(&[3, 4]), &z(&[4, 5]), &z(&[4]), 1e-5).is_err());
        assert!(residual_block(&z(&[3, 4]), &z(&[4, 4]), &z(&[3]), 1e-5).is_err());
    }

    #[test]
    fn a_strided_input_gives_what_its_contiguous_copy_gives() {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 1.0, (6, 4), &dev).unwrap().t().unwrap();
        let w = Tensor::randn(0f32, 1.0, (6, 6), &dev).unwrap();
        let b = Tensor::randn(0f32, 1.0, 6, &dev).unwrap();
        let strided = residual_block(&x, &w.t().unwrap(), &b, 1e-5).unwrap();
        let copied = residual_block(
            &x.contiguous().unwrap(),
            &w.t().unwrap().contiguous().unwrap(),
            &b,
            1e-5,
        )
        .unwrap();
        assert_eq!(max_diff(&strided, &copied), 0.0);
    }
}

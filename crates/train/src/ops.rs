//! The encoder's two hottest element-wise steps as single candle operations with one-pass
//! gradients (a training step's time was mostly element-wise passes, not matrix products):
//! - [`layer_norm_relu`]: `ReLU(LayerNorm(x))` over the last axis (no scale or shift: SPEC §2's
//!   block ending); composed from candle's operations it took eight tensors forward and about
//!   twice that backward, each a fresh buffer and a pass over memory.
//! - [`add_bias`]: `x + b` for each row, whose gradient for `b` sums the rows in one
//!   contiguous pass (candle's reduction over the first axis, which `broadcast_add`'s gradient
//!   uses, took about 50× its reduction over the last on a `[500, 64]` gradient).
use candle_core::{CpuStorage, CustomOp1, CustomOp2, Layout, Shape, Tensor};

/// `ReLU(LayerNorm(x))` over the last axis of `x` (float32), without scale or shift.
pub(crate) fn layer_norm_relu(x: &Tensor, eps: f32) -> candle_core::Result<Tensor> {
    x.contiguous()?.apply_op1(LayerNormRelu { eps })
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

/// The forward operation; its gradient is [`LayerNormReluGrad`].
struct LayerNormRelu {
    eps: f32,
}

/// The gradient with respect to `x` given the gradient of the output; not differentiable itself.
struct LayerNormReluGrad {
    eps: f32,
}

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

impl CustomOp1 for LayerNormRelu {
    fn name(&self) -> &'static str {
        "layer-norm-relu"
    }

    fn cpu_fwd(
        &self,
        storage: &CpuStorage,
        layout: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, width) = rows(storage, layout)?;
        let mut out = vec![0f32; x.len()];
        for (row, y) in x.chunks_exact(width).zip(out.chunks_exact_mut(width)) {
            let (mean, inv) = moments(row, self.eps);
            for (y, v) in y.iter_mut().zip(row) {
                *y = ((v - mean) * inv).max(0.0);
            }
        }
        Ok((CpuStorage::F32(out), layout.shape().clone()))
    }

    fn bwd(
        &self,
        arg: &Tensor,
        _res: &Tensor,
        grad: &Tensor,
    ) -> candle_core::Result<Option<Tensor>> {
        let (x, g) = (arg.contiguous()?, grad.contiguous()?);
        Ok(Some(x.apply_op2_no_bwd(
            &g,
            &LayerNormReluGrad { eps: self.eps },
        )?))
    }
}

impl CustomOp2 for LayerNormReluGrad {
    fn name(&self) -> &'static str {
        "layer-norm-relu-grad"
    }

    /// With `x̂ = (x − mean)·inv` and `g = dy` where `x̂ > 0` (else 0):
    /// `dx = inv · (g − mean(g) − x̂ · mean(g·x̂))`.
    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let (x, width) = rows(s1, l1)?;
        let (dy, _) = rows(s2, l2)?;
        if x.len() != dy.len() {
            return Err(candle_core::Error::Msg(
                "layer_norm_relu: gradient shape".into(),
            ));
        }
        let mut dx = vec![0f32; x.len()];
        let n = width as f32;
        for ((row, dy), dx) in x
            .chunks_exact(width)
            .zip(dy.chunks_exact(width))
            .zip(dx.chunks_exact_mut(width))
        {
            let (mean, inv) = moments(row, self.eps);
            for ((&v, &d), out) in row.iter().zip(dy).zip(dx.iter_mut()) {
                *out = if v >= mean { d } else { 0.0 };
            }
            let mean_g = lane_sum(dx, dx, |g, _| g) / n;
            let mean_gx = lane_sum(dx, row, |g, v| g * (v - mean) * inv) / n;
            for (out, &v) in dx.iter_mut().zip(row) {
                *out = inv * (*out - mean_g - (v - mean) * inv * mean_gx);
            }
        }
        Ok((CpuStorage::F32(dx), l1.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
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

    #[test]
    fn forward_and_gradient_match_the_composed_ops() {
        let dev = Device::Cpu;
        for (rows, width) in [(5, 7), (33, 96), (1, 1)] {
            let x = Var::from_tensor(&Tensor::randn(0.5f32, 2.0, (rows, width), &dev).unwrap())
                .unwrap();
            let w = Tensor::randn(0f32, 1.0, (rows, width), &dev).unwrap();
            let fused = layer_norm_relu(x.as_tensor(), 1e-5).unwrap();
            let plain = reference(x.as_tensor(), 1e-5).unwrap();
            assert!(max_diff(&fused, &plain) < 1e-5, "{rows}x{width} forward");
            let gf = (fused * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let gp = (plain * &w).unwrap().sum_all().unwrap().backward().unwrap();
            let (gf, gp) = (
                gf.get(x.as_tensor()).unwrap(),
                gp.get(x.as_tensor()).unwrap(),
            );
            assert!(
                max_diff(gf, gp) < 1e-5,
                "{rows}x{width} gradient {}",
                max_diff(gf, gp)
            );
        }
    }

    #[test]
    fn a_strided_input_gives_what_its_contiguous_copy_gives() {
        let x = Tensor::randn(0f32, 1.0, (4, 6), &Device::Cpu)
            .unwrap()
            .t()
            .unwrap();
        let strided = layer_norm_relu(&x, 1e-5).unwrap();
        let copied = layer_norm_relu(&x.contiguous().unwrap(), 1e-5).unwrap();
        assert_eq!(max_diff(&strided, &copied), 0.0);
    }
}

//! Encoder weights as plain Rust data: what the trainer produces, the exporter writes to ONNX,
//! and the reference forward pass computes with (SPEC §2).
use ndarray::{Array2, ArrayView2, Axis, s};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crossview_core::{Error, Result};

/// Largest accepted magnitude of a normalised box coordinate. Real boxes lie near [0, 1];
/// far larger finite values would overflow the Fourier features to inf/NaN.
pub const MAX_NORMALIZED_COORD: f32 = 1e3;

/// A dense layer `y = x W^T + b` with `weight` row-major `[out_dim, in_dim]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Linear {
    /// Input features.
    pub in_dim: usize,
    /// Output features.
    pub out_dim: usize,
    /// Row-major `[out_dim, in_dim]`.
    pub weight: Vec<f32>,
    /// `[out_dim]`.
    pub bias: Vec<f32>,
}

impl Linear {
    /// A layer initialised like PyTorch's default `nn.Linear`: weight and bias drawn from
    /// `U(-1/sqrt(in_dim), 1/sqrt(in_dim))`.
    pub fn random(in_dim: usize, out_dim: usize, rng: &mut impl Rng) -> Self {
        let bound = 1.0 / (in_dim.max(1) as f32).sqrt();
        let weight = (0..in_dim * out_dim)
            .map(|_| rng.random_range(-bound..bound))
            .collect();
        let bias = (0..out_dim)
            .map(|_| rng.random_range(-bound..bound))
            .collect();
        Linear {
            in_dim,
            out_dim,
            weight,
            bias,
        }
    }

    /// The weight as an `[out_dim, in_dim]` view (fails when the vector length is wrong).
    pub(crate) fn weight_view(&self) -> Result<ArrayView2<'_, f32>> {
        ArrayView2::from_shape((self.out_dim, self.in_dim), &self.weight).map_err(|_| {
            Error::invalid(
                "linear.weight",
                format!(
                    "expected {}x{} values, got {}",
                    self.out_dim,
                    self.in_dim,
                    self.weight.len()
                ),
            )
        })
    }

    /// `x W^T + b` for a batch `x` of shape `[n, in_dim]`.
    pub fn apply(&self, x: &Array2<f32>) -> Result<Array2<f32>> {
        let w = self.weight_view()?;
        let mut y = x.dot(&w.t());
        y += &ndarray::ArrayView1::from(&self.bias);
        Ok(y)
    }

    fn validate(&self, name: &str, in_dim: usize, out_dim: usize) -> Result<()> {
        if self.in_dim != in_dim || self.out_dim != out_dim {
            return Err(Error::invalid(
                name,
                format!(
                    "expected shape [{out_dim}, {in_dim}], got [{}, {}]",
                    self.out_dim, self.in_dim
                ),
            ));
        }
        check_len(&format!("{name}.weight"), &self.weight, in_dim * out_dim)?;
        check_len(&format!("{name}.bias"), &self.bias, out_dim)
    }
}

fn check_len(name: &str, values: &[f32], expected: usize) -> Result<()> {
    if values.len() != expected {
        return Err(Error::invalid(
            name,
            format!("expected {expected} values, got {}", values.len()),
        ));
    }
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(Error::invalid(
            format!("{name}[{i}]"),
            format!("must be finite, got {}", values[i]),
        ));
    }
    Ok(())
}

/// Encoder shape. The reference (SPEC §2) is 128 Fourier features, a 256-wide camera
/// embedding, width 768 (= 4·128 + 256) and 3 residual blocks. When `width != 4·fourier +
/// camera_dim` an input projection maps `x0` to `width` before the blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncoderConfig {
    /// Columns F of the Fourier matrix `B` (features per corner: 2F).
    pub fourier_features: usize,
    /// Width of a camera embedding row.
    pub camera_dim: usize,
    /// Embedding width G (width of every residual block).
    pub width: usize,
    /// Number of residual blocks.
    pub blocks: usize,
}

impl Default for EncoderConfig {
    fn default() -> Self {
        EncoderConfig {
            fourier_features: 128,
            camera_dim: 256,
            width: 768,
            blocks: 3,
        }
    }
}

impl EncoderConfig {
    /// Width of `x0 = [gamma(tl) | gamma(br) | E[c]]`.
    pub fn input_dim(&self) -> usize {
        4 * self.fourier_features + self.camera_dim
    }

    /// True when an input projection `Linear(input_dim -> width)` precedes the blocks.
    pub fn has_input_proj(&self) -> bool {
        self.width != self.input_dim()
    }

    /// Rejects zero sizes (a zero-width encoder cannot embed anything).
    pub fn validate(&self) -> Result<()> {
        for (name, v) in [
            ("fourier_features", self.fourier_features),
            ("camera_dim", self.camera_dim),
            ("width", self.width),
        ] {
            if v == 0 {
                return Err(Error::invalid(format!("config.{name}"), "must be > 0"));
            }
        }
        Ok(())
    }
}

/// Default LayerNorm epsilon (PyTorch's).
pub(crate) const DEFAULT_LAYER_NORM_EPS: f32 = 1e-5;

/// All encoder parameters.
///
/// The forward pass (SPEC §2), which the ONNX export, the trainer and [`EncoderWeights::forward`]
/// all follow exactly, for a box `v = [x1, y1, x2, y2]` (normalised) of camera `c`:
///
/// 1. `tl = (x1, y1)`, `br = (x2, y2)`; `p_tl = 2π·((2·tl − 1) @ B)`, `p_br = 2π·((2·br − 1) @ B)`
///    with `B` = [`fourier`](Self::fourier) `[2, F]` (row 0 multiplies x, row 1 multiplies y).
/// 2. `x0 = [sin p_tl | cos p_tl | sin p_br | cos p_br | E[c]]` — this order is the contract;
///    width `4F + camera_dim`.
/// 3. If [`input_proj`](Self::input_proj) is present: `x = x0 W_in^T + b_in` (no activation).
/// 4. For each block: `x = ReLU(LayerNorm(x W^T + b + x))`, LayerNorm over the last axis with
///    biased variance, epsilon [`layer_norm_eps`](Self::layer_norm_eps), no scale/shift.
/// 5. The last block's output is the embedding (not L2-normalised).
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderWeights {
    /// Shape of the encoder.
    pub config: EncoderConfig,
    /// Rows of the camera embedding table (cameras of the scene, in index order).
    pub num_cameras: usize,
    /// Frozen Fourier matrix `B`, row-major `[2, fourier_features]`.
    pub fourier: Vec<f32>,
    /// Camera embedding table `E`, row-major `[num_cameras, camera_dim]`.
    pub camera_embedding: Vec<f32>,
    /// Present only when `config.width != config.input_dim()`.
    pub input_proj: Option<Linear>,
    /// `config.blocks` residual blocks, each `[width, width]`.
    pub blocks: Vec<Linear>,
    /// LayerNorm epsilon (no learnable scale/shift).
    pub layer_norm_eps: f32,
}

impl EncoderWeights {
    /// A freshly initialised encoder: `B ~ N(0, 1)`, camera table from a normal with std 1
    /// truncated to [-2, 2], linear layers as PyTorch's default. Deterministic in `seed`.
    pub fn random(num_cameras: usize, config: EncoderConfig, seed: u64) -> Result<Self> {
        config.validate()?;
        if num_cameras == 0 {
            return Err(Error::invalid("num_cameras", "must be > 0"));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let fourier = (0..2 * config.fourier_features)
            .map(|_| rng.sample::<f32, _>(StandardNormal))
            .collect();
        let camera_embedding = (0..num_cameras * config.camera_dim)
            .map(|_| truncated_normal(&mut rng))
            .collect();
        let input_proj = config
            .has_input_proj()
            .then(|| Linear::random(config.input_dim(), config.width, &mut rng));
        let blocks = (0..config.blocks)
            .map(|_| Linear::random(config.width, config.width, &mut rng))
            .collect();
        Ok(EncoderWeights {
            config,
            num_cameras,
            fourier,
            camera_embedding,
            input_proj,
            blocks,
            layer_norm_eps: DEFAULT_LAYER_NORM_EPS,
        })
    }

    /// Embedding width G.
    pub fn width(&self) -> usize {
        self.config.width
    }

    /// Checks that every tensor has the shape the config implies and only finite values.
    pub fn validate(&self) -> Result<()> {
        let c = &self.config;
        c.validate()?;
        if self.num_cameras == 0 {
            return Err(Error::invalid("num_cameras", "must be > 0"));
        }
        check_len("fourier", &self.fourier, 2 * c.fourier_features)?;
        check_len(
            "camera_embedding",
            &self.camera_embedding,
            self.num_cameras * c.camera_dim,
        )?;
        match (&self.input_proj, c.has_input_proj()) {
            (Some(p), true) => p.validate("input_proj", c.input_dim(), c.width)?,
            (None, false) => {}
            (Some(_), false) => {
                return Err(Error::invalid(
                    "input_proj",
                    format!("present although width {} equals the input width", c.width),
                ));
            }
            (None, true) => {
                return Err(Error::invalid(
                    "input_proj",
                    format!(
                        "missing although width {} differs from the input width {}",
                        c.width,
                        c.input_dim()
                    ),
                ));
            }
        }
        if self.blocks.len() != c.blocks {
            return Err(Error::invalid(
                "blocks",
                format!("expected {} blocks, got {}", c.blocks, self.blocks.len()),
            ));
        }
        for (k, b) in self.blocks.iter().enumerate() {
            b.validate(&format!("blocks[{k}]"), c.width, c.width)?;
        }
        if !self.layer_norm_eps.is_finite() || self.layer_norm_eps <= 0.0 {
            return Err(Error::invalid(
                "layer_norm_eps",
                format!("must be finite and > 0, got {}", self.layer_norm_eps),
            ));
        }
        Ok(())
    }

    /// Checks inputs shared by every encoder: equal lengths, finite boxes, cameras in range.
    pub(crate) fn check_inputs(
        boxes: &[[f32; 4]],
        cameras: &[i64],
        num_cameras: usize,
    ) -> Result<()> {
        if boxes.len() != cameras.len() {
            return Err(Error::invalid(
                "cameras",
                format!("{} boxes but {} camera indices", boxes.len(), cameras.len()),
            ));
        }
        if let Some(i) = boxes.iter().position(|b| b.iter().any(|v| !v.is_finite())) {
            return Err(Error::invalid(
                format!("boxes[{i}]"),
                format!("coordinates must be finite, got {:?}", boxes[i]),
            ));
        }
        if let Some(i) = boxes
            .iter()
            .position(|b| b.iter().any(|v| v.abs() > MAX_NORMALIZED_COORD))
        {
            return Err(Error::invalid(
                format!("boxes[{i}]"),
                format!(
                    "normalised coordinates must be within ±{MAX_NORMALIZED_COORD} image sizes, got {:?}",
                    boxes[i]
                ),
            ));
        }
        if let Some(i) = cameras
            .iter()
            .position(|&c| c < 0 || c as u64 >= num_cameras as u64)
        {
            return Err(Error::invalid(
                format!("cameras[{i}]"),
                format!(
                    "camera index {} out of range (model has {num_cameras} cameras)",
                    cameras[i]
                ),
            ));
        }
        Ok(())
    }

    /// The first layer input `x0 = [sin p_tl | cos p_tl | sin p_br | cos p_br | E[c]]`
    /// (see the type's doc), shape `[N, input_dim]`.
    pub(crate) fn input_features(
        &self,
        boxes: &[[f32; 4]],
        cameras: &[i64],
    ) -> Result<Array2<f32>> {
        self.validate()?;
        Self::check_inputs(boxes, cameras, self.num_cameras)?;
        let f = self.config.fourier_features;
        let d = self.config.camera_dim;
        let two_pi = 2.0 * std::f32::consts::PI;
        let mut x0 = Array2::<f32>::zeros((boxes.len(), self.config.input_dim()));
        for (n, (b, &c)) in boxes.iter().zip(cameras).enumerate() {
            let mut row = x0.row_mut(n);
            for (corner, (vx, vy)) in [(b[0], b[1]), (b[2], b[3])].into_iter().enumerate() {
                let (ux, uy) = (2.0 * vx - 1.0, 2.0 * vy - 1.0);
                let base = corner * 2 * f;
                for j in 0..f {
                    let p = two_pi * (ux * self.fourier[j] + uy * self.fourier[f + j]);
                    row[base + j] = p.sin();
                    row[base + f + j] = p.cos();
                }
            }
            let c = c as usize;
            row.slice_mut(s![4 * f..])
                .assign(&ndarray::ArrayView1::from(
                    &self.camera_embedding[c * d..(c + 1) * d],
                ));
        }
        Ok(x0)
    }

    /// Reference forward pass in plain Rust (SPEC §2, see the type's doc): `[N, width]`.
    /// Used to check the ONNX export and as a dependency-free fallback.
    pub fn forward(&self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        let mut x = self.input_features(boxes, cameras)?;
        if let Some(p) = &self.input_proj {
            x = p.apply(&x)?;
        }
        for block in &self.blocks {
            let mut h = block.apply(&x)?;
            h += &x;
            layer_norm_relu(&mut h, self.layer_norm_eps);
            x = h;
        }
        Ok(x)
    }
}

/// In place `ReLU(LayerNorm(x))` over each row (no scale/shift; statistics in f64).
fn layer_norm_relu(x: &mut Array2<f32>, eps: f32) {
    for mut row in x.axis_iter_mut(Axis(0)) {
        let n = row.len().max(1) as f64;
        let mean = row.iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n;
        let inv = 1.0 / (var + eps as f64).sqrt();
        row.mapv_inplace(|v| (((v as f64 - mean) * inv) as f32).max(0.0));
    }
}

/// A standard normal sample truncated to [-2, 2] by rejection.
fn truncated_normal(rng: &mut impl Rng) -> f32 {
    loop {
        let v: f32 = rng.sample(StandardNormal);
        if (-2.0..=2.0).contains(&v) {
            return v;
        }
    }
}

/// The plain-Rust forward pass as an [`crossview_core::Encoder`] (used where a model must be run
/// without ONNX Runtime, e.g. calibrating right after training).
impl crossview_core::Encoder for EncoderWeights {
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        self.forward(boxes, cameras)
    }
    fn dim(&self) -> usize {
        self.width()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn random_is_seeded_and_valid() {
        let cfg = EncoderConfig {
            fourier_features: 8,
            camera_dim: 4,
            width: 16,
            blocks: 2,
        };
        let a = EncoderWeights::random(3, cfg, 7).unwrap();
        let b = EncoderWeights::random(3, cfg, 7).unwrap();
        let c = EncoderWeights::random(3, cfg, 8).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, c);
        a.validate().unwrap();
        assert!(a.input_proj.is_some());
        assert!(a.camera_embedding.iter().all(|v| v.abs() <= 2.0));
        let bound = 1.0 / (16f32).sqrt();
        assert!(a.blocks[0].weight.iter().all(|v| v.abs() <= bound));
    }

    #[test]
    fn forward_shapes_and_layer_norm() {
        let cfg = EncoderConfig {
            fourier_features: 4,
            camera_dim: 4,
            width: 20,
            blocks: 1,
        };
        let w = EncoderWeights::random(2, cfg, 1).unwrap();
        assert!(w.input_proj.is_none());
        let boxes = [[0.1, 0.2, 0.3, 0.9], [0.5, 0.5, 0.6, 0.7]];
        let y = w.forward(&boxes, &[0, 1]).unwrap();
        assert_eq!(y.dim(), (2, 20));
        assert!(y.iter().all(|&v| v >= 0.0 && v.is_finite()));
        // x0 layout: sin/cos pairs satisfy sin² + cos² = 1; camera part equals E[c].
        let x0 = w.input_features(&boxes, &[0, 1]).unwrap();
        for j in 0..4 {
            let (sn, cs) = (x0[[0, j]], x0[[0, 4 + j]]);
            assert!((sn * sn + cs * cs - 1.0).abs() < 1e-5);
        }
        assert_eq!(x0.row(1).slice(s![16..]).to_vec(), w.camera_embedding[4..8]);
        let empty = w.forward(&[], &[]).unwrap();
        assert_eq!(empty.dim(), (0, 20));
    }

    #[test]
    fn forward_rejects_bad_inputs() {
        let w = EncoderWeights::random(2, EncoderConfig::default(), 0).unwrap();
        assert!(matches!(
            w.forward(&[[0.1, 0.1, 0.2, 0.2]], &[2]),
            Err(Error::InvalidArgument { .. })
        ));
        assert!(matches!(
            w.forward(&[[f32::NAN, 0.1, 0.2, 0.2]], &[0]),
            Err(Error::InvalidArgument { .. })
        ));
        assert!(w.forward(&[[0.1, 0.1, 0.2, 0.2]], &[]).is_err());
        let mut bad = w.clone();
        bad.blocks[1].bias[3] = f32::INFINITY;
        assert!(bad.validate().is_err());
    }
}

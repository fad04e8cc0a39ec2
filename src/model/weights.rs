//! Encoder weights as plain Rust data: what the trainer produces, the exporter writes to ONNX,
//! and the reference forward pass computes with (SPEC §2).

/// A dense layer `y = x W^T + b` with `weight` row-major `[out_dim, in_dim]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Linear {
    pub in_dim: usize,
    pub out_dim: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

/// Encoder shape. The reference (SPEC §2) is 128 Fourier features, a 256-wide camera
/// embedding, width 768 (= 4·128 + 256) and 3 residual blocks. When `width != 4·fourier +
/// camera_dim` an input projection maps `x0` to `width` before the blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncoderConfig {
    pub fourier_features: usize,
    pub camera_dim: usize,
    pub width: usize,
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
}

/// All encoder parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct EncoderWeights {
    pub config: EncoderConfig,
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

//! The encoder file contract (SPEC §8): plain-Rust weights, ONNX export, metadata, and the
//! ONNX Runtime encoder used for inference.

pub mod export;
pub mod metadata;
pub mod onnx;
pub mod runtime;
pub mod weights;

#[cfg(test)]
pub(crate) mod testing;

use ndarray::Array2;

pub use export::{read_weights, read_weights_from_bytes, to_onnx_bytes, write_onnx};
pub use metadata::ModelMetadata;
pub use runtime::{EncoderOptions, OnnxEncoder};
pub use weights::{EncoderConfig, EncoderWeights, Linear};

/// Anything that turns normalised boxes into geometric embeddings (SPEC §2).
pub trait Encoder: Send {
    /// Embeds `boxes` (normalised `[x1, y1, x2, y2]`, SPEC §2) of cameras `cameras` in one call.
    /// Returns `[N, dim]`.
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> crate::Result<Array2<f32>>;
    /// Embedding width G.
    fn dim(&self) -> usize;
}

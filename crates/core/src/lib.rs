//! The method (SPEC §2–§3), free of I/O: scene and detection types, box normalisation,
//! distances, Hungarian matching, global identities, the label-free calibration, and the
//! [`Encoder`] trait every encoder (ONNX Runtime, candle, test stand-ins) implements.
//!
//! "SPEC §N" in these docs is section N of `docs/method.md`, the project's account of the
//! method, the metrics and the shared formats.

pub mod association;
pub mod calibration;
pub mod capture;
pub mod distances;
pub mod embeddings;
mod error;
pub mod fit;
pub mod identity;
pub mod integral;
pub(crate) mod lsa;
pub mod matching;
pub mod memory;
pub(crate) mod motion;
pub mod offsets;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod tracking;
pub mod types;

use ndarray::Array2;

pub use embeddings::FrameEmbeddings;
pub use error::{Error, Result, report_chain};
pub use types::{Batch, CameraSpec, Detection, Frame, SceneSpec};

/// Anything that turns normalised boxes into geometric embeddings (SPEC §2).
pub trait Encoder: Send {
    /// Embeds `boxes` (normalised `[x1, y1, x2, y2]`, SPEC §2) of cameras `cameras` in one call.
    /// Returns `[N, dim]`.
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>>;
    /// Embedding width G.
    fn dim(&self) -> usize;
    /// Width of the embedding's leading block that describes the geometry on its own: the
    /// first member's, for an ensemble of encoders whose embeddings are concatenated (the best
    /// by the trainer's label-free key), else the whole width. What keeps many frames of
    /// embeddings (the live clock watch) keeps only these columns.
    fn leading_width(&self) -> usize {
        self.dim()
    }
}

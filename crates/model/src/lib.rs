//! The encoder file contract (SPEC §8): plain-Rust weights, ONNX export, metadata, and the
//! ONNX Runtime encoder used for inference.

pub mod export;
pub mod inspect;
pub mod metadata;
pub mod onnx;
pub mod runtime;
pub mod weights;

pub use export::{read_weights, to_onnx_bytes, write_onnx};
pub use metadata::ModelMetadata;
pub use runtime::{EncoderOptions, OnnxEncoder};
pub use weights::{EncoderConfig, EncoderWeights, Linear};

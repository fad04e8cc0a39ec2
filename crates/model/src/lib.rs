//! The encoder file contract (SPEC §8): plain-Rust weights, ensembles of encoders, the ONNX
//! graph, export and import, metadata, and the ONNX Runtime encoder used for inference.

pub mod ensemble;
pub mod export;
pub mod graph;
pub mod inspect;
pub mod metadata;
pub mod onnx;
pub mod runtime;
pub mod weights;

pub use ensemble::Ensemble;
pub use export::{read_ensemble, read_weights, to_onnx_bytes, write_ensemble_onnx, write_onnx};
pub use metadata::ModelMetadata;
pub use runtime::{EncoderOptions, OnnxEncoder};
pub use weights::{EncoderConfig, EncoderWeights, Linear};

//! Self-supervised training (SPEC §2–§4) with candle, exporting SPEC §8 ONNX files.
//!
//! - [`data`]: the recording as per-frame, per-camera normalised images.
//! - [`clean`]: **[ours]** dropping static and small detector boxes before training.
//! - [`prepare`]: a recording thinned and filtered as training uses it, and what a model
//!   file records of that.
//! - [`sampler`]: anchor/positive/negative triplets.
//! - [`model`]: the candle encoder + decoder, convertible to [`crossview_model::EncoderWeights`]
//!   (`ops`: each residual block and each bias add as one operation with a one-pass gradient).
//! - [`losses`]: synchronization, re-projection and edge losses, batched over triplets
//!   (`hinge`: their triplet hinge over many pairs at once).
//! - `transport`: **[ours]** the soft assignment that may replace the Hungarian pairs of the
//!   synchronization loss early in the first stage.
//! - [`distil`]: **[ours]** one student encoder taught an ensemble's cross-view distances.
//! - [`pseudo`]: **[ours]** pseudo-identity labels from confident identities (self-training).
//! - [`member`]: one run that advances an epoch at a time, scored, checkpointed, cloned.
//! - [`population`]: **[ours]** members on every core, the worse half dropped by the
//!   label-free key.
//! - [`adam`]: the optimiser, with checkpointable state.
//! - [`label_free`]: **[ours]** scores on held-out unlabelled frames that choose the epoch
//!   and the threshold without labels.
//! - [`calibrate`]: **[ours]** label-free `P(same person | distance)` for a trained encoder.
//! - [`student`]: **[ours]** whether a run exports its ensemble or its student.
//! - [`run`]: one whole run as `crossview train` does it, files written.

pub mod adam;
pub mod calibrate;
pub mod checkpoint;
pub mod clean;
pub mod config;
pub mod curve;
pub mod data;
pub mod distil;
mod hinge;
pub mod label_free;
pub mod losses;
pub mod member;
pub mod model;
mod ops;
pub mod population;
pub mod prepare;
pub mod pseudo;
pub mod run;
pub mod sampler;
pub mod state;
pub mod student;
pub mod trainer;
mod transport;
pub mod validate;

pub use data::TrainingSet;
pub use model::TrainModel;

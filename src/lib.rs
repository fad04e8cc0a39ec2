//! crossview: self-supervised, calibration-free multi-view person association (Self-MVA).
//!
//! "SPEC §N" in these docs is section N of `docs/method.md`, the project's account of the
//! method, the metrics and the shared formats.
//!
//! Layout:
//! - [`core`]: the method itself — box features, distances, Hungarian matching, global identities.
//! - [`model`]: the encoder file contract (SPEC §8): weights, ONNX export, the ONNX Runtime encoder.
//! - [`io`]: the JSONL recording format (SPEC §7), dataset importers, chronological splits.
//! - [`eval`]: the paper's metrics (SPEC §5) and the evaluation driver.
//! - [`sim`]: a synthetic multi-camera scene simulator with ground truth.
//! - [`train`]: the self-supervised trainer (SPEC §2–§4).
//! - [`serve`]: the streaming association service (gRPC + HTTP).
//! - [`demo`]: the newcomer's demo client (simulated scene → server → live accuracy).
//! - [`cli`]: the `crossview` command line.

pub mod cli;
pub mod core;
pub mod demo;
pub mod error;
pub mod eval;
pub mod io;
pub mod model;
pub mod serve;
pub mod sim;
pub mod train;

pub use error::{Error, Result};

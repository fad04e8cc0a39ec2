//! crossview: self-supervised, calibration-free multi-view person association (Self-MVA).
//!
//! "SPEC §N" in these docs is section N of `docs/method.md`, the project's account of the
//! method, the metrics and the shared formats.
//!
//! This package is the edge: the `crossview` command line ([`cli`]) and the newcomer's demo
//! client ([`demo`]). The work happens in the workspace crates, whose dependency arrows run
//! one way:
//! - `crossview-core`: the method itself — types, distances, assignment, identities, the
//!   `Encoder` trait (no I/O);
//! - `crossview-model`: the encoder file contract (SPEC §8) and the ONNX Runtime encoder;
//! - `crossview-data`: recordings (SPEC §7), importers, splits, the scene simulator;
//! - `crossview-eval`: the paper's metrics (SPEC §5) and the evaluation driver;
//! - `crossview-train`: the self-supervised trainer (SPEC §2–§4) on candle;
//! - `crossview-api`: the wire format (protobuf, JSON) and every conversion;
//! - `crossview-serve`: the streaming association service (gRPC + HTTP).

pub mod cli;
pub mod demo;

//! Evaluation: the paper's metrics (SPEC §5) and the driver behind `crossview eval`.
//!
//! - [`metrics`]: per-image-pair records and the SPEC §5 metrics over them.
//! - [`driver`]: run an encoder over a recording with ids and produce the records.
//! - [`dump`]: the `--dump-pairs` JSON Lines file (write and read back).
//! - [`identities`]: whole-identity scores (frames exactly right, precision by confidence).
//! - [`report`]: the printed table and the JSON report.
//! - [`parallel`]: frames dealt to worker threads, results back in frame order.
//! - [`throughput`]: in-process frames/s of the inference pipeline (the `pipeline` bench).
//! - [`tracking`]: track ids over time scored against the ground-truth ids (IDF1, switches).

pub mod driver;
pub mod dump;
pub mod identities;
pub mod metrics;
pub mod parallel;
pub mod report;
pub mod throughput;
pub mod tracking;

pub use driver::{EvalRun, evaluate, evaluate_settings, evaluate_settings_on};
pub use metrics::{Metrics, PairRecord, compute_metrics};

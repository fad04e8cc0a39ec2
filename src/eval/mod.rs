//! Evaluation: the paper's metrics (SPEC §5) and the driver behind `crossview eval`.

pub mod metrics;

pub use metrics::{Metrics, PairRecord, compute_metrics};

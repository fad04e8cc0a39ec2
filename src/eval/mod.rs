//! Evaluation: the paper's metrics (SPEC §5) and the driver behind `crossview eval`.

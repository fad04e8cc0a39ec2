//! Data I/O: the JSONL recording format (SPEC §7), dataset importers and chronological splits.

pub mod recording;

pub use recording::Recording;

//! Data I/O: the JSONL recording format (SPEC §7), dataset importers and chronological splits.

pub mod recording;
pub mod split;
pub mod wildtrack;

pub use recording::{
    ReadStats, Recording, RecordingReader, RecordingWriter, read_recording, read_recording_with,
    write_recording,
};
pub use split::{Part, split_bounds, split_frames, split_ranges};

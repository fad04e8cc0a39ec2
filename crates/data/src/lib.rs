//! The data the method runs on: the JSONL recording format (SPEC §7), dataset importers,
//! chronological splits, and [`sim`], a synthetic multi-camera scene simulator with ground truth.

pub mod recording;
pub mod sim;
pub mod split;
pub mod wildtrack;

pub use recording::{
    ReadStats, Recording, RecordingReader, RecordingWriter, read_recording, read_recording_with,
    read_recordings, recording_files, write_recording,
};
pub use split::{Part, split_bounds, split_frames};

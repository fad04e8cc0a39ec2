//! The data the method runs on: the JSONL recording format (SPEC §7), dataset importers,
//! chronological splits, and [`sim`], a synthetic multi-camera scene simulator with ground truth.

mod imported;
pub mod mvor;
pub mod recording;
mod selfmva;
pub mod sim;
pub mod split;
pub mod wildtrack;

pub use imported::Imported;
pub use recording::{
    ReadStats, Recording, RecordingReader, RecordingWriter, read_recording, read_recording_with,
    read_recordings, recording_files, write_recording,
};
pub use split::{Part, split_bounds, split_frames};

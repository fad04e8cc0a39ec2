//! The method (SPEC §2–§3), free of I/O: scene and detection types, box normalisation,
//! distances, Hungarian matching and global identities.

pub mod association;
pub mod calibration;
pub mod embeddings;
pub mod identity;
pub mod lsa;
pub mod matching;
pub mod types;

pub use embeddings::FrameEmbeddings;
pub use types::{Batch, CameraSpec, Detection, Frame, SceneSpec};

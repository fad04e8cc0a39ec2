//! The SPEC §7 JSONL recording: a scene header line, then one camera batch per line.
use crate::core::{Frame, SceneSpec};

/// A whole recording in memory: the scene and its frames sorted by frame id.
/// `frames[k].views[c]` is `None` when camera `c` sent no batch for that frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    pub scene: SceneSpec,
    pub frames: Vec<Frame>,
}

//! **[ours]** Global identities: the pairwise matches of all camera pairs of a frame turned
//! into clusters with at most one box per camera, each with a confidence.

/// A person seen by one or more cameras in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Identity {
    /// Identity number within the frame (0-based, dense).
    pub id: usize,
    /// Confidence in [0, 1].
    pub confidence: f32,
    /// Members as `(camera index, index into that camera's detections)`, sorted by camera.
    pub members: Vec<(usize, usize)>,
}

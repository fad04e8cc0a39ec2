//! Whole-frame association: embed every box of a frame in one encoder call, match every pair of
//! reported views, and build global identities.
use ndarray::Array2;

use crate::core::identity::Identity;
use crate::core::matching::PairMatching;

/// The association of one camera pair within a frame.
#[derive(Debug, Clone, PartialEq)]
pub struct ViewPair {
    pub cam_a: usize,
    pub cam_b: usize,
    pub matching: PairMatching,
}

/// Everything computed for one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameAssociation {
    pub frame_id: u64,
    /// Per-view embeddings (`None` for views that did not report).
    pub embeddings: Vec<Option<Array2<f32>>>,
    /// Every pair `cam_a < cam_b` where both views have at least one box.
    pub pairs: Vec<ViewPair>,
    /// Global identities over all views.
    pub identities: Vec<Identity>,
}

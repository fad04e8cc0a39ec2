//! Association of one synchronized frame: every box of the frame embedded in one encoder call
//! ([`embed_frame`]), then the method's pairwise matching and global identities
//! ([`associate_frame`]).
use crate::Result;
use crate::core::association::{AssociationConfig, Mode, associate_frame, embed_frame};
use crate::core::identity::Identity;
use crate::core::{Frame, SceneSpec};
use crate::model::Encoder;

/// The association settings of a scene (from its model metadata).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EngineConfig {
    /// Confidence threshold (SPEC §3).
    pub threshold: f32,
    /// Appearance fusion weight (SPEC §3).
    pub alpha: f32,
}

/// Associates `frame` of `scene`: returns its global identities. Runs the encoder once for all
/// boxes of the frame. Blocking (call it off the async runtime).
pub fn associate(
    encoder: &mut dyn Encoder,
    scene: &SceneSpec,
    frame: &Frame,
    config: EngineConfig,
) -> Result<Vec<Identity>> {
    let embeddings = embed_frame(encoder, scene, frame)?;
    let cfg = AssociationConfig {
        threshold: config.threshold,
        alpha: config.alpha,
        mode: Mode::Pairwise,
    };
    Ok(associate_frame(frame, embeddings, &cfg).identities)
}

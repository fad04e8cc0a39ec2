//! Association of one synchronized frame: every box of the frame embedded in one encoder call
//! ([`embed_frame`]), then the frame's identities ([`frame_identities`]) — the only thing the
//! service returns, so nothing else is built.
use crate::Result;
use crate::core::association::{AssociationConfig, embed_frame, frame_identities};
use crate::core::identity::Identity;
use crate::core::{Frame, SceneSpec};
use crate::model::Encoder;

/// The association settings of a scene (from its model metadata, see
/// [`crate::model::ModelMetadata::association_config`]).
pub type EngineConfig = AssociationConfig;

/// Associates `frame` of `scene`: returns its identities. Runs the encoder once for all
/// boxes of the frame. Blocking (call it off the async runtime).
pub fn associate(
    encoder: &mut dyn Encoder,
    scene: &SceneSpec,
    frame: &Frame,
    config: &EngineConfig,
) -> Result<Vec<Identity>> {
    let embeddings = embed_frame(encoder, scene, frame)?;
    Ok(frame_identities(frame, &embeddings, config))
}

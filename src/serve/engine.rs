//! Association of one synchronized frame: every box of the frame embedded in one encoder call,
//! then the method's matching and identities (`crate::core::association`).
use crate::Result;
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
    let _ = (encoder, scene, config);
    // Placeholder until core::association lands: every box is its own identity.
    let mut out = Vec::new();
    for (c, view) in frame.views.iter().enumerate() {
        for (i, _) in view.iter().flatten().enumerate() {
            out.push(Identity {
                id: out.len(),
                confidence: 1.0,
                members: vec![(c, i)],
            });
        }
    }
    Ok(out)
}

//! Scene registry: loads SPEC §8 model files into scenes (name, cameras from the metadata,
//! threshold, alpha, version) and their encoders.
use super::config::{Limits, ModelSpec};
use super::scene::SceneInfo;
use crossview_core::Encoder;
use crossview_core::SceneSpec;
use crossview_core::{Error, Result};
use crossview_model::{ModelMetadata, OnnxEncoder};

/// The scene description a model's metadata defines, checked against `limits`.
pub fn scene_info(name: &str, meta: &ModelMetadata, limits: &Limits) -> Result<SceneInfo> {
    if meta.cameras.is_empty() || meta.cameras.len() > limits.max_cameras {
        return Err(Error::model(
            name,
            format!(
                "{} cameras; 1..={} are supported",
                meta.cameras.len(),
                limits.max_cameras
            ),
        ));
    }
    Ok(SceneInfo {
        spec: SceneSpec {
            name: name.to_string(),
            cameras: meta.cameras.clone(),
        },
        association: meta.association_config(),
        version: meta.version.clone(),
    })
}

/// Loads one model file (blocking: creates its ONNX Runtime session) into its scene
/// description and encoder.
pub(crate) fn load_model(
    spec: &ModelSpec,
    limits: &Limits,
) -> Result<(SceneInfo, Box<dyn Encoder>)> {
    let encoder = OnnxEncoder::load(&spec.path)?;
    let info = scene_info(&spec.name, encoder.metadata(), limits)?;
    Ok((info, Box::new(encoder)))
}

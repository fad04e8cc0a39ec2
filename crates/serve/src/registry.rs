//! Scene registry: loads SPEC §8 model files into scenes (name, cameras from the metadata,
//! threshold, alpha, version) and their encoders, and checks that a replacement model fits
//! the scene it is meant for.
use std::path::Path;

use sha2::{Digest, Sha256};

use super::config::{Limits, ModelSpec};
use crate::error::Result;
use crossview_core::Encoder;
use crossview_core::SceneSpec;
use crossview_core::association::AssociationConfig;
use crossview_model::{ModelMetadata, OnnxEncoder};

/// What a model file says about its scene: name and cameras, association settings, version.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneInfo {
    /// Name and cameras.
    pub spec: SceneSpec,
    /// Association settings (SPEC §3 threshold and alpha, identity confidence), from the
    /// model's metadata ([`crossview_model::ModelMetadata::association_config`]).
    pub association: AssociationConfig,
    /// Model version string.
    pub version: String,
    /// The frame rate the model was trained at, if its file says (`crossview.train_fps`).
    pub fps: Option<f64>,
}

/// The scene description a model's metadata defines, checked against `limits`; `version` is
/// what results will name ([`model_version`]).
pub fn scene_info(
    name: &str,
    meta: &ModelMetadata,
    version: String,
    limits: &Limits,
) -> Result<SceneInfo> {
    if meta.cameras.is_empty() || meta.cameras.len() > limits.max_cameras {
        return Err(crossview_core::Error::model(
            name,
            format!(
                "{} cameras; 1..={} are supported",
                meta.cameras.len(),
                limits.max_cameras
            ),
        )
        .into());
    }
    Ok(SceneInfo {
        spec: SceneSpec {
            name: name.to_string(),
            cameras: meta.cameras.clone(),
        },
        association: meta.association_config(),
        version,
        // A scene's clock when nothing else declares one (a rate that is no rate: none).
        fps: meta
            .train_fps()
            .filter(|&f| crossview_core::types::check_fps(f).is_ok()),
    })
}

/// The version a served model goes by: its `crossview.version` and the first 12 hex digits
/// of the SHA-256 of the file, `VERSION@HASH`, so two different files never share one (a
/// retrained model keeps the crate's version string but not its bytes).
pub fn model_version(meta_version: &str, bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
    let hex: String = digest.iter().take(6).map(|b| format!("{b:02x}")).collect();
    format!("{meta_version}@{hex}")
}

/// Loads one model file (blocking: creates its ONNX Runtime session) into its scene
/// description and encoder.
pub(crate) fn load_model(
    spec: &ModelSpec,
    limits: &Limits,
) -> Result<(SceneInfo, Box<dyn Encoder>)> {
    let bytes = read(&spec.path)?;
    load_model_bytes(spec, &bytes, limits)
}

/// [`load_model`] on bytes already read from `spec.path` (a reload reads the file once, for
/// its hash and its session).
pub(crate) fn load_model_bytes(
    spec: &ModelSpec,
    bytes: &[u8],
    limits: &Limits,
) -> Result<(SceneInfo, Box<dyn Encoder>)> {
    let encoder = OnnxEncoder::from_bytes(&spec.path.display().to_string(), bytes)?;
    let version = model_version(&encoder.metadata().version, bytes);
    let info = scene_info(&spec.name, encoder.metadata(), version, limits)?;
    Ok((info, Box::new(encoder)))
}

fn read(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| {
        crossview_core::Error::Io {
            path: path.to_path_buf(),
            source: e,
        }
        .into()
    })
}

/// Refuses a model for `scene` whose cameras (names, order or image sizes) are not the
/// scene's: its camera indices and box normalisation would not mean the same.
pub(crate) fn check_fits(scene: &SceneSpec, new: &SceneInfo) -> Result<()> {
    // Clock offsets belong to the scene's declaration, not to the model.
    if new.spec.cameras.len() == scene.cameras.len()
        && new
            .spec
            .cameras
            .iter()
            .zip(&scene.cameras)
            .all(|(m, s)| m.same_camera(s))
    {
        return Ok(());
    }
    let describe = |s: &SceneSpec| {
        s.cameras
            .iter()
            .map(|c| format!("{}:{}x{}", c.name, c.width, c.height))
            .collect::<Vec<_>>()
            .join(",")
    };
    Err(crossview_core::Error::model(
        &scene.name,
        format!(
            "the model is for cameras {} but the scene has {}",
            describe(&new.spec),
            describe(scene)
        ),
    )
    .into())
}

//! The model file's `metadata_props` (SPEC §8): cameras, threshold, alpha, version and any
//! extra provenance (training data, steps, validation scores).
use std::collections::BTreeMap;

use crate::core::CameraSpec;

/// Metadata keys defined by SPEC §8.
pub const KEY_CAMERAS: &str = "crossview.cameras";
pub const KEY_THRESHOLD: &str = "crossview.threshold";
pub const KEY_ALPHA: &str = "crossview.alpha";
pub const KEY_VERSION: &str = "crossview.version";

/// Parsed, validated model metadata.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelMetadata {
    /// Cameras in camera-index order.
    pub cameras: Vec<CameraSpec>,
    /// Inference confidence threshold in [0, 1].
    pub threshold: f32,
    /// Appearance fusion weight in [0, 1].
    pub alpha: f32,
    /// Model version string.
    pub version: String,
    /// Any other `crossview.*` or free-form entries, kept verbatim.
    pub extra: BTreeMap<String, String>,
}

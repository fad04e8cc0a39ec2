//! The model file's `metadata_props` (SPEC §8): cameras, threshold, alpha, version and any
//! extra provenance (training data, steps, validation scores).
use std::collections::BTreeMap;

use crate::core::{CameraSpec, SceneSpec};
use crate::{Error, Result};

/// Metadata keys defined by SPEC §8.
pub const KEY_CAMERAS: &str = "crossview.cameras";
/// Inference confidence threshold (decimal string in [0, 1]).
pub const KEY_THRESHOLD: &str = "crossview.threshold";
/// Appearance fusion weight (decimal string in [0, 1]).
pub const KEY_ALPHA: &str = "crossview.alpha";
/// Model version string.
pub const KEY_VERSION: &str = "crossview.version";
/// Optional: the scene name the model was built for (an `extra` entry by convention).
pub const KEY_SCENE: &str = "crossview.scene";

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

impl ModelMetadata {
    /// Metadata for `cameras` with the WILDTRACK defaults (threshold 0.4, alpha 0.1) and the
    /// crossview crate version as model version.
    pub fn new(cameras: Vec<CameraSpec>) -> Self {
        ModelMetadata {
            cameras,
            threshold: 0.4,
            alpha: 0.1,
            version: env!("CARGO_PKG_VERSION").to_string(),
            extra: BTreeMap::new(),
        }
    }

    /// The scene these cameras form, under the name `name`.
    pub fn scene(&self, name: &str) -> SceneSpec {
        SceneSpec {
            name: name.to_string(),
            cameras: self.cameras.clone(),
        }
    }

    /// Checks the SPEC §8 rules; `source_name` (usually the file path) prefixes errors.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let bad = |key: &str, reason: String| Error::model(source_name, format!("{key}: {reason}"));
        if self.cameras.is_empty() {
            return Err(bad(KEY_CAMERAS, "camera list is empty".into()));
        }
        let mut seen = std::collections::HashSet::new();
        for (i, c) in self.cameras.iter().enumerate() {
            if c.name.trim().is_empty() {
                return Err(bad(KEY_CAMERAS, format!("camera {i} has an empty name")));
            }
            if !seen.insert(c.name.as_str()) {
                return Err(bad(
                    KEY_CAMERAS,
                    format!("duplicate camera name '{}'", c.name),
                ));
            }
            if c.width == 0 || c.height == 0 {
                return Err(bad(
                    KEY_CAMERAS,
                    format!(
                        "camera '{}' has size {}x{}; width and height must be > 0",
                        c.name, c.width, c.height
                    ),
                ));
            }
        }
        for (key, v) in [(KEY_THRESHOLD, self.threshold), (KEY_ALPHA, self.alpha)] {
            if !v.is_finite() || !(0.0..=1.0).contains(&v) {
                return Err(bad(key, format!("must be within [0, 1], got {v}")));
            }
        }
        if self.version.trim().is_empty() {
            return Err(bad(KEY_VERSION, "is empty".into()));
        }
        Ok(())
    }

    /// The `metadata_props` entries: the four SPEC §8 keys plus `extra` (an `extra` entry
    /// under one of the four keys is overridden by the typed field).
    pub fn to_props(&self) -> BTreeMap<String, String> {
        let mut props = self.extra.clone();
        let cameras = serde_json::to_string(&self.cameras).expect("CameraSpec always serializes");
        props.insert(KEY_CAMERAS.into(), cameras);
        props.insert(KEY_THRESHOLD.into(), self.threshold.to_string());
        props.insert(KEY_ALPHA.into(), self.alpha.to_string());
        props.insert(KEY_VERSION.into(), self.version.clone());
        props
    }

    /// Parses and validates `metadata_props`; errors are [`Error::Model`] naming `source_name`
    /// (the file) and the offending key.
    pub fn from_props(source_name: &str, props: &BTreeMap<String, String>) -> Result<Self> {
        let get = |key: &str| {
            props
                .get(key)
                .ok_or_else(|| Error::model(source_name, format!("metadata key {key} is missing")))
        };
        let cameras: Vec<CameraSpec> = serde_json::from_str(get(KEY_CAMERAS)?).map_err(|e| {
            Error::model(
                source_name,
                format!(
                    "{KEY_CAMERAS}: expected a JSON list of {{\"name\",\"width\",\"height\"}}: {e}"
                ),
            )
        })?;
        let unit = |key: &str| -> Result<f32> {
            let raw = get(key)?;
            raw.trim().parse::<f32>().map_err(|_| {
                Error::model(
                    source_name,
                    format!("{key}: expected a decimal number, got '{raw}'"),
                )
            })
        };
        let meta = ModelMetadata {
            cameras,
            threshold: unit(KEY_THRESHOLD)?,
            alpha: unit(KEY_ALPHA)?,
            version: get(KEY_VERSION)?.clone(),
            extra: props
                .iter()
                .filter(|(k, _)| {
                    ![KEY_CAMERAS, KEY_THRESHOLD, KEY_ALPHA, KEY_VERSION].contains(&k.as_str())
                })
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        };
        meta.validate(source_name)?;
        Ok(meta)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cams() -> Vec<CameraSpec> {
        vec![
            CameraSpec {
                name: "a".into(),
                width: 1920,
                height: 1080,
            },
            CameraSpec {
                name: "b".into(),
                width: 640,
                height: 480,
            },
        ]
    }

    #[test]
    fn props_round_trip() {
        let mut m = ModelMetadata::new(cams());
        m.extra.insert("crossview.epochs".into(), "12".into());
        let back = ModelMetadata::from_props("m.onnx", &m.to_props()).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.scene("s").cameras.len(), 2);
    }

    fn err_of(props: &BTreeMap<String, String>) -> String {
        ModelMetadata::from_props("m.onnx", props)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn bad_props_name_key_and_file() {
        let good = ModelMetadata::new(cams()).to_props();
        for (key, value) in [
            (KEY_THRESHOLD, "1.5"),
            (KEY_THRESHOLD, "abc"),
            (KEY_ALPHA, "NaN"),
            (KEY_CAMERAS, "[]"),
            (KEY_CAMERAS, "{"),
            (
                KEY_CAMERAS,
                r#"[{"name":"a","width":1,"height":1},{"name":"a","width":1,"height":1}]"#,
            ),
            (KEY_CAMERAS, r#"[{"name":"","width":1,"height":1}]"#),
            (KEY_CAMERAS, r#"[{"name":"a","width":0,"height":1}]"#),
            (KEY_VERSION, " "),
        ] {
            let mut p = good.clone();
            p.insert(key.into(), value.into());
            let msg = err_of(&p);
            assert!(msg.contains(key) && msg.contains("m.onnx"), "{msg}");
        }
        let mut p = good.clone();
        p.remove(KEY_VERSION);
        assert!(err_of(&p).contains(KEY_VERSION));
    }
}

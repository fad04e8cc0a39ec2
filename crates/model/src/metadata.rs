//! The model file's `metadata_props` (SPEC §8): cameras, threshold, alpha, version and any
//! extra provenance (training data, steps, validation scores).
use std::collections::BTreeMap;
use std::sync::Arc;

use crossview_core::association::{AssociationConfig, Mode};
use crossview_core::calibration::Calibration;
use crossview_core::identity::IdentityConfig;
use crossview_core::{CameraSpec, SceneSpec};
use crossview_core::{Error, Result};

/// Metadata keys defined by SPEC §8.
pub(crate) const KEY_CAMERAS: &str = "crossview.cameras";
/// Inference confidence threshold (decimal string in [0, 1]).
pub(crate) const KEY_THRESHOLD: &str = "crossview.threshold";
/// Appearance fusion weight (decimal string in [0, 1]).
pub(crate) const KEY_ALPHA: &str = "crossview.alpha";
/// Model version string.
pub(crate) const KEY_VERSION: &str = "crossview.version";
/// Optional: the scene name the model was built for (an `extra` entry by convention).
pub const KEY_SCENE: &str = "crossview.scene";
/// **[ours]** Optional: the training recording's frame rate and the step it was thinned by,
/// `{"fps": 2.0, "frame_step": 1}` (an `extra` entry, written by `crossview train`).
pub const KEY_TRAIN_FPS: &str = "crossview.train_fps";
/// **[ours]** Optional: the label-free calibration `P(same | distance)` (JSON, see
/// [`Calibration`]).
pub(crate) const KEY_CALIBRATION: &str = "crossview.calibration";
/// **[ours]** Optional: the threshold on the identity confidence (decimal string in [0, 1]);
/// without it identities use [`KEY_THRESHOLD`].
pub(crate) const KEY_MATCH_THRESHOLD: &str = "crossview.match_threshold";

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
    /// **[ours]** Calibrated match confidence, when the model has one.
    pub calibration: Option<Arc<Calibration>>,
    /// **[ours]** Threshold on the identity confidence (`None`: [`Self::threshold`]).
    pub match_threshold: Option<f32>,
    /// Any other `crossview.*` or free-form entries, kept verbatim.
    pub extra: BTreeMap<String, String>,
}

impl ModelMetadata {
    /// Metadata for `cameras` with the WILDTRACK defaults (threshold 0.4, alpha 0.1) and the
    /// crossview crate version as model version.
    pub fn new(cameras: Vec<CameraSpec>) -> Self {
        ModelMetadata {
            cameras: without_offsets(cameras),
            threshold: 0.4,
            alpha: 0.1,
            version: env!("CARGO_PKG_VERSION").to_string(),
            calibration: None,
            match_threshold: None,
            extra: BTreeMap::new(),
        }
    }

    /// The threshold identities use: [`Self::match_threshold`], else [`Self::threshold`].
    pub fn identity_threshold(&self) -> f32 {
        self.match_threshold.unwrap_or(self.threshold)
    }

    /// The association settings this model file asks for: SPEC §3 threshold and alpha for
    /// the pairwise matches, and identities scored with the model's calibration (when it has
    /// one) at [`Self::identity_threshold`].
    pub fn association_config(&self) -> AssociationConfig {
        AssociationConfig {
            threshold: self.threshold,
            alpha: self.alpha,
            mode: Mode::Pairwise,
            identity: IdentityConfig::new(self.calibration.clone(), self.identity_threshold()),
        }
    }

    /// The frame rate the model's training recording had ([`KEY_TRAIN_FPS`]), when the file
    /// records one.
    pub fn train_fps(&self) -> Option<f64> {
        let v: serde_json::Value = serde_json::from_str(self.extra.get(KEY_TRAIN_FPS)?).ok()?;
        v["fps"].as_f64()
    }

    /// The scene these cameras form, under the name `name` (every camera in sync: clock
    /// offsets belong to a scene's declaration, not to the model).
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
            c.check()
                .map_err(|e| bad(KEY_CAMERAS, format!("camera {i}: {e}")))?;
            if !seen.insert(c.name.as_str()) {
                return Err(bad(
                    KEY_CAMERAS,
                    format!("duplicate camera name '{}'", c.name),
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
        if let Some(t) = self.match_threshold
            && (!t.is_finite() || !(0.0..=1.0).contains(&t))
        {
            return Err(bad(
                KEY_MATCH_THRESHOLD,
                format!("must be within [0, 1], got {t}"),
            ));
        }
        if let Some(c) = &self.calibration {
            c.validate()
                .map_err(|e| bad(KEY_CALIBRATION, e.to_string()))?;
        }
        Ok(())
    }

    /// The `metadata_props` entries: the four SPEC §8 keys plus `extra` (an `extra` entry
    /// under one of the four keys is overridden by the typed field).
    pub(crate) fn to_props(&self) -> BTreeMap<String, String> {
        let mut props = self.extra.clone();
        let cameras = serde_json::to_string(&self.cameras).expect("CameraSpec always serializes");
        props.insert(KEY_CAMERAS.into(), cameras);
        props.insert(KEY_THRESHOLD.into(), self.threshold.to_string());
        props.insert(KEY_ALPHA.into(), self.alpha.to_string());
        props.insert(KEY_VERSION.into(), self.version.clone());
        props.remove(KEY_CALIBRATION);
        props.remove(KEY_MATCH_THRESHOLD);
        if let Some(c) = &self.calibration {
            let json = serde_json::to_string(c.as_ref()).expect("Calibration always serializes");
            props.insert(KEY_CALIBRATION.into(), json);
        }
        if let Some(t) = self.match_threshold {
            props.insert(KEY_MATCH_THRESHOLD.into(), t.to_string());
        }
        props
    }

    /// Parses and validates `metadata_props`; errors are [`Error::Model`] naming `source_name`
    /// (the file) and the offending key.
    pub(crate) fn from_props(source_name: &str, props: &BTreeMap<String, String>) -> Result<Self> {
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
        let calibration = props
            .get(KEY_CALIBRATION)
            .map(|raw| {
                serde_json::from_str::<Calibration>(raw).map_err(|e| {
                    Error::model(
                        source_name,
                        format!("{KEY_CALIBRATION}: not a calibration table: {e}"),
                    )
                })
            })
            .transpose()?
            .map(Arc::new);
        let match_threshold = props
            .contains_key(KEY_MATCH_THRESHOLD)
            .then(|| unit(KEY_MATCH_THRESHOLD))
            .transpose()?;
        let meta = ModelMetadata {
            cameras: without_offsets(cameras),
            threshold: unit(KEY_THRESHOLD)?,
            alpha: unit(KEY_ALPHA)?,
            version: get(KEY_VERSION)?.clone(),
            calibration,
            match_threshold,
            extra: props
                .iter()
                .filter(|(k, _)| {
                    ![
                        KEY_CAMERAS,
                        KEY_THRESHOLD,
                        KEY_ALPHA,
                        KEY_VERSION,
                        KEY_CALIBRATION,
                        KEY_MATCH_THRESHOLD,
                    ]
                    .contains(&k.as_str())
                })
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect(),
        };
        meta.validate(source_name)?;
        Ok(meta)
    }
}

/// `cameras` with every clock offset at 0: a model describes cameras (names, image sizes),
/// the installation's clocks are the scene declaration's (`@±N`), so a model trained on a
/// recording with declared offsets does not carry them.
fn without_offsets(cameras: Vec<CameraSpec>) -> Vec<CameraSpec> {
    cameras
        .into_iter()
        .map(|c| CameraSpec {
            offset: 0,
            offset_ms: 0,
            ..c
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cams() -> Vec<CameraSpec> {
        vec![
            CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: "a".into(),
                width: 1920,
                height: 1080,
            },
            CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: "b".into(),
                width: 640,
                height: 480,
            },
        ]
    }

    #[test]
    fn models_carry_no_clock_offsets() {
        let mut cameras = cams();
        cameras[1].offset = 5;
        let m = ModelMetadata::new(cameras);
        assert!(m.cameras.iter().all(|c| c.offset == 0));
        let mut props = m.to_props();
        props.insert(
            KEY_CAMERAS.into(),
            r#"[{"name":"a","width":8,"height":6,"offset":3}]"#.into(),
        );
        let back = ModelMetadata::from_props("m.onnx", &props).unwrap();
        assert_eq!(back.cameras[0].offset, 0);
    }

    #[test]
    fn props_round_trip() {
        let mut m = ModelMetadata::new(cams());
        m.extra.insert("crossview.epochs".into(), "12".into());
        let back = ModelMetadata::from_props("m.onnx", &m.to_props()).unwrap();
        assert_eq!(back, m);
        assert_eq!(back.scene("s").cameras.len(), 2);
        assert_eq!(back.association_config().identity.threshold, m.threshold);
        m.calibration = Some(Arc::new(Calibration {
            distances: vec![1.0, 2.0],
            probabilities: vec![0.9, 0.1],
            false_share: 0.5,
            samples: [60, 60],
        }));
        m.match_threshold = Some(0.25);
        let back = ModelMetadata::from_props("m.onnx", &m.to_props()).unwrap();
        assert_eq!(back, m);
        let cfg = back.association_config();
        assert_eq!(cfg.identity.threshold, 0.25);
        assert!(cfg.identity.calibration.is_some());
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
            (KEY_MATCH_THRESHOLD, "2"),
            (KEY_CALIBRATION, "{}"),
            (
                KEY_CALIBRATION,
                r#"{"distances":[1,2],"probabilities":[0.1,0.9],"false_share":0.5,"samples":[1,1]}"#,
            ),
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

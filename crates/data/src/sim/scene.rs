//! Scene layouts: the walkable area and the cameras, from a built-in preset or a JSON file.
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::camera::{Camera, CameraConfig};
use crossview_core::SceneSpec;
use crossview_core::{Error, Result};

/// Names accepted by [`SceneConfig::preset`].
pub(crate) const PRESETS: &[&str] = &["square4", "wildtrack", "pair"];

/// A simulated scene: a rectangular walkable area `[0, area[0]] x [0, area[1]]` metres on
/// the ground plane and the static cameras watching it. This is the scene-file format (JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneConfig {
    /// Scene name, written into recordings.
    pub name: String,
    /// Size of the walkable area `[x, y]` in metres.
    pub area: [f64; 2],
    /// Cameras in camera-index order.
    pub cameras: Vec<CameraConfig>,
}

fn look(name: &str, pos: [f64; 3], target: [f64; 3], f: f64, w: u32, h: u32) -> CameraConfig {
    CameraConfig {
        name: name.to_string(),
        position: pos,
        yaw_deg: None,
        pitch_deg: None,
        look_at: Some(target),
        focal_px: f,
        width: w,
        height: h,
        principal: None,
    }
}

fn posed(name: &str, pos: [f64; 3], yaw: f64, pitch: f64, f: f64) -> CameraConfig {
    CameraConfig {
        name: name.to_string(),
        position: pos,
        yaw_deg: Some(yaw),
        pitch_deg: Some(pitch),
        look_at: None,
        focal_px: f,
        width: 1920,
        height: 1080,
        principal: None,
    }
}

impl SceneConfig {
    /// A built-in layout:
    /// - `square4`: 12x12 m, four 1280x720 cameras 4 m high at the corners, 2 m outside,
    ///   looking at the centre;
    /// - `wildtrack`: 12x36 m, seven 1920x1080 cameras placed like WILDTRACK's (positions,
    ///   headings, tilts and focal lengths taken from its calibration, rounded);
    /// - `pair`: 8x8 m, two 1280x720 cameras at right angles (small and fast, for tests).
    pub fn preset(name: &str) -> Result<Self> {
        let scene = match name {
            "square4" => {
                let c = [6.0, 6.0, 0.0];
                SceneConfig {
                    name: "square4".into(),
                    area: [12.0, 12.0],
                    cameras: vec![
                        look("cam0", [-2.0, -2.0, 4.0], c, 800.0, 1280, 720),
                        look("cam1", [14.0, -2.0, 4.0], c, 800.0, 1280, 720),
                        look("cam2", [14.0, 14.0, 4.0], c, 800.0, 1280, 720),
                        look("cam3", [-2.0, 14.0, 4.0], c, 800.0, 1280, 720),
                    ],
                }
            }
            "wildtrack" => SceneConfig {
                name: "wildtrack".into(),
                area: [12.0, 36.0],
                // From the WILDTRACK calibration, shifted so the area starts at the origin.
                cameras: vec![
                    posed("C1", [12.1, 3.16, 2.89], 118.3, 13.6, 1740.0),
                    posed("C2", [1.86, 32.78, 1.99], -57.0, 14.4, 1713.0),
                    posed("C3", [12.01, 26.71, 2.65], -115.1, 13.6, 1746.0),
                    posed("C4", [12.0, 3.15, 2.77], 149.2, 16.9, 1723.0),
                    posed("C5", [-0.99, 18.38, 1.68], -11.7, 8.7, 1723.0),
                    posed("C6", [1.37, -1.64, 2.25], 63.0, 8.8, 1745.0),
                    posed("C7", [14.76, 10.87, 3.4], 155.9, 20.1, 1745.0),
                ],
            },
            "pair" => {
                let c = [4.0, 4.0, 0.0];
                SceneConfig {
                    name: "pair".into(),
                    area: [8.0, 8.0],
                    cameras: vec![
                        look("south", [4.0, -3.0, 3.0], c, 700.0, 1280, 720),
                        look("west", [-3.0, 4.0, 3.0], c, 700.0, 1280, 720),
                    ],
                }
            }
            other => {
                return Err(Error::invalid(
                    "preset",
                    format!("unknown preset '{other}', expected one of {PRESETS:?}"),
                ));
            }
        };
        Ok(scene)
    }

    /// Parses a JSON scene description (`source_name` names it in errors) and validates it.
    pub(crate) fn from_json_str(text: &str, source_name: &str) -> Result<Self> {
        let scene: SceneConfig = serde_json::from_str(text).map_err(|e| Error::Format {
            source_name: source_name.to_string(),
            line: e.line(),
            message: e.to_string(),
        })?;
        scene.validate()?;
        Ok(scene)
    }

    /// Reads and validates a JSON scene file.
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_json_str(&text, &path.display().to_string())
    }

    /// Checks the area and every camera; cameras must have unique names.
    pub fn validate(&self) -> Result<()> {
        self.build_cameras().map(|_| ())
    }

    /// The cameras, built and validated, in camera-index order.
    pub(crate) fn build_cameras(&self) -> Result<Vec<Camera>> {
        if !self.area.iter().all(|a| a.is_finite() && *a > 0.0) {
            return Err(Error::invalid(
                "area",
                format!("both sides must be positive metres, got {:?}", self.area),
            ));
        }
        if self.cameras.is_empty() {
            return Err(Error::invalid(
                "cameras",
                "a scene needs at least one camera",
            ));
        }
        let mut out = Vec::with_capacity(self.cameras.len());
        for (i, c) in self.cameras.iter().enumerate() {
            if c.name.is_empty() {
                return Err(Error::invalid(format!("cameras[{i}].name"), "is empty"));
            }
            if self.cameras[..i].iter().any(|o| o.name == c.name) {
                return Err(Error::invalid(
                    format!("cameras[{i}].name"),
                    format!("duplicate camera name '{}'", c.name),
                ));
            }
            out.push(c.build(&format!("cameras[{i}]"))?);
        }
        Ok(out)
    }

    /// The recording's scene header: names and image sizes.
    pub fn spec(&self) -> SceneSpec {
        SceneSpec {
            name: self.name.clone(),
            cameras: self
                .cameras
                .iter()
                .map(|c| crossview_core::CameraSpec {
                    offset: 0,
                    offset_ms: 0,
                    name: c.name.clone(),
                    width: c.width,
                    height: c.height,
                })
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_build_and_look_into_the_area() {
        for name in PRESETS {
            let scene = SceneConfig::preset(name).unwrap();
            let cams = scene.build_cameras().unwrap();
            let centre = [scene.area[0] / 2.0, scene.area[1] / 2.0, 0.0];
            let mut seen_by = 0;
            for cam in &cams {
                if let Some(p) = cam.project(centre)
                    && (0.0..cam.spec.width as f64).contains(&p[0])
                    && (0.0..cam.spec.height as f64).contains(&p[1])
                {
                    seen_by += 1;
                }
            }
            assert!(seen_by >= 2, "{name}: centre seen by {seen_by} cameras");
        }
        assert!(SceneConfig::preset("nope").is_err());
    }

    #[test]
    fn scene_file_round_trips_and_bad_files_are_named() {
        let scene = SceneConfig::preset("square4").unwrap();
        let text = serde_json::to_string_pretty(&scene).unwrap();
        assert_eq!(SceneConfig::from_json_str(&text, "s.json").unwrap(), scene);
        let err = SceneConfig::from_json_str("{\"name\": 3}", "bad.json").unwrap_err();
        assert!(err.to_string().starts_with("bad.json:1:"), "{err}");
        let mut dup = scene.clone();
        dup.cameras[1].name = "cam0".into();
        let err = dup.validate().unwrap_err().to_string();
        assert!(err.contains("duplicate camera name"), "{err}");
        let mut bad = scene;
        bad.area = [0.0, 5.0];
        assert!(bad.validate().is_err());
    }
}

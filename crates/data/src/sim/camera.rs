//! Pinhole camera geometry: world-to-image projection and its inverse on the ground plane.
//!
//! World frame: metres, ground plane `z = 0`, `z` up. Camera frame (OpenCV convention):
//! `x` right, `y` down, `z` forward; pixels `u = fx * x/z + cx`, `v = fy * y/z + cy`.
use serde::{Deserialize, Serialize};

use crossview_core::CameraSpec;
use crossview_core::{Error, Result};

/// Points closer than this in front of the camera (metres) count as behind it.
pub(crate) const NEAR_PLANE: f64 = 0.1;

/// One camera as written in a scene file. Orientation is either `yaw_deg` + `pitch_deg`
/// (yaw: heading in the ground plane, counter-clockwise from +x; pitch: downward tilt) or a
/// `look_at` point in world coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Camera name (unique in the scene).
    pub name: String,
    /// Optical centre `[x, y, z]` in metres (`z` = mounting height).
    pub position: [f64; 3],
    /// Heading in degrees, counter-clockwise from the +x axis.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub yaw_deg: Option<f64>,
    /// Downward tilt in degrees (0 = horizontal, positive = looking down).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pitch_deg: Option<f64>,
    /// A world point the camera looks at; replaces `yaw_deg`/`pitch_deg`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub look_at: Option<[f64; 3]>,
    /// Focal length in pixels (square pixels).
    pub focal_px: f64,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Principal point `[cx, cy]` in pixels; default: the image centre.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub principal: Option<[f64; 2]>,
}

impl CameraConfig {
    /// Builds the camera, checking every value (`field` prefixes error messages).
    pub fn build(&self, field: &str) -> Result<Camera> {
        let (yaw, pitch) = match (self.look_at, self.yaw_deg, self.pitch_deg) {
            (Some(target), None, None) => {
                check_finite(&format!("{field}.look_at"), &target)?;
                let d = [
                    target[0] - self.position[0],
                    target[1] - self.position[1],
                    target[2] - self.position[2],
                ];
                let horiz = d[0].hypot(d[1]);
                if horiz < 1e-9 {
                    return Err(Error::invalid(
                        format!("{field}.look_at"),
                        "must not be straight above or below the camera",
                    ));
                }
                (d[1].atan2(d[0]), (-d[2]).atan2(horiz))
            }
            (None, Some(yaw), Some(pitch)) => (yaw.to_radians(), pitch.to_radians()),
            _ => {
                return Err(Error::invalid(
                    field,
                    "give either look_at or both yaw_deg and pitch_deg",
                ));
            }
        };
        let (cx, cy) = match self.principal {
            Some([cx, cy]) => (cx, cy),
            None => (self.width as f64 / 2.0, self.height as f64 / 2.0),
        };
        Camera::from_pose(
            CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: self.name.clone(),
                width: self.width,
                height: self.height,
            },
            self.position,
            yaw,
            pitch,
            [self.focal_px, self.focal_px, cx, cy],
        )
        .map_err(|e| prefix(field, e))
    }
}

fn prefix(field: &str, e: Error) -> Error {
    match e {
        Error::InvalidArgument { field: f, reason } => Error::InvalidArgument {
            field: format!("{field}.{f}"),
            reason,
        },
        other => other,
    }
}

fn check_finite(field: &str, v: &[f64]) -> Result<()> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(Error::invalid(field, format!("must be finite, got {v:?}")))
    }
}

/// A change of one camera's pose or focal length at a given second of a simulated recording
/// (`crossview simulate --move`): the truth the camera-fit watch is tested against.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraMove {
    /// The camera that moves.
    pub camera: String,
    /// Seconds after the first frame.
    pub at_s: f64,
    /// Turn about the camera's vertical axis, degrees (positive: the view swings right).
    #[serde(default)]
    pub pan_deg: f64,
    /// Turn about the camera's horizontal axis, degrees (positive: the view swings down).
    #[serde(default)]
    pub tilt_deg: f64,
    /// Focal length factor (1: unchanged; 1.2: zoomed in by 20 %).
    #[serde(default = "one")]
    pub zoom: f64,
}

fn one() -> f64 {
    1.0
}

impl CameraMove {
    /// A pan of `camera` at `at_s` seconds that moves its image centre by `fraction` of the
    /// image width (no tilt, no zoom).
    pub fn pan(camera: &CameraConfig, at_s: f64, fraction: f64) -> Self {
        CameraMove {
            camera: camera.name.clone(),
            at_s,
            pan_deg: Self::pan_for(fraction, camera.width, camera.focal_px),
            tilt_deg: 0.0,
            zoom: 1.0,
        }
    }

    /// Checks the values: finite, within ±60° and a zoom within `[0.25, 4]`.
    pub fn validate(&self) -> Result<()> {
        if !self.at_s.is_finite() || self.at_s < 0.0 {
            return Err(Error::invalid(
                "move.at_s",
                format!(
                    "must be a non-negative number of seconds, got {}",
                    self.at_s
                ),
            ));
        }
        for (field, v) in [
            ("move.pan_deg", self.pan_deg),
            ("move.tilt_deg", self.tilt_deg),
        ] {
            if !v.is_finite() || v.abs() > 60.0 {
                return Err(Error::invalid(
                    field,
                    format!("must be within ±60, got {v}"),
                ));
            }
        }
        if !self.zoom.is_finite() || !(0.25..=4.0).contains(&self.zoom) {
            return Err(Error::invalid(
                "move.zoom",
                format!("must be within [0.25, 4], got {}", self.zoom),
            ));
        }
        Ok(())
    }

    /// The pan, in degrees, that moves the image centre by `fraction` of the width of a
    /// camera `width` pixels wide with focal length `focal_px`.
    pub fn pan_for(fraction: f64, width: u32, focal_px: f64) -> f64 {
        (fraction * f64::from(width) / focal_px).atan().to_degrees()
    }
}

/// A calibrated static pinhole camera (no lens distortion).
#[derive(Debug, Clone, PartialEq)]
pub struct Camera {
    /// Name and image size, as written into recordings.
    pub spec: CameraSpec,
    /// Intrinsics `[fx, fy, cx, cy]` in pixels.
    k: [f64; 4],
    /// World-to-camera rotation; rows are the camera's right, down and forward axes in world
    /// coordinates.
    r: [[f64; 3]; 3],
    /// Optical centre in world coordinates.
    center: [f64; 3],
}

impl Camera {
    /// A camera at `position` with heading `yaw` and downward tilt `pitch` (radians, no roll)
    /// and intrinsics `[fx, fy, cx, cy]`.
    pub(crate) fn from_pose(
        spec: CameraSpec,
        position: [f64; 3],
        yaw: f64,
        pitch: f64,
        k: [f64; 4],
    ) -> Result<Self> {
        check_finite("position", &position)?;
        check_finite("intrinsics", &k)?;
        if !yaw.is_finite() {
            return Err(Error::invalid("yaw_deg", "must be finite"));
        }
        if !pitch.is_finite() || pitch.abs() >= std::f64::consts::FRAC_PI_2 {
            return Err(Error::invalid(
                "pitch_deg",
                format!(
                    "must be strictly between -90 and 90 degrees, got {}",
                    pitch.to_degrees()
                ),
            ));
        }
        let (sy, cy) = yaw.sin_cos();
        let (sp, cp) = pitch.sin_cos();
        let forward = [cp * cy, cp * sy, -sp];
        let right = [sy, -cy, 0.0];
        let down = cross(forward, right);
        Self::new(spec, k, [right, down, forward], position)
    }

    /// A camera from OpenCV-style calibration: intrinsic matrix `K` and extrinsics `R`, `t`
    /// with `x_cam = R * X_world + t` (world units as given, ground plane `z = 0`). Test-only:
    /// it checks the simulator's cameras against the calibration form datasets use.
    #[cfg(test)]
    pub(crate) fn from_krt(
        spec: CameraSpec,
        k: [[f64; 3]; 3],
        r: [[f64; 3]; 3],
        t: [f64; 3],
    ) -> Result<Self> {
        for row in k.iter().chain(r.iter()) {
            check_finite("calibration", row)?;
        }
        check_finite("calibration.t", &t)?;
        // centre = -R^T t
        let center = [
            -(r[0][0] * t[0] + r[1][0] * t[1] + r[2][0] * t[2]),
            -(r[0][1] * t[0] + r[1][1] * t[1] + r[2][1] * t[2]),
            -(r[0][2] * t[0] + r[1][2] * t[1] + r[2][2] * t[2]),
        ];
        Self::new(spec, [k[0][0], k[1][1], k[0][2], k[1][2]], r, center)
    }

    fn new(spec: CameraSpec, k: [f64; 4], r: [[f64; 3]; 3], center: [f64; 3]) -> Result<Self> {
        if spec.width == 0 || spec.height == 0 {
            return Err(Error::invalid(
                "width/height",
                format!(
                    "image size must be positive, got {}x{}",
                    spec.width, spec.height
                ),
            ));
        }
        if k[0] <= 0.0 || k[1] <= 0.0 {
            return Err(Error::invalid(
                "focal_px",
                format!("must be positive, got {}", k[0].min(k[1])),
            ));
        }
        Ok(Camera { spec, k, r, center })
    }

    /// The same camera after a move: turned by `pan_deg` about its own vertical (image-down)
    /// axis (positive: the view swings right, what was at the centre moves left in the image),
    /// tilted by `tilt_deg` about its own horizontal axis (positive: the view swings down),
    /// and its focal length times `zoom`. What a bump, a re-aim or a zoom does to a static
    /// camera: the pose changes, the mount stays.
    pub fn moved(&self, m: &CameraMove) -> Result<Camera> {
        m.validate()?;
        let (sp, cp) = m.pan_deg.to_radians().sin_cos();
        let (st, ct) = m.tilt_deg.to_radians().sin_cos();
        // Rows of the new camera axes in the old camera frame: pan about y, then tilt about x.
        let pan = [[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]];
        let tilt = [[1.0, 0.0, 0.0], [0.0, ct, -st], [0.0, st, ct]];
        let turn = matmul(tilt, pan);
        let r = matmul(turn, self.r);
        let k = [self.k[0] * m.zoom, self.k[1] * m.zoom, self.k[2], self.k[3]];
        Camera::new(self.spec.clone(), k, r, self.center)
    }

    /// Optical centre in world coordinates.
    pub(crate) fn center(&self) -> [f64; 3] {
        self.center
    }

    /// A world point in camera coordinates (`z` = depth along the optical axis).
    pub(crate) fn to_camera(&self, p: [f64; 3]) -> [f64; 3] {
        let d = [
            p[0] - self.center[0],
            p[1] - self.center[1],
            p[2] - self.center[2],
        ];
        [dot(self.r[0], d), dot(self.r[1], d), dot(self.r[2], d)]
    }

    /// Pixel of a world point, or `None` when it lies behind the near plane.
    /// The pixel may fall outside the image.
    pub fn project(&self, p: [f64; 3]) -> Option<[f64; 2]> {
        let c = self.to_camera(p);
        if c[2] < NEAR_PLANE {
            return None;
        }
        Some([
            self.k[0] * c[0] / c[2] + self.k[2],
            self.k[1] * c[1] / c[2] + self.k[3],
        ])
    }

    /// The ground-plane point (`z = 0`) seen at pixel `(u, v)`: the inverse of the ground
    /// homography. `None` when the pixel's ray does not hit the ground in front of the camera
    /// (at or above the horizon).
    pub fn ground_point(&self, u: f64, v: f64) -> Option<[f64; 2]> {
        if !u.is_finite() || !v.is_finite() {
            return None;
        }
        let ray_cam = [
            (u - self.k[2]) / self.k[0],
            (v - self.k[3]) / self.k[1],
            1.0,
        ];
        // world ray = R^T ray_cam
        let ray = [
            self.r[0][0] * ray_cam[0] + self.r[1][0] * ray_cam[1] + self.r[2][0] * ray_cam[2],
            self.r[0][1] * ray_cam[0] + self.r[1][1] * ray_cam[1] + self.r[2][1] * ray_cam[2],
            self.r[0][2] * ray_cam[0] + self.r[1][2] * ray_cam[1] + self.r[2][2] * ray_cam[2],
        ];
        if ray[2].abs() < 1e-12 {
            return None;
        }
        let t = -self.center[2] / ray[2];
        if t <= 0.0 {
            return None;
        }
        Some([self.center[0] + t * ray[0], self.center[1] + t * ray[1]])
    }

    /// The ground position of a person from their box: the bottom-centre of `bbox`
    /// (`[x1, y1, x2, y2]` pixels) mapped through [`Camera::ground_point`].
    pub(crate) fn ground_point_of_box(&self, bbox: [f32; 4]) -> Option<[f64; 2]> {
        let u = (bbox[0] as f64 + bbox[2] as f64) / 2.0;
        self.ground_point(u, bbox[3] as f64)
    }

    /// The 3x3 homography mapping ground points `(x, y, 1)` to homogeneous pixels:
    /// `K [r1 r2 t]` with `r1`, `r2` the first two columns of `R` and `t = -R c` (test-only).
    #[cfg(test)]
    pub(crate) fn ground_homography(&self) -> [[f64; 3]; 3] {
        let t = [
            -dot(self.r[0], self.center),
            -dot(self.r[1], self.center),
            -dot(self.r[2], self.center),
        ];
        let [fx, fy, cx, cy] = self.k;
        let mut h = [[0.0; 3]; 3];
        for (col, src) in [
            [self.r[0][0], self.r[1][0], self.r[2][0]],
            [self.r[0][1], self.r[1][1], self.r[2][1]],
            t,
        ]
        .iter()
        .enumerate()
        {
            h[0][col] = fx * src[0] + cx * src[2];
            h[1][col] = fy * src[1] + cy * src[2];
            h[2][col] = src[2];
        }
        h
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn matmul(a: [[f64; 3]; 3], b: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        CameraConfig {
            name: "c".into(),
            position: [0.0, 0.0, 3.0],
            yaw_deg: None,
            pitch_deg: None,
            look_at: Some([10.0, 0.0, 0.0]),
            focal_px: 1000.0,
            width: 1920,
            height: 1080,
            principal: None,
        }
        .build("camera")
        .unwrap()
    }

    fn turn(pan_deg: f64, tilt_deg: f64, zoom: f64) -> CameraMove {
        CameraMove {
            camera: "c".into(),
            at_s: 0.0,
            pan_deg,
            tilt_deg,
            zoom,
        }
    }

    #[test]
    fn a_move_turns_the_view_about_the_mount_and_zooms_about_the_centre() {
        let c = cam();
        let centre = [10.0, 0.0, 0.0];
        // Panned right by 5 % of the width: what was at the centre is 96 px further left.
        let pan = c
            .moved(&turn(CameraMove::pan_for(0.05, 1920, 1000.0), 0.0, 1.0))
            .unwrap();
        let p = pan.project(centre).unwrap();
        assert!(
            (p[0] - (960.0 - 96.0)).abs() < 1e-6 && (p[1] - 540.0).abs() < 1e-6,
            "{p:?}"
        );
        assert_eq!(pan.center(), c.center());
        // Tilted down: it moves up.
        assert!(
            c.moved(&turn(0.0, 3.0, 1.0))
                .unwrap()
                .project(centre)
                .unwrap()[1]
                < 540.0
        );
        // Zoomed 1.2×: offsets from the centre grow by 1.2, the centre stays.
        let zoom = c.moved(&turn(0.0, 0.0, 1.2)).unwrap();
        let (a, b) = (
            c.project([10.0, 1.0, 0.0]).unwrap(),
            zoom.project([10.0, 1.0, 0.0]).unwrap(),
        );
        assert!(((b[0] - 960.0) - 1.2 * (a[0] - 960.0)).abs() < 1e-6);
        assert_eq!(zoom.project(centre).unwrap(), c.project(centre).unwrap());
        // Nothing moves: the same camera.
        assert_eq!(c.moved(&turn(0.0, 0.0, 1.0)).unwrap(), c);
        for bad in [
            turn(f64::NAN, 0.0, 1.0),
            turn(0.0, 61.0, 1.0),
            turn(0.0, 0.0, 0.0),
        ] {
            assert!(c.moved(&bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn optical_axis_hits_image_centre_and_ground_round_trips() {
        let c = cam();
        let p = c.project([10.0, 0.0, 0.0]).unwrap();
        assert!((p[0] - 960.0).abs() < 1e-9 && (p[1] - 540.0).abs() < 1e-9);
        // a point to the camera's left (+y when facing +x) lands left of centre
        assert!(c.project([10.0, 1.0, 0.0]).unwrap()[0] < 960.0);
        // higher points land higher in the image
        assert!(c.project([10.0, 0.0, 1.0]).unwrap()[1] < 540.0);
        for g in [[5.0, 1.0], [12.0, -3.0], [30.0, 4.0]] {
            let px = c.project([g[0], g[1], 0.0]).unwrap();
            let back = c.ground_point(px[0], px[1]).unwrap();
            assert!((back[0] - g[0]).abs() < 1e-6 && (back[1] - g[1]).abs() < 1e-6);
            let h = c.ground_homography();
            let w = h[2][0] * g[0] + h[2][1] * g[1] + h[2][2];
            let hu = (h[0][0] * g[0] + h[0][1] * g[1] + h[0][2]) / w;
            let hv = (h[1][0] * g[0] + h[1][1] * g[1] + h[1][2]) / w;
            assert!((hu - px[0]).abs() < 1e-6 && (hv - px[1]).abs() < 1e-6);
        }
    }

    #[test]
    fn behind_camera_and_above_horizon_are_none() {
        let c = cam();
        assert!(c.project([-5.0, 0.0, 0.0]).is_none());
        assert!(c.ground_point(960.0, 0.0).is_none());
        assert!(c.ground_point(f64::NAN, 500.0).is_none());
    }

    #[test]
    fn krt_matches_pose() {
        let c = cam();
        let r = c.r;
        let t = [
            -dot(r[0], c.center),
            -dot(r[1], c.center),
            -dot(r[2], c.center),
        ];
        let k = [[1000.0, 0.0, 960.0], [0.0, 1000.0, 540.0], [0.0, 0.0, 1.0]];
        let c2 = Camera::from_krt(c.spec.clone(), k, r, t).unwrap();
        let p = [7.0, 2.0, 1.5];
        let (a, b) = (c.project(p).unwrap(), c2.project(p).unwrap());
        assert!((a[0] - b[0]).abs() < 1e-9 && (a[1] - b[1]).abs() < 1e-9);
    }

    #[test]
    fn bad_cameras_are_rejected() {
        let mut cfg = CameraConfig {
            name: "c".into(),
            position: [0.0, 0.0, 3.0],
            yaw_deg: Some(0.0),
            pitch_deg: Some(95.0),
            look_at: None,
            focal_px: 1000.0,
            width: 100,
            height: 100,
            principal: None,
        };
        assert!(cfg.build("cameras[0]").is_err());
        cfg.pitch_deg = Some(10.0);
        cfg.focal_px = -1.0;
        let err = cfg.build("cameras[0]").unwrap_err().to_string();
        assert!(err.contains("cameras[0].focal_px"), "{err}");
        cfg.focal_px = 1000.0;
        cfg.position[0] = f64::NAN;
        assert!(cfg.build("cameras[0]").is_err());
        cfg.position[0] = 0.0;
        cfg.look_at = Some([1.0, 0.0, 0.0]);
        assert!(cfg.build("cameras[0]").is_err(), "look_at with yaw/pitch");
    }
}

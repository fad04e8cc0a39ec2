//! Calibrated ground-plane recovery: where a box stands on the ground for a known camera
//! (the inverse ground homography of its bottom-centre), and ground distances between two
//! views' boxes. Used by the simulator's sanity checks and by a calibrated baseline.
use ndarray::Array2;

use super::camera::Camera;
use crossview_core::Detection;

/// Cost given to pairs where either box has no ground position (its bottom-centre is above
/// the horizon): finite, so assignment still works, and larger than any real distance.
pub(crate) const UNREACHABLE_M: f32 = 1.0e6;

/// Typical body radius in metres: a box's bottom-centre is the front of the feet, about this
/// far in front of where the person stands.
pub const BODY_RADIUS_M: f64 = 0.25;

/// Where a person stands, from their box in `cam`: the ground point of the box's
/// bottom-centre, pushed `body_radius` further away from the camera (0 keeps the raw point).
/// `None` where the pixel does not see the ground.
pub(crate) fn standing_point(cam: &Camera, bbox: [f32; 4], body_radius: f64) -> Option<[f64; 2]> {
    let g = cam.ground_point_of_box(bbox)?;
    let c = cam.center();
    let (dx, dy) = (g[0] - c[0], g[1] - c[1]);
    let n = dx.hypot(dy);
    if n < 1e-9 {
        return Some(g);
    }
    Some([g[0] + dx / n * body_radius, g[1] + dy / n * body_radius])
}

/// The standing point (see [`standing_point`]) of each detection.
pub(crate) fn ground_positions(
    cam: &Camera,
    dets: &[Detection],
    body_radius: f64,
) -> Vec<Option<[f64; 2]>> {
    dets.iter()
        .map(|d| standing_point(cam, d.bbox, body_radius))
        .collect()
}

/// Ground-plane distances `[n, m]` between the boxes of two views (world units), with
/// 10⁶ (unreachable) where a position is unknown.
pub fn ground_distances(
    cam_a: &Camera,
    dets_a: &[Detection],
    cam_b: &Camera,
    dets_b: &[Detection],
    body_radius: f64,
) -> Array2<f32> {
    let pa = ground_positions(cam_a, dets_a, body_radius);
    let pb = ground_positions(cam_b, dets_b, body_radius);
    Array2::from_shape_fn((pa.len(), pb.len()), |(i, j)| match (pa[i], pb[j]) {
        (Some(a), Some(b)) => ((a[0] - b[0]).hypot(a[1] - b[1]) as f32).min(UNREACHABLE_M),
        _ => UNREACHABLE_M,
    })
}

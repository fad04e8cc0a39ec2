//! From people on the ground to ground-truth boxes in one camera: cylinder projection, image
//! border clipping, size limits and occlusion by nearer people (depth order).
use super::camera::Camera;
use super::crowd::Person;
use crossview_core::{Error, Result};

/// Rules that turn projections into ground-truth boxes.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderConfig {
    /// Boxes shorter than this many pixels (after clipping) are dropped.
    pub min_height_px: f64,
    /// A person whose projection lies less than this fraction inside the image is dropped.
    pub min_inside: f64,
    /// A person hidden by nearer people over more than this fraction of their box is dropped.
    pub max_occluded: f64,
    /// Shrink partly occluded boxes to their visible part (as a detector would).
    pub shrink_occluded: bool,
}

impl Default for RenderConfig {
    fn default() -> Self {
        RenderConfig {
            min_height_px: 20.0,
            min_inside: 0.35,
            max_occluded: 0.8,
            shrink_occluded: true,
        }
    }
}

impl RenderConfig {
    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        if !self.min_height_px.is_finite() || self.min_height_px < 0.0 {
            return Err(Error::invalid(
                "render.min_height_px",
                format!("must be >= 0, got {}", self.min_height_px),
            ));
        }
        for (name, v) in [
            ("render.min_inside", self.min_inside),
            ("render.max_occluded", self.max_occluded),
        ] {
            if !(0.0..=1.0).contains(&v) {
                return Err(Error::invalid(name, format!("must be in [0, 1], got {v}")));
            }
        }
        Ok(())
    }
}

/// A ground-truth box of one person in one camera.
#[derive(Debug, Clone, PartialEq)]
pub struct TruthBox {
    /// Index of the person in the slice given to [`render_camera`].
    pub person: usize,
    /// Identity of the person.
    pub id: u64,
    /// `[x1, y1, x2, y2]` pixels, inside the image.
    pub bbox: [f64; 4],
    /// Fraction of the (clipped) box hidden by nearer people, in `[0, 1]`.
    pub occluded: f64,
    /// Depth of the person's axis in front of the camera (metres).
    pub depth: f64,
}

const RING: usize = 12;
const GRID_X: usize = 8;
const GRID_Y: usize = 16;
/// Occluders are people, not boxes: their silhouette covers about this fraction of their
/// box's width.
const SILHOUETTE_WIDTH: f64 = 0.8;

/// The unclipped pixel box of a person (the bounding box of their cylinder), or `None` when
/// any part is behind the camera's near plane.
pub(crate) fn project_person(cam: &Camera, p: &Person) -> Option<[f64; 4]> {
    let r = p.apparent_width() / 2.0;
    let mut b = [
        f64::INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::NEG_INFINITY,
    ];
    for k in 0..RING {
        let a = k as f64 * std::f64::consts::TAU / RING as f64;
        let (s, c) = a.sin_cos();
        for z in [0.0, p.height] {
            let px = cam.project([p.pos[0] + r * c, p.pos[1] + r * s, z])?;
            b[0] = b[0].min(px[0]);
            b[1] = b[1].min(px[1]);
            b[2] = b[2].max(px[0]);
            b[3] = b[3].max(px[1]);
        }
    }
    Some(b)
}

fn area(b: &[f64; 4]) -> f64 {
    (b[2] - b[0]).max(0.0) * (b[3] - b[1]).max(0.0)
}

/// One person's projection in a camera, before occlusion.
struct InView {
    person: usize,
    /// Silhouette (the box narrowed to the body's width), clipped to the image.
    silhouette: [f64; 4],
    /// The box clipped to the image.
    clipped: [f64; 4],
    depth: f64,
    /// Enough of the person is inside the image to be boxed.
    boxable: bool,
}

/// The ground-truth boxes of `people` in `cam`, nearest first. Everyone in view occludes
/// those behind them, including people too cut off by the border to be boxed themselves.
pub fn render_camera(cam: &Camera, people: &[Person], cfg: &RenderConfig) -> Vec<TruthBox> {
    let (w, h) = (cam.spec.width as f64, cam.spec.height as f64);
    let clip = |b: [f64; 4]| [b[0].max(0.0), b[1].max(0.0), b[2].min(w), b[3].min(h)];
    let mut in_view: Vec<InView> = Vec::with_capacity(people.len());
    for (i, p) in people.iter().enumerate() {
        let Some(full) = project_person(cam, p) else {
            continue;
        };
        let clipped = clip(full);
        if clipped[2] <= clipped[0] || clipped[3] <= clipped[1] {
            continue;
        }
        let inset = (full[2] - full[0]) * (1.0 - SILHOUETTE_WIDTH) / 2.0;
        in_view.push(InView {
            person: i,
            silhouette: clip([full[0] + inset, full[1], full[2] - inset, full[3]]),
            clipped,
            depth: cam.to_camera([p.pos[0], p.pos[1], p.height / 2.0])[2],
            boxable: area(&clipped) >= cfg.min_inside * area(&full),
        });
    }
    in_view.sort_by(|a, b| a.depth.total_cmp(&b.depth).then(a.person.cmp(&b.person)));

    let mut out = Vec::with_capacity(in_view.len());
    let mut occluders: Vec<[f64; 4]> = Vec::new();
    for (k, v) in in_view.iter().enumerate() {
        if !v.boxable {
            continue;
        }
        let b = v.clipped;
        occluders.clear();
        for o in &in_view[..k] {
            let s = o.silhouette;
            if s[0] < b[2] && s[2] > b[0] && s[1] < b[3] && s[3] > b[1] {
                occluders.push(s);
            }
        }
        let (mut bbox, occluded) = if occluders.is_empty() {
            (b, 0.0)
        } else {
            visible_part(&b, &occluders)
        };
        if occluded > cfg.max_occluded {
            continue;
        }
        if !cfg.shrink_occluded {
            bbox = b;
        }
        if bbox[3] - bbox[1] < cfg.min_height_px {
            continue;
        }
        out.push(TruthBox {
            person: v.person,
            id: people[v.person].id,
            bbox,
            occluded,
            depth: v.depth,
        });
    }
    out
}

/// Samples a grid over `b`; returns the visible part (the box with mostly hidden outer
/// columns and rows trimmed away, as a detector would box it) and the covered fraction.
fn visible_part(b: &[f64; 4], occluders: &[[f64; 4]]) -> ([f64; 4], f64) {
    let cw = (b[2] - b[0]) / GRID_X as f64;
    let ch = (b[3] - b[1]) / GRID_Y as f64;
    let mut col_vis = [0usize; GRID_X];
    let mut row_vis = [0usize; GRID_Y];
    let mut covered = 0usize;
    for (gy, row) in row_vis.iter_mut().enumerate() {
        let y = b[1] + (gy as f64 + 0.5) * ch;
        for (gx, col) in col_vis.iter_mut().enumerate() {
            let x = b[0] + (gx as f64 + 0.5) * cw;
            if occluders
                .iter()
                .any(|o| x >= o[0] && x <= o[2] && y >= o[1] && y <= o[3])
            {
                covered += 1;
            } else {
                *row += 1;
                *col += 1;
            }
        }
    }
    let frac = covered as f64 / (GRID_X * GRID_Y) as f64;
    // keep the span of columns (rows) that are at least half visible
    let span = |counts: &[usize], full: usize| {
        let ok = |c: &usize| 2 * *c >= full;
        let first = counts.iter().position(ok)?;
        let last = counts.iter().rposition(ok)?;
        Some((first, last))
    };
    match (span(&col_vis, GRID_Y), span(&row_vis, GRID_X)) {
        (Some((c0, c1)), Some((r0, r1))) => (
            [
                b[0] + c0 as f64 * cw,
                b[1] + r0 as f64 * ch,
                b[0] + (c1 + 1) as f64 * cw,
                b[1] + (r1 + 1) as f64 * ch,
            ],
            frac,
        ),
        _ => (*b, frac),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::camera::CameraConfig;

    fn cam() -> Camera {
        CameraConfig {
            name: "c".into(),
            position: [0.0, 0.0, 2.0],
            yaw_deg: Some(0.0),
            pitch_deg: Some(10.0),
            look_at: None,
            focal_px: 1000.0,
            width: 1920,
            height: 1080,
            principal: None,
        }
        .build("camera")
        .unwrap()
    }

    #[test]
    fn person_in_front_lands_where_geometry_says() {
        let c = cam();
        let p = Person::standing(7, [10.0, 0.0], 1.8, 0.5);
        let boxes = render_camera(&c, std::slice::from_ref(&p), &RenderConfig::default());
        assert_eq!(boxes.len(), 1);
        let b = boxes[0].bbox;
        assert_eq!(boxes[0].id, 7);
        // centred horizontally on the optical axis
        assert!(((b[0] + b[2]) / 2.0 - 960.0).abs() < 1.0, "{b:?}");
        // feet: the nearest ground point of the cylinder; head: its top
        let feet = c.project([9.75, 0.0, 0.0]).unwrap();
        let head = c.project([10.25, 0.0, 1.8]).unwrap();
        assert!((b[3] - feet[1]).abs() < 1e-6, "{b:?} vs feet {feet:?}");
        assert!((b[1] - head[1]).abs() < 1.0, "{b:?} vs head {head:?}");
        // ~0.5 m wide at ~10 m with f = 1000 px: ~50 px
        assert!((b[2] - b[0] - 50.0).abs() < 3.0, "{b:?}");
        // ground point of the bottom-centre is (close to) the person's front
        let g = c.ground_point_of_box([b[0] as f32, b[1] as f32, b[2] as f32, b[3] as f32]);
        let g = g.unwrap();
        assert!((g[0] - 9.75).abs() < 0.01 && g[1].abs() < 0.01, "{g:?}");
    }

    #[test]
    fn occlusion_drops_the_farther_of_two_in_line() {
        let c = cam();
        let near = Person::standing(1, [6.0, 0.0], 1.8, 0.5);
        let far = Person::standing(2, [9.0, 0.0], 1.7, 0.5);
        let cfg = RenderConfig::default();
        let boxes = render_camera(&c, &[far.clone(), near.clone()], &cfg);
        assert_eq!(boxes.len(), 1, "{boxes:?}");
        assert_eq!(boxes[0].id, 1);
        // side by side: both visible, nothing occluded
        let beside = Person::standing(2, [9.0, 2.0], 1.7, 0.5);
        let boxes = render_camera(&c, &[beside, near.clone()], &cfg);
        assert_eq!(boxes.len(), 2);
        assert!(boxes.iter().all(|b| b.occluded == 0.0));
        // half hidden: kept, shrunk to the visible side, occlusion reported
        let half = Person::standing(2, [9.0, 0.3], 1.8, 0.5);
        let boxes = render_camera(&c, &[half.clone(), near.clone()], &cfg);
        assert_eq!(boxes.len(), 2, "{boxes:?}");
        let full = project_person(&c, &half).unwrap();
        let b = boxes.iter().find(|b| b.id == 2).unwrap();
        assert!(b.occluded > 0.2 && b.occluded < 0.8, "{b:?}");
        assert!(
            b.bbox[2] - b.bbox[0] < full[2] - full[0],
            "{b:?} vs {full:?}"
        );
        let unshrunk = RenderConfig {
            shrink_occluded: false,
            ..cfg
        };
        let boxes = render_camera(&c, &[half, near], &unshrunk);
        let b = boxes.iter().find(|b| b.id == 2).unwrap();
        assert_eq!(b.bbox, full);
    }

    #[test]
    fn people_cut_off_by_the_border_still_occlude() {
        let c = cam();
        let cfg = RenderConfig::default();
        let near = Person::standing(1, [2.0, -2.25], 1.8, 0.5);
        let far = Person::standing(2, [10.0, -9.45], 1.8, 0.5);
        // preconditions: near is mostly outside the image (not boxed), far is boxable
        let nb = project_person(&c, &near).unwrap();
        assert!(nb[0] < 1920.0 && (1920.0 - nb[0]) / (nb[2] - nb[0]) < cfg.min_inside);
        let alone = render_camera(&c, std::slice::from_ref(&far), &cfg);
        assert_eq!(alone.len(), 1);
        assert_eq!(alone[0].occluded, 0.0);
        let both = render_camera(&c, &[far, near], &cfg);
        assert_eq!(both.len(), 1, "{both:?}");
        assert_eq!(both[0].id, 2);
        assert!(both[0].occluded > 0.2, "{both:?}");
    }

    #[test]
    fn behind_tiny_and_outside_are_dropped() {
        let c = cam();
        let cfg = RenderConfig::default();
        let behind = Person::standing(1, [-5.0, 0.0], 1.8, 0.5);
        let tiny = Person::standing(2, [200.0, 0.0], 1.8, 0.5);
        let outside = Person::standing(3, [5.0, 10.0], 1.8, 0.5);
        assert!(render_camera(&c, &[behind, tiny, outside], &cfg).is_empty());
        // cut at the border: partly inside is kept and clipped
        let edge = Person::standing(4, [10.0, -9.55], 1.8, 0.5);
        let boxes = render_camera(&c, &[edge], &cfg);
        assert_eq!(boxes.len(), 1);
        assert_eq!(boxes[0].bbox[2], 1920.0);
    }
}

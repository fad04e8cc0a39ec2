//! **[ours]** Cleaning of detector boxes before self-supervised training.
//!
//! The synchronization signal of SPEC §4 comes from boxes that *move*: the positive image
//! (same instant, other camera) must explain the anchor better than the negative image (same
//! camera, seconds away). Two kinds of detector boxes carry no such signal and, on WILDTRACK's
//! detections, keep training on its loss plateau (validation ACC ≈ 42 %, BENCHMARKS.md):
//!
//! - **static boxes**: a box with an almost identical box (IoU above a threshold) in the same
//!   camera a few frames earlier or later — false detections on fixed structures and people
//!   standing still. They look the same in the positive and the negative image, so they pull
//!   the anchor equally towards both;
//! - **small boxes**: far-away people, mostly outside the area the cameras share.
//!
//! Neither rule uses labels, and both only shape what training sees; inference still
//! associates every box it is given.
use serde::{Deserialize, Serialize};

use crate::data::{Image, TrainingSet};

/// Which training boxes to drop. The default drops nothing (the reference behaviour).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoxFilter {
    /// Drop boxes whose height is below this fraction of their image height (0 = off).
    pub min_height: f32,
    /// Drop a box when a box of the same camera `static_offset` frames earlier or later
    /// overlaps it with an IoU above this (0 = off).
    pub static_iou: f32,
    /// Frame distance (positions in the recording) at which static boxes are looked for.
    pub static_offset: usize,
}

impl Default for BoxFilter {
    fn default() -> Self {
        BoxFilter {
            min_height: 0.0,
            static_iou: 0.0,
            static_offset: 10,
        }
    }
}

/// What a [`BoxFilter`] removed.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FilterStats {
    /// Boxes before filtering.
    pub before: usize,
    /// Boxes dropped as too small.
    pub small: usize,
    /// Boxes dropped as static (and not already too small).
    pub stationary: usize,
}

impl BoxFilter {
    /// True when the filter keeps every box.
    pub fn is_off(&self) -> bool {
        self.min_height <= 0.0 && (self.static_iou <= 0.0 || self.static_offset == 0)
    }

    /// Applies the filter to every image of `set`. Static boxes are judged against the
    /// unfiltered neighbouring frames, so the result does not depend on processing order.
    pub fn apply(&self, set: &mut TrainingSet) -> FilterStats {
        let mut stats = FilterStats {
            before: set.num_boxes(),
            ..FilterStats::default()
        };
        if self.is_off() {
            return stats;
        }
        // Decide every box on the unfiltered set first, then drop.
        let images = &set.images;
        let keep: Vec<Vec<Vec<bool>>> = (0..images.len())
            .map(|t| {
                (0..images[t].len())
                    .map(|c| self.keep_mask(images, t, c, &mut stats))
                    .collect()
            })
            .collect();
        for (row, row_keep) in set.images.iter_mut().zip(&keep) {
            for (img, k) in row.iter_mut().zip(row_keep) {
                retain(img, k);
            }
        }
        stats
    }

    /// Which boxes of camera `c` at frame position `t` survive, counting the dropped ones.
    fn keep_mask(
        &self,
        images: &[Vec<Image>],
        t: usize,
        c: usize,
        stats: &mut FilterStats,
    ) -> Vec<bool> {
        let neighbours: Vec<&Image> = if self.static_iou > 0.0 && self.static_offset > 0 {
            [
                t.checked_sub(self.static_offset),
                Some(t + self.static_offset).filter(|&u| u < images.len()),
            ]
            .into_iter()
            .flatten()
            .filter_map(|u| images[u].get(c))
            .collect()
        } else {
            Vec::new()
        };
        images[t][c]
            .boxes
            .iter()
            .map(|b| {
                if b[3] - b[1] < self.min_height {
                    stats.small += 1;
                    return false;
                }
                let still = neighbours
                    .iter()
                    .any(|n| n.boxes.iter().any(|o| iou(b, o) > self.static_iou));
                if still {
                    stats.stationary += 1;
                }
                !still
            })
            .collect()
    }
}

fn retain(img: &mut Image, keep: &[bool]) {
    let mut k = keep.iter();
    img.boxes.retain(|_| *k.next().unwrap_or(&true));
    if let Some(app) = img.appearance.as_mut() {
        let mut k = keep.iter();
        app.retain(|_| *k.next().unwrap_or(&true));
        if app.is_empty() {
            img.appearance = None;
        }
    }
}

/// Intersection over union of two `[x1, y1, x2, y2]` boxes (0 for degenerate boxes).
/// Invariant to scaling either axis, so normalised boxes give pixel IoU.
pub fn iou(a: &[f32; 4], b: &[f32; 4]) -> f32 {
    let iw = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0);
    let ih = (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let inter = iw * ih;
    let union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter;
    if union > 0.0 { inter / union } else { 0.0 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::SceneSpec;
    use crossview_core::testing::cameras;

    fn set(images: Vec<Vec<Vec<[f32; 4]>>>) -> TrainingSet {
        let cams = images[0].len();
        TrainingSet {
            scene: SceneSpec {
                name: "t".into(),
                cameras: cameras(cams, 100, 100),
            },
            frame_ids: (0..images.len() as u64).collect(),
            images: images
                .into_iter()
                .map(|row| {
                    row.into_iter()
                        .map(|boxes| Image {
                            boxes,
                            appearance: None,
                        })
                        .collect()
                })
                .collect(),
        }
    }

    const STILL: [f32; 4] = [0.1, 0.1, 0.2, 0.5];

    fn moving(t: usize) -> [f32; 4] {
        let x = 0.05 * t as f32;
        [x, 0.3, x + 0.1, 0.7]
    }

    #[test]
    fn iou_of_known_boxes() {
        assert_eq!(iou(&[0.0, 0.0, 1.0, 1.0], &[0.0, 0.0, 1.0, 1.0]), 1.0);
        assert_eq!(iou(&[0.0, 0.0, 1.0, 1.0], &[2.0, 2.0, 3.0, 3.0]), 0.0);
        let v = iou(&[0.0, 0.0, 2.0, 1.0], &[1.0, 0.0, 3.0, 1.0]);
        assert!((v - 1.0 / 3.0).abs() < 1e-6);
        assert_eq!(iou(&[0.0, 0.0, 0.0, 0.0], &[0.0, 0.0, 0.0, 0.0]), 0.0);
    }

    #[test]
    fn default_keeps_everything() {
        let mut s = set((0..4).map(|t| vec![vec![STILL, moving(t)]]).collect());
        let before = s.clone();
        let st = BoxFilter::default().apply(&mut s);
        assert_eq!(s, before);
        assert_eq!(st.before, 8);
        assert_eq!(st.small + st.stationary, 0);
    }

    #[test]
    fn drops_static_boxes_and_keeps_moving_ones() {
        let frames = 6;
        let mut s = set((0..frames).map(|t| vec![vec![STILL, moving(t)]]).collect());
        let f = BoxFilter {
            static_iou: 0.8,
            static_offset: 2,
            ..BoxFilter::default()
        };
        let st = f.apply(&mut s);
        assert_eq!(st.stationary, frames);
        for (t, row) in s.images.iter().enumerate() {
            assert_eq!(row[0].boxes, vec![moving(t)]);
        }
    }

    #[test]
    fn static_is_per_camera_and_needs_a_neighbour_in_range() {
        // Camera 0 sees the still box only at frame 0, camera 1 only at frame 2: no camera
        // has it twice, so nothing is static.
        let mut s = set(vec![
            vec![vec![STILL], vec![]],
            vec![vec![], vec![]],
            vec![vec![], vec![STILL]],
        ]);
        let f = BoxFilter {
            static_iou: 0.5,
            static_offset: 2,
            ..BoxFilter::default()
        };
        assert_eq!(f.apply(&mut s).stationary, 0);
        assert_eq!(s.num_boxes(), 2);
    }

    #[test]
    fn drops_small_boxes_with_their_appearance() {
        let mut s = set(vec![vec![vec![
            [0.0, 0.0, 0.1, 0.05],
            [0.0, 0.0, 0.1, 0.5],
        ]]]);
        s.images[0][0].appearance = Some(vec![vec![1.0], vec![2.0]]);
        let f = BoxFilter {
            min_height: 0.1,
            ..BoxFilter::default()
        };
        let st = f.apply(&mut s);
        assert_eq!(st.small, 1);
        assert_eq!(s.images[0][0].boxes, vec![[0.0, 0.0, 0.1, 0.5]]);
        assert_eq!(s.images[0][0].appearance, Some(vec![vec![2.0]]));
    }
}

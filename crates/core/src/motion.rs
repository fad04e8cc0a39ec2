//! A box followed within one camera: its last position and smoothed motion, so that where
//! it should be next frame can be compared with where boxes are (the trackers' image cue).

/// A box's last position in one camera (pixels) and its motion.
#[derive(Debug, Clone)]
pub(crate) struct MovingBox {
    pub(crate) bbox: [f32; 4],
    /// Change of each coordinate per frame (smoothed).
    velocity: [f32; 4],
    /// Frames since the box was seen (0 = this frame).
    pub(crate) unseen: u32,
}

impl MovingBox {
    pub(crate) fn new(bbox: [f32; 4]) -> Self {
        MovingBox {
            bbox,
            velocity: [0.0; 4],
            unseen: 0,
        }
    }

    /// Where the box is expected this frame.
    pub(crate) fn predicted(&self) -> [f32; 4] {
        let k = (self.unseen + 1) as f32;
        std::array::from_fn(|i| self.bbox[i] + k * self.velocity[i])
    }

    /// The box seen again at `bbox`; its velocity follows the observed motion by `weight`.
    pub(crate) fn observe(&mut self, bbox: [f32; 4], weight: f32) {
        let k = (self.unseen + 1) as f32;
        for ((v, new), old) in self.velocity.iter_mut().zip(bbox).zip(self.bbox) {
            let moved = (new - old) / k;
            *v += weight * (moved - *v);
        }
        self.bbox = bbox;
        self.unseen = 0;
    }
}

/// Intersection over union of two boxes `[x1, y1, x2, y2]` (0 when either is empty or the
/// result is not finite).
pub(crate) fn iou(a: &[f32; 4], b: &[f32; 4]) -> f32 {
    let w = (a[2].min(b[2]) - a[0].max(b[0])).max(0.0);
    let h = (a[3].min(b[3]) - a[1].max(b[1])).max(0.0);
    let inter = w * h;
    let union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter;
    if union > 0.0 && inter.is_finite() {
        inter / union
    } else {
        0.0
    }
}

//! Detector realism on top of ground-truth boxes: size-proportional jitter, missed
//! detections (more likely when occluded), false positives, duplicates and scores.
//!
//! Identity convention: a false positive carries no `id`; a duplicate carries the `id` of the
//! person it duplicates (evaluation then sees two boxes of one person in a view).
use rand::Rng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal, Poisson};

use super::render::TruthBox;
use crossview_core::Detection;
use crossview_core::{Error, Result};

/// Detector error rates. [`DetectorNoise::none`] gives the ground-truth boxes unchanged
/// (score 1); [`Default`] is a moderately good detector.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectorNoise {
    /// Standard deviation of each box edge, as a fraction of the box's width (x edges) or
    /// height (y edges).
    pub jitter: f64,
    /// Probability of missing a fully visible person.
    pub miss_rate: f64,
    /// Extra miss probability for a fully occluded person (scaled by the hidden fraction).
    pub occluded_miss: f64,
    /// Mean number of false positives per camera image (Poisson).
    pub false_positives: f64,
    /// Probability that a detected person yields a second, shifted box.
    pub duplicate_rate: f64,
}

impl Default for DetectorNoise {
    fn default() -> Self {
        DetectorNoise {
            jitter: 0.03,
            miss_rate: 0.05,
            occluded_miss: 0.4,
            false_positives: 0.3,
            duplicate_rate: 0.02,
        }
    }
}

impl DetectorNoise {
    /// A perfect detector: ground-truth boxes, score 1, nothing added or lost.
    pub fn none() -> Self {
        DetectorNoise {
            jitter: 0.0,
            miss_rate: 0.0,
            occluded_miss: 0.0,
            false_positives: 0.0,
            duplicate_rate: 0.0,
        }
    }

    /// True when this is [`DetectorNoise::none`].
    pub fn is_none(&self) -> bool {
        *self == Self::none()
    }

    /// Checks every rate.
    pub fn validate(&self) -> Result<()> {
        if !self.jitter.is_finite() || !(0.0..=1.0).contains(&self.jitter) {
            return Err(Error::invalid(
                "detector.jitter",
                format!("must be in [0, 1], got {}", self.jitter),
            ));
        }
        for (name, p) in [
            ("detector.miss_rate", self.miss_rate),
            ("detector.occluded_miss", self.occluded_miss),
            ("detector.duplicate_rate", self.duplicate_rate),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(Error::invalid(name, format!("must be in [0, 1], got {p}")));
            }
        }
        if !self.false_positives.is_finite() || !(0.0..=100.0).contains(&self.false_positives) {
            return Err(Error::invalid(
                "detector.false_positives",
                format!(
                    "must be in [0, 100] per image, got {}",
                    self.false_positives
                ),
            ));
        }
        Ok(())
    }
}

/// A box as the detector reports it, before appearance vectors are attached.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectedBox {
    /// Index into the truth boxes for real people (duplicates included); `None` for false
    /// positives.
    pub truth: Option<usize>,
    /// `[x1, y1, x2, y2]` pixels, inside the image, at least one pixel wide and high.
    pub bbox: [f64; 4],
    /// Detector confidence in `[0, 1]`.
    pub score: f64,
}

/// Rounds to 0.1 px: plenty for boxes, and keeps recordings compact.
fn round_px(v: f64) -> f64 {
    (v * 10.0).round() / 10.0
}

/// Clamps to the image, rounds and enforces a minimal size; `None` if nothing is left.
fn finish(b: [f64; 4], w: f64, h: f64) -> Option<[f64; 4]> {
    let x1 = round_px(b[0].min(b[2]).clamp(0.0, w - 1.0));
    let y1 = round_px(b[1].min(b[3]).clamp(0.0, h - 1.0));
    let x2 = round_px(b[0].max(b[2]).clamp(x1 + 1.0, w));
    let y2 = round_px(b[1].max(b[3]).clamp(y1 + 1.0, h));
    (x2 > x1 && y2 > y1).then_some([x1, y1, x2, y2])
}

/// Turns one camera's ground-truth boxes into detector output (shuffled: output order
/// carries no identity information).
pub fn detect(
    truth: &[TruthBox],
    width: u32,
    height: u32,
    noise: &DetectorNoise,
    rng: &mut ChaCha8Rng,
) -> Vec<DetectedBox> {
    let (w, h) = (width as f64, height as f64);
    let mut out = Vec::with_capacity(truth.len() + 2);
    if noise.is_none() {
        for (i, t) in truth.iter().enumerate() {
            if let Some(bbox) = finish(t.bbox, w, h) {
                out.push(DetectedBox {
                    truth: Some(i),
                    bbox,
                    score: 1.0,
                });
            }
        }
        out.shuffle(rng);
        return out;
    }
    let unit = Normal::new(0.0, 1.0).expect("unit normal");
    let jitter = |b: &[f64; 4], s: f64, rng: &mut ChaCha8Rng| {
        let (bw, bh) = (b[2] - b[0], b[3] - b[1]);
        [
            b[0] + unit.sample(rng) * s * bw,
            b[1] + unit.sample(rng) * s * bh,
            b[2] + unit.sample(rng) * s * bw,
            b[3] + unit.sample(rng) * s * bh,
        ]
    };
    for (i, t) in truth.iter().enumerate() {
        let p_miss = (noise.miss_rate + noise.occluded_miss * t.occluded).min(1.0);
        if rng.random::<f64>() < p_miss {
            continue;
        }
        let score = (0.88 + 0.07 * unit.sample(rng) - 0.3 * t.occluded).clamp(0.3, 1.0);
        if let Some(bbox) = finish(jitter(&t.bbox, noise.jitter, rng), w, h) {
            out.push(DetectedBox {
                truth: Some(i),
                bbox,
                score: (score * 1000.0).round() / 1000.0,
            });
        }
        if rng.random::<f64>() < noise.duplicate_rate {
            // a second box on the same person: shifted and rescaled, less confident
            let dup = jitter(&t.bbox, noise.jitter * 2.0 + 0.08, rng);
            if let Some(bbox) = finish(dup, w, h) {
                let s = (score - rng.random_range(0.1..0.4)).clamp(0.05, 1.0);
                out.push(DetectedBox {
                    truth: Some(i),
                    bbox,
                    score: (s * 1000.0).round() / 1000.0,
                });
            }
        }
    }
    if noise.false_positives > 0.0 {
        let n = Poisson::new(noise.false_positives)
            .map(|p| p.sample(rng) as usize)
            .unwrap_or(0);
        for _ in 0..n {
            // person-shaped clutter, standing somewhere on the lower part of the image
            let bh = rng.random_range(0.06..0.4) * h;
            let bw = bh * rng.random_range(0.25..0.6);
            let foot = rng.random_range(0.35..1.0) * h;
            let cx = rng.random_range(0.0..w);
            let b = [cx - bw / 2.0, foot - bh, cx + bw / 2.0, foot];
            if let Some(bbox) = finish(b, w, h) {
                let s = rng.random_range(0.3..0.75);
                out.push(DetectedBox {
                    truth: None,
                    bbox,
                    score: (s * 1000.0f64).round() / 1000.0,
                });
            }
        }
    }
    out.shuffle(rng);
    out
}

/// Converts to the recording type; `id` and `appearance` are filled in by the caller.
pub fn to_detection(d: &DetectedBox) -> Detection {
    let mut det = Detection::new(d.bbox.map(|v| v as f32));
    det.score = d.score as f32;
    det
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn truth(n: usize) -> Vec<TruthBox> {
        (0..n)
            .map(|i| TruthBox {
                person: i,
                id: i as u64,
                bbox: [
                    100.0 + 60.0 * i as f64,
                    200.0,
                    150.0 + 60.0 * i as f64,
                    400.0,
                ],
                occluded: 0.0,
                depth: 5.0,
            })
            .collect()
    }

    #[test]
    fn clean_detector_returns_truth() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let t = truth(5);
        let d = detect(&t, 1280, 720, &DetectorNoise::none(), &mut rng);
        assert_eq!(d.len(), 5);
        for b in &d {
            assert_eq!(b.bbox, t[b.truth.unwrap()].bbox);
            assert_eq!(b.score, 1.0);
        }
    }

    #[test]
    fn noisy_detector_rates_are_roughly_right_and_boxes_valid() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let t = truth(10);
        let noise = DetectorNoise {
            jitter: 0.05,
            miss_rate: 0.1,
            occluded_miss: 0.0,
            false_positives: 1.0,
            duplicate_rate: 0.1,
        };
        let (mut real, mut fp, mut shift) = (0usize, 0usize, 0.0f64);
        let rounds = 2000;
        for _ in 0..rounds {
            for b in detect(&t, 1280, 720, &noise, &mut rng) {
                let det = to_detection(&b);
                det.validate("d", None).unwrap();
                match b.truth {
                    Some(i) => {
                        real += 1;
                        shift += (b.bbox[3] - t[i].bbox[3]).abs();
                    }
                    None => fp += 1,
                }
            }
        }
        let per_round = real as f64 / rounds as f64;
        // 10 people * (0.9 detected + 0.9 * 0.1 duplicates) = 9.9
        assert!((per_round - 9.9).abs() < 0.3, "{per_round}");
        let fp_rate = fp as f64 / rounds as f64;
        assert!((fp_rate - 1.0).abs() < 0.15, "{fp_rate}");
        // jitter ~ 5% of a 200 px box => mean |shift| ~ 8 px
        let mean_shift = shift / real as f64;
        assert!(mean_shift > 4.0 && mean_shift < 16.0, "{mean_shift}");
    }

    #[test]
    fn bad_rates_are_rejected() {
        let mut n = DetectorNoise::default();
        assert!(n.validate().is_ok());
        n.miss_rate = 1.5;
        assert!(n.validate().is_err());
        n.miss_rate = 0.1;
        n.false_positives = f64::NAN;
        assert!(n.validate().is_err());
    }
}

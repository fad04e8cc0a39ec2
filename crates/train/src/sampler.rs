//! Triplet sampling (SPEC §4): anchor = (frame p, view i), positive = (frame p, view j ≠ i),
//! negative = (frame p ± d, view j) with d uniform in [5, 20) frame positions, random
//! direction, the other direction when out of range.
use rand::Rng;
use rand::seq::SliceRandom;

use crossview_core::{Error, Result};

/// Smallest negative offset in frame positions.
pub(crate) const MIN_OFFSET: usize = 5;
/// Largest negative offset in frame positions (inclusive; SPEC: d < 20).
pub(crate) const MAX_OFFSET: usize = 19;
/// Fewest frames the sampler accepts: every frame then has a partner ≥ 5 positions away.
pub const MIN_FRAMES: usize = 2 * MIN_OFFSET + 1;

/// One image of a triplet: frame position and camera index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ImageRef {
    /// Position of the frame in the training sequence.
    pub frame: usize,
    /// Camera index.
    pub camera: usize,
}

/// Anchor, positive and negative images of one training step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Triplet {
    /// Frame p of view i.
    pub anchor: ImageRef,
    /// Frame p of view j.
    pub positive: ImageRef,
    /// Frame p ± d of view j.
    pub negative: ImageRef,
}

/// Draws triplets over `num_frames` frames of `num_cameras` synchronized cameras.
#[derive(Debug, Clone)]
pub(crate) struct TripletSampler {
    num_frames: usize,
    num_cameras: usize,
}

impl TripletSampler {
    /// A sampler; needs ≥ 2 cameras and ≥ [`MIN_FRAMES`] frames.
    pub fn new(num_frames: usize, num_cameras: usize) -> Result<Self> {
        if num_cameras < 2 {
            return Err(Error::Training(format!(
                "triplets need at least two cameras, got {num_cameras}"
            )));
        }
        if num_frames < MIN_FRAMES {
            return Err(Error::Training(format!(
                "triplets need at least {MIN_FRAMES} frames for negatives {MIN_OFFSET}..={MAX_OFFSET} \
                 frames away, got {num_frames}"
            )));
        }
        Ok(TripletSampler {
            num_frames,
            num_cameras,
        })
    }

    /// One epoch's anchor frames: every frame position once, shuffled.
    pub(crate) fn epoch_order<R: Rng>(&self, rng: &mut R) -> Vec<usize> {
        let mut order: Vec<usize> = (0..self.num_frames).collect();
        order.shuffle(rng);
        order
    }

    /// A triplet anchored at frame position `p`.
    pub fn sample<R: Rng>(&self, p: usize, rng: &mut R) -> Triplet {
        let i = rng.random_range(0..self.num_cameras);
        let mut j = rng.random_range(0..self.num_cameras - 1);
        if j >= i {
            j += 1;
        }
        let q = self.negative_frame(p, rng);
        Triplet {
            anchor: ImageRef {
                frame: p,
                camera: i,
            },
            positive: ImageRef {
                frame: p,
                camera: j,
            },
            negative: ImageRef {
                frame: q,
                camera: j,
            },
        }
    }

    /// The negative's frame: `p ± d`, `d` uniform in [5, 19], random direction, the other
    /// direction when out of range. If neither fits (short sequences), `d` is redrawn within
    /// the room on the roomier side, which is ≥ 5 because of [`MIN_FRAMES`].
    pub(crate) fn negative_frame<R: Rng>(&self, p: usize, rng: &mut R) -> usize {
        let fwd_room = self.num_frames - 1 - p;
        let back_room = p;
        let d = rng.random_range(MIN_OFFSET..=MAX_OFFSET);
        let forward_first = rng.random_bool(0.5);
        let try_dir = |fwd: bool| -> Option<usize> {
            if fwd && d <= fwd_room {
                Some(p + d)
            } else if !fwd && d <= back_room {
                Some(p - d)
            } else {
                None
            }
        };
        if let Some(q) = try_dir(forward_first).or_else(|| try_dir(!forward_first)) {
            return q;
        }
        if fwd_room >= back_room {
            p + rng.random_range(MIN_OFFSET..=fwd_room.min(MAX_OFFSET))
        } else {
            p - rng.random_range(MIN_OFFSET..=back_room.min(MAX_OFFSET))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn offsets_stay_within_five_to_nineteen_and_in_range() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for n in [MIN_FRAMES, 12, 25, 40, 288] {
            let s = TripletSampler::new(n, 3).unwrap();
            for p in 0..n {
                for _ in 0..50 {
                    let t = s.sample(p, &mut rng);
                    assert_eq!(t.anchor.frame, p);
                    assert_eq!(t.positive.frame, p);
                    assert_ne!(t.anchor.camera, t.positive.camera);
                    assert_eq!(t.negative.camera, t.positive.camera);
                    assert!(t.negative.frame < n);
                    let d = t.negative.frame.abs_diff(p);
                    assert!((MIN_OFFSET..=MAX_OFFSET).contains(&d), "n={n} p={p} d={d}");
                }
            }
        }
    }

    #[test]
    fn both_directions_and_all_offsets_occur_in_the_middle() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let s = TripletSampler::new(100, 2).unwrap();
        let mut seen = [false; 2 * MAX_OFFSET + 1];
        for _ in 0..4000 {
            let q = s.negative_frame(50, &mut rng) as i64 - 50;
            seen[(q + MAX_OFFSET as i64) as usize] = true;
        }
        for d in MIN_OFFSET..=MAX_OFFSET {
            assert!(
                seen[MAX_OFFSET + d] && seen[MAX_OFFSET - d],
                "offset ±{d} never drawn"
            );
        }
    }

    #[test]
    fn near_the_start_it_goes_forward() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let s = TripletSampler::new(288, 7).unwrap();
        for _ in 0..200 {
            assert!(s.negative_frame(0, &mut rng) >= MIN_OFFSET);
            assert!(s.negative_frame(287, &mut rng) <= 287 - MIN_OFFSET);
        }
    }

    #[test]
    fn rejects_one_camera_and_too_few_frames() {
        assert!(TripletSampler::new(100, 1).is_err());
        assert!(TripletSampler::new(MIN_FRAMES - 1, 2).is_err());
        assert!(TripletSampler::new(MIN_FRAMES, 2).is_ok());
    }

    #[test]
    fn epoch_order_is_a_permutation() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let s = TripletSampler::new(30, 2).unwrap();
        let mut o = s.epoch_order(&mut rng);
        o.sort_unstable();
        assert_eq!(o, (0..30).collect::<Vec<_>>());
    }
}

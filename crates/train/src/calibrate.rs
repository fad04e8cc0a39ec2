//! **[ours]** Label-free calibration of a trained encoder: the raw distances of Hungarian pairs
//! between synchronized images (mostly one person) and between time-shifted images (never one
//! person) of an unlabelled recording, turned into `P(same person | distance)` by
//! [`Calibration::fit`]. The trainer runs it on its training set after training;
//! `crossview model calibrate` runs it on any recording for an existing model file.
use ndarray::{Array2, ArrayView2};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::data::TrainingSet;
use crossview_core::Encoder;
use crossview_core::FrameEmbeddings;
use crossview_core::Result;
use crossview_core::calibration::Calibration;
use crossview_core::distances::euclidean_distances;
use crossview_core::matching::hungarian;

/// Frame offsets of the time-shifted image, as the training negatives (SPEC §4).
const SHIFT: std::ops::Range<usize> = 5..20;

/// Embeds every image of `set` (one encoder call per frame), each frame's rows split by camera.
pub(crate) fn embed_all(
    encoder: &mut dyn Encoder,
    set: &TrainingSet,
) -> Result<Vec<FrameEmbeddings>> {
    set.images
        .iter()
        .map(|row| {
            let boxes: Vec<[f32; 4]> = row.iter().flat_map(|i| i.boxes.iter().copied()).collect();
            let cams: Vec<i64> = row
                .iter()
                .enumerate()
                .flat_map(|(c, i)| std::iter::repeat_n(c as i64, i.boxes.len()))
                .collect();
            let all = if boxes.is_empty() {
                Array2::zeros((0, encoder.dim()))
            } else {
                encoder.embed(&boxes, &cams)?
            };
            let rows: Vec<Option<usize>> = row.iter().map(|i| Some(i.boxes.len())).collect();
            FrameEmbeddings::new(all, &rows)
        })
        .collect()
}

/// Raw geometric distances of the Hungarian pairs of two images.
fn assigned_distances(a: ArrayView2<f32>, b: ArrayView2<f32>, out: &mut Vec<f32>) {
    if a.nrows() == 0 || b.nrows() == 0 {
        return;
    }
    let d = euclidean_distances(a, b);
    out.extend(hungarian(d.view()).into_iter().map(|(i, j)| d[(i, j)]));
}

/// The synchronized and time-shifted Hungarian distances of `set` under `encoder`: for every
/// frame and ordered camera pair with boxes, the pair at the same frame and the pair with the
/// second camera 5–19 frames away (direction random, the other one at the ends; seeded).
pub(crate) fn calibration_samples(
    encoder: &mut dyn Encoder,
    set: &TrainingSet,
    seed: u64,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let emb = embed_all(encoder, set)?;
    let (frames, cams) = (set.num_frames(), set.num_cameras());
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (mut sync, mut shifted) = (Vec::new(), Vec::new());
    let view = |t: usize, c: usize| emb[t].view(c).expect("every camera of a frame has rows");
    for t in 0..frames {
        for i in 0..cams {
            for j in 0..cams {
                if i == j || view(t, i).nrows() == 0 || view(t, j).nrows() == 0 {
                    continue;
                }
                assigned_distances(view(t, i), view(t, j), &mut sync);
                let d = rng.random_range(SHIFT);
                let forward = rng.random::<bool>();
                let t2 = match (forward, t + d < frames, t >= d) {
                    (true, true, _) | (false, true, false) => Some(t + d),
                    (false, _, true) | (true, false, true) => Some(t - d),
                    _ => None,
                };
                if let Some(t2) = t2 {
                    assigned_distances(view(t, i), view(t2, j), &mut shifted);
                }
            }
        }
    }
    Ok((sync, shifted))
}

/// Fits the calibration of `encoder` on `set` (see the module documentation).
pub fn calibrate(encoder: &mut dyn Encoder, set: &TrainingSet, seed: u64) -> Result<Calibration> {
    let (sync, shifted) = calibration_samples(encoder, set, seed)?;
    let cal = Calibration::fit(&sync, &shifted)?;
    tracing::info!(
        synchronized = sync.len(),
        shifted = shifted.len(),
        false_share = cal.false_share,
        "calibrated match confidence"
    );
    Ok(cal)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::testing::{BottomCentre, cameras};
    use crossview_core::{Detection, Frame, SceneSpec};
    use crossview_data::Recording;

    /// Two cameras that see the same walkers at the same place (the test encoder embeds a box
    /// as its bottom centre): synchronized pairs are close, shifted ones are not.
    #[test]
    fn synchronized_pairs_are_closer_and_calibrate() {
        let scene = SceneSpec {
            name: "s".into(),
            cameras: cameras(2, 100, 100),
        };
        let frames = (0..60u64)
            .map(|t| {
                let mut f = Frame::new(t, 2);
                let walkers: Vec<Detection> = (0..3)
                    .map(|k| {
                        let x = ((t as f32 * (1.5 + k as f32)) + 30.0 * k as f32) % 80.0;
                        Detection::new([x, 10.0, x + 10.0, 50.0])
                    })
                    .collect();
                f.views[0] = Some(walkers.clone());
                f.views[1] = Some(walkers);
                f
            })
            .collect();
        let set = TrainingSet::from_recording(
            &Recording {
                scene,
                frames,
                fps: None,
            },
            20,
        )
        .unwrap();
        let (sync, shifted) = calibration_samples(&mut BottomCentre, &set, 1).unwrap();
        assert_eq!(sync.len(), 60 * 2 * 3);
        assert!(shifted.len() == sync.len());
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        assert!(mean(&sync) < 1e-6 && mean(&shifted) > 0.01);
        let cal = calibrate(&mut BottomCentre, &set, 1).unwrap();
        assert!(cal.probability(0.0) > 0.9, "{cal:?}");
        // Same seed, same table.
        assert_eq!(calibrate(&mut BottomCentre, &set, 1).unwrap(), cal);
    }
}

//! In-process throughput of the association pipeline, for comparison with the Python
//! reference (`bench/python_reference.py`): per frame ONE encoder call over every box
//! ([`embed_frame`]), then SPEC §3 matching for every camera pair plus the global identities
//! ([`associate_frame`]). Reading the recording is not timed.
use std::time::Instant;

use serde::Serialize;

use crate::core::association::{AssociationConfig, Mode, associate_frame, embed_frame};
use crate::io::Recording;
use crate::model::Encoder;
use crate::{Error, Result};

/// What one measurement found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Throughput {
    /// Frames timed (frames × repeats, warm-up excluded).
    pub frames: usize,
    /// Boxes per timed frame, on average.
    pub boxes_per_frame: f64,
    /// Camera pairs matched per timed frame, on average.
    pub pairs_per_frame: f64,
    /// Wall-clock seconds of the timed loop.
    pub seconds: f64,
    /// Frames per second (encoder + matchings + identities).
    pub frames_per_second: f64,
    /// Of which encoder calls, seconds.
    pub encoder_seconds: f64,
    /// Kept pairwise matches over one pass of the recording (a cross-check with the
    /// reference's count on the same model and frames).
    pub kept_matches: usize,
}

/// Runs the pipeline over `recording` `warmup` frames untimed, then `repeat` timed passes.
pub fn measure(
    encoder: &mut dyn Encoder,
    recording: &Recording,
    threshold: f32,
    warmup: usize,
    repeat: usize,
) -> Result<Throughput> {
    if recording.frames.is_empty() {
        return Err(Error::invalid("data", "the recording has no frames"));
    }
    if repeat == 0 {
        return Err(Error::invalid("repeat", "must be at least 1"));
    }
    if !threshold.is_finite() {
        return Err(Error::invalid(
            "threshold",
            format!("must be finite, got {threshold}"),
        ));
    }
    let cfg = AssociationConfig {
        threshold,
        mode: Mode::Pairwise,
        ..AssociationConfig::default()
    };
    let scene = &recording.scene;
    for frame in recording.frames.iter().cycle().take(warmup) {
        let e = embed_frame(encoder, scene, frame)?;
        std::hint::black_box(associate_frame(frame, e, &cfg));
    }
    let (mut boxes, mut pairs, mut kept, mut frames) = (0usize, 0usize, 0usize, 0usize);
    let mut encoder_seconds = 0.0;
    let start = Instant::now();
    for pass in 0..repeat {
        for frame in &recording.frames {
            let t = Instant::now();
            let e = embed_frame(encoder, scene, frame)?;
            encoder_seconds += t.elapsed().as_secs_f64();
            let assoc = std::hint::black_box(associate_frame(frame, e, &cfg));
            frames += 1;
            boxes += frame.num_boxes();
            pairs += assoc.pairs.len();
            if pass == 0 {
                kept += assoc
                    .pairs
                    .iter()
                    .map(|p| p.matching.matches.len())
                    .sum::<usize>();
            }
        }
    }
    let seconds = start.elapsed().as_secs_f64();
    Ok(Throughput {
        frames,
        boxes_per_frame: boxes as f64 / frames as f64,
        pairs_per_frame: pairs as f64 / frames as f64,
        seconds,
        frames_per_second: frames as f64 / seconds.max(f64::MIN_POSITIVE),
        encoder_seconds,
        kept_matches: kept,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::{CameraSpec, Detection, Frame, SceneSpec};

    use crate::model::testing::BottomCentre;

    fn recording() -> Recording {
        let cameras = (0..3)
            .map(|i| CameraSpec {
                name: format!("c{i}"),
                width: 100,
                height: 100,
            })
            .collect();
        let mut frame = Frame::new(0, 3);
        for c in 0..3 {
            frame.views[c] = Some(vec![
                Detection::new([10.0, 10.0, 20.0, 50.0]),
                Detection::new([60.0, 10.0, 70.0, 90.0]),
            ]);
        }
        Recording {
            scene: SceneSpec {
                name: "s".into(),
                cameras,
            },
            frames: vec![frame],
        }
    }

    #[test]
    fn counts_frames_pairs_and_kept_matches() {
        let t = measure(&mut BottomCentre, &recording(), 0.0, 2, 3).unwrap();
        assert_eq!(t.frames, 3);
        assert_eq!(t.pairs_per_frame, 3.0);
        assert_eq!(t.boxes_per_frame, 6.0);
        assert_eq!(t.kept_matches, 6, "2 matches in each of 3 pairs, one pass");
        assert!(t.frames_per_second > 0.0);
    }

    #[test]
    fn bad_settings_are_errors() {
        let rec = recording();
        assert!(measure(&mut BottomCentre, &rec, 0.4, 0, 0).is_err());
        assert!(measure(&mut BottomCentre, &rec, f32::NAN, 0, 1).is_err());
        let empty = Recording {
            frames: vec![],
            ..rec
        };
        assert!(measure(&mut BottomCentre, &empty, 0.4, 0, 1).is_err());
    }
}

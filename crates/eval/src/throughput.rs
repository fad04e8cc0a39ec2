//! In-process throughput of the association pipeline, for comparison with the Python
//! reference (`bench/python_reference.py`): per frame ONE encoder call over every box
//! ([`embed_frame`]), then SPEC §3 matching for every camera pair ([`associate_pairs`]), and
//! optionally the global identities ([`associate_frame`]). Frames are spread over one worker
//! thread per encoder. Reading the recording is not timed.
use std::time::Instant;

use serde::Serialize;

use crossview_core::Encoder;
use crossview_core::association::{
    AssociationConfig, Mode, ViewPair, associate_frame, associate_pairs, embed_frame,
};
use crossview_core::{Error, Result};
use crossview_core::{Frame, SceneSpec};
use crossview_data::Recording;

/// What one measurement found.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Throughput {
    /// Frames timed (frames × repeats, warm-up excluded).
    pub frames: usize,
    /// Worker threads (one encoder each).
    pub workers: usize,
    /// Whether the global identities were built too.
    pub identities: bool,
    /// Boxes per timed frame, on average.
    pub boxes_per_frame: f64,
    /// Camera pairs matched per timed frame, on average.
    pub pairs_per_frame: f64,
    /// Wall-clock seconds of the timed loop.
    pub seconds: f64,
    /// Frames per second (wall clock, all workers together).
    pub frames_per_second: f64,
    /// Seconds spent in encoder calls, summed over workers.
    pub encoder_seconds: f64,
    /// Busy seconds summed over workers (encoder + matching).
    pub worker_seconds: f64,
    /// Kept pairwise matches over one pass of the recording (a cross-check with the
    /// reference's count on the same model and frames).
    pub kept_matches: usize,
}

/// Per-worker tallies.
#[derive(Default)]
struct Tally {
    frames: usize,
    boxes: usize,
    pairs: usize,
    kept: usize,
    encoder_seconds: f64,
    busy_seconds: f64,
}

/// Runs the pipeline over `recording`: `warmup` frames untimed on every worker, then `repeat`
/// timed passes, frame `i` of each pass going to worker `i % encoders.len()`.
pub fn measure<E: Encoder + Send>(
    encoders: &mut [E],
    recording: &Recording,
    threshold: f32,
    identities: bool,
    warmup: usize,
    repeat: usize,
) -> Result<Throughput> {
    if recording.frames.is_empty() {
        return Err(Error::invalid("data", "the recording has no frames"));
    }
    if repeat == 0 {
        return Err(Error::invalid("repeat", "must be at least 1"));
    }
    if encoders.is_empty() {
        return Err(Error::invalid("workers", "must be at least 1"));
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
    for encoder in encoders.iter_mut() {
        for frame in recording.frames.iter().cycle().take(warmup) {
            std::hint::black_box(run_frame(encoder, scene, frame, &cfg, identities)?);
        }
    }
    let workers = encoders.len();
    let start = Instant::now();
    let tallies: Vec<Result<Tally>> = std::thread::scope(|scope| {
        let handles: Vec<_> = encoders
            .iter_mut()
            .enumerate()
            .map(|(w, encoder)| {
                let cfg = &cfg;
                scope.spawn(move || -> Result<Tally> {
                    let mut t = Tally::default();
                    for pass in 0..repeat {
                        for frame in recording.frames.iter().skip(w).step_by(workers) {
                            let t0 = Instant::now();
                            let e = embed_frame(encoder, scene, frame)?;
                            t.encoder_seconds += t0.elapsed().as_secs_f64();
                            let pairs =
                                std::hint::black_box(match_frame(frame, e, cfg, identities));
                            t.busy_seconds += t0.elapsed().as_secs_f64();
                            t.frames += 1;
                            t.boxes += frame.num_boxes();
                            t.pairs += pairs.len();
                            if pass == 0 {
                                t.kept += pairs
                                    .iter()
                                    .map(|p| p.matching.matches.len())
                                    .sum::<usize>();
                            }
                        }
                    }
                    Ok(t)
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(Error::internal("benchmark worker panicked")))
            })
            .collect()
    });
    let seconds = start.elapsed().as_secs_f64();
    let mut sum = Tally::default();
    for t in tallies {
        let t = t?;
        sum.frames += t.frames;
        sum.boxes += t.boxes;
        sum.pairs += t.pairs;
        sum.kept += t.kept;
        sum.encoder_seconds += t.encoder_seconds;
        sum.busy_seconds += t.busy_seconds;
    }
    Ok(Throughput {
        frames: sum.frames,
        workers,
        identities,
        boxes_per_frame: sum.boxes as f64 / sum.frames as f64,
        pairs_per_frame: sum.pairs as f64 / sum.frames as f64,
        seconds,
        frames_per_second: sum.frames as f64 / seconds.max(f64::MIN_POSITIVE),
        encoder_seconds: sum.encoder_seconds,
        worker_seconds: sum.busy_seconds,
        kept_matches: sum.kept,
    })
}

fn run_frame<E: Encoder>(
    encoder: &mut E,
    scene: &SceneSpec,
    frame: &Frame,
    cfg: &AssociationConfig,
    identities: bool,
) -> Result<Vec<ViewPair>> {
    let e = embed_frame(encoder, scene, frame)?;
    Ok(match_frame(frame, e, cfg, identities))
}

/// The matching part of one frame: pairs only (the reference's work) or pairs + identities.
fn match_frame(
    frame: &Frame,
    embeddings: crossview_core::FrameEmbeddings,
    cfg: &AssociationConfig,
    identities: bool,
) -> Vec<ViewPair> {
    if identities {
        associate_frame(frame, embeddings, cfg).pairs
    } else {
        associate_pairs(frame, &embeddings, cfg)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::{Detection, Frame, SceneSpec};

    use crossview_core::testing::{BottomCentre, cameras};

    fn recording() -> Recording {
        let cameras = cameras(3, 100, 100);
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
            fps: None,
        }
    }

    #[test]
    fn counts_frames_pairs_and_kept_matches() {
        for identities in [false, true] {
            let t = measure(&mut [BottomCentre], &recording(), 0.0, identities, 2, 3).unwrap();
            assert_eq!(t.frames, 3);
            assert_eq!(t.pairs_per_frame, 3.0);
            assert_eq!(t.boxes_per_frame, 6.0);
            assert_eq!(t.kept_matches, 6, "2 matches in each of 3 pairs, one pass");
            assert!(t.frames_per_second > 0.0);
        }
    }

    #[test]
    fn workers_share_the_frames() {
        let mut rec = recording();
        let f = rec.frames[0].clone();
        rec.frames = (0..5)
            .map(|i| Frame {
                frame_id: i,
                ..f.clone()
            })
            .collect();
        let t = measure(&mut [BottomCentre, BottomCentre], &rec, 0.0, false, 1, 2).unwrap();
        assert_eq!((t.frames, t.workers), (10, 2));
        assert_eq!(t.kept_matches, 5 * 6, "one pass over 5 frames");
    }

    #[test]
    fn bad_settings_are_errors() {
        let rec = recording();
        assert!(measure(&mut [BottomCentre], &rec, 0.4, false, 0, 0).is_err());
        assert!(measure(&mut [BottomCentre], &rec, f32::NAN, false, 0, 1).is_err());
        assert!(measure::<BottomCentre>(&mut [], &rec, 0.4, false, 0, 1).is_err());
        let empty = Recording {
            frames: vec![],
            ..rec
        };
        assert!(measure(&mut [BottomCentre], &empty, 0.4, false, 0, 1).is_err());
    }
}

//! Tracking scores of `crossview eval --tracking`: every frame associated in frame order, its
//! identities linked over time by [`crossview_core::tracking::Tracker`], and each box's track
//! id scored against its ground-truth person id.
//!
//! The detections are the recording's boxes, so every ground-truth box has exactly one
//! predicted box (itself): no false positives or misses, and the scores reduce to identity
//! bookkeeping. IDF1 (Ristani et al. 2016) is the share of boxes on the one-to-one mapping of
//! ground-truth ids to track ids that covers the most boxes (identity precision = recall =
//! IDF1 here); *multi-camera* IDF1 takes all cameras as one sequence (as the MOTChallenge
//! multi-camera devkit does), *per camera* each camera alone. An ID switch is a ground-truth
//! person whose track id in a camera differs from the one it had there when last seen;
//! MOTA = 1 − switches / boxes (no misses or false positives).
use std::collections::HashMap;

use serde::Serialize;

use crossview_core::association::{AssociationConfig, embed_frame, frame_identities_with};
use crossview_core::matching::hungarian;
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::tracking::{Tracker, TrackerConfig};
use crossview_core::{Encoder, Error, Frame, Result};
use crossview_data::Recording;

use crate::driver::frame_ids;
use crate::parallel::{DEFAULT_WINDOW, map_ordered};

/// Identity scores of one sequence of observations.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TrackScores {
    /// Boxes scored.
    pub boxes: usize,
    /// Distinct ground-truth people.
    pub people: usize,
    /// Distinct track ids.
    pub tracks: usize,
    /// IDF1 in [0, 1].
    pub idf1: f64,
    /// ID switches (per camera; summed over cameras for the multi-camera row).
    pub id_switches: usize,
    /// 1 − switches / boxes.
    pub mota: f64,
}

/// `crossview eval --tracking`: multi-camera and per-camera scores.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackingReport {
    /// All cameras as one sequence.
    pub multi_camera: TrackScores,
    /// Each camera alone, in scene order.
    pub per_camera: Vec<(String, TrackScores)>,
}

/// One scored box: camera index, ground-truth id, track id.
pub type Observation = (usize, u64, u64);

/// Associates every frame of `recording` (ids required) with `cfg` (and, when given, a
/// [`Memory`] of the past frames, as the server's streams), tracks its identities with a fresh
/// [`Tracker`] in frame order, and scores the track ids. Frames are embedded (and, without
/// memory, associated) on one worker per encoder; the tracker sees them in frame order.
pub fn evaluate_tracking(
    encoders: &mut [&mut dyn Encoder],
    recording: &Recording,
    cfg: &AssociationConfig,
    tracker: &TrackerConfig,
    memory: Option<&MemoryConfig>,
) -> Result<TrackingReport> {
    let scene = &recording.scene;
    let mut tracker = Tracker::new(tracker.clone());
    let mut memory = memory.map(|m| Memory::new(m.clone()));
    let remember = memory.is_some();
    let mut obs: Vec<Observation> = Vec::new();
    let work = |encoder: &mut &mut dyn Encoder, _: usize, frame: &Frame| {
        let truth = frame_ids(scene, frame)?;
        let embeddings = embed_frame(*encoder, scene, frame)?;
        let identities =
            (!remember).then(|| frame_identities_with(frame, &embeddings, cfg, &[], None));
        Ok::<_, Error>((truth, embeddings, identities))
    };
    map_ordered(
        &recording.frames,
        encoders,
        DEFAULT_WINDOW,
        work,
        |i, (truth, embeddings, identities)| {
            let identities = identities.unwrap_or_else(|| {
                let frame = &recording.frames[i];
                frame_identities_with(frame, &embeddings, cfg, &[], memory.as_mut())
            });
            let tracks = tracker.update(&recording.frames[i], &identities, &embeddings);
            for (identity, track) in identities.iter().zip(tracks) {
                for &(c, i) in &identity.members {
                    if let Some(gt) = truth.get(c).and_then(Option::as_ref).and_then(|v| v.get(i)) {
                        obs.push((c, *gt, track));
                    }
                }
            }
            Ok(())
        },
    )?;
    let cameras: Vec<String> = scene.cameras.iter().map(|c| c.name.clone()).collect();
    Ok(score_tracks(&cameras, &obs))
}

/// Scores track ids given box by box, in frame order: `(camera index, ground-truth id, track
/// id)` for each box, `cameras` the scene's camera names. What [`evaluate_tracking`] reports
/// from its own tracker, for track ids that came from elsewhere (a server's stream).
pub fn score_tracks(cameras: &[String], obs: &[Observation]) -> TrackingReport {
    let per_camera: Vec<(String, TrackScores)> = cameras
        .iter()
        .enumerate()
        .map(|(c, name)| {
            let mine: Vec<Observation> = obs.iter().copied().filter(|o| o.0 == c).collect();
            (name.clone(), scores(&mine))
        })
        .collect();
    let mut multi_camera = scores(obs);
    multi_camera.id_switches = per_camera.iter().map(|(_, s)| s.id_switches).sum();
    multi_camera.mota = mota(multi_camera.id_switches, multi_camera.boxes);
    TrackingReport {
        multi_camera,
        per_camera,
    }
}

/// The scores of `obs` (in frame order).
fn scores(obs: &[Observation]) -> TrackScores {
    let mut gt_index: HashMap<u64, usize> = HashMap::new();
    let mut tr_index: HashMap<u64, usize> = HashMap::new();
    let mut counts: HashMap<(usize, usize), usize> = HashMap::new();
    let mut last: HashMap<(usize, u64), u64> = HashMap::new();
    let mut switches = 0;
    for &(c, gt, tr) in obs {
        let n = gt_index.len();
        let g = *gt_index.entry(gt).or_insert(n);
        let n = tr_index.len();
        let t = *tr_index.entry(tr).or_insert(n);
        *counts.entry((g, t)).or_default() += 1;
        if let Some(prev) = last.insert((c, gt), tr)
            && prev != tr
        {
            switches += 1;
        }
    }
    let boxes = obs.len();
    TrackScores {
        boxes,
        people: gt_index.len(),
        tracks: tr_index.len(),
        idf1: if boxes == 0 {
            0.0
        } else {
            best_mapping(gt_index.len(), tr_index.len(), &counts) as f64 / boxes as f64
        },
        id_switches: switches,
        mota: mota(switches, boxes),
    }
}

fn mota(switches: usize, boxes: usize) -> f64 {
    if boxes == 0 {
        0.0
    } else {
        1.0 - switches as f64 / boxes as f64
    }
}

/// Boxes on the one-to-one mapping of ground-truth ids to track ids that covers the most
/// (IDTP): a maximum-weight assignment on the co-occurrence counts.
fn best_mapping(people: usize, tracks: usize, counts: &HashMap<(usize, usize), usize>) -> usize {
    if people == 0 || tracks == 0 {
        return 0;
    }
    // Counts stay exact in f32 up to 2^24 boxes per pair.
    let mut cost = ndarray::Array2::<f32>::zeros((people, tracks));
    for (&(g, t), &n) in counts {
        cost[(g, t)] = -(n as f32);
    }
    hungarian(cost.view())
        .into_iter()
        .map(|(g, t)| counts.get(&(g, t)).copied().unwrap_or(0))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn perfect_tracks_score_one() {
        let obs = vec![
            (0, 1, 10),
            (0, 2, 20),
            (1, 1, 10),
            (0, 1, 10),
            (0, 2, 20),
            (1, 1, 10),
        ];
        let s = scores(&obs);
        assert_eq!((s.boxes, s.people, s.tracks, s.id_switches), (6, 2, 2, 0));
        assert_eq!((s.idf1, s.mota), (1.0, 1.0));
    }

    #[test]
    fn a_switch_costs_idf1_and_mota() {
        // Person 1 is track 10 for 3 frames, then track 11 for 1: IDF1 = 3/4 of its boxes.
        let obs = vec![(0, 1, 10), (0, 1, 10), (0, 1, 10), (0, 1, 11)];
        let s = scores(&obs);
        assert_eq!(s.id_switches, 1);
        assert!((s.idf1 - 0.75).abs() < 1e-12);
        assert!((s.mota - 0.75).abs() < 1e-12);
        // Two people sharing one track: only one of them maps to it.
        let s = scores(&[(0, 1, 5), (0, 2, 5), (1, 1, 5)]);
        assert!((s.idf1 - 2.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn switches_count_per_camera() {
        // The same person on two cameras with two different tracks is no switch by itself.
        let s = scores(&[(0, 1, 1), (1, 1, 2), (0, 1, 1), (1, 1, 2)]);
        assert_eq!(s.id_switches, 0);
        assert!((s.idf1 - 0.5).abs() < 1e-12);
        assert_eq!(scores(&[]).idf1, 0.0);
    }
}

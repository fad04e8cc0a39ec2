//! Camera clock offsets from the detections alone (no calibration, no timestamps).
//!
//! The encoder was trained to tell synchronized frames from shifted ones, so for two cameras
//! `a` and `b` that see the same people, the mean Hungarian-matched embedding distance between
//! `a` at frame `t` and `b` at frame `t + δ`, averaged over many `t`, is smallest at the true
//! offset `δ` ([`profile`]). Each pair's profile gives one measurement `o_b − o_a = δ_ab`; a
//! robust weighted least-squares fit over every confident pair gives each camera's offset
//! ([`solve`]). A camera linked to the others by no confident pair — it overlaps with none, or
//! nobody moves — is *unknown*, never guessed.
//!
//! Sign: a camera with offset `+k` shows in its frame `t + k` what the others show in frame
//! `t` (its frame ids run `k` frames late, e.g. an encoder that adds latency). Correcting it
//! means grouping its batch `N` with the others' frame `N − k`.
//!
//! Offsets are measured in frame-id units on the recording's frame step (the greatest common
//! divisor of its frame-id gaps: WILDTRACK's ids step by 5), so a shift by one frame interval
//! of a stride-5 recording is 5 ids; [`OffsetEstimate`] reports both.
//!
//! Pure and single-threaded: the caller embeds the boxes ([`CameraSeries`]) and may compute
//! the pairs' profiles on several threads.

mod profile;
mod solve;

use std::collections::BTreeMap;

use ndarray::{Array1, Array2};
use serde::Serialize;

pub(crate) use profile::column_means;
pub use profile::{PairProfile, profile};
pub use solve::solve;

use crate::distances::row_sq_norms;

/// Settings of the estimate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OffsetConfig {
    /// Largest offset searched, in frame steps either way (bounds the work: the profile of
    /// one pair costs `2 × max_offset + 1` matchings per frame).
    pub max_offset: u32,
    /// Frames a shift needs in common between the two cameras to be scored.
    pub min_frames: usize,
    /// Smallest paired z-score of the profile's minimum against every shift at least two
    /// steps away for a pair to count: below it the profile is too flat to say anything.
    pub min_z: f32,
    /// A pair whose measurement disagrees with the joint fit by more than this many frame
    /// steps is dropped as an outlier (and the fit redone).
    pub outlier_steps: f32,
}

impl Default for OffsetConfig {
    /// 20 steps, 20 frames per shift, z ≥ 4, outliers beyond 0.75 step.
    fn default() -> Self {
        OffsetConfig {
            max_offset: 20,
            min_frames: 20,
            min_z: 4.0,
            outlier_steps: 0.75,
        }
    }
}

/// One camera's embeddings over time: per frame id, the `[n, G]` embeddings of its boxes and
/// their squared norms. Frames where the camera saw nobody are left out.
#[derive(Debug, Clone, Default)]
pub struct CameraSeries {
    frames: BTreeMap<i64, (Array2<f32>, Array1<f32>)>,
}

impl CameraSeries {
    /// An empty series.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds (or replaces) frame `frame_id`'s embeddings; an empty matrix is ignored.
    pub fn insert(&mut self, frame_id: i64, embeddings: Array2<f32>) {
        if embeddings.nrows() == 0 {
            return;
        }
        let norms = row_sq_norms(embeddings.view());
        self.frames.insert(frame_id, (embeddings, norms));
    }

    /// Drops every frame before `frame_id` (a rolling window).
    pub fn retain_from(&mut self, frame_id: i64) {
        self.frames = self.frames.split_off(&frame_id);
    }

    /// A copy of the frames from `from` to `to`, both included (a window of a longer series).
    pub fn between(&self, from: i64, to: i64) -> CameraSeries {
        CameraSeries {
            frames: self
                .frames
                .range(from..=to.max(from))
                .map(|(&t, v)| (t, v.clone()))
                .collect(),
        }
    }

    /// Number of frames held.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// True when no frame is held.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The frame ids held, ascending.
    pub fn frame_ids(&self) -> impl DoubleEndedIterator<Item = i64> + '_ {
        self.frames.keys().copied()
    }

    fn get(&self, frame_id: i64) -> Option<&(Array2<f32>, Array1<f32>)> {
        self.frames.get(&frame_id)
    }
}

/// The frame step of a set of frame ids: the greatest common divisor of their gaps (1 when
/// there is fewer than two ids).
pub fn frame_step(ids: impl IntoIterator<Item = i64>) -> i64 {
    let mut ids: Vec<i64> = ids.into_iter().collect();
    ids.sort_unstable();
    ids.dedup();
    let g = ids.windows(2).fold(0i64, |g, w| gcd(g, w[1] - w[0]));
    g.max(1)
}

fn gcd(a: i64, b: i64) -> i64 {
    if b == 0 { a.abs() } else { gcd(b, a % b) }
}

/// Every pair `(a, b)` with `a < b` of `n` cameras, in order.
pub fn camera_pairs(n: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..n).flat_map(move |a| (a + 1..n).map(move |b| (a, b)))
}

/// The whole estimate for `series` (one per camera, in camera order) on one thread: every
/// pair's [`profile`], then the joint fit ([`solve`]). The work is bounded by the frames held,
/// the pairs and `2 × max_offset + 1` shifts.
pub fn estimate(
    series: &[CameraSeries],
    step: i64,
    reference: Option<usize>,
    cfg: &OffsetConfig,
) -> OffsetEstimate {
    let profiles = profiles(series, step, cfg);
    let frames: Vec<usize> = series.iter().map(CameraSeries::len).collect();
    solve(series.len(), &profiles, &frames, step, reference, cfg)
}

/// Every pair's [`profile`] on one thread, `(a, b)` with `a < b` in [`camera_pairs`] order
/// (what [`estimate`] solves; the camera fit, [`crate::fit`], reads them again).
pub fn profiles(
    series: &[CameraSeries],
    step: i64,
    cfg: &OffsetConfig,
) -> Vec<(usize, usize, PairProfile)> {
    camera_pairs(series.len())
        .map(|(a, b)| (a, b, profile(&series[a], &series[b], step, cfg)))
        .collect()
}

/// Why a camera has no offset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Unknown {
    /// No confident pair links the camera to the reference: it overlaps with no other camera,
    /// or nobody moved in the frames it shares with them.
    NoConfidentPair,
    /// The camera sent too few frames.
    TooFewFrames,
}

/// One camera's estimated offset.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraOffset {
    /// Camera index in the scene.
    pub camera: usize,
    /// Offset in frame ids, rounded to the frame step (what a correction applies); `None`
    /// when unknown.
    pub frames: Option<i64>,
    /// Sub-step estimate in frame ids (parabola through each pair's minimum, fitted jointly).
    pub refined: Option<f32>,
    /// Confident pairs kept by the fit that involve this camera.
    pub pairs: usize,
    /// Strongest paired z-score among those pairs (how deep its profiles' minima are).
    pub z: f32,
    /// Root-mean-square disagreement of those pairs with the fit, in frame steps.
    pub residual: f32,
    /// Confidence in `[0, 1]`: `1 − exp(−z / 8)` of the strongest pair, lowered when the
    /// pairs disagree (0 when unknown).
    pub confidence: f32,
    /// Why the offset is unknown.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unknown: Option<Unknown>,
}

/// The joint estimate for a scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OffsetEstimate {
    /// Camera index every offset is relative to (its offset is 0).
    pub reference: usize,
    /// Frame step of the ids (offsets are multiples of it).
    pub step: i64,
    /// One entry per camera, in camera order.
    pub cameras: Vec<CameraOffset>,
    /// Every camera pair's profile summary, with whether the fit kept it.
    pub pairs: Vec<PairSummary>,
}

/// What the fit made of one camera pair.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PairSummary {
    pub a: usize,
    pub b: usize,
    /// `o_b − o_a` at the profile's minimum, in frame ids (`None`: no shift had enough frames).
    pub delta: Option<i64>,
    /// Sub-step `o_b − o_a` in frame ids.
    pub refined: Option<f32>,
    /// Paired z-score of the minimum against every shift at least two steps away.
    pub z: f32,
    /// Frames scored at the minimum.
    pub frames: usize,
    /// Kept by the joint fit.
    pub used: bool,
}

#[cfg(test)]
mod tests;

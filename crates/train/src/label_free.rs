//! **[ours]** Label-free model selection: scores of an encoder on unlabelled frames held out
//! from training, used to keep the best epoch and to pick the inference threshold when no
//! labels are given.
//!
//! Every score is computed in one pass over the held-out frames (one encoder call per frame,
//! one Hungarian assignment per camera pair and per time-shifted pair):
//! - **synchronization accuracy**: how often the Hungarian image distance `H` (mean raw
//!   distance of the assigned pairs, as the training loss sees it) of a synchronized pair of
//!   views is below that of the same views 5–19 frames apart;
//! - **cycle consistency**: over camera triples `(i, j, k)`, how often the assignments
//!   `i→j→k` land on the box `i→k` picks;
//! - **expected decision accuracy** (`expected_acc`): with a calibration ([`Calibration`])
//!   fitted on the same frames, a kept Hungarian pair is right with probability `p` and a
//!   dropped one with `1 − p`; the candidate threshold on `S` with the most expected right
//!   decisions (reported; on WILDTRACK it lands too high, so `crossview train` stores the
//!   reference threshold instead — BENCHMARKS.md, "Training");
//! - **consistent**: the share of boxes in confident identities spanning three or more
//!   cameras (what the self-training stage labels).
//!
//! Measured over real runs (BENCHMARKS.md, "Label-free model selection"), cycle consistency
//! tracks the labelled scores best, so it is the selection [`LabelFreeScores::key`]. An
//! untrained model rates its own expected accuracy highly (it "knows" it matches nothing), so
//! `expected_acc` never picks epochs.
//!
//! The shifted frames are drawn once, when the scorer is built, so that the scores of
//! different epochs compare like with like.
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::calibrate::embed_all;
use crate::data::TrainingSet;
use crate::pseudo::{PseudoOptions, frame_labels, frame_pairs, identity_config};
use crossview_core::Encoder;
use crossview_core::association::ViewPair;
use crossview_core::calibration::Calibration;
use crossview_core::distances::euclidean_distances;
use crossview_core::matching::hungarian;
use crossview_core::{Error, Result};

/// The threshold on `S` when the held-out frames cannot be calibrated.
const FALLBACK_THRESHOLD: f32 = 0.4;

/// Frame offsets of the time-shifted views (as the training negatives, SPEC §4).
const SHIFT: std::ops::RangeInclusive<usize> = 5..=19;

/// The label-free scores of one model on the held-out frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LabelFreeScores {
    /// Fraction of (frame, ordered camera pair) where the synchronized views are closer than
    /// the time-shifted ones, in [0, 1].
    pub sync_acc: f64,
    /// Fraction of assignment chains `i→j→k` that agree with `i→k`, in [0, 1].
    pub cycle: f64,
    /// Expected share of right keep/drop decisions over the Hungarian pairs at
    /// `threshold`, from the calibration, in [0, 1].
    pub expected_acc: f64,
    /// The threshold on `S` with the best expected decision accuracy.
    pub threshold: f32,
    /// Fraction of the held-out boxes in confident identities that span at least three
    /// cameras (what the self-training stage would label), in [0, 1].
    #[serde(default)]
    pub consistent: f64,
}

impl LabelFreeScores {
    /// The selection score: higher is better (see BENCHMARKS.md, "Label-free model selection",
    /// for how well each candidate tracks the labelled scores).
    pub fn key(&self) -> f64 {
        self.cycle
    }
}

/// Scores encoders on a fixed set of unlabelled frames.
pub struct LabelFreeScorer {
    set: TrainingSet,
    /// `shift[t][i]`: the frame the views of camera `i` are compared with at frame `t`.
    shift: Vec<Vec<Option<usize>>>,
    thresholds: Vec<f32>,
}

impl LabelFreeScorer {
    /// A scorer over `set` (frames never used for training), searching `thresholds` on `S`.
    /// Needs at least 2 cameras and 2·5+1 frames so every frame has a shifted partner.
    pub fn new(set: TrainingSet, thresholds: Vec<f32>, seed: u64) -> Result<Self> {
        let n = set.num_frames();
        if set.num_cameras() < 2 || n <= 2 * SHIFT.start() {
            return Err(Error::Training(format!(
                "label-free scoring needs at least 2 cameras and {} held-out frames, got {} and {n}",
                2 * SHIFT.start() + 1,
                set.num_cameras()
            )));
        }
        if thresholds.is_empty() {
            return Err(Error::invalid("thresholds", "at least one is needed"));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let shift = (0..n)
            .map(|t| {
                (0..set.num_cameras())
                    .map(|_| {
                        let d = rng.random_range(SHIFT);
                        let fwd = rng.random::<bool>();
                        match (fwd, t + d < n, t >= d) {
                            (true, true, _) | (false, true, false) => Some(t + d),
                            (false, _, true) | (true, false, true) => Some(t - d),
                            _ => None,
                        }
                    })
                    .collect()
            })
            .collect();
        Ok(LabelFreeScorer {
            set,
            shift,
            thresholds,
        })
    }

    /// The scores of `encoder`, plus the calibration fitted on the held-out frames. When the
    /// frames hold too few pairs for a calibration, the calibrated scores are 0 and the
    /// threshold is the reference 0.4 (SPEC §3's WILDTRACK setting).
    // Camera indices address views, shifts and both triangles of the assignment table.
    #[allow(clippy::needless_range_loop)]
    pub fn score(
        &self,
        encoder: &mut dyn Encoder,
    ) -> Result<(LabelFreeScores, Option<Calibration>)> {
        let emb = embed_all(encoder, &self.set)?;
        let cams = self.set.num_cameras();
        // Each frame's box counts and camera-pair matchings, kept for the calibrated scores.
        let mut frames: Vec<(Vec<usize>, Vec<ViewPair>)> = Vec::with_capacity(emb.len());
        let (mut sync_d, mut shift_d) = (Vec::new(), Vec::new());
        let (mut wins, mut trials) = (0usize, 0usize);
        let (mut agree, mut chains) = (0usize, 0usize);
        // assignment[i][j]: for each box of camera i, its Hungarian partner in camera j.
        let mut assignment: Vec<Vec<Vec<Option<usize>>>> = vec![vec![Vec::new(); cams]; cams];
        for (t, frame) in emb.iter().enumerate() {
            for row in assignment.iter_mut() {
                row.iter_mut().for_each(Vec::clear);
            }
            let (sizes, pairs) = frame_pairs(frame);
            for p in &pairs {
                let (i, j) = (p.cam_a, p.cam_b);
                let assigned = &p.matching.assignment;
                let mut fwd = vec![None; sizes[i]];
                let mut back = vec![None; sizes[j]];
                for q in assigned {
                    fwd[q.a] = Some(q.b);
                    back[q.b] = Some(q.a);
                    sync_d.push(q.distance);
                }
                let h_sync =
                    assigned.iter().map(|q| q.distance).sum::<f32>() / assigned.len() as f32;
                // Both directions: i's views against j's shifted views, and j's against i's.
                for (anchor, other) in [(i, j), (j, i)] {
                    let Some(t2) = self.shift[t][other] else {
                        continue;
                    };
                    let a = frame.view(anchor).expect("every camera has rows");
                    let neg = emb[t2].view(other).expect("every camera has rows");
                    if neg.nrows() == 0 {
                        continue;
                    }
                    let dn = euclidean_distances(a, neg);
                    let pn = hungarian(dn.view());
                    shift_d.extend(pn.iter().map(|&(x, y)| dn[(x, y)]));
                    trials += 1;
                    if h_sync < mean_assigned(&dn, &pn) {
                        wins += 1;
                    }
                }
                assignment[i][j] = fwd;
                assignment[j][i] = back;
            }
            let (a, c) = cycle_counts(&assignment);
            agree += a;
            chains += c;
            frames.push((sizes, pairs));
        }
        let cal = Calibration::fit(&sync_d, &shift_d).ok();
        let (expected_acc, threshold, labelled) = match &cal {
            Some(cal) => calibrated_scores(&frames, cal, &self.thresholds),
            None => (0.0, FALLBACK_THRESHOLD, 0),
        };
        let ratio = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        Ok((
            LabelFreeScores {
                sync_acc: ratio(wins, trials),
                cycle: ratio(agree, chains),
                expected_acc,
                threshold,
                consistent: ratio(labelled, self.set.num_boxes()),
            },
            cal,
        ))
    }
}

/// Over every ordered camera triple `(i, j, k)` of one frame's assignment table: how many
/// chains `i→j→k` land where `i→k` does, and how many chains there are.
fn cycle_counts(assignment: &[Vec<Vec<Option<usize>>>]) -> (usize, usize) {
    let cams = assignment.len();
    let (mut agree, mut chains) = (0, 0);
    for i in 0..cams {
        for j in 0..cams {
            for k in 0..cams {
                if i == j || j == k || i == k {
                    continue;
                }
                for (x, &y) in assignment[i][j].iter().enumerate() {
                    let Some(y) = y else { continue };
                    let Some(z) = assignment[j][k].get(y).copied().flatten() else {
                        continue;
                    };
                    chains += 1;
                    if assignment[i][k].get(x).copied().flatten() == Some(z) {
                        agree += 1;
                    }
                }
            }
        }
    }
    (agree, chains)
}

/// The scores that need the held-out frames' calibration: the expected decision accuracy,
/// its threshold, and how many boxes fall in confident identities (pseudo-labels).
fn calibrated_scores(
    frames: &[(Vec<usize>, Vec<ViewPair>)],
    cal: &Calibration,
    thresholds: &[f32],
) -> (f64, f32, usize) {
    let (e, t) = expected_acc(frames, cal, thresholds);
    let opts = PseudoOptions::default();
    let cfg = identity_config(cal, &opts);
    let labelled = frames
        .iter()
        .map(|(sizes, pairs)| {
            let row = frame_labels(sizes, pairs, &cfg, &opts);
            row.iter().flatten().flatten().count()
        })
        .sum();
    (e, t, labelled)
}

/// The best expected decision accuracy over `thresholds` and the threshold reaching it (the
/// lowest on ties). Boxes left without a Hungarian partner count as right decisions.
fn expected_acc(
    frames: &[(Vec<usize>, Vec<ViewPair>)],
    cal: &Calibration,
    thresholds: &[f32],
) -> (f64, f32) {
    let mut num = vec![0.0f64; thresholds.len()];
    let mut den = 0.0f64;
    for p in frames.iter().flat_map(|(_, pairs)| pairs) {
        let (n, m) = p.matching.scores.dim();
        let unassigned = n.abs_diff(m) as f64;
        den += unassigned;
        num.iter_mut().for_each(|v| *v += unassigned);
        for q in &p.matching.assignment {
            let (d, s) = (q.distance, q.score);
            let q = cal.probability(d) as f64;
            den += 1.0;
            for (n, &t) in num.iter_mut().zip(thresholds) {
                *n += if s >= t { q } else { 1.0 - q };
            }
        }
    }
    let mut best = (0.0, thresholds[0]);
    for (n, &t) in num.iter().zip(thresholds) {
        let acc = if den > 0.0 { n / den } else { 0.0 };
        if acc > best.0 {
            best = (acc, t);
        }
    }
    best
}

fn mean_assigned(d: &Array2<f32>, pairs: &[(usize, usize)]) -> f32 {
    if pairs.is_empty() {
        return f32::INFINITY;
    }
    pairs.iter().map(|&(x, y)| d[(x, y)]).sum::<f32>() / pairs.len() as f32
}

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

use crate::core::calibration::Calibration;
use crate::core::matching::{euclidean_distances, hungarian};
use crate::model::Encoder;
use crate::train::calibrate::embed_all;
use crate::train::data::TrainingSet;
use crate::train::pseudo::{PseudoOptions, pseudo_labels};
use crate::{Error, Result};

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

    /// Number of held-out frames.
    pub fn num_frames(&self) -> usize {
        self.set.num_frames()
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
        let mut pairs: Vec<PairSample> = Vec::new();
        let (mut sync_d, mut shift_d) = (Vec::new(), Vec::new());
        let (mut wins, mut trials) = (0usize, 0usize);
        let (mut agree, mut chains) = (0usize, 0usize);
        // assignment[i][j]: for each box of camera i, its Hungarian partner in camera j.
        let mut assignment: Vec<Vec<Vec<Option<usize>>>> = vec![vec![Vec::new(); cams]; cams];
        for (t, frame) in emb.iter().enumerate() {
            let view = |c: usize| frame.view(c).expect("every camera has rows");
            for row in assignment.iter_mut() {
                row.iter_mut().for_each(Vec::clear);
            }
            for i in 0..cams {
                for j in i + 1..cams {
                    let (a, b) = (view(i), view(j));
                    if a.nrows() == 0 || b.nrows() == 0 {
                        continue;
                    }
                    let dg = euclidean_distances(a, b);
                    let pairs_ij = hungarian(dg.view());
                    let max = dg.iter().copied().fold(0.0f32, f32::max) + 1e-12;
                    let mut fwd = vec![None; a.nrows()];
                    let mut back = vec![None; b.nrows()];
                    let mut sample = PairSample {
                        assigned: Vec::with_capacity(pairs_ij.len()),
                        unassigned: a.nrows().abs_diff(b.nrows()),
                    };
                    for &(x, y) in &pairs_ij {
                        fwd[x] = Some(y);
                        back[y] = Some(x);
                        sync_d.push(dg[(x, y)]);
                        sample.assigned.push((dg[(x, y)], 1.0 - dg[(x, y)] / max));
                    }
                    let h_sync = mean_assigned(&dg, &pairs_ij);
                    // Both directions: i's views against j's shifted views, and j's against i's.
                    for (anchor, other, oc) in [(a, j, j), (b, i, i)] {
                        let Some(t2) = self.shift[t][oc] else {
                            continue;
                        };
                        let neg = emb[t2].view(other).expect("every camera has rows");
                        if neg.nrows() == 0 {
                            continue;
                        }
                        let dn = euclidean_distances(anchor, neg);
                        let pn = hungarian(dn.view());
                        shift_d.extend(pn.iter().map(|&(x, y)| dn[(x, y)]));
                        trials += 1;
                        if h_sync < mean_assigned(&dn, &pn) {
                            wins += 1;
                        }
                    }
                    assignment[i][j] = fwd;
                    assignment[j][i] = back;
                    pairs.push(sample);
                }
            }
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
        }
        let cal = Calibration::fit(&sync_d, &shift_d).ok();
        let (expected_acc, threshold, labelled) = match &cal {
            Some(cal) => {
                let (e, t) = expected_acc(&pairs, cal, &self.thresholds);
                let opts = PseudoOptions::default();
                (
                    e,
                    t,
                    pseudo_labels(encoder, &self.set, cal, &opts)?.labelled(),
                )
            }
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

/// One image pair's Hungarian pairs as `(raw distance, S)`, and its boxes left unassigned.
struct PairSample {
    assigned: Vec<(f32, f32)>,
    unassigned: usize,
}

/// The best expected decision accuracy over `thresholds` and the threshold reaching it (the
/// lowest on ties). Boxes left without a Hungarian partner count as right decisions.
fn expected_acc(pairs: &[PairSample], cal: &Calibration, thresholds: &[f32]) -> (f64, f32) {
    let mut num = vec![0.0f64; thresholds.len()];
    let mut den = 0.0f64;
    for p in pairs {
        den += p.unassigned as f64;
        num.iter_mut().for_each(|n| *n += p.unassigned as f64);
        for &(d, s) in &p.assigned {
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

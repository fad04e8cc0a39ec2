//! **[ours]** Identities: the camera pairs' matchings of one frame turned into persons —
//! clusters with at most one box per camera — that are consistent across views.
//!
//! # Scheme: correlation clustering of the full pairwise affinities
//!
//! Pairwise matching decides each camera pair alone, so its results can contradict each other
//! (A1↔B1, B1↔C1 but A1↔C2), and with binary matches a contradicted camera triangle is a tie
//! no vote can break. Here every pair of boxes `u`, `v` in different cameras gets an additive
//! weight from the full score matrices ([`evidence`]):
//! - a Hungarian pair: `c − t + b · k`, with `c = max(S, P)` (SPEC §3's `S`, and the calibrated
//!   `P(same | distance)` when the model has a calibration, which keeps a lone correct match
//!   whose `S` is ≈ 0) and `k` the third cameras whose Hungarian partners of `u` and of `v` are
//!   one box;
//! - any other entry: `min(0, P − t)` (`S` without a calibration): no evidence for, and
//!   evidence against as far as its own confidence falls below `t`.
//!
//! Starting from single boxes, the two clusters with the largest total weight between them
//! merge while that total is positive, their cameras are disjoint and no pair of their boxes
//! weighs below `−t/2` (greedy additive edge contraction, the standard heuristic for
//! correlation clustering, grown best-first with camera exclusivity as in 4D association,
//! with a complete-linkage veto so that many weak links cannot outvote one clear
//! contradiction; [`clustering`]). Two tuned parameters, the link threshold `t` and the
//! support `b`, and the veto's share of `t` picked from {0, ¼, ½, none}, all chosen on the
//! WILDTRACK training frames — scored under six models, the committed one and five
//! ensembles of the default trainer, so that the setting holds for the models users train —
//! and the simulator presets (BENCHMARKS.md, "Identities"); the validation frames only
//! report.
//!
//! The plain baseline — union-find over the kept `S` matches, strongest first, with a bonus
//! per agreeing third camera ([`union_find`]) — stays as [`IdentityMethod::UnionFind`]: the
//! tests' oracle, and a fallback.
//!
//! Properties (tested): identities are camera-exclusive and cover every box once; with two
//! cameras they are the Hungarian pairs whose `max(S, P)` exceeds `t`; transitively consistent
//! matches are returned unchanged; one camera pair that swaps two persons while the others
//! agree is repaired; deterministic (ties go to the lowest box indices).
//!
//! # Confidence
//! See [`confidence`]: the geometric mean of cohesion, completeness and camera coverage.
use std::sync::Arc;

use crate::calibration::Calibration;
use crate::matching::ViewPair;
use crate::matching::{Assigned, Match, PairMatching};

mod clustering;
mod confidence;
mod evidence;
mod union_find;

use clustering::Clustering;
use evidence::{Evidence, NONE};

/// A person seen by one or more cameras in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Identity {
    /// Identity number within the frame (0-based, dense).
    pub id: usize,
    /// Confidence in [0, 1] (see the module documentation).
    pub confidence: f32,
    /// Members as `(camera index, index into that camera's detections)`, sorted by camera.
    pub members: Vec<(usize, usize)>,
}

impl Identity {
    /// Cross-view links of this identity (pairs of members), `k·(k−1)/2` for `k` members.
    pub fn links(&self) -> usize {
        let k = self.members.len();
        k * k.saturating_sub(1) / 2
    }
}

/// How a frame's boxes are grouped into identities.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum IdentityMethod {
    /// Correlation clustering of the full pairwise affinities (the module documentation).
    #[default]
    Clustering,
    /// The plain baseline: union-find over the kept `S` matches ([`union_find`]).
    UnionFind,
}

impl IdentityMethod {
    /// The measured `(link threshold, support)` of this method (BENCHMARKS.md).
    pub fn defaults(self) -> (f32, f32) {
        match self {
            IdentityMethod::Clustering => (0.4, 0.125),
            IdentityMethod::UnionFind => (0.5, 0.3),
        }
    }
}

impl std::str::FromStr for IdentityMethod {
    type Err = crate::Error;
    fn from_str(s: &str) -> crate::Result<Self> {
        match s {
            "clustering" => Ok(IdentityMethod::Clustering),
            "union-find" => Ok(IdentityMethod::UnionFind),
            other => Err(crate::Error::invalid(
                "identity method",
                format!("expected 'clustering' or 'union-find', got '{other}'"),
            )),
        }
    }
}

impl std::fmt::Display for IdentityMethod {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            IdentityMethod::Clustering => "clustering",
            IdentityMethod::UnionFind => "union-find",
        })
    }
}

/// How a frame's pairs become identities.
#[derive(Debug, Clone, PartialEq)]
pub struct IdentityConfig {
    /// The model's calibration: with it a pair's probability is `P(same | distance)`.
    pub calibration: Option<Arc<Calibration>>,
    /// Threshold of the calibrated pairwise matches ([`Self::kept`]; `P`, else `S`).
    pub threshold: f32,
    /// How boxes are grouped.
    pub method: IdentityMethod,
    /// `t`: the confidence a link must exceed (on `max(S, P)` for the clustering, on `S`
    /// for the union-find).
    pub link_threshold: f32,
    /// `b`: weight added to a link per third camera that agrees with it.
    pub support: f32,
    /// The clustering's veto as a share of `t`: two clusters never merge while one pair of
    /// their boxes weighs below `−veto · t` (`f32::INFINITY` = no veto).
    pub veto: f32,
}

impl IdentityConfig {
    /// The default method with its measured parameters; `threshold` is the calibrated
    /// pairwise threshold ([`Self::kept`]).
    pub fn new(calibration: Option<Arc<Calibration>>, threshold: f32) -> Self {
        IdentityConfig::with_method(calibration, threshold, IdentityMethod::default())
    }

    /// `method` with its measured parameters ([`IdentityMethod::defaults`]).
    pub fn with_method(
        calibration: Option<Arc<Calibration>>,
        threshold: f32,
        method: IdentityMethod,
    ) -> Self {
        let (link_threshold, support) = method.defaults();
        IdentityConfig {
            calibration,
            threshold,
            method,
            link_threshold,
            support,
            veto: clustering::VETO,
        }
    }

    /// The probability of one Hungarian pair: calibrated `P`, or `S` without a calibration.
    /// Non-finite values become 0 (no evidence).
    pub fn confidence(&self, p: &Assigned) -> f32 {
        let c = match &self.calibration {
            Some(cal) => cal.probability(p.distance),
            None => p.score,
        };
        if c.is_finite() { c } else { 0.0 }
    }

    /// The link confidence of one Hungarian pair: `max(S, P)` (`S` without a calibration):
    /// `S` ranks a pair among its camera pair's boxes, `P` keeps a lone match whose `S` is
    /// ≈ 0. Non-finite values become 0.
    pub fn link_confidence(&self, p: &Assigned) -> f32 {
        let s = if p.score.is_finite() { p.score } else { 0.0 };
        match &self.calibration {
            Some(_) => self.confidence(p).max(s),
            None => s,
        }
    }

    /// The Hungarian pairs of `m` whose [`Self::confidence`] reaches [`Self::threshold`]:
    /// pairwise matching on the calibrated probability.
    pub fn kept(&self, m: &PairMatching) -> Vec<Match> {
        m.assignment
            .iter()
            .filter_map(|p| {
                let c = self.confidence(p);
                (c >= self.threshold).then_some(Match {
                    a: p.a,
                    b: p.b,
                    score: c,
                })
            })
            .collect()
    }
}

impl Default for IdentityConfig {
    /// Uncalibrated, calibrated-pairwise threshold 0.4 (SPEC §3's WILDTRACK setting).
    fn default() -> Self {
        IdentityConfig::new(None, 0.4)
    }
}

/// Builds the identities of one frame.
///
/// `view_sizes[c]` is the number of boxes of camera `c` (0 for cameras without boxes or
/// that did not report); `pairs` holds the matchings of camera pairs (`cam_a != cam_b`,
/// score matrices of shape `view_sizes[cam_a] × view_sizes[cam_b]`; pairs that break this,
/// and repeats of a camera pair, are ignored with a warning). Every box ends in exactly one
/// identity, and identities are ordered by their first member. See the module documentation.
pub fn build_identities(
    view_sizes: &[usize],
    pairs: &[ViewPair],
    cfg: &IdentityConfig,
) -> Vec<Identity> {
    let (offsets, n) = box_offsets(view_sizes);
    if n == 0 {
        return Vec::new();
    }
    if n >= NONE as usize {
        tracing::warn!(
            boxes = n,
            "frame too large for identities; every box left alone"
        );
        return singletons(view_sizes);
    }
    let ev = Evidence::collect(view_sizes, offsets, pairs, cfg);
    let clusters = match cfg.method {
        IdentityMethod::Clustering => {
            let mut cl = Clustering::new(&ev);
            cl.run();
            cl.clusters()
        }
        IdentityMethod::UnionFind => union_find::clusters(
            view_sizes,
            &ev.offsets,
            pairs,
            cfg.link_threshold,
            cfg.support,
        ),
    };
    clusters
        .into_iter()
        .enumerate()
        .map(|(id, m)| Identity {
            id,
            confidence: confidence::confidence(&ev, &m),
            members: m
                .iter()
                .map(|&i| (ev.cam_of[i], i - ev.offsets[ev.cam_of[i]]))
                .collect(),
        })
        .collect()
}

/// Where each camera's boxes start in the frame's box numbering (plus the total at the end),
/// and the total.
fn box_offsets(view_sizes: &[usize]) -> (Vec<usize>, usize) {
    let mut offsets = Vec::with_capacity(view_sizes.len() + 1);
    let mut n = 0usize;
    for &s in view_sizes {
        offsets.push(n);
        n += s;
    }
    offsets.push(n);
    (offsets, n)
}

/// Every box its own identity (with no evidence to go on).
fn singletons(view_sizes: &[usize]) -> Vec<Identity> {
    view_sizes
        .iter()
        .enumerate()
        .flat_map(|(c, &k)| (0..k).map(move |i| (c, i)))
        .enumerate()
        .map(|(id, m)| Identity {
            id,
            confidence: 0.0,
            members: vec![m],
        })
        .collect()
}

/// The matches of camera pair `p` implied by `identities`, sorted by `a`, scored with `S`.
pub fn identity_matches(identities: &[Identity], p: &ViewPair) -> Vec<Match> {
    let s = &p.matching.scores;
    let mut matches: Vec<Match> = identities
        .iter()
        .filter_map(|ident| {
            let a = ident.members.iter().find(|m| m.0 == p.cam_a)?.1;
            let b = ident.members.iter().find(|m| m.0 == p.cam_b)?.1;
            let score = *s.get((a, b))?;
            Some(Match { a, b, score })
        })
        .collect();
    matches.sort_unstable_by_key(|m| m.a);
    matches
}

#[cfg(test)]
mod tests;

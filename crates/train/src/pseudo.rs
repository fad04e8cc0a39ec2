//! **[ours]** Pseudo-identity labels for the self-training stage: the most confident,
//! multi-view consistent identities ([`crossview_core::identity`]) of a first-stage encoder on
//! the training frames, kept as a per-box label. No ground truth is involved: the labels come
//! from the model's own calibrated matches, filtered to identities that at least
//! `min_views` cameras agree on and whose every member pair has a calibrated probability of
//! `min_confidence` or more (`weakest_link`).
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::calibrate::embed_all;
use crate::data::TrainingSet;
use crossview_core::Encoder;
use crossview_core::FrameEmbeddings;
use crossview_core::Result;
use crossview_core::association::ViewPair;
use crossview_core::calibration::Calibration;
use crossview_core::identity::{IdentityConfig, build_identities};
use crossview_core::matching::match_views;

/// Which identities become labels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PseudoOptions {
    /// Smallest calibrated `P(same | distance)` of every member pair of a labelled identity.
    pub min_confidence: f32,
    /// Fewest cameras an identity must span (3 = confirmed by a cycle).
    pub min_views: usize,
    /// Threshold on the calibrated pair confidence for the identities (as
    /// `crossview.match_threshold`).
    pub match_threshold: f32,
    /// **[ours]** The self-training stage trains only on boxes in identities (any confidence)
    /// that span at least this many cameras: boxes the first stage places in no other camera
    /// are mostly detections outside the shared area or false ones (0 = keep every box).
    #[serde(default)]
    pub keep_views: usize,
}

impl Default for PseudoOptions {
    fn default() -> Self {
        PseudoOptions {
            min_confidence: 0.5,
            min_views: 3,
            match_threshold: 0.2,
            keep_views: 0,
        }
    }
}

/// Per-box pseudo-identities: `labels[frame][camera][box]`, unique within a frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PseudoLabels {
    /// The labels; `None` for boxes in no kept identity.
    pub labels: Vec<Vec<Vec<Option<u32>>>>,
    /// `keep[frame][camera][box]`: the boxes the self-training losses use
    /// ([`PseudoOptions::keep_views`]); empty = every box.
    #[serde(default)]
    pub keep: Vec<Vec<Vec<bool>>>,
}

impl PseudoLabels {
    /// The label of box `b` of camera `c` at frame position `t`.
    pub fn get(&self, t: usize, c: usize, b: usize) -> Option<u32> {
        self.labels.get(t)?.get(c)?.get(b).copied().flatten()
    }

    /// Number of labelled boxes.
    pub fn labelled(&self) -> usize {
        self.labels.iter().flatten().flatten().flatten().count()
    }

    /// Number of boxes the self-training losses use (`None` = every box).
    pub fn kept(&self) -> Option<usize> {
        (!self.keep.is_empty())
            .then(|| self.keep.iter().flatten().flatten().filter(|&&k| k).count())
    }

    /// `set` restricted to the kept boxes, with the labels renumbered to it; `None` when
    /// every box is kept.
    pub(crate) fn restrict(&self, set: &TrainingSet) -> Option<(TrainingSet, PseudoLabels)> {
        if self.keep.is_empty() {
            return None;
        }
        let mut out = set.clone();
        let mut labels = Vec::with_capacity(set.images.len());
        for (t, frame) in out.images.iter_mut().enumerate() {
            let mut row = Vec::with_capacity(frame.len());
            for (c, image) in frame.iter_mut().enumerate() {
                let keep = |b: usize| {
                    self.keep
                        .get(t)
                        .and_then(|f| f.get(c))
                        .and_then(|v| v.get(b))
                        .copied()
                        .unwrap_or(true)
                };
                let kept: Vec<usize> = (0..image.boxes.len()).filter(|&b| keep(b)).collect();
                image.boxes = kept.iter().map(|&b| image.boxes[b]).collect();
                if let Some(app) = &mut image.appearance {
                    *app = kept.iter().map(|&b| app[b].clone()).collect();
                }
                row.push(kept.iter().map(|&b| self.get(t, c, b)).collect());
            }
            labels.push(row);
        }
        Some((
            out,
            PseudoLabels {
                labels,
                keep: Vec::new(),
            },
        ))
    }
}

/// Labels the boxes of `set` with `encoder`'s confident identities under `cal`.
pub(crate) fn pseudo_labels(
    encoder: &mut dyn Encoder,
    set: &TrainingSet,
    cal: &Calibration,
    opts: &PseudoOptions,
) -> Result<PseudoLabels> {
    let cfg = identity_config(cal, opts);
    let (labels, keep): (Vec<_>, Vec<_>) = embed_all(encoder, set)?
        .iter()
        .map(|frame| {
            let (sizes, pairs) = frame_pairs(frame);
            labels_and_keep(&sizes, &pairs, &cfg, opts)
        })
        .unzip();
    let keep = if opts.keep_views > 0 {
        keep
    } else {
        Vec::new()
    };
    Ok(PseudoLabels { labels, keep })
}

/// The identity step's `(t, b, veto)` for pseudo-labels: the setting every training run in
/// BENCHMARKS.md ("Training") was measured with. The served default moved on 2026-12-04 (chosen
/// with ensembles in view); a change here changes every run, so it waits for a paired training
/// measurement.
const PSEUDO_IDENTITY: (f32, f32, f32) = (0.35, 0.125, 0.25);

/// The identity step's configuration for pseudo-labels under `cal`.
pub(crate) fn identity_config(cal: &Calibration, opts: &PseudoOptions) -> IdentityConfig {
    let (link_threshold, support, veto) = PSEUDO_IDENTITY;
    IdentityConfig {
        link_threshold,
        support,
        veto,
        ..IdentityConfig::new(Some(Arc::new(cal.clone())), opts.match_threshold)
    }
}

/// One frame's box count per camera and the SPEC §3 matching (geometry only, nothing
/// dropped) of every camera pair with boxes on both sides.
pub(crate) fn frame_pairs(frame: &FrameEmbeddings) -> (Vec<usize>, Vec<ViewPair>) {
    let cams = frame.num_views();
    let sizes: Vec<usize> = (0..cams)
        .map(|c| frame.view(c).map_or(0, |v| v.nrows()))
        .collect();
    let mut pairs = Vec::new();
    for i in 0..cams {
        for j in i + 1..cams {
            let (Some(a), Some(b)) = (frame.view(i), frame.view(j)) else {
                continue;
            };
            if a.nrows() == 0 || b.nrows() == 0 {
                continue;
            }
            pairs.push(ViewPair {
                cam_a: i,
                cam_b: j,
                matching: match_views(a, b, None, None, 0.0, 0.0),
            });
        }
    }
    (sizes, pairs)
}

/// One frame's labels (`[camera][box]`): its identities that span at least `opts.min_views`
/// cameras and whose every member pair has a probability ([`weakest_link`]) of
/// `opts.min_confidence` or more, numbered from 0.
pub(crate) fn frame_labels(
    sizes: &[usize],
    pairs: &[ViewPair],
    cfg: &IdentityConfig,
    opts: &PseudoOptions,
) -> Vec<Vec<Option<u32>>> {
    labels_and_keep(sizes, pairs, cfg, opts).0
}

/// [`frame_labels`] and which boxes are in identities spanning at least
/// `opts.keep_views` cameras (`[camera][box]`).
fn labels_and_keep(
    sizes: &[usize],
    pairs: &[ViewPair],
    cfg: &IdentityConfig,
    opts: &PseudoOptions,
) -> (Vec<Vec<Option<u32>>>, Vec<Vec<bool>>) {
    let mut row: Vec<Vec<Option<u32>>> = sizes.iter().map(|&n| vec![None; n]).collect();
    let mut keep: Vec<Vec<bool>> = sizes.iter().map(|&n| vec![false; n]).collect();
    let mut next = 0u32;
    for id in build_identities(sizes, pairs, cfg) {
        if id.members.len() >= opts.keep_views {
            for &(c, b) in &id.members {
                keep[c][b] = true;
            }
        }
        if id.members.len() >= opts.min_views
            && weakest_link(&id.members, pairs, cfg) >= opts.min_confidence
        {
            for &(c, b) in &id.members {
                row[c][b] = Some(next);
            }
            next += 1;
        }
    }
    (row, keep)
}

/// The lowest pairwise probability among an identity's members: the calibrated
/// `P(same | distance)` of each member pair (SPEC §3's `S` without a calibration), whether or
/// not the pair was a Hungarian match.
///
/// The identity's own confidence ranks identities within a frame (its cohesion uses
/// `max(S, P)`, and `S` is relative to the frame's other boxes), so an encoder that has learnt
/// little still produces confident-looking identities — on the 3-camera synthetic scene of the
/// training tests, 60 first-stage epochs gave 792 labelled boxes at 23 % link precision. `P`
/// is fitted on synchronized against time-shifted views and stays low for such an encoder:
/// the same frames give 72 boxes at 64 % (BENCHMARKS.md, "Training").
fn weakest_link(members: &[(usize, usize)], pairs: &[ViewPair], cfg: &IdentityConfig) -> f32 {
    let mut weakest = 1f32;
    for (i, &(ca, a)) in members.iter().enumerate() {
        for &(cb, b) in &members[i + 1..] {
            let Some(pair) = pairs.iter().find(|p| p.cam_a == ca && p.cam_b == cb) else {
                return 0.0;
            };
            let m = &pair.matching;
            let p = match &cfg.calibration {
                Some(cal) => cal.probability(m.distance(a, b)),
                None => m.scores.get((a, b)).copied().unwrap_or(0.0),
            };
            weakest = weakest.min(if p.is_finite() { p } else { 0.0 });
        }
    }
    weakest
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Image;
    use crossview_core::{CameraSpec, SceneSpec};

    fn image(n: usize) -> Image {
        Image {
            boxes: (0..n)
                .map(|k| [k as f32 * 0.1, 0.0, k as f32 * 0.1 + 0.05, 0.3])
                .collect(),
            appearance: None,
        }
    }

    #[test]
    fn restrict_drops_unkept_boxes_and_keeps_their_labels_aligned() {
        let cam = |name: &str| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: name.into(),
            width: 100,
            height: 100,
        };
        let set = TrainingSet {
            scene: SceneSpec {
                name: "s".into(),
                cameras: vec![cam("a"), cam("b")],
            },
            frame_ids: vec![0],
            images: vec![vec![image(3), image(2)]],
        };
        let all = PseudoLabels {
            labels: vec![vec![vec![Some(0), None, Some(1)], vec![Some(1), None]]],
            keep: Vec::new(),
        };
        assert!(all.restrict(&set).is_none());
        assert_eq!(all.kept(), None);
        let some = PseudoLabels {
            keep: vec![vec![vec![false, true, true], vec![true, false]]],
            ..all
        };
        assert_eq!(some.kept(), Some(3));
        let (s, l) = some.restrict(&set).unwrap();
        assert_eq!(s.images[0][0].boxes, set.images[0][0].boxes[1..].to_vec());
        assert_eq!(s.images[0][1].boxes, set.images[0][1].boxes[..1].to_vec());
        assert_eq!(l.labels, vec![vec![vec![None, Some(1)], vec![Some(1)]]]);
        assert!(l.keep.is_empty());
    }

    /// Three cameras see two well separated people the same way: the identities are
    /// confident whatever the calibration, but they become labels only where the calibrated
    /// `P` of every member pair says so — an encoder whose `P` is low everywhere (it has learnt
    /// little) labels nothing.
    #[test]
    fn labels_need_every_member_pair_probable_not_a_confident_identity() {
        use crossview_core::matching::match_views;
        let emb = ndarray::array![[0.0f32, 0.0], [5.0, 5.0]];
        let mut pairs = Vec::new();
        for (a, b) in [(0, 1), (0, 2), (1, 2)] {
            pairs.push(ViewPair {
                cam_a: a,
                cam_b: b,
                matching: match_views(emb.view(), emb.view(), None, None, 0.0, 0.0),
            });
        }
        let sizes = [2, 2, 2];
        let cal = |p_near: f32, p_far: f32| Calibration {
            distances: vec![0.5, 4.0],
            probabilities: vec![p_near, p_far],
            false_share: 0.5,
            samples: [100, 100],
        };
        let opts = PseudoOptions::default();
        let learnt = identity_config(&cal(0.95, 0.0), &opts);
        let ids = build_identities(&sizes, &pairs, &learnt);
        assert_eq!(ids.len(), 2);
        assert!(ids.iter().all(|i| i.members.len() == 3));
        let row = frame_labels(&sizes, &pairs, &learnt, &opts);
        assert_eq!(row, vec![vec![Some(0), Some(1)]; 3]);
        // Nothing learnt: P ≈ the share of right pairs by chance, everywhere.
        let flat = identity_config(&cal(0.3, 0.3), &opts);
        let ids = build_identities(&sizes, &pairs, &flat);
        assert!(
            ids.iter()
                .any(|i| i.members.len() == 3 && i.confidence >= opts.min_confidence),
            "the identity confidence alone would label them: {ids:?}"
        );
        assert_eq!(
            frame_labels(&sizes, &pairs, &flat, &opts),
            vec![vec![None, None]; 3]
        );
        // One weak member pair is enough to keep an identity out.
        assert_eq!(weakest_link(&[(0, 0), (1, 0), (2, 0)], &pairs, &flat), 0.3);
    }
}

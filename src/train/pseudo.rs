//! **[ours]** Pseudo-identity labels for the self-training stage: the most confident,
//! multi-view consistent identities ([`crate::core::identity`]) of a first-stage encoder on
//! the training frames, kept as a per-box label. No ground truth is involved: the labels come
//! from the model's own calibrated matches, filtered to identities that at least
//! `min_views` cameras agree on with confidence `min_confidence` or more.
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::Result;
use crate::core::FrameEmbeddings;
use crate::core::association::ViewPair;
use crate::core::calibration::Calibration;
use crate::core::identity::{IdentityConfig, build_identities};
use crate::core::matching::match_views;
use crate::model::Encoder;
use crate::train::calibrate::embed_all;
use crate::train::data::TrainingSet;

/// Which identities become labels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PseudoOptions {
    /// Smallest identity confidence kept.
    pub min_confidence: f32,
    /// Fewest cameras an identity must span (3 = confirmed by a cycle).
    pub min_views: usize,
    /// Threshold on the calibrated pair confidence for the identities (as
    /// `crossview.match_threshold`).
    pub match_threshold: f32,
}

impl Default for PseudoOptions {
    fn default() -> Self {
        PseudoOptions {
            min_confidence: 0.5,
            min_views: 3,
            match_threshold: 0.2,
        }
    }
}

/// Per-box pseudo-identities: `labels[frame][camera][box]`, unique within a frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PseudoLabels {
    /// The labels; `None` for boxes in no kept identity.
    pub labels: Vec<Vec<Vec<Option<u32>>>>,
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
}

/// Labels the boxes of `set` with `encoder`'s confident identities under `cal`.
pub fn pseudo_labels(
    encoder: &mut dyn Encoder,
    set: &TrainingSet,
    cal: &Calibration,
    opts: &PseudoOptions,
) -> Result<PseudoLabels> {
    let cfg = identity_config(cal, opts);
    let labels = embed_all(encoder, set)?
        .iter()
        .map(|frame| {
            let (sizes, pairs) = frame_pairs(frame);
            frame_labels(&sizes, &pairs, &cfg, opts)
        })
        .collect();
    Ok(PseudoLabels { labels })
}

/// The identity step's configuration for pseudo-labels under `cal`.
pub(crate) fn identity_config(cal: &Calibration, opts: &PseudoOptions) -> IdentityConfig {
    IdentityConfig::new(Some(Arc::new(cal.clone())), opts.match_threshold)
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
/// cameras with confidence `opts.min_confidence` or more, numbered from 0.
pub(crate) fn frame_labels(
    sizes: &[usize],
    pairs: &[ViewPair],
    cfg: &IdentityConfig,
    opts: &PseudoOptions,
) -> Vec<Vec<Option<u32>>> {
    let mut row: Vec<Vec<Option<u32>>> = sizes.iter().map(|&n| vec![None; n]).collect();
    let mut next = 0u32;
    for id in build_identities(sizes, pairs, cfg) {
        if id.members.len() >= opts.min_views && id.confidence >= opts.min_confidence {
            for &(c, b) in &id.members {
                row[c][b] = Some(next);
            }
            next += 1;
        }
    }
    row
}

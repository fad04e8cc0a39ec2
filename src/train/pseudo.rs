//! **[ours]** Pseudo-identity labels for the self-training stage: the most confident,
//! multi-view consistent identities ([`crate::core::identity`]) of a first-stage encoder on
//! the training frames, kept as a per-box label. No ground truth is involved: the labels come
//! from the model's own calibrated matches, filtered to identities that at least
//! `min_views` cameras agree on with confidence `min_confidence` or more.
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::Result;
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
    let cfg = IdentityConfig::new(Some(Arc::new(cal.clone())), opts.match_threshold);
    let emb = embed_all(encoder, set)?;
    let cams = set.num_cameras();
    let mut labels = Vec::with_capacity(emb.len());
    for (t, frame) in emb.iter().enumerate() {
        let sizes: Vec<usize> = (0..cams).map(|c| set.images[t][c].boxes.len()).collect();
        let mut pairs = Vec::new();
        for i in 0..cams {
            for j in i + 1..cams {
                let (a, b) = (frame.view(i), frame.view(j));
                let (Some(a), Some(b)) = (a, b) else { continue };
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
        let mut row: Vec<Vec<Option<u32>>> = sizes.iter().map(|&n| vec![None; n]).collect();
        let mut next = 0u32;
        for id in build_identities(&sizes, &pairs, &cfg) {
            if id.members.len() >= opts.min_views && id.confidence >= opts.min_confidence {
                for &(c, b) in &id.members {
                    row[c][b] = Some(next);
                }
                next += 1;
            }
        }
        labels.push(row);
    }
    Ok(PseudoLabels { labels })
}

//! **[ours]** Several encoders as one: the embedding of a box is the concatenation of the
//! members' embeddings, each scaled by `1/√M`, so the Euclidean distance between two boxes is
//! the root mean square of the members' distances. Members trained from different seeds err on
//! different boxes; matching on the mean of their distances errs less than the best member
//! alone (BENCHMARKS.md, "Population training"). A model file holds one encoder or an
//! ensemble (SPEC §8 is unchanged: `boxes`, `camera` in, `embedding` out).
use ndarray::{Array2, s};

use crate::EncoderWeights;
use crossview_core::{Encoder, Error, Result};

/// One encoder or several whose embeddings are concatenated (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Ensemble {
    members: Vec<EncoderWeights>,
}

impl Ensemble {
    /// An ensemble of `members` (at least one, each valid, all for the same cameras).
    pub fn new(members: Vec<EncoderWeights>) -> Result<Self> {
        let Some(first) = members.first() else {
            return Err(Error::invalid("ensemble", "needs at least one encoder"));
        };
        for (k, m) in members.iter().enumerate() {
            m.validate()?;
            if m.num_cameras != first.num_cameras {
                return Err(Error::invalid(
                    "ensemble",
                    format!(
                        "member {k} has {} cameras, member 0 has {}",
                        m.num_cameras, first.num_cameras
                    ),
                ));
            }
        }
        Ok(Ensemble { members })
    }

    /// A single encoder.
    pub fn single(weights: EncoderWeights) -> Self {
        Ensemble {
            members: vec![weights],
        }
    }

    /// The members, in the order of their parts of the embedding.
    pub fn members(&self) -> &[EncoderWeights] {
        &self.members
    }

    /// Cameras every member embeds.
    pub fn num_cameras(&self) -> usize {
        self.members[0].num_cameras
    }

    /// Embedding width: the sum of the members' widths.
    pub fn width(&self) -> usize {
        self.members.iter().map(EncoderWeights::width).sum()
    }

    /// The factor each member's embedding is multiplied by (`1/√M`).
    pub fn scale(&self) -> f32 {
        1.0 / (self.members.len() as f32).sqrt()
    }

    /// The plain-Rust forward pass: the members' [`EncoderWeights::forward`], scaled and
    /// concatenated, `[N, width]`.
    pub fn forward(&self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        if let [only] = self.members.as_slice() {
            return only.forward(boxes, cameras);
        }
        let mut out = Array2::zeros((boxes.len(), self.width()));
        let mut at = 0;
        for m in &self.members {
            let part = m.forward(boxes, cameras)?;
            let w = part.ncols();
            out.slice_mut(s![.., at..at + w])
                .assign(&(part * self.scale()));
            at += w;
        }
        Ok(out)
    }
}

impl Encoder for Ensemble {
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        self.forward(boxes, cameras)
    }
    fn dim(&self) -> usize {
        self.width()
    }
    fn leading_width(&self) -> usize {
        self.members[0].width()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::EncoderConfig;
    use crossview_core::distances::euclidean_distances;

    fn member(seed: u64, width: usize) -> EncoderWeights {
        let cfg = EncoderConfig {
            fourier_features: 8,
            camera_dim: 4,
            width,
            blocks: 1,
        };
        EncoderWeights::random(3, cfg, seed).unwrap()
    }

    /// The ensemble's distances are the root mean square of its members' distances.
    #[test]
    fn distances_are_the_rms_of_the_members() {
        let e = Ensemble::new(vec![member(1, 16), member(2, 24)]).unwrap();
        let boxes = [
            [0.1, 0.2, 0.3, 0.6],
            [0.5, 0.1, 0.7, 0.9],
            [0.2, 0.2, 0.4, 0.8],
        ];
        let cams = [0, 1, 2];
        let all = e.forward(&boxes, &cams).unwrap();
        assert_eq!(all.dim(), (3, 40));
        let d = euclidean_distances(all.view(), all.view());
        let d1 = {
            let x = e.members()[0].forward(&boxes, &cams).unwrap();
            euclidean_distances(x.view(), x.view())
        };
        let d2 = {
            let x = e.members()[1].forward(&boxes, &cams).unwrap();
            euclidean_distances(x.view(), x.view())
        };
        for i in 0..3 {
            for j in (0..3).filter(|&j| j != i) {
                let rms = ((d1[(i, j)].powi(2) + d2[(i, j)].powi(2)) / 2.0).sqrt();
                assert!((d[(i, j)] - rms).abs() < 1e-4, "{i},{j}");
            }
        }
    }

    #[test]
    fn one_member_is_that_encoder() {
        let m = member(3, 16);
        let e = Ensemble::single(m.clone());
        let b = [[0.1, 0.2, 0.3, 0.6]];
        assert_eq!(e.forward(&b, &[1]).unwrap(), m.forward(&b, &[1]).unwrap());
        assert_eq!(e.width(), 16);
    }

    #[test]
    fn members_must_share_cameras_and_exist() {
        assert!(Ensemble::new(Vec::new()).is_err());
        let other = EncoderWeights::random(2, member(1, 16).config, 1).unwrap();
        assert!(Ensemble::new(vec![member(1, 16), other]).is_err());
    }
}

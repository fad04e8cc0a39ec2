//! Validation during training: the candle model as an [`Encoder`], scored on labelled frames
//! through the evaluation code ([`crossview_eval`]), with the inference threshold chosen on that
//! data (SPEC §3: the paper picks it from 0.0–0.9).
use ndarray::Array2;

use crate::model::TrainModel;
use crate::state::{ValScores, Validator};
use crossview_core::Encoder;
use crossview_core::association::{AssociationConfig, Mode};
use crossview_core::{Error, Result};
use crossview_data::Recording;
use crossview_eval::driver::evaluate_settings;

/// The thresholds searched: 0.0, 0.1, …, 0.9.
pub fn candidate_thresholds() -> Vec<f32> {
    (0..10).map(|i| i as f32 / 10.0).collect()
}

/// A model under training seen through the inference [`Encoder`] trait.
pub struct CandleEncoder<'a> {
    model: &'a TrainModel,
}

impl<'a> CandleEncoder<'a> {
    /// Wraps `model`.
    pub fn new(model: &'a TrainModel) -> Self {
        CandleEncoder { model }
    }
}

impl Encoder for CandleEncoder<'_> {
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        if boxes.len() != cameras.len() {
            return Err(Error::invalid(
                "cameras",
                format!("{} boxes but {} camera indices", boxes.len(), cameras.len()),
            ));
        }
        let n = self.model.num_cameras as i64;
        let cams = cameras
            .iter()
            .map(|&c| {
                if (0..n).contains(&c) {
                    Ok(c as u32)
                } else {
                    Err(Error::invalid(
                        "camera",
                        format!("index {c} outside 0..{n}"),
                    ))
                }
            })
            .collect::<Result<Vec<u32>>>()?;
        self.model.embed(boxes, &cams)
    }

    fn dim(&self) -> usize {
        self.model.config.width
    }
}

/// Scores models on a labelled recording and selects the threshold with the best ACC.
pub struct EvalValidator {
    recording: Recording,
    thresholds: Vec<f32>,
    alpha: f32,
}

impl EvalValidator {
    /// A validator over `recording` (every box needs a ground-truth id) searching
    /// `thresholds` (the fixed `[t]` keeps a given threshold).
    pub fn new(recording: Recording, thresholds: Vec<f32>, alpha: f32) -> Result<Self> {
        if thresholds.is_empty() {
            return Err(Error::invalid("thresholds", "at least one is needed"));
        }
        let unlabelled = recording
            .frames
            .iter()
            .flat_map(|f| f.views.iter().flatten().flatten())
            .filter(|d| d.id.is_none())
            .count();
        if unlabelled > 0 {
            return Err(Error::invalid(
                "validation recording",
                format!("{unlabelled} box(es) have no ground-truth id"),
            ));
        }
        Ok(EvalValidator {
            recording,
            thresholds,
            alpha,
        })
    }

    /// Scores of `encoder` at each candidate threshold (pairwise matching, SPEC §5), computed
    /// by the evaluation driver: every frame is embedded once.
    pub(crate) fn scores_per_threshold(&self, encoder: &mut dyn Encoder) -> Result<Vec<ValScores>> {
        let settings: Vec<(Mode, f32)> = self
            .thresholds
            .iter()
            .map(|&t| (Mode::Pairwise, t))
            .collect();
        let base = AssociationConfig {
            alpha: self.alpha,
            ..AssociationConfig::default()
        };
        let runs = evaluate_settings(encoder, &self.recording, &base, &settings)?;
        Ok(runs
            .iter()
            .map(|r| ValScores {
                acc: r.metrics.acc,
                ipaa100: r.metrics.ipaa_100,
                precision: r.metrics.precision,
                recall: r.metrics.recall,
                threshold: r.threshold,
            })
            .collect())
    }
}

impl Validator for EvalValidator {
    fn validate(&mut self, model: &TrainModel) -> Result<ValScores> {
        let mut enc = CandleEncoder::new(model);
        let all = self.scores_per_threshold(&mut enc)?;
        let mut best = all[0];
        for s in &all[1..] {
            if s.better_than(&best) {
                best = *s;
            }
        }
        Ok(best)
    }
}

//! What a run holds and reports: scores, per-epoch records, the best weights kept, the
//! mutable run state a checkpoint saves, and the outcome. Shared by the training loop, the
//! checkpoints and the validators, none of which needs the others for it.
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use serde::{Deserialize, Serialize};

use crate::adam::Adam;
use crate::label_free::{LabelFreeScorer, LabelFreeScores};
use crate::model::TrainModel;
use crate::pseudo::PseudoLabels;
use crossview_core::Result;
use crossview_model::EncoderWeights;

/// Validation scores of one model at its selected threshold.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ValScores {
    /// Association accuracy (SPEC §5), in [0, 1].
    pub acc: f64,
    /// Fraction of image pairs fully correct, in [0, 1].
    pub ipaa100: f64,
    /// Precision.
    pub precision: f64,
    /// Recall.
    pub recall: f64,
    /// The threshold these scores were obtained at.
    pub threshold: f32,
}

impl ValScores {
    /// Ordering used to keep the best model: ACC, then IPAA-100.
    pub(crate) fn better_than(&self, other: &ValScores) -> bool {
        (self.acc, self.ipaa100) > (other.acc, other.ipaa100)
    }
}

/// Scores a model under training on labelled data (implemented over the eval code).
pub trait Validator {
    /// Evaluates `model` and returns the scores at the best threshold it selects.
    fn validate(&mut self, model: &TrainModel) -> Result<ValScores>;
}

/// Per-epoch record for the training curve.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpochRecord {
    /// 1-based epoch.
    pub epoch: usize,
    /// Mean losses over the epoch's steps.
    pub total: f32,
    /// Synchronization loss.
    pub syn: f32,
    /// Re-projection loss.
    pub pro: f32,
    /// Edge loss.
    pub edge: f32,
    /// **[ours]** Pseudo-identity loss (self-training stage).
    #[serde(default)]
    pub id: f32,
    /// Seconds of training so far (excluding validation).
    pub train_seconds: f64,
    /// Validation at the end of this epoch, when run.
    pub val: Option<ValScores>,
    /// Label-free scores at the end of this epoch, when run.
    #[serde(default)]
    pub label_free: Option<LabelFreeScores>,
}

/// What chooses the exported epoch and threshold.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Select {
    /// The label-free score on held-out frames (no labels needed).
    #[default]
    LabelFree,
    /// Labelled validation (ACC, then IPAA-100).
    Labelled,
}

/// How a run is scored while it trains: none, label-free, labelled, or both (one chooses).
#[derive(Default)]
pub struct Scoring<'a> {
    /// Label-free scorer over frames held out from training.
    pub label_free: Option<&'a LabelFreeScorer>,
    /// Labelled validation.
    pub validator: Option<&'a mut dyn Validator>,
    /// What chooses the exported weights (falls back to the other score, then the last epoch).
    pub select: Select,
}

/// The weights kept so far and why.
#[derive(Debug, Clone)]
pub struct Best {
    /// Encoder weights.
    pub weights: EncoderWeights,
    /// Their epoch.
    pub epoch: usize,
    /// Their validation scores, when validated.
    pub val: Option<ValScores>,
    /// Their label-free scores, when scored.
    pub label_free: Option<LabelFreeScores>,
}

/// Where and how often to checkpoint, and the flag that interrupts a run.
#[derive(Debug, Clone, Default)]
pub struct CheckpointOptions {
    /// Checkpoint directory (none = no checkpoints).
    pub dir: Option<PathBuf>,
    /// Save every this many epochs (0 = only at the end).
    pub every: usize,
    /// Continue from the checkpoint in `dir` when one exists.
    pub resume: bool,
    /// When this becomes true (Ctrl-C), the run ends after the epoch in progress: it is
    /// scored, checkpointed to `dir`, and the best weights so far are its outcome.
    pub interrupt: Option<Arc<AtomicBool>>,
}

impl CheckpointOptions {
    /// True once the run was asked to stop.
    pub fn interrupted(&self) -> bool {
        self.interrupt
            .as_ref()
            .is_some_and(|f| f.load(Ordering::Relaxed))
    }
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct TrainOutcome {
    /// The weights to export: the best scored ones when scoring ran, else the last.
    pub weights: EncoderWeights,
    /// Validation scores of `weights` (when validated).
    pub best: Option<ValScores>,
    /// Label-free scores of `weights` (when scored).
    pub label_free: Option<LabelFreeScores>,
    /// What chose `weights` (`None`: nothing scored, the last epoch).
    pub selected_by: Option<Select>,
    /// Epoch of `weights`.
    pub best_epoch: usize,
    /// Per-epoch history.
    pub history: Vec<EpochRecord>,
    /// Optimiser steps taken.
    pub steps: u64,
    /// Seconds spent training (excluding validation).
    pub train_seconds: f64,
}

/// The mutable state of a run (what a checkpoint holds).
pub struct RunState {
    /// Model under training.
    pub model: TrainModel,
    /// Optimiser.
    pub adam: Adam,
    /// The moving average of the weights (when `ema_decay > 0`).
    pub ema: Option<TrainModel>,
    /// Completed epochs.
    pub epoch: usize,
    /// History so far.
    pub history: Vec<EpochRecord>,
    /// Best scored weights so far.
    pub best: Option<Best>,
    /// The pseudo-identity labels of the self-training stage, once it started.
    pub pseudo: Option<PseudoLabels>,
    /// Optimiser steps of earlier stages (each stage starts a fresh optimiser).
    pub stage_steps: u64,
    /// Seconds of training so far.
    pub train_seconds: f64,
}

impl RunState {
    /// An independent copy of the run's state (a population clones its best member).
    pub fn try_clone(&self) -> Result<Self> {
        let model = self.model.deep_copy()?;
        let adam = self.adam.clone_for(model.named_vars());
        Ok(RunState {
            adam,
            model,
            ema: self.ema.as_ref().map(TrainModel::deep_copy).transpose()?,
            epoch: self.epoch,
            history: self.history.clone(),
            best: self.best.clone(),
            pseudo: self.pseudo.clone(),
            stage_steps: self.stage_steps,
            train_seconds: self.train_seconds,
        })
    }
}

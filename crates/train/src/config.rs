//! What shapes a training run: [`TrainConfig`] (the recipe, its presets and checks) and the
//! learning-rate schedule.
use serde::{Deserialize, Serialize};

use crate::pseudo::PseudoOptions;
use crossview_core::{Error, Result};
use crossview_model::EncoderConfig;

/// Everything that shapes a training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Fourier features per corner (F).
    pub fourier_features: usize,
    /// Camera embedding width (C).
    pub camera_dim: usize,
    /// Block width (G); an input projection is added when `width != 4F + C`.
    pub width: usize,
    /// Residual blocks.
    pub blocks: usize,
    /// Epochs; one epoch = every training frame once as an anchor.
    pub epochs: usize,
    /// Triplets per optimiser step.
    pub triplets_per_step: usize,
    /// Adam learning rate (the peak of the schedule).
    pub lr: f64,
    /// Fraction of training after which the learning rate is multiplied by 0.1
    /// ([`LrSchedule::Step`] only).
    pub lr_drop_at: f64,
    /// **[ours]** How the learning rate changes over training.
    #[serde(default)]
    pub schedule: LrSchedule,
    /// **[ours]** Fraction of training over which the learning rate ramps up linearly from 0.
    #[serde(default)]
    pub warmup: f64,
    /// **[ours]** Decay of the exponential moving average of the encoder weights, per step
    /// (0 = off). The average is what is scored and exported.
    #[serde(default)]
    pub ema_decay: f64,
    /// **[ours]** Epochs of the self-training stage after `epochs` (0 = none): training goes
    /// on from the best first-stage weights with the pseudo-identity loss added.
    #[serde(default)]
    pub self_train_epochs: usize,
    /// **[ours]** Peak learning rate of the self-training stage (same schedule as the first).
    #[serde(default = "self_train_lr")]
    pub self_train_lr: f64,
    /// **[ours]** Which first-stage identities become pseudo-labels.
    #[serde(default)]
    pub pseudo: PseudoOptions,
    /// **[ours]** Recompute the pseudo-labels from the current (averaged) weights every this
    /// many self-training epochs (0 = keep the first stage's labels for the whole stage).
    #[serde(default)]
    pub pseudo_refresh_every: usize,
    /// Edge pairs per matching (0 = all unique unordered edges).
    pub max_edges: usize,
    /// Appearance weight (used only when boxes carry appearance vectors).
    pub alpha: f32,
    /// **[ours]** Fraction of the most confident Hungarian pairs used by the losses
    /// (1.0 = SPEC §4).
    #[serde(default = "one")]
    pub pair_fraction: f32,
    /// **[ours]** Fraction of the first stage during which the synchronization loss uses a soft
    /// assignment (entropy-regularised transport) instead of the Hungarian pairs, its
    /// temperature falling linearly from [`Self::soft_temperature`] to 0 (0 = off).
    #[serde(default)]
    pub soft_assignment: f64,
    /// **[ours]** Starting temperature of the soft assignment, in units of the max-normalised
    /// distance.
    #[serde(default = "soft_temperature")]
    pub soft_temperature: f32,
    /// Seed of initialisation and sampling.
    pub seed: u64,
    /// Validate every this many epochs (0 = only at the end); needs a validator.
    pub val_every: usize,
    /// Optional wall-clock budget for training in seconds: training stops after the first
    /// epoch that exceeds it, and the learning-rate drop happens at `lr_drop_at` of the
    /// budget instead of the epochs. For exploration: such runs are not reproducible.
    #[serde(default)]
    pub max_train_seconds: Option<f64>,
}

impl Default for TrainConfig {
    fn default() -> Self {
        TrainConfig {
            fourier_features: 128,
            camera_dim: 256,
            width: 768,
            blocks: 3,
            epochs: 1200,
            triplets_per_step: 1,
            lr: 1e-4,
            lr_drop_at: 0.75,
            schedule: LrSchedule::Step,
            warmup: 0.0,
            ema_decay: 0.0,
            self_train_epochs: 0,
            self_train_lr: self_train_lr(),
            pseudo: PseudoOptions::default(),
            pseudo_refresh_every: 0,
            max_edges: 0,
            alpha: 0.1,
            pair_fraction: 1.0,
            soft_assignment: 0.0,
            soft_temperature: soft_temperature(),
            seed: 0,
            val_every: 0,
            max_train_seconds: None,
        }
    }
}

/// **[ours]** Learning-rate schedules.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    /// The paper's: constant, × 0.1 after `lr_drop_at` of training.
    #[default]
    Step,
    /// Cosine decay from `lr` to `lr / 100` after the warm-up.
    Cosine,
}

impl TrainConfig {
    /// **[ours]** The recipe `crossview train` uses by default: it learns from detector boxes
    /// in minutes on one core (BENCHMARKS.md, "Training"). [`TrainConfig::default`] is the
    /// paper's.
    pub fn recommended() -> Self {
        TrainConfig {
            fourier_features: 32,
            camera_dim: 32,
            width: 64,
            triplets_per_step: 8,
            lr: 1e-3,
            lr_drop_at: 1.0,
            schedule: LrSchedule::Step,
            warmup: 0.02,
            ema_decay: 0.999,
            epochs: 1100,
            self_train_epochs: 300,
            max_edges: 16,
            val_every: 25,
            ..TrainConfig::default()
        }
    }

    /// The learning rate at `progress` ∈ [0, 1] of training.
    pub(crate) fn lr_at(&self, progress: f64) -> f64 {
        let f = progress.clamp(0.0, 1.0);
        if self.warmup > 0.0 && f < self.warmup {
            return self.lr * (f / self.warmup).max(0.01);
        }
        match self.schedule {
            LrSchedule::Step if f >= self.lr_drop_at => self.lr * 0.1,
            LrSchedule::Step => self.lr,
            LrSchedule::Cosine => {
                let x = if self.warmup < 1.0 {
                    (f - self.warmup) / (1.0 - self.warmup)
                } else {
                    1.0
                };
                let lo = self.lr * 0.01;
                lo + (self.lr - lo) * 0.5 * (1.0 + (std::f64::consts::PI * x).cos())
            }
        }
    }

    /// The encoder shape.
    pub fn encoder(&self) -> EncoderConfig {
        EncoderConfig {
            fourier_features: self.fourier_features,
            camera_dim: self.camera_dim,
            width: self.width,
            blocks: self.blocks,
        }
    }

    pub(crate) fn check(&self) -> Result<()> {
        if self.epochs == 0 || self.triplets_per_step == 0 {
            return Err(Error::invalid(
                "train",
                "epochs and triplets per step must be positive",
            ));
        }
        if !(self.lr.is_finite() && self.lr > 0.0) {
            return Err(Error::invalid(
                "train.lr",
                format!("must be > 0, got {}", self.lr),
            ));
        }
        if !(self.pair_fraction > 0.0 && self.pair_fraction <= 1.0) {
            return Err(Error::invalid(
                "train.pair_fraction",
                "must be within (0, 1]",
            ));
        }
        if !(0.0..=1.0).contains(&self.lr_drop_at) {
            return Err(Error::invalid("train.lr_drop_at", "must be within [0, 1]"));
        }
        if !(0.0..1.0).contains(&self.warmup) {
            return Err(Error::invalid("train.warmup", "must be within [0, 1)"));
        }
        if !(0.0..=1.0).contains(&self.soft_assignment) {
            return Err(Error::invalid(
                "train.soft_assignment",
                "must be within [0, 1]",
            ));
        }
        if !(self.soft_temperature.is_finite() && self.soft_temperature >= 0.0) {
            return Err(Error::invalid(
                "train.soft_temperature",
                "must be a finite number ≥ 0",
            ));
        }
        if !(0.0..1.0).contains(&self.ema_decay) {
            return Err(Error::invalid("train.ema_decay", "must be within [0, 1)"));
        }
        Ok(())
    }
}

fn one() -> f32 {
    1.0
}

fn soft_temperature() -> f32 {
    0.1
}

fn self_train_lr() -> f64 {
    3e-4
}

//! The training loop: batches of triplets, Adam with the step schedule (lr × 0.1 at 3/4),
//! progress bar, periodic validation with threshold selection and best-model keeping,
//! checkpoints and resume. Deterministic in the seed on one machine.
use std::path::PathBuf;
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::model::{EncoderConfig, EncoderWeights};
use crate::train::adam::Adam;
use crate::train::checkpoint;
use crate::train::data::TrainingSet;
use crate::train::losses::{LossOptions, StepStats, step_loss};
use crate::train::model::{TrainModel, ce};
use crate::train::sampler::{MIN_FRAMES, TripletSampler};
use crate::{Error, Result};

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
    /// Adam learning rate.
    pub lr: f64,
    /// Fraction of training after which the learning rate is multiplied by 0.1.
    pub lr_drop_at: f64,
    /// Edge pairs per matching (0 = all unique unordered edges).
    pub max_edges: usize,
    /// Appearance weight (used only when boxes carry appearance vectors).
    pub alpha: f32,
    /// **[ours]** Fraction of the most confident Hungarian pairs used by the losses
    /// (1.0 = SPEC §4).
    #[serde(default = "one")]
    pub pair_fraction: f32,
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
            max_edges: 0,
            alpha: 0.1,
            pair_fraction: 1.0,
            seed: 0,
            val_every: 0,
            max_train_seconds: None,
        }
    }
}

impl TrainConfig {
    /// The encoder shape.
    pub fn encoder(&self) -> EncoderConfig {
        EncoderConfig {
            fourier_features: self.fourier_features,
            camera_dim: self.camera_dim,
            width: self.width,
            blocks: self.blocks,
        }
    }

    fn check(&self) -> Result<()> {
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
        Ok(())
    }
}

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
    pub fn better_than(&self, other: &ValScores) -> bool {
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
    /// Seconds of training so far (excluding validation).
    pub train_seconds: f64,
    /// Validation at the end of this epoch, when run.
    pub val: Option<ValScores>,
}

/// Where and how often to checkpoint.
#[derive(Debug, Clone, Default)]
pub struct CheckpointOptions {
    /// Checkpoint directory (none = no checkpoints).
    pub dir: Option<PathBuf>,
    /// Save every this many epochs (0 = only at the end).
    pub every: usize,
    /// Continue from the checkpoint in `dir` when one exists.
    pub resume: bool,
}

/// The result of a run.
#[derive(Debug, Clone)]
pub struct TrainOutcome {
    /// The weights to export: the best validated ones when validation ran, else the last.
    pub weights: EncoderWeights,
    /// Scores of `weights` (when validated).
    pub best: Option<ValScores>,
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
    /// Completed epochs.
    pub epoch: usize,
    /// History so far.
    pub history: Vec<EpochRecord>,
    /// Best validated weights, scores and epoch.
    pub best: Option<(EncoderWeights, ValScores, usize)>,
    /// Seconds of training so far.
    pub train_seconds: f64,
}

/// Trains on `set` with `cfg`; validates with `validator` every `cfg.val_every` epochs and at
/// the end. `progress` shows a progress bar on stderr.
pub fn train(
    set: &TrainingSet,
    cfg: &TrainConfig,
    mut validator: Option<&mut dyn Validator>,
    ckpt: &CheckpointOptions,
    progress: bool,
) -> Result<TrainOutcome> {
    cfg.check()?;
    if set.num_frames() < MIN_FRAMES {
        return Err(Error::Training(format!(
            "{} frames; training needs at least {MIN_FRAMES}",
            set.num_frames()
        )));
    }
    let sampler = TripletSampler::new(set.num_frames(), set.num_cameras())?;
    let mut st = match (&ckpt.dir, ckpt.resume) {
        (Some(dir), true) if checkpoint::exists(dir) => {
            let st = checkpoint::load(dir, cfg, set.num_cameras())?;
            tracing::info!(epoch = st.epoch, dir = %dir.display(), "resuming from checkpoint");
            st
        }
        _ => {
            let model = TrainModel::new(cfg.encoder(), set.num_cameras(), cfg.seed)?;
            let adam = Adam::new(model.named_vars(), cfg.lr)?;
            RunState {
                model,
                adam,
                epoch: 0,
                history: Vec::new(),
                best: None,
                train_seconds: 0.0,
            }
        }
    };
    let tps = cfg.triplets_per_step;
    let steps_per_epoch = set.num_frames().div_ceil(tps);
    let total_steps = (steps_per_epoch * cfg.epochs) as u64;
    let drop_epoch = (cfg.epochs as f64 * cfg.lr_drop_at).round() as usize;
    let opts = LossOptions {
        max_edges: cfg.max_edges,
        alpha: cfg.alpha,
        pair_fraction: cfg.pair_fraction,
    };
    let bar = if progress {
        let b = ProgressBar::new(total_steps);
        b.set_style(
            ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        b.set_position(st.epoch as u64 * steps_per_epoch as u64);
        b
    } else {
        ProgressBar::hidden()
    };
    while st.epoch < cfg.epochs {
        let epoch = st.epoch + 1;
        let dropped = match cfg.max_train_seconds {
            Some(budget) => st.train_seconds >= budget * cfg.lr_drop_at,
            None => st.epoch >= drop_epoch,
        };
        st.adam.lr = if dropped { cfg.lr * 0.1 } else { cfg.lr };
        let out_of_time = |secs: f64| cfg.max_train_seconds.is_some_and(|b| secs >= b);
        let started = Instant::now();
        let mut rng = ChaCha8Rng::seed_from_u64(mix(cfg.seed, epoch as u64));
        let order = sampler.epoch_order(&mut rng);
        let mut sums = StepStats::default();
        let mut n = 0usize;
        for chunk in order.chunks(tps) {
            let triplets: Vec<_> = chunk.iter().map(|&p| sampler.sample(p, &mut rng)).collect();
            if let Some((loss, s)) = step_loss(&st.model, set, &triplets, &opts, &mut rng)? {
                if !s.total.is_finite() {
                    return Err(Error::Training(format!(
                        "loss became {} at epoch {epoch}; lower the learning rate",
                        s.total
                    )));
                }
                let grads = loss.backward().map_err(ce)?;
                st.adam.step(&grads)?;
                sums.total += s.total;
                sums.syn += s.syn;
                sums.pro += s.pro;
                sums.edge += s.edge;
                n += 1;
            }
            bar.inc(1);
        }
        st.train_seconds += started.elapsed().as_secs_f64();
        let k = n.max(1) as f32;
        let mut rec = EpochRecord {
            epoch,
            total: sums.total / k,
            syn: sums.syn / k,
            pro: sums.pro / k,
            edge: sums.edge / k,
            train_seconds: st.train_seconds,
            val: None,
        };
        bar.set_message(format!(
            "epoch {epoch} loss {:.3} (syn {:.3} pro {:.3} edge {:.3})",
            rec.total, rec.syn, rec.pro, rec.edge
        ));
        let last = epoch == cfg.epochs || out_of_time(st.train_seconds);
        let due = last || (cfg.val_every > 0 && epoch % cfg.val_every == 0);
        if let (true, Some(v)) = (due, validator.as_deref_mut()) {
            let scores = v.validate(&st.model)?;
            bar.println(format!(
                "epoch {epoch}: val ACC {:.2} IPAA-100 {:.2} (threshold {:.1}) after {:.0}s",
                100.0 * scores.acc,
                100.0 * scores.ipaa100,
                scores.threshold,
                st.train_seconds
            ));
            tracing::info!(
                epoch,
                acc = scores.acc,
                ipaa100 = scores.ipaa100,
                threshold = scores.threshold,
                train_seconds = st.train_seconds,
                "validation"
            );
            rec.val = Some(scores);
            if st
                .best
                .as_ref()
                .is_none_or(|(_, b, _)| scores.better_than(b))
            {
                st.best = Some((st.model.to_weights()?, scores, epoch));
            }
        }
        tracing::info!(
            epoch,
            loss = rec.total,
            syn = rec.syn,
            pro = rec.pro,
            edge = rec.edge,
            steps = n,
            train_seconds = st.train_seconds,
            "epoch done"
        );
        st.history.push(rec);
        st.epoch = epoch;
        if let Some(dir) = &ckpt.dir
            && (last || (ckpt.every > 0 && epoch % ckpt.every == 0))
        {
            checkpoint::save(dir, cfg, &st)?;
        }
        if last {
            break;
        }
    }
    bar.finish_and_clear();
    let steps = st.adam.t;
    let (weights, best, best_epoch) = match st.best {
        Some((w, s, e)) => (w, Some(s), e),
        None => (st.model.to_weights()?, None, st.epoch),
    };
    Ok(TrainOutcome {
        weights,
        best,
        best_epoch,
        history: st.history,
        steps,
        train_seconds: st.train_seconds,
    })
}

fn one() -> f32 {
    1.0
}

/// A per-epoch seed from the run seed (splitmix64 finaliser), so resumed runs draw the same
/// triplets as uninterrupted ones.
fn mix(seed: u64, epoch: u64) -> u64 {
    let mut z = seed ^ epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

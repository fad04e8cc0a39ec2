//! One run that can be advanced an epoch at a time, scored, checkpointed and cloned: what the
//! single-run loop ([`crate::trainer`]) and the population ([`crate::population`]) both drive.
//! A member owns its whole state (weights, optimiser, moving average, pseudo-labels, history,
//! best weights); its randomness is drawn per epoch from its seed, so a member advanced in
//! pieces, resumed from a checkpoint or cloned draws the same triplets as one run straight
//! through.
use std::path::Path;
use std::time::Instant;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::adam::Adam;
use crate::checkpoint;
use crate::config::TrainConfig;
use crate::data::TrainingSet;
use crate::losses::{LossOptions, StepStats, step_loss};
use crate::model::{TrainModel, ce};
use crate::pseudo::{PseudoLabels, pseudo_labels};
use crate::sampler::{MIN_FRAMES, TripletSampler};
use crate::state::{Best, EpochRecord, RunState, Select, TrainOutcome};
use crate::transport::temperature;
use crossview_core::{Error, Result};
use crossview_model::EncoderWeights;

/// A run in progress on one training set.
pub struct Member<'s> {
    set: &'s TrainingSet,
    cfg: TrainConfig,
    sampler: TripletSampler,
    st: RunState,
    /// The self-training stage's boxes and labels when its labels drop boxes.
    restricted: Option<(TrainingSet, PseudoLabels)>,
}

impl<'s> Member<'s> {
    /// A fresh member: initialised from `cfg.seed`, or from `init` (an exported encoder of the
    /// same shape and cameras).
    pub fn new(
        set: &'s TrainingSet,
        cfg: &TrainConfig,
        init: Option<&EncoderWeights>,
    ) -> Result<Self> {
        check_set(set, cfg)?;
        let model = match init {
            Some(w) if w.config != cfg.encoder() || w.num_cameras != set.num_cameras() => {
                return Err(Error::Training(format!(
                    "initial model is {:?} for {} cameras, the run wants {:?} for {}",
                    w.config,
                    w.num_cameras,
                    cfg.encoder(),
                    set.num_cameras()
                )));
            }
            Some(w) => TrainModel::from_weights(w, cfg.seed)?,
            None => TrainModel::new(cfg.encoder(), set.num_cameras(), cfg.seed)?,
        };
        let adam = Adam::new(model.named_vars(), cfg.lr)?;
        let ema = (cfg.ema_decay > 0.0)
            .then(|| TrainModel::from_weights(&model.to_weights()?, cfg.seed))
            .transpose()?;
        let st = RunState {
            model,
            adam,
            ema,
            epoch: 0,
            history: Vec::new(),
            best: None,
            pseudo: None,
            stage_steps: 0,
            train_seconds: 0.0,
        };
        Self::with_state(set, cfg, st)
    }

    /// The member saved in checkpoint directory `dir` (see [`checkpoint`]).
    pub fn resume(set: &'s TrainingSet, cfg: &TrainConfig, dir: &Path) -> Result<Self> {
        check_set(set, cfg)?;
        let st = checkpoint::load(dir, cfg, set.num_cameras())?;
        tracing::info!(epoch = st.epoch, dir = %dir.display(), "resuming from checkpoint");
        Self::with_state(set, cfg, st)
    }

    fn with_state(set: &'s TrainingSet, cfg: &TrainConfig, st: RunState) -> Result<Self> {
        let restricted = st.pseudo.as_ref().and_then(|p| p.restrict(set));
        Ok(Member {
            set,
            cfg: cfg.clone(),
            sampler: TripletSampler::new(set.num_frames(), set.num_cameras())?,
            st,
            restricted,
        })
    }

    /// A copy of this member with its own state (weights, optimiser, moving average,
    /// pseudo-labels, history, best weights) that trains on with `seed`.
    pub fn clone_with_seed(&self, seed: u64) -> Result<Self> {
        let mut cfg = self.cfg.clone();
        cfg.seed = seed;
        Self::with_state(self.set, &cfg, self.st.try_clone()?)
    }

    /// The member's configuration (its seed included).
    pub fn config(&self) -> &TrainConfig {
        &self.cfg
    }

    /// Completed epochs.
    pub fn epoch(&self) -> usize {
        self.st.epoch
    }

    /// Epochs of both stages.
    pub fn total_epochs(&self) -> usize {
        self.cfg.epochs + self.cfg.self_train_epochs
    }

    /// Optimiser steps per epoch.
    pub fn steps_per_epoch(&self) -> usize {
        self.set.num_frames().div_ceil(self.cfg.triplets_per_step)
    }

    /// True when the run is over: every epoch done, or the time budget spent.
    pub fn finished(&self) -> bool {
        self.st.epoch >= self.total_epochs()
            || self
                .cfg
                .max_train_seconds
                .is_some_and(|b| self.st.train_seconds >= b)
    }

    /// Seconds of training so far (scoring that chooses the model included).
    pub fn train_seconds(&self) -> f64 {
        self.st.train_seconds
    }

    /// The history so far.
    pub fn history(&self) -> &[EpochRecord] {
        &self.st.history
    }

    /// The best scored weights so far.
    pub fn best(&self) -> Option<&Best> {
        self.st.best.as_ref()
    }

    /// The weights that are scored and exported: the moving average when there is one.
    pub fn scored_model(&self) -> &TrainModel {
        self.st.ema.as_ref().unwrap_or(&self.st.model)
    }

    /// A progress bar over every optimiser step of this member's run, drawn with
    /// `template` and already at the member's current epoch.
    pub fn steps_bar(&self, template: &str) -> indicatif::ProgressBar {
        let per_epoch = self.steps_per_epoch() as u64;
        let b = indicatif::ProgressBar::new(per_epoch * self.total_epochs() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(template)
                .expect("valid template")
                .progress_chars("=> "),
        );
        b.set_position(self.epoch() as u64 * per_epoch);
        b
    }

    /// Adds scoring time (it chooses the exported model, so it counts as training time).
    pub fn add_seconds(&mut self, secs: f64) {
        self.st.train_seconds += secs;
    }

    /// Keeps the scored weights as the best ones, with the scores of `rec`.
    pub fn keep_best(&mut self, rec: &EpochRecord) -> Result<()> {
        self.st.best = Some(Best {
            weights: self.scored_model().to_weights()?,
            epoch: rec.epoch,
            val: rec.val,
            label_free: rec.label_free,
        });
        Ok(())
    }

    /// Appends the (scored) record of the epoch just trained to the history.
    pub fn record(&mut self, rec: EpochRecord) {
        self.st.history.push(rec);
    }

    /// Saves the member to checkpoint directory `dir`.
    pub fn save(&self, dir: &Path) -> Result<()> {
        checkpoint::save(dir, &self.cfg, &self.st)
    }

    /// Trains one epoch (starting or refreshing the self-training stage first when due) and
    /// returns its unscored record; `on_step` runs after every optimiser step. The returned
    /// string, when any, says that the self-training stage started.
    pub fn train_epoch(&mut self, on_step: &dyn Fn()) -> Result<(EpochRecord, Option<String>)> {
        let epoch = self.st.epoch + 1;
        let note = self.enter_stage(epoch)?;
        self.st.adam.lr = self.lr_for(epoch);
        let started = Instant::now();
        let (sums, n) = self.run_steps(epoch, on_step)?;
        self.st.train_seconds += started.elapsed().as_secs_f64();
        self.st.epoch = epoch;
        let k = n.max(1) as f32;
        let rec = EpochRecord {
            epoch,
            total: sums.total / k,
            syn: sums.syn / k,
            pro: sums.pro / k,
            edge: sums.edge / k,
            id: sums.id / k,
            train_seconds: self.st.train_seconds,
            val: None,
            label_free: None,
        };
        tracing::debug!(
            epoch,
            seed = self.cfg.seed,
            loss = rec.total,
            steps = n,
            lr = self.st.adam.lr,
            "epoch done"
        );
        Ok((rec, note))
    }

    /// Starts the self-training stage at the first epoch after the first stage, and refreshes
    /// its pseudo-labels when due.
    fn enter_stage(&mut self, epoch: usize) -> Result<Option<String>> {
        let cfg = &self.cfg;
        let note = if epoch > cfg.epochs && self.st.pseudo.is_none() {
            self.start_self_training()?;
            Some(format!(
                "self-training: {} of {} training boxes pseudo-labelled",
                self.st.pseudo.as_ref().map_or(0, PseudoLabels::labelled),
                self.set.num_boxes()
            ))
        } else if cfg.pseudo_refresh_every > 0
            && epoch > cfg.epochs + 1
            && (epoch - cfg.epochs - 1).is_multiple_of(cfg.pseudo_refresh_every)
        {
            self.refresh_pseudo_labels()?;
            None
        } else {
            return Ok(None);
        };
        self.restricted = self.st.pseudo.as_ref().and_then(|p| p.restrict(self.set));
        Ok(note)
    }

    /// The learning rate of `epoch`: the schedule at the run's progress (of the time budget
    /// when there is one), scaled down in the self-training stage.
    fn lr_for(&self, epoch: usize) -> f64 {
        let cfg = &self.cfg;
        let progress = match cfg.max_train_seconds {
            Some(budget) => self.st.train_seconds / budget,
            None if epoch > cfg.epochs => {
                (self.st.epoch - cfg.epochs) as f64 / cfg.self_train_epochs as f64
            }
            None => self.st.epoch as f64 / cfg.epochs as f64,
        };
        if epoch > cfg.epochs {
            cfg.lr_at(progress) * cfg.self_train_lr / cfg.lr
        } else {
            cfg.lr_at(progress)
        }
    }

    /// The optimiser steps of one epoch; the summed step statistics and their count.
    fn run_steps(&mut self, epoch: usize, on_step: &dyn Fn()) -> Result<(StepStats, usize)> {
        let cfg = &self.cfg;
        let opts = LossOptions {
            max_edges: cfg.max_edges,
            alpha: cfg.alpha,
            pair_fraction: cfg.pair_fraction,
            // `None` past the soft fraction of the first stage, so in self-training too.
            temperature: temperature(epoch, cfg.epochs, cfg.soft_assignment, cfg.soft_temperature),
        };
        let (set, labels) = match &self.restricted {
            Some((s, l)) => (s, Some(l)),
            None => (self.set, self.st.pseudo.as_ref()),
        };
        let mut rng = ChaCha8Rng::seed_from_u64(mix(cfg.seed, epoch as u64));
        let order = self.sampler.epoch_order(&mut rng);
        let mut sums = StepStats::default();
        let mut n = 0usize;
        for chunk in order.chunks(cfg.triplets_per_step) {
            let triplets: Vec<_> = chunk
                .iter()
                .map(|&p| self.sampler.sample(p, &mut rng))
                .collect();
            let step = step_loss(&self.st.model, set, &triplets, &opts, labels, &mut rng)?;
            if let Some((loss, s)) = step {
                if !s.total.is_finite() {
                    return Err(Error::Training(format!(
                        "loss became {} at epoch {epoch}; lower the learning rate",
                        s.total
                    )));
                }
                let grads = loss.backward().map_err(ce)?;
                self.st.adam.step(&grads)?;
                if let Some(ema) = &self.st.ema {
                    update_ema(ema, &self.st.model, cfg.ema_decay, self.st.adam.t)?;
                }
                sums.total += s.total;
                sums.syn += s.syn;
                sums.pro += s.pro;
                sums.edge += s.edge;
                sums.id += s.id;
                n += 1;
            }
            on_step();
        }
        Ok((sums, n))
    }

    /// Starts the self-training stage: pseudo-labels from the best first-stage weights (the
    /// last ones when nothing was scored), calibrated on the training frames (none when the
    /// frames are too few to calibrate); training restarts from those weights (keeping the
    /// current decoder) with a fresh optimiser and moving average.
    fn start_self_training(&mut self) -> Result<()> {
        let (cfg, st) = (&self.cfg, &mut self.st);
        let mut source = match &st.best {
            Some(b) => b.weights.clone(),
            None => st.ema.as_ref().unwrap_or(&st.model).to_weights()?,
        };
        // A recording too small to calibrate trains its second stage without pseudo-labels.
        let labels = calibrated_labels(&mut source, self.set, cfg)?.unwrap_or_default();
        let model = TrainModel::from_weights(&source, cfg.seed)?;
        for ((name, v), (_, cur)) in model.named_vars().into_iter().zip(st.model.named_vars()) {
            if name.starts_with("decoder") {
                v.set(cur.as_tensor()).map_err(ce)?;
            }
        }
        st.stage_steps += st.adam.t;
        st.adam = Adam::new(model.named_vars(), cfg.lr)?;
        st.ema = (cfg.ema_decay > 0.0)
            .then(|| TrainModel::from_weights(&source, cfg.seed))
            .transpose()?;
        st.model = model;
        st.pseudo = Some(labels);
        Ok(())
    }

    /// Recomputes the self-training stage's pseudo-labels from the current (averaged) weights,
    /// keeping the optimiser: as the encoder improves, more boxes join confident multi-view
    /// identities. Keeps the old labels when calibration fails.
    fn refresh_pseudo_labels(&mut self) -> Result<()> {
        let mut source = self.scored_model().to_weights()?;
        if let Some(labels) = calibrated_labels(&mut source, self.set, &self.cfg)? {
            self.st.pseudo = Some(labels);
        }
        Ok(())
    }

    /// The run's outcome: the best scored weights (the last ones when nothing was scored).
    pub fn finish(self, select: Select) -> Result<TrainOutcome> {
        let st = self.st;
        let steps = st.stage_steps + st.adam.t;
        let selected_by =
            st.best.as_ref().map(
                |b| match (select, b.label_free.is_some(), b.val.is_some()) {
                    (Select::LabelFree, true, _) | (Select::Labelled, _, false) => {
                        Select::LabelFree
                    }
                    _ => Select::Labelled,
                },
            );
        let best = match st.best {
            Some(b) => b,
            None => Best {
                weights: st.ema.as_ref().unwrap_or(&st.model).to_weights()?,
                epoch: st.epoch,
                val: None,
                label_free: None,
            },
        };
        Ok(TrainOutcome {
            weights: best.weights,
            best: best.val,
            label_free: best.label_free,
            selected_by,
            best_epoch: best.epoch,
            history: st.history,
            steps,
            train_seconds: st.train_seconds,
        })
    }
}

/// The configuration and the training set can make a run.
fn check_set(set: &TrainingSet, cfg: &TrainConfig) -> Result<()> {
    cfg.check()?;
    if set.num_frames() < MIN_FRAMES {
        return Err(Error::Training(format!(
            "{} frames; training needs at least {MIN_FRAMES}",
            set.num_frames()
        )));
    }
    Ok(())
}

/// Pseudo-identity labels from `source`'s confident multi-view identities under its own
/// label-free calibration; `None` (with a warning) when the recording is too small to
/// calibrate.
fn calibrated_labels(
    source: &mut EncoderWeights,
    set: &TrainingSet,
    cfg: &TrainConfig,
) -> Result<Option<PseudoLabels>> {
    let cal = match crate::calibrate::calibrate(source, set, cfg.seed) {
        Ok(cal) => cal,
        Err(e) => {
            tracing::warn!(error = %e, "no pseudo-labels: calibration failed");
            return Ok(None);
        }
    };
    let labels = pseudo_labels(source, set, &cal, &cfg.pseudo)?;
    tracing::info!(
        labelled = labels.labelled(),
        kept = labels.kept(),
        boxes = set.num_boxes(),
        "self-training: pseudo-identity labels"
    );
    Ok(Some(labels))
}

/// `ema ← β·ema + (1 − β)·model` over the encoder's variables, with the usual warm-up of the
/// decay (`β_t = min(β, (1 + t) / (10 + t))`) so early averages are not dominated by the
/// initialisation.
fn update_ema(ema: &TrainModel, model: &TrainModel, decay: f64, step: u64) -> Result<()> {
    let t = step as f64;
    let beta = decay.min((1.0 + t) / (10.0 + t));
    for ((name, e), (_, v)) in ema.named_vars().into_iter().zip(model.named_vars()) {
        if name.starts_with("decoder") {
            continue;
        }
        let next = ((e.as_tensor() * beta).map_err(ce)?
            + (v.as_tensor() * (1.0 - beta)).map_err(ce)?)
        .map_err(ce)?;
        e.set(&next.detach()).map_err(ce)?;
    }
    Ok(())
}

/// A per-epoch seed from the run seed (splitmix64 finaliser), so resumed runs draw the same
/// triplets as uninterrupted ones.
pub(crate) fn mix(seed: u64, epoch: u64) -> u64 {
    let mut z = seed ^ epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

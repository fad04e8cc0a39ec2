//! The training loop: batches of triplets, Adam with a learning-rate schedule (the paper's
//! step, or warm-up and cosine decay), an optional exponential moving average of the weights,
//! progress bar, periodic scoring (label-free on held-out frames and/or labelled validation)
//! with best-model keeping, checkpoints and resume. Deterministic in the seed on one machine.
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

use crate::adam::Adam;
use crate::checkpoint;
pub use crate::config::{LrSchedule, TrainConfig};
use crate::data::TrainingSet;
use crate::label_free::LabelFreeScores;
use crate::losses::{LossOptions, StepStats, step_loss};
use crate::model::{TrainModel, ce};
use crate::pseudo::{PseudoLabels, pseudo_labels};
use crate::sampler::{MIN_FRAMES, TripletSampler};
pub use crate::state::{
    Best, CheckpointOptions, EpochRecord, RunState, Scoring, Select, TrainOutcome, ValScores,
    Validator,
};
use crate::validate::CandleEncoder;
use crossview_core::{Error, Result};
use crossview_model::EncoderWeights;

/// Trains on `set` with `cfg`; scores with `scoring` every `cfg.val_every` epochs and at the
/// end, keeping the best weights by `scoring.select`. `progress` shows a progress bar on
/// stderr.
pub fn train(
    set: &TrainingSet,
    cfg: &TrainConfig,
    scoring: Scoring<'_>,
    ckpt: &CheckpointOptions,
    progress: bool,
) -> Result<TrainOutcome> {
    train_from(set, cfg, None, scoring, ckpt, progress)
}

/// [`train`] starting from `init` (an exported encoder of the same shape and cameras, e.g. to
/// fine-tune a model on a new recording) instead of a fresh initialisation.
pub fn train_from(
    set: &TrainingSet,
    cfg: &TrainConfig,
    init: Option<&EncoderWeights>,
    mut scoring: Scoring<'_>,
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
            RunState {
                model,
                adam,
                ema,
                epoch: 0,
                history: Vec::new(),
                best: None,
                pseudo: None,
                stage_steps: 0,
                train_seconds: 0.0,
            }
        }
    };
    let tps = cfg.triplets_per_step;
    let steps_per_epoch = set.num_frames().div_ceil(tps);
    let epochs = cfg.epochs + cfg.self_train_epochs;
    let total_steps = (steps_per_epoch * epochs) as u64;
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
    let mut last_score = String::new();
    // The self-training stage's boxes and labels when its labels drop boxes.
    let restrict = |st: &RunState| st.pseudo.as_ref().and_then(|p| p.restrict(set));
    let mut restricted = restrict(&st);
    while st.epoch < epochs {
        let epoch = st.epoch + 1;
        let relabelled = if epoch > cfg.epochs && st.pseudo.is_none() {
            start_self_training(&mut st, set, cfg)?;
            bar.println(format!(
                "self-training: {} of {} training boxes pseudo-labelled",
                st.pseudo.as_ref().map_or(0, PseudoLabels::labelled),
                set.num_boxes()
            ));
            true
        } else if cfg.pseudo_refresh_every > 0
            && epoch > cfg.epochs + 1
            && (epoch - cfg.epochs - 1).is_multiple_of(cfg.pseudo_refresh_every)
        {
            refresh_pseudo_labels(&mut st, set, cfg)?;
            true
        } else {
            false
        };
        if relabelled {
            restricted = restrict(&st);
        }
        let (stage_set, stage_labels) = match &restricted {
            Some((s, l)) => (s, Some(l)),
            None => (set, st.pseudo.as_ref()),
        };
        let progress_now = match cfg.max_train_seconds {
            Some(budget) => st.train_seconds / budget,
            None if epoch > cfg.epochs => {
                (st.epoch - cfg.epochs) as f64 / cfg.self_train_epochs as f64
            }
            None => st.epoch as f64 / cfg.epochs as f64,
        };
        st.adam.lr = if epoch > cfg.epochs {
            cfg.lr_at(progress_now) * cfg.self_train_lr / cfg.lr
        } else {
            cfg.lr_at(progress_now)
        };
        let out_of_time = |secs: f64| cfg.max_train_seconds.is_some_and(|b| secs >= b);
        let started = Instant::now();
        let mut rng = ChaCha8Rng::seed_from_u64(mix(cfg.seed, epoch as u64));
        let order = sampler.epoch_order(&mut rng);
        let mut sums = StepStats::default();
        let mut n = 0usize;
        for chunk in order.chunks(tps) {
            let triplets: Vec<_> = chunk.iter().map(|&p| sampler.sample(p, &mut rng)).collect();
            if let Some((loss, s)) = step_loss(
                &st.model,
                stage_set,
                &triplets,
                &opts,
                stage_labels,
                &mut rng,
            )? {
                if !s.total.is_finite() {
                    return Err(Error::Training(format!(
                        "loss became {} at epoch {epoch}; lower the learning rate",
                        s.total
                    )));
                }
                let grads = loss.backward().map_err(ce)?;
                st.adam.step(&grads)?;
                if let Some(ema) = &st.ema {
                    update_ema(ema, &st.model, cfg.ema_decay, st.adam.t)?;
                }
                sums.total += s.total;
                sums.syn += s.syn;
                sums.pro += s.pro;
                sums.edge += s.edge;
                sums.id += s.id;
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
            id: sums.id / k,
            train_seconds: st.train_seconds,
            val: None,
            label_free: None,
        };
        let last = epoch == epochs || out_of_time(st.train_seconds);
        let due = last || (cfg.val_every > 0 && epoch % cfg.val_every == 0);
        let scored_model = st.ema.as_ref().unwrap_or(&st.model);
        if due && let Some(scorer) = scoring.label_free {
            // Part of the run's cost (it chooses the exported model): counted as training time.
            let scoring_started = Instant::now();
            let (lf, _) = scorer.score(&mut CandleEncoder::new(scored_model))?;
            st.train_seconds += scoring_started.elapsed().as_secs_f64();
            rec.train_seconds = st.train_seconds;
            tracing::info!(
                epoch,
                expected_acc = lf.expected_acc,
                sync_acc = lf.sync_acc,
                cycle = lf.cycle,
                consistent = lf.consistent,
                threshold = lf.threshold,
                "label-free score"
            );
            rec.label_free = Some(lf);
        }
        if due && let Some(v) = scoring.validator.as_deref_mut() {
            let scores = v.validate(scored_model)?;
            tracing::info!(
                epoch,
                acc = scores.acc,
                ipaa100 = scores.ipaa100,
                threshold = scores.threshold,
                train_seconds = st.train_seconds,
                "validation"
            );
            rec.val = Some(scores);
        }
        if due {
            last_score = score_message(&rec);
            if !last_score.is_empty() {
                bar.println(format!(
                    "epoch {epoch}: {last_score} after {:.0}s",
                    st.train_seconds
                ));
            }
            if improves(&rec, st.best.as_ref(), scoring.select) {
                st.best = Some(Best {
                    weights: scored_model.to_weights()?,
                    epoch,
                    val: rec.val,
                    label_free: rec.label_free,
                });
            }
        }
        bar.set_message(format!(
            "epoch {epoch} loss {:.3} (syn {:.3} pro {:.3} edge {:.3}) {last_score}",
            rec.total, rec.syn, rec.pro, rec.edge
        ));
        tracing::info!(
            epoch,
            loss = rec.total,
            syn = rec.syn,
            pro = rec.pro,
            edge = rec.edge,
            id = rec.id,
            steps = n,
            lr = st.adam.lr,
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
    let steps = st.stage_steps + st.adam.t;
    let selected_by =
        st.best.as_ref().map(
            |b| match (scoring.select, b.label_free.is_some(), b.val.is_some()) {
                (Select::LabelFree, true, _) | (Select::Labelled, _, false) => Select::LabelFree,
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

/// Starts the self-training stage: pseudo-labels from the best first-stage weights (the last
/// ones when nothing was scored), calibrated on the training frames (none when the frames are
/// too few to calibrate); training restarts from
/// those weights (keeping the current decoder) with a fresh optimiser and moving average.
fn start_self_training(st: &mut RunState, set: &TrainingSet, cfg: &TrainConfig) -> Result<()> {
    let mut source = match &st.best {
        Some(b) => b.weights.clone(),
        None => st.ema.as_ref().unwrap_or(&st.model).to_weights()?,
    };
    // A recording too small to calibrate trains its second stage without pseudo-labels.
    let labels = calibrated_labels(&mut source, set, cfg)?.unwrap_or_default();
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

/// Recomputes the self-training stage's pseudo-labels from the current weights (their moving
/// average when there is one), keeping the optimiser: as the encoder improves, more boxes
/// join confident multi-view identities. Keeps the old labels when calibration fails.
fn refresh_pseudo_labels(st: &mut RunState, set: &TrainingSet, cfg: &TrainConfig) -> Result<()> {
    let mut source = st.ema.as_ref().unwrap_or(&st.model).to_weights()?;
    if let Some(labels) = calibrated_labels(&mut source, set, cfg)? {
        st.pseudo = Some(labels);
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

/// True when the scores in `rec` beat `best` under `select` (label-free: its key; labelled:
/// ACC then IPAA-100). When the selecting score is missing, the other one decides.
fn improves(rec: &EpochRecord, best: Option<&Best>, select: Select) -> bool {
    let Some(best) = best else {
        return rec.val.is_some() || rec.label_free.is_some();
    };
    let by_lf = |a: &LabelFreeScores, b: &LabelFreeScores| a.key() > b.key();
    let by_val = |a: &ValScores, b: &ValScores| a.better_than(b);
    match select {
        Select::LabelFree => match (&rec.label_free, &best.label_free) {
            (Some(a), Some(b)) => by_lf(a, b),
            _ => matches!((&rec.val, &best.val), (Some(a), Some(b)) if by_val(a, b)),
        },
        Select::Labelled => match (&rec.val, &best.val) {
            (Some(a), Some(b)) => by_val(a, b),
            _ => matches!((&rec.label_free, &best.label_free), (Some(a), Some(b)) if by_lf(a, b)),
        },
    }
}

/// The scores of a scored epoch for the progress bar, e.g.
/// `"label-free cycle 41.09 sync 87.32 val ACC 88.29 IPAA-100 42.59 (t 0.5)"`.
fn score_message(rec: &EpochRecord) -> String {
    let mut m = String::new();
    if let Some(lf) = &rec.label_free {
        m.push_str(&format!(
            "label-free cycle {:.2} sync {:.2}",
            100.0 * lf.cycle,
            100.0 * lf.sync_acc
        ));
    }
    if let Some(v) = &rec.val {
        if !m.is_empty() {
            m.push(' ');
        }
        m.push_str(&format!(
            "val ACC {:.2} IPAA-100 {:.2} (t {:.1})",
            100.0 * v.acc,
            100.0 * v.ipaa100,
            v.threshold
        ));
    }
    m
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
fn mix(seed: u64, epoch: u64) -> u64 {
    let mut z = seed ^ epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

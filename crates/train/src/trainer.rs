//! The training loop: batches of triplets, Adam with a learning-rate schedule (the paper's
//! step, or warm-up and cosine decay), an optional exponential moving average of the weights,
//! progress bar, periodic scoring (label-free on held-out frames and/or labelled validation)
//! with best-model keeping, checkpoints and resume. Deterministic in the seed on one machine.
use std::time::Instant;

use crate::checkpoint;
pub use crate::config::{LrSchedule, TrainConfig};
use crate::data::TrainingSet;
use crate::label_free::{LabelFreeScorer, LabelFreeScores};
use crate::member::Member;
pub use crate::state::{
    Best, CheckpointOptions, EpochRecord, RunState, Scoring, Select, TrainOutcome, ValScores,
    Validator,
};
use crate::validate::CandleEncoder;
use crossview_core::Result;
use crossview_model::EncoderWeights;
use indicatif::ProgressBar;

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
    let mut member = match &ckpt.dir {
        Some(dir) if ckpt.resume && checkpoint::exists(dir) => Member::resume(set, cfg, dir)?,
        _ => Member::new(set, cfg, init)?,
    };
    let bar = progress_bar(&member, progress);
    let mut last_score = String::new();
    while !member.finished() {
        let (mut rec, note) = member.train_epoch(&|| bar.inc(1))?;
        if let Some(note) = note {
            bar.println(note);
        }
        let last = member.finished() || ckpt.interrupted();
        let due = last || (cfg.val_every > 0 && rec.epoch % cfg.val_every == 0);
        if due {
            score_epoch(&mut member, &mut rec, &mut scoring)?;
            last_score = score_message(&rec);
            if !last_score.is_empty() {
                bar.println(format!(
                    "epoch {}: {last_score} after {:.0}s",
                    rec.epoch, rec.train_seconds
                ));
            }
        }
        bar.set_message(format!(
            "epoch {} loss {:.3} (syn {:.3} pro {:.3} edge {:.3}) {last_score}",
            rec.epoch, rec.total, rec.syn, rec.pro, rec.edge
        ));
        tracing::info!(
            epoch = rec.epoch,
            loss = rec.total,
            syn = rec.syn,
            pro = rec.pro,
            edge = rec.edge,
            id = rec.id,
            train_seconds = rec.train_seconds,
            "epoch done"
        );
        let epoch = rec.epoch;
        member.record(rec);
        if let Some(dir) = &ckpt.dir
            && (last || (ckpt.every > 0 && epoch % ckpt.every == 0))
        {
            member.save(dir)?;
        }
        if last {
            break;
        }
    }
    bar.finish_and_clear();
    if ckpt.interrupted() && member.epoch() < member.total_epochs() {
        tracing::warn!(
            epoch = member.epoch(),
            "interrupted: the best weights so far are the outcome; resume from the checkpoint"
        );
    }
    member.finish(scoring.select)
}

/// The run's progress bar over every optimiser step (hidden when `show` is false).
fn progress_bar(member: &Member<'_>, show: bool) -> ProgressBar {
    if !show {
        return ProgressBar::hidden();
    }
    member.steps_bar("{elapsed_precise} [{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}")
}

/// Scores the member's current (averaged) weights into `rec` — label-free and/or labelled —
/// and keeps them when they beat the best so far under `scoring.select`.
pub(crate) fn score_epoch(
    member: &mut Member<'_>,
    rec: &mut EpochRecord,
    scoring: &mut Scoring<'_>,
) -> Result<()> {
    if let Some(scorer) = scoring.label_free {
        rec.label_free = Some(score_label_free(member, rec, scorer)?);
    }
    if let Some(v) = scoring.validator.as_deref_mut() {
        let scores = v.validate(member.scored_model())?;
        tracing::info!(
            epoch = rec.epoch,
            seed = member.config().seed,
            acc = scores.acc,
            ipaa100 = scores.ipaa100,
            threshold = scores.threshold,
            train_seconds = rec.train_seconds,
            "validation"
        );
        rec.val = Some(scores);
    }
    if improves(rec, member.best(), scoring.select) {
        member.keep_best(rec)?;
    }
    Ok(())
}

/// The label-free scores of the member's current weights; the scoring time counts as
/// training time (it chooses the exported model) and is added to `rec`.
pub(crate) fn score_label_free(
    member: &mut Member<'_>,
    rec: &mut EpochRecord,
    scorer: &LabelFreeScorer,
) -> Result<LabelFreeScores> {
    let started = Instant::now();
    let (lf, _) = scorer.score(&mut CandleEncoder::new(member.scored_model()))?;
    member.add_seconds(started.elapsed().as_secs_f64());
    rec.train_seconds = member.train_seconds();
    tracing::info!(
        epoch = rec.epoch,
        seed = member.config().seed,
        expected_acc = lf.expected_acc,
        sync_acc = lf.sync_acc,
        cycle = lf.cycle,
        consistent = lf.consistent,
        threshold = lf.threshold,
        "label-free score"
    );
    Ok(lf)
}

/// True when the scores in `rec` beat `best` under `select` (label-free: its key; labelled:
/// ACC then IPAA-100). When the selecting score is missing, the other one decides.
pub(crate) fn improves(rec: &EpochRecord, best: Option<&Best>, select: Select) -> bool {
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

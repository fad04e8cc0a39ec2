//! **[ours]** Population training: several members (same data and recipe, different seeds)
//! train side by side, one thread per core, and successive halving by the label-free key drops
//! the worse half at set points of the first stage. A single run's outcome depends on its seed
//! by several ACC points; the label-free key ranks runs the way their accuracy does
//! (BENCHMARKS.md, "Training"), so keeping the best members needs no labels.
//!
//! Members advance in lockstep, one scoring interval (`val_every` epochs) per round: each
//! thread trains its members through the round and scores them label-free; the labelled
//! validator (research runs only) and the halving run between rounds. Member 0 has the run's
//! seed, so a population of one is the single run; the same seed and population give the same
//! model.
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

use indicatif::{MultiProgress, ProgressBar};
use serde::{Deserialize, Serialize};

use crate::config::TrainConfig;
use crate::data::TrainingSet;
use crate::label_free::{LabelFreeScorer, LabelFreeScores};
use crate::member::{Member, mix};
use crate::state::{CheckpointOptions, EpochRecord, Scoring, Select, TrainOutcome, ValScores};
use crate::trainer::{improves, score_label_free};
use crossview_core::{Error, Result};
use crossview_model::{EncoderWeights, Ensemble};

/// Fewest members of the default population (more where the machine has more cores).
pub const DEFAULT_MEMBERS: usize = 6;

/// Members exported together by default: the encoder is this many times wider, and the
/// per-frame encoder cost grows with it (BENCHMARKS.md, "Training").
pub const DEFAULT_ENSEMBLE: usize = 6;

/// How a population is run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PopulationOptions {
    /// Members at the start (1 = a single run).
    pub size: usize,
    /// Threads (members train in parallel on this many cores).
    pub threads: usize,
    /// Points of the first stage (fractions of its epochs) where the worse half is dropped.
    pub halve_at: Vec<f64>,
    /// Halving never leaves fewer members than this.
    pub keep_at_least: usize,
    /// Consecutive scorings averaged into the key that ranks the members (one scoring is
    /// noisy).
    pub window: usize,
    /// The best this many finalists (by the key of their kept weights) are exported together
    /// as one encoder ([`crossview_model::Ensemble`]); 1 = the winner alone.
    #[serde(default = "one")]
    pub ensemble: usize,
}

fn one() -> usize {
    1
}

impl PopulationOptions {
    /// The default for this machine: a member per core and at least [`DEFAULT_MEMBERS`],
    /// every member trained to the end (no halving), ranked by the mean of 3 scorings, and the
    /// best [`DEFAULT_ENSEMBLE`] exported together (on 2 to 6 cores: all of them). Chosen on
    /// the WILDTRACK training frames (BENCHMARKS.md, "Training"): halving dropped members that
    /// ended best, and every member added to the ensemble, up to all 6, raised accuracy.
    pub fn for_machine() -> Self {
        let threads = std::thread::available_parallelism().map_or(1, usize::from);
        PopulationOptions {
            size: threads.max(DEFAULT_MEMBERS),
            threads,
            halve_at: Vec::new(),
            keep_at_least: threads,
            window: 3,
            ensemble: DEFAULT_ENSEMBLE,
        }
    }

    /// A single run (no population).
    pub fn single() -> Self {
        PopulationOptions {
            size: 1,
            threads: 1,
            halve_at: Vec::new(),
            keep_at_least: 1,
            window: 1,
            ensemble: 1,
        }
    }
}

/// One member's fate, for the progress display, the summary and the model card.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MemberReport {
    /// The member's seed.
    pub seed: u64,
    /// The ranking key (mean of the last `window` scorings) when it was dropped or when the
    /// run ended.
    pub key: Option<f64>,
    /// The epoch at which halving dropped it (`None`: it trained to the end).
    pub dropped_at: Option<usize>,
    /// The key of its best kept weights (what chooses the winner among the finalists).
    pub best_key: Option<f64>,
}

/// A finished population: the winner's outcome and every member's fate.
#[derive(Debug, Clone)]
pub struct PopulationOutcome {
    /// The winning member's outcome (its best weights, history and scores).
    pub outcome: TrainOutcome,
    /// Index of the winner in `members`.
    pub winner: usize,
    /// Every member, in seed order.
    pub members: Vec<MemberReport>,
    /// The finalists' best weights and keys, best first (the winner's first).
    pub finalists: Vec<(usize, EncoderWeights, f64)>,
}

impl PopulationOutcome {
    /// One line on why the winner won, e.g. `"member 2 (seed 123) of 4: key 41.20; dropped
    /// 0, 1 at epoch 275"`.
    pub fn summary(&self) -> String {
        let w = &self.members[self.winner];
        let mut s = format!(
            "member {} (seed {}) of {}: best key {}",
            self.winner,
            w.seed,
            self.members.len(),
            w.best_key
                .map_or("-".into(), |k| format!("{:.2}", 100.0 * k))
        );
        for (i, m) in self.members.iter().enumerate() {
            if let Some(e) = m.dropped_at {
                s.push_str(&format!(
                    "; member {i} dropped at epoch {e} (key {})",
                    m.key.map_or("-".into(), |k| format!("{:.2}", 100.0 * k))
                ));
            }
        }
        s
    }
}

/// The seed of member `i` of a population run with `seed` (member 0: `seed` itself).
pub fn member_seed(seed: u64, i: usize) -> u64 {
    if i == 0 {
        seed
    } else {
        mix(seed, (1u64 << 32) | i as u64)
    }
}

/// Trains a population of `opts.size` members on `set` (see the module docs). With `init`
/// (an exported encoder or ensemble), member `i` starts from its member `i mod M`.
pub fn train_population(
    set: &TrainingSet,
    cfg: &TrainConfig,
    init: Option<&Ensemble>,
    scoring: Scoring<'_>,
    ckpt: &CheckpointOptions,
    progress: bool,
    opts: &PopulationOptions,
) -> Result<PopulationOutcome> {
    let members = (0..opts.size.max(1))
        .map(|i| {
            let mut c = cfg.clone();
            c.seed = member_seed(cfg.seed, i);
            let dir = ckpt.dir.as_ref().map(|d| member_dir(d, i));
            match dir {
                Some(d) if ckpt.resume && crate::checkpoint::exists(&d) => {
                    Member::resume(set, &c, &d)
                }
                _ => {
                    let start = init.map(|e| &e.members()[i % e.members().len()]);
                    Member::new(set, &c, start)
                }
            }
        })
        .collect::<Result<Vec<_>>>()?;
    run_population(members, scoring, ckpt, progress, opts)
}

/// The checkpoint directory of member `i` under `dir`.
pub fn member_dir(dir: &Path, i: usize) -> std::path::PathBuf {
    dir.join(format!("member-{i}"))
}

/// A member and what the population knows of it.
struct Slot<'s> {
    member: Member<'s>,
    report: MemberReport,
    bar: ProgressBar,
}

/// Runs the given members as a population (see the module docs); a test can plant a member.
pub fn run_population(
    members: Vec<Member<'_>>,
    mut scoring: Scoring<'_>,
    ckpt: &CheckpointOptions,
    progress: bool,
    opts: &PopulationOptions,
) -> Result<PopulationOutcome> {
    if members.is_empty() {
        return Err(Error::Training(
            "a population needs at least one member".into(),
        ));
    }
    if members.len() > 1 && scoring.label_free.is_none() && scoring.validator.is_none() {
        return Err(Error::Training(
            "a population needs a score to choose its members: hold out frames (--holdout)".into(),
        ));
    }
    let multi = if progress {
        MultiProgress::new()
    } else {
        MultiProgress::with_draw_target(indicatif::ProgressDrawTarget::hidden())
    };
    let mut slots: Vec<Slot<'_>> = members
        .into_iter()
        .enumerate()
        .map(|(i, member)| {
            let bar = multi.add(member_bar(&member, i));
            let report = MemberReport {
                seed: member.config().seed,
                key: None,
                dropped_at: None,
                best_key: None,
            };
            Slot {
                member,
                report,
                bar,
            }
        })
        .collect();
    let cfg = slots[0].member.config().clone();
    let halvings = halving_epochs(&cfg, &opts.halve_at);
    loop {
        let alive: Vec<usize> = (0..slots.len())
            .filter(|&i| slots[i].report.dropped_at.is_none() && !slots[i].member.finished())
            .collect();
        let Some(&first) = alive.first() else { break };
        let from = slots[first].member.epoch();
        let to = round_end(&cfg, from, &halvings);
        let stop = ckpt.interrupt.as_deref();
        let recs = train_round(
            &mut slots,
            &alive,
            to,
            scoring.label_free,
            opts.threads,
            stop,
        )?;
        for (i, mut rec) in alive.iter().copied().zip(recs) {
            end_round(&mut slots[i], &mut rec, &mut scoring)?;
            let epoch = rec.epoch;
            slots[i].member.record(rec);
            slots[i].report.key = mean_key(slots[i].member.history(), scoring.select, opts);
            let due = slots[i].member.finished()
                || ckpt.interrupted()
                || (ckpt.every > 0 && epoch % ckpt.every == 0);
            if let Some(dir) = &ckpt.dir
                && due
            {
                slots[i].member.save(&member_dir(dir, i))?;
            }
        }
        if halvings.contains(&to) {
            halve(&mut slots, &alive, to, opts);
        }
        for s in &slots {
            s.bar.set_message(member_message(&s.report));
        }
        if ckpt.interrupted() {
            tracing::warn!("interrupted: the best finalist so far is the outcome");
            break;
        }
    }
    for s in &slots {
        s.bar.finish();
    }
    let outcome = finish(slots, scoring.select)?;
    if let Some(dir) = &ckpt.dir {
        save_reports(dir, &outcome.members)?;
    }
    Ok(outcome)
}

/// The first-stage epochs where halving happens: each point rounded to a scoring epoch.
fn halving_epochs(cfg: &TrainConfig, halve_at: &[f64]) -> Vec<usize> {
    let step = cfg.val_every.max(1);
    let mut v: Vec<usize> = halve_at
        .iter()
        .filter(|f| f.is_finite() && **f > 0.0 && **f < 1.0)
        .map(|f| (((f * cfg.epochs as f64) / step as f64).round() as usize).max(1) * step)
        .filter(|&e| e < cfg.epochs)
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// Where a round that starts after epoch `from` ends: the next scoring epoch, halving point
/// or the end of the run, whichever comes first.
fn round_end(cfg: &TrainConfig, from: usize, halvings: &[usize]) -> usize {
    let total = cfg.epochs + cfg.self_train_epochs;
    let next_score = from
        .checked_div(cfg.val_every)
        .map_or(total, |k| (k + 1) * cfg.val_every);
    let next_halving = halvings
        .iter()
        .copied()
        .find(|&e| e > from)
        .unwrap_or(total);
    next_score.min(next_halving).min(total)
}

/// Trains every member in `alive` up to epoch `to` (or its end) on `threads` threads; each
/// member's round ends with a label-free scoring when there is a scorer. Returns each
/// member's last (unrecorded) epoch record, in `alive`'s order.
fn train_round(
    slots: &mut [Slot<'_>],
    alive: &[usize],
    to: usize,
    scorer: Option<&LabelFreeScorer>,
    threads: usize,
    stop: Option<&AtomicBool>,
) -> Result<Vec<EpochRecord>> {
    let mut chosen: Vec<&mut Slot<'_>> = slots
        .iter_mut()
        .enumerate()
        .filter(|(i, _)| alive.contains(i))
        .map(|(_, s)| s)
        .collect();
    let threads = threads.clamp(1, chosen.len());
    let per_thread = chosen.len().div_ceil(threads);
    let results: Vec<Result<Vec<EpochRecord>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = chosen
            .chunks_mut(per_thread)
            .map(|group| {
                scope.spawn(move || {
                    group
                        .iter_mut()
                        .map(|s| advance(s, to, scorer, stop))
                        .collect::<Result<Vec<_>>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(Error::internal("a population thread panicked")))
            })
            .collect()
    });
    let mut recs = Vec::with_capacity(alive.len());
    for r in results {
        recs.extend(r?);
    }
    Ok(recs)
}

/// One member's part of a round: epochs up to `to` (all but the last recorded), then the
/// label-free scoring of the last. An interrupt ends the round after the epoch in progress.
fn advance(
    slot: &mut Slot<'_>,
    to: usize,
    scorer: Option<&LabelFreeScorer>,
    stop: Option<&AtomicBool>,
) -> Result<EpochRecord> {
    let stopped = || stop.is_some_and(|f| f.load(Ordering::Relaxed));
    let bar = slot.bar.clone();
    loop {
        let (mut rec, note) = slot.member.train_epoch(&|| bar.inc(1))?;
        if let Some(note) = note {
            tracing::info!(seed = slot.report.seed, "{note}");
        }
        if rec.epoch >= to || slot.member.finished() || stopped() {
            if let Some(scorer) = scorer {
                rec.label_free = Some(score_label_free(&mut slot.member, &mut rec, scorer)?);
            }
            return Ok(rec);
        }
        slot.member.record(rec);
    }
}

/// Between rounds: the labelled validation (when given) and keeping the best weights.
fn end_round(slot: &mut Slot<'_>, rec: &mut EpochRecord, scoring: &mut Scoring<'_>) -> Result<()> {
    if let Some(v) = scoring.validator.as_deref_mut() {
        rec.val = Some(v.validate(slot.member.scored_model())?);
    }
    if improves(rec, slot.member.best(), scoring.select) {
        slot.member.keep_best(rec)?;
    }
    Ok(())
}

/// The key of one scored record under `select` (label-free: cycle consistency; labelled:
/// ACC), falling back to the other score.
fn record_key(rec: &EpochRecord, select: Select) -> Option<f64> {
    scores_key(rec.label_free, rec.val, select)
}

/// [`record_key`] of a pair of scores.
fn scores_key(lf: Option<LabelFreeScores>, val: Option<ValScores>, select: Select) -> Option<f64> {
    let lf = lf.map(|l| l.key());
    let val = val.map(|v| v.acc);
    match select {
        Select::LabelFree => lf.or(val),
        Select::Labelled => val.or(lf),
    }
}

/// The mean key over the last `opts.window` scored epochs of `history`.
fn mean_key(history: &[EpochRecord], select: Select, opts: &PopulationOptions) -> Option<f64> {
    let keys: Vec<f64> = history
        .iter()
        .rev()
        .filter_map(|r| record_key(r, select))
        .take(opts.window.max(1))
        .collect();
    (!keys.is_empty()).then(|| keys.iter().sum::<f64>() / keys.len() as f64)
}

/// Drops the worse half of `alive` by their mean key (never below `opts.keep_at_least`);
/// members without a key rank last, ties keep the lower index.
fn halve(slots: &mut [Slot<'_>], alive: &[usize], epoch: usize, opts: &PopulationOptions) {
    let keep = alive.len().div_ceil(2).max(opts.keep_at_least.max(1));
    if keep >= alive.len() {
        return;
    }
    let mut ranked = alive.to_vec();
    let key = |i: usize| slots[i].report.key.unwrap_or(f64::NEG_INFINITY);
    ranked.sort_by(|&a, &b| key(b).total_cmp(&key(a)).then(a.cmp(&b)));
    for &i in &ranked[keep..] {
        slots[i].report.dropped_at = Some(epoch);
        tracing::info!(
            member = i,
            seed = slots[i].report.seed,
            epoch,
            key = slots[i].report.key,
            "population: member dropped"
        );
    }
}

/// The winner (the finalist whose best weights have the best key) and every member's fate.
fn finish(slots: Vec<Slot<'_>>, select: Select) -> Result<PopulationOutcome> {
    let mut reports = Vec::with_capacity(slots.len());
    let mut finalists = Vec::new();
    let mut winner_outcome: Option<(usize, f64, TrainOutcome)> = None;
    for (i, s) in slots.into_iter().enumerate() {
        let mut report = s.report;
        report.best_key = s
            .member
            .best()
            .and_then(|b| scores_key(b.label_free, b.val, select));
        if report.dropped_at.is_none() {
            let key = report.best_key.unwrap_or(f64::NEG_INFINITY);
            let outcome = s.member.finish(select)?;
            finalists.push((i, outcome.weights.clone(), key));
            if winner_outcome.as_ref().is_none_or(|(_, k, _)| key > *k) {
                winner_outcome = Some((i, key, outcome));
            }
        }
        reports.push(report);
    }
    let (winner, _, outcome) =
        winner_outcome.ok_or_else(|| Error::internal("a population ended with no member"))?;
    finalists.sort_by(|a, b| b.2.total_cmp(&a.2).then(a.0.cmp(&b.0)));
    Ok(PopulationOutcome {
        outcome,
        winner,
        members: reports,
        finalists,
    })
}

/// Writes every member's fate beside the members' checkpoints (`population.json`).
fn save_reports(dir: &Path, members: &[MemberReport]) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let path = dir.join("population.json");
    let json = serde_json::to_vec_pretty(members)
        .map_err(|e| Error::Training(format!("population report: {e}")))?;
    std::fs::write(&path, json).map_err(|e| Error::io(&path, e))
}

/// A member's progress bar.
fn member_bar(member: &Member<'_>, i: usize) -> ProgressBar {
    let b = member.steps_bar("{prefix} {elapsed_precise} [{bar:24}] {percent:>3}% eta {eta} {msg}");
    b.set_prefix(format!("member {i} (seed {})", member.config().seed));
    b
}

/// The message beside a member's bar: its key, or when and why it was dropped.
fn member_message(r: &MemberReport) -> String {
    let key = r.key.map_or("-".into(), |k| format!("{:.2}", 100.0 * k));
    match r.dropped_at {
        Some(e) => format!("dropped at epoch {e} (key {key})"),
        None => format!("key {key}"),
    }
}

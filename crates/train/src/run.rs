//! One whole training run, as `crossview train` does it: read and clean the recording, hold
//! out frames for the label-free score, train ([`crate::trainer`]), fit the label-free
//! calibration, and write the ONNX model (with its metadata), the SVG curve and the history.
use std::collections::BTreeMap;
use std::path::PathBuf;

use crossview_core::{CameraSpec, Error, Result};
use crossview_data::recording::read_recording;
use crossview_model::export::{read_ensemble, write_ensemble_onnx};
use crossview_model::{Ensemble, ModelMetadata};

use crate::TrainingSet;
use crate::calibrate::calibrate;
use crate::clean::BoxFilter;
use crate::curve::write_svg;
use crate::data::frame_step;
use crate::label_free::LabelFreeScorer;
use crate::population::{PopulationOptions, PopulationOutcome, train_population};
use crate::prepare::{KEY_TRAIN_BOX_FILTER, KEY_TRAIN_FPS, Loaded, read_training_set};
use crate::sampler::MIN_FRAMES;
use crate::student::{Choice, StudentOptions, choose};
use crate::trainer::{
    CheckpointOptions, Scoring, Select, TrainConfig, TrainOutcome, Validator, train_from,
};
use crate::validate::{EvalValidator, candidate_thresholds};

/// Everything one run needs, resolved from the command line (`crossview train`).
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Training recording (SPEC §7): files and directories read as one recording
    /// ([`crossview_data::read_recordings`]); ids, if any, are ignored.
    pub data: Vec<PathBuf>,
    /// Abort on the first broken box or line instead of skipping it.
    pub strict: bool,
    /// Labelled validation recording (periodic validation; `Select::Labelled` keeps by it).
    pub val: Option<PathBuf>,
    /// Start from this model file's encoder (its shape overrides the configuration's).
    pub init: Option<PathBuf>,
    /// Output model; the history goes beside it (`.history.json`).
    pub out: PathBuf,
    /// Training curve (SVG); default: `out` with `.svg`.
    pub curve: Option<PathBuf>,
    /// Training data name stored in the model (default: the file name).
    pub data_name: Option<String>,
    /// The training configuration.
    pub config: TrainConfig,
    /// The training-box cleaning.
    pub filter: BoxFilter,
    /// **[ours]** Frames per second of the training recording: a faster one trains on one
    /// frame in [`frame_step`], so negatives stay seconds away
    /// ([`REFERENCE_FPS`](crate::data::REFERENCE_FPS)). `None`: the rate the recording's
    /// header declares, else the reference rate.
    pub fps: Option<f64>,
    /// Share of the last frames held out for the label-free score (0 = none).
    pub holdout: f64,
    /// What chooses the exported epoch.
    pub select: Select,
    /// Threshold on `S` stored when labelled validation does not choose one.
    pub threshold: f32,
    /// Appearance weight stored in the model.
    pub alpha: f32,
    /// Match threshold on the calibrated confidence stored with the calibration.
    pub match_threshold: f32,
    /// Checkpointing.
    pub checkpoint: CheckpointOptions,
    /// Show a progress bar.
    pub progress: bool,
    /// **[ours]** How many members train side by side ([`PopulationOptions::single`]: one
    /// run).
    pub population: PopulationOptions,
    /// **[ours]** Whether a population's ensemble is distilled into one student, and which
    /// of the two is written ([`crate::student`]).
    pub student: StudentOptions,
    /// **[ours]** Also write every finalist of a population as its own model file here
    /// (`member-<i>.onnx`), to compare them or combine them differently later.
    pub members_out: Option<PathBuf>,
}

/// What a run wrote, in words for the user.
#[derive(Debug, Clone)]
pub struct RunReport {
    /// The exported epoch, what chose it, the threshold and the scores.
    pub summary: String,
    /// What reading the training data clipped and skipped.
    pub data: String,
    /// Where the SVG curve went.
    pub curve: PathBuf,
}

/// Runs one training run (see the module docs) and writes its files.
pub fn run(opts: RunOptions) -> Result<RunReport> {
    let Loaded {
        rec,
        mut set,
        read_summary,
        fps,
    } = read_training_set(&opts.data, opts.strict, opts.fps, &opts.filter)?;
    // The calibration is fitted on every frame, the held-out ones included (no labels are
    // involved): on WILDTRACK's training frames that beat fitting it on the 90 % trained on
    // (BENCHMARKS.md, "Training").
    let whole = set.clone();
    let scorer = hold_out(&mut set, opts.holdout, opts.config.seed)?;
    let mut cfg = opts.config.clone();
    let init = initial_weights(&opts, &rec.scene.cameras, &mut cfg)?;
    let mut validator = validator(&opts, &rec.scene.cameras)?;
    tracing::info!(
        frames = set.num_frames(),
        cameras = set.num_cameras(),
        boxes = set.num_boxes(),
        ?cfg,
        "training"
    );
    let scoring = Scoring {
        label_free: scorer.as_ref(),
        validator: validator.as_mut().map(|v| v as &mut dyn Validator),
        select: opts.select,
    };
    let (outcome, population) = train_members(&set, &cfg, init.as_ref(), scoring, &opts)?;
    let data_name = opts.data_name.clone().unwrap_or_else(|| {
        opts.data
            .iter()
            .map(|p| {
                p.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default()
            })
            .collect::<Vec<_>>()
            .join(",")
    });
    // The run's own shape (an `--init` model's overrides the requested one).
    let opts = RunOptions {
        config: cfg.clone(),
        ..opts
    };
    let mut meta = metadata(
        &rec.scene.cameras,
        &opts,
        fps,
        &outcome,
        &data_name,
        &rec.scene.name,
    );
    if let Some(p) = &population {
        meta.extra.insert(
            "crossview.population".into(),
            serde_json::json!({
                "winner": p.winner,
                "why": "best label-free key of its kept weights among the finalists",
                "options": opts.population,
                "members": p.members,
                "ensemble": p.finalists.iter().take(opts.population.ensemble.max(1))
                    .map(|(i, _, key)| serde_json::json!({"member": i, "key": key}))
                    .collect::<Vec<_>>(),
            })
            .to_string(),
        );
    }
    if let (Some(p), Some(dir)) = (&population, &opts.members_out) {
        write_members(dir, p, &meta, &whole, &opts)?;
    }
    let ensemble = exported_ensemble(&outcome, population.as_ref(), opts.population.ensemble)?;
    let threshold = meta.threshold;
    let (ensemble, choice) = choose(ensemble, &set, scorer.as_ref(), &opts.student)?;
    tracing::info!(exported = choice.exported, why = %choice.why, "export");
    if choice.student.is_some() || ensemble.members().len() > 1 {
        meta.extra.insert(
            "crossview.export".into(),
            serde_json::to_string(&choice).expect("the choice serialises"),
        );
    }
    export(&opts.out, &ensemble, meta, &whole, &opts)?;
    let curve = write_curve_and_history(&opts, &outcome, &data_name)?;
    let mut summary = summary(&outcome, threshold);
    warn_if_unsynchronized(&outcome, fps);
    if let Some(p) = &population {
        summary.push_str(&population_summary(p, &ensemble, &choice));
    }
    Ok(RunReport {
        summary,
        data: read_summary,
        curve,
    })
}

/// The population's part of the run's summary: its members, what was exported and why.
fn population_summary(p: &PopulationOutcome, exported: &Ensemble, choice: &Choice) -> String {
    let mut s = format!("; population: {}", p.summary());
    let m = exported.members().len();
    if m > 1 {
        let chosen: Vec<String> = p.finalists[..m].iter().map(|f| f.0.to_string()).collect();
        s.push_str(&format!(
            "; exported members {} together (width {})",
            chosen.join(", "),
            exported.width()
        ));
    }
    if choice.student.is_some() {
        s.push_str(&format!(
            "; exported the {}: {}",
            choice.exported, choice.why
        ));
    }
    s
}

/// What is exported: the best `size` finalists of a population as one encoder, or the
/// outcome's weights alone.
fn exported_ensemble(
    outcome: &TrainOutcome,
    population: Option<&PopulationOutcome>,
    size: usize,
) -> Result<Ensemble> {
    match population {
        Some(p) if size > 1 && p.finalists.len() > 1 => Ensemble::new(
            p.finalists
                .iter()
                .take(size)
                .map(|(_, w, _)| w.clone())
                .collect(),
        ),
        _ => Ok(Ensemble::single(outcome.weights.clone())),
    }
}

/// Fits the label-free confidence (synchronized vs time-shifted pairs of `set`, the whole
/// recording) into `meta` and writes the model file.
fn export(
    out: &std::path::Path,
    ensemble: &Ensemble,
    mut meta: ModelMetadata,
    set: &TrainingSet,
    opts: &RunOptions,
) -> Result<()> {
    let mut encoder = ensemble.clone();
    match calibrate(&mut encoder, set, opts.config.seed) {
        Ok(cal) => {
            meta.calibration = Some(std::sync::Arc::new(cal));
            meta.match_threshold = Some(opts.match_threshold);
        }
        Err(e) => tracing::warn!(error = %e, "no calibration stored: identities will use S"),
    }
    write_ensemble_onnx(out, ensemble, &meta)
}

/// Writes every finalist of `population` as `dir/member-<i>.onnx`, each with its own
/// calibration and `crossview.member` (index, seed, key) in its metadata.
fn write_members(
    dir: &std::path::Path,
    population: &PopulationOutcome,
    meta: &ModelMetadata,
    set: &TrainingSet,
    opts: &RunOptions,
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    for (i, weights, key) in &population.finalists {
        let mut m = meta.clone();
        // What chose the winner's epoch does not describe this member.
        for key in [
            "crossview.epochs",
            "crossview.selection",
            "crossview.validation",
        ] {
            m.extra.remove(key);
        }
        m.extra.insert(
            "crossview.member".into(),
            serde_json::json!({
                "member": i,
                "seed": population.members[*i].seed,
                "key": key,
            })
            .to_string(),
        );
        let single = Ensemble::single(weights.clone());
        export(&dir.join(format!("member-{i}.onnx")), &single, m, set, opts)?;
    }
    Ok(())
}

/// Trains a population (when `opts.population` asks for one and something can rank its
/// members) or a single run; the outcome to export and the population's report.
fn train_members(
    set: &TrainingSet,
    cfg: &TrainConfig,
    init: Option<&Ensemble>,
    scoring: Scoring<'_>,
    opts: &RunOptions,
) -> Result<(TrainOutcome, Option<PopulationOutcome>)> {
    let rankable = scoring.label_free.is_some() || scoring.validator.is_some();
    if opts.population.size > 1 && !rankable {
        tracing::warn!(
            population = opts.population.size,
            "nothing to rank a population by (no frames held out): training one member"
        );
    }
    let (outcome, population) = if opts.population.size > 1 && rankable {
        let p = train_population(
            set,
            cfg,
            init,
            scoring,
            &opts.checkpoint,
            opts.progress,
            &opts.population,
        )?;
        (p.outcome.clone(), Some(p))
    } else {
        let init = init.map(|e| &e.members()[0]);
        let out = train_from(set, cfg, init, scoring, &opts.checkpoint, opts.progress)?;
        (out, None)
    };
    Ok((outcome, population))
}

/// The `--init` model's encoder (or ensemble: member `i` of a population starts from its
/// member `i mod M`, a single run from its first), when given; its (first member's) shape
/// overrides `cfg`'s.
fn initial_weights(
    opts: &RunOptions,
    cameras: &[CameraSpec],
    cfg: &mut TrainConfig,
) -> Result<Option<Ensemble>> {
    let Some(p) = &opts.init else {
        return Ok(None);
    };
    let (e, m) = read_ensemble(p)?;
    let w = &e.members()[0];
    if m.cameras != cameras {
        return Err(Error::Training(format!(
            "{} was trained for other cameras than the training data",
            p.display()
        )));
    }
    cfg.fourier_features = w.config.fourier_features;
    cfg.camera_dim = w.config.camera_dim;
    cfg.width = w.config.width;
    cfg.blocks = w.config.blocks;
    Ok(Some(e))
}

/// The labelled validator over `--val`, when given.
fn validator(opts: &RunOptions, cameras: &[CameraSpec]) -> Result<Option<EvalValidator>> {
    let Some(p) = &opts.val else {
        return Ok(None);
    };
    let v = read_recording(p)?;
    if v.scene.cameras != cameras {
        return Err(Error::Training(format!(
            "validation recording {} has other cameras than the training data",
            p.display()
        )));
    }
    Ok(Some(EvalValidator::new(
        v,
        candidate_thresholds(),
        opts.alpha,
    )?))
}

/// Writes the SVG training curve and the JSON history beside the model; the curve's path.
fn write_curve_and_history(
    opts: &RunOptions,
    outcome: &TrainOutcome,
    data_name: &str,
) -> Result<PathBuf> {
    let curve = opts
        .curve
        .clone()
        .unwrap_or_else(|| opts.out.with_extension("svg"));
    write_svg(
        &curve,
        &outcome.history,
        &format!(
            "crossview train on {data_name} (width {})",
            opts.config.width
        ),
    )?;
    let history = opts.out.with_extension("history.json");
    let json = serde_json::to_vec_pretty(&outcome.history)
        .map_err(|e| Error::Training(format!("cannot encode the history: {e}")))?;
    std::fs::write(&history, json).map_err(|e| Error::io(&history, e))?;
    Ok(curve)
}

/// The model file's metadata (SPEC §8): cameras, thresholds, and how the run trained (on a
/// recording of `fps` frames per second) and chose its epoch.
fn metadata(
    cameras: &[CameraSpec],
    opts: &RunOptions,
    fps: f64,
    out: &TrainOutcome,
    data_name: &str,
    scene: &str,
) -> ModelMetadata {
    let cfg = &opts.config;
    let mut meta = ModelMetadata::new(cameras.to_vec());
    meta.alpha = opts.alpha;
    meta.threshold = chosen_threshold(out).unwrap_or(opts.threshold);
    let mut extra = BTreeMap::new();
    extra.insert("crossview.scene".into(), scene.to_string());
    extra.insert("crossview.training_data".into(), data_name.to_string());
    extra.insert("crossview.steps".into(), out.steps.to_string());
    // `epochs`: the epoch the exported weights come from (the best validated one);
    // `epochs_run` / `steps`: how long the run trained in total.
    extra.insert("crossview.epochs".into(), out.best_epoch.to_string());
    extra.insert(
        "crossview.epochs_run".into(),
        out.history.last().map_or(0, |r| r.epoch).to_string(),
    );
    extra.insert(
        "crossview.train_seconds".into(),
        format!("{:.0}", out.train_seconds),
    );
    extra.insert(
        "crossview.train_config".into(),
        serde_json::to_string(cfg).unwrap_or_default(),
    );
    extra.insert(
        KEY_TRAIN_BOX_FILTER.into(),
        serde_json::to_string(&opts.filter).unwrap_or_default(),
    );
    extra.insert(
        KEY_TRAIN_FPS.into(),
        serde_json::json!({"fps": fps, "frame_step": frame_step(fps).unwrap_or(1)}).to_string(),
    );
    extra.insert(
        "crossview.selection".into(),
        serde_json::json!({
            "by": match out.selected_by {
                Some(Select::LabelFree) => "label-free (cycle consistency on held-out training frames)",
                Some(Select::Labelled) => "labelled validation",
                None => "none (last epoch)",
            },
            "held_out_fraction": opts.holdout,
            "epoch": out.best_epoch,
            "label_free": out.label_free,
        })
        .to_string(),
    );
    if let Some(s) = out.best {
        extra.insert(
            "crossview.validation".into(),
            format!(
                "{{\"data\":{:?},\"acc\":{:.4},\"ipaa100\":{:.4},\"precision\":{:.4},\"recall\":{:.4},\"threshold\":{:.1}}}",
                opts.val
                    .as_ref()
                    .and_then(|p| p.file_name())
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                s.acc,
                s.ipaa100,
                s.precision,
                s.recall,
                s.threshold
            ),
        );
    }
    meta.extra = extra;
    meta
}

/// Splits the last `fraction` of the frames (at least [`MIN_HELD_OUT`]) off `set` for the
/// label-free score. A recording too short to spare them trains on everything, unscored,
/// with a warning.
fn hold_out(set: &mut TrainingSet, fraction: f64, seed: u64) -> Result<Option<LabelFreeScorer>> {
    if fraction <= 0.0 {
        return Ok(None);
    }
    let n = set.num_frames();
    let held_out = ((n as f64 * fraction).round() as usize).max(MIN_HELD_OUT);
    if n < held_out + MIN_FRAMES {
        tracing::warn!(
            frames = n,
            held_out,
            "recording too short to hold out frames for the label-free score: training on \
             all of them and exporting the last epoch"
        );
        return Ok(None);
    }
    let tail = set.split_off_tail(held_out);
    tracing::info!(
        held_out,
        training = set.num_frames(),
        "frames held out for the label-free score"
    );
    Ok(Some(LabelFreeScorer::new(
        tail,
        candidate_thresholds(),
        seed,
    )?))
}

/// Fewest frames held out for the label-free score (every one needs a partner 5–19 frames
/// away).
const MIN_HELD_OUT: usize = 11;

/// The threshold on `S` that labelled selection chose. Label-free selection keeps
/// `--threshold`: the calibrated decision threshold of the label-free score ran 3–4 ACC points
/// below the labelled choice on WILDTRACK, the fixed reference 0.4 within 1 point
/// (BENCHMARKS.md, "Training"); it is recorded in `crossview.selection` for reference.
fn chosen_threshold(out: &TrainOutcome) -> Option<f32> {
    match out.selected_by? {
        Select::LabelFree => None,
        Select::Labelled => out.best.map(|s| s.threshold),
    }
}

/// Synchronization accuracy of the exported weights (label-free) below which the run learnt
/// no geometry: chance is 0.5.
const NO_SIGNAL_SYNC_ACC: f64 = 0.6;

/// Warns when the exported weights tell synchronized images from time-shifted ones barely
/// better than chance: the usual cause is a recording faster than the `fps` it was declared
/// at (negatives then lie a fraction of a second away).
fn warn_if_unsynchronized(out: &TrainOutcome, fps: f64) {
    if let Some(lf) = out.label_free
        && lf.sync_acc < NO_SIGNAL_SYNC_ACC
    {
        tracing::warn!(
            sync_acc = lf.sync_acc,
            fps,
            "the model tells synchronized images from time-shifted ones barely better than \
             chance: it has learnt little geometry. If the recording runs faster than {fps} \
             frames per second, pass its rate with --fps; people must move between frames \
             that are seconds apart"
        );
    }
}

/// One line on what was exported and why: epoch, steps, time, threshold and scores.
fn summary(out: &TrainOutcome, threshold: f32) -> String {
    let by = match out.selected_by {
        Some(Select::LabelFree) => "chosen by the label-free score",
        Some(Select::Labelled) => "chosen by labelled validation",
        None => "last epoch, nothing scored",
    };
    let mut s = format!(
        "epoch {} {by}, {} steps, {:.0}s training, threshold {:.1}",
        out.best_epoch, out.steps, out.train_seconds, threshold
    );
    if let Some(lf) = out.label_free {
        s.push_str(&format!(
            "; label-free: cycle {:.2} sync {:.2} (expected decision accuracy {:.2} at {:.1})",
            100.0 * lf.cycle,
            100.0 * lf.sync_acc,
            100.0 * lf.expected_acc,
            lf.threshold
        ));
    }
    if let Some(v) = out.best {
        s.push_str(&format!(
            "; val ACC {:.2} IPAA-100 {:.2} P {:.2} R {:.2} (at its own best threshold {:.1})",
            100.0 * v.acc,
            100.0 * v.ipaa100,
            100.0 * v.precision,
            100.0 * v.recall,
            v.threshold
        ));
    }
    s
}

//! `crossview train`: self-supervised training on a recording, ONNX export with metadata,
//! training curve and optional validation on a labelled recording.
use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::io::recording::{read_recording, read_recording_with};
use crate::model::ModelMetadata;
use crate::model::export::write_onnx;
use crate::train::calibrate::calibrate;
use crate::train::clean::BoxFilter;
use crate::train::curve::write_svg;
use crate::train::trainer::{CheckpointOptions, TrainConfig, TrainOutcome, Validator, train};
use crate::train::validate::{EvalValidator, candidate_thresholds};
use crate::train::{TrainingSet, sampler::MIN_FRAMES};

/// Options of `crossview train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training recording (SPEC §7 JSONL); ids, if any, are ignored.
    #[arg(long, env = "CROSSVIEW_TRAIN_DATA")]
    pub data: PathBuf,
    /// Labelled validation recording: periodic validation, best-model keeping and
    /// threshold selection.
    #[arg(long, env = "CROSSVIEW_TRAIN_VAL")]
    pub val: Option<PathBuf>,
    /// Output ONNX model (SPEC §8).
    #[arg(long, env = "CROSSVIEW_TRAIN_OUT")]
    pub out: PathBuf,
    /// Training curve (SVG); default: the output path with `.svg`.
    #[arg(long)]
    pub curve: Option<PathBuf>,
    /// Epochs (one epoch = every training frame once as an anchor).
    #[arg(long, default_value_t = 1200)]
    pub epochs: usize,
    /// Triplets per optimiser step.
    #[arg(long, default_value_t = 1)]
    pub triplets_per_step: usize,
    /// Adam learning rate (× 0.1 after `--lr-drop-at` of the epochs).
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    /// Fraction of the epochs after which the learning rate drops ×0.1.
    #[arg(long, default_value_t = 0.75)]
    pub lr_drop_at: f64,
    /// Block width G (an input projection is added when G != 4·F + C).
    #[arg(long, default_value_t = 768)]
    pub width: usize,
    /// Fourier features per corner (F).
    #[arg(long, default_value_t = 128)]
    pub fourier_features: usize,
    /// Camera embedding width (C).
    #[arg(long, default_value_t = 256)]
    pub camera_dim: usize,
    /// Residual blocks.
    #[arg(long, default_value_t = 3)]
    pub blocks: usize,
    /// Edge pairs per matching (0 = all unique unordered pairs).
    #[arg(long, default_value_t = 0)]
    pub max_edges: usize,
    /// [ours] Fraction of each image pair's Hungarian pairs (the most confident) used by the
    /// losses; 1.0 = the paper.
    #[arg(long, default_value_t = 1.0)]
    pub pair_fraction: f32,
    /// [ours] Drop training boxes shorter than this fraction of their image height
    /// (0 = keep all; far-away people rarely appear in another camera).
    #[arg(long, default_value_t = 0.0)]
    pub min_box_height: f32,
    /// [ours] Drop training boxes that overlap a box of the same camera `--static-offset`
    /// frames away with an IoU above this (0 = keep all; static boxes carry no
    /// synchronization signal).
    #[arg(long, default_value_t = 0.0)]
    pub drop_static_iou: f32,
    /// Frame distance (positions in the recording) at which `--drop-static-iou` looks.
    #[arg(long, default_value_t = 10)]
    pub static_offset: usize,
    /// Inference threshold stored when no validation data is given.
    #[arg(long, default_value_t = 0.4)]
    pub threshold: f32,
    /// Appearance weight stored in the model and used when boxes carry appearance.
    #[arg(long, default_value_t = 0.1)]
    pub alpha: f32,
    /// [ours] Threshold on the calibrated match confidence P(same person | distance) stored
    /// as `crossview.match_threshold` (the calibration itself is fitted on the training
    /// frames after training, without labels).
    #[arg(long, default_value_t = 0.2)]
    pub match_threshold: f32,
    /// Seed for initialisation and sampling (same seed + machine = same run).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Validate every this many epochs (0 = only at the end).
    #[arg(long, default_value_t = 0)]
    pub val_every: usize,
    /// Checkpoint directory.
    #[arg(long)]
    pub checkpoint_dir: Option<PathBuf>,
    /// Checkpoint every this many epochs (0 = at the end only).
    #[arg(long, default_value_t = 0)]
    pub checkpoint_every: usize,
    /// Continue from the checkpoint in `--checkpoint-dir`.
    #[arg(long, requires = "checkpoint_dir")]
    pub resume: bool,
    /// Abort on the first broken box or line of the training data instead of skipping it
    /// with a count (boxes overlapping the image edge are clipped either way).
    #[arg(long)]
    pub strict: bool,
    /// Compute threads (default: all cores).
    #[arg(long, env = "CROSSVIEW_THREADS")]
    pub threads: Option<usize>,
    /// Stop training after this many seconds (exploration; drops the learning rate at
    /// `--lr-drop-at` of the budget; not reproducible).
    #[arg(long)]
    pub max_train_seconds: Option<f64>,
    /// Name of the training data stored in the model (default: the file name).
    #[arg(long)]
    pub data_name: Option<String>,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

impl TrainArgs {
    /// The training-box cleaning the options ask for.
    fn box_filter(&self) -> BoxFilter {
        BoxFilter {
            min_height: self.min_box_height,
            static_iou: self.drop_static_iou,
            static_offset: self.static_offset,
        }
    }
}

/// Runs `crossview train`.
pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    if let Some(t) = args.threads {
        // candle reads RAYON_NUM_THREADS when it first sizes its thread pool.
        // SAFETY: set before any worker thread exists.
        unsafe { std::env::set_var("RAYON_NUM_THREADS", t.max(1).to_string()) };
    }
    if !(0.0..=1.0).contains(&args.threshold)
        || !(0.0..=1.0).contains(&args.alpha)
        || !(0.0..=1.0).contains(&args.match_threshold)
    {
        anyhow::bail!("--threshold, --match-threshold and --alpha must be within [0, 1]");
    }
    if !(0.0..1.0).contains(&args.min_box_height) || !(0.0..=1.0).contains(&args.drop_static_iou) {
        anyhow::bail!("--min-box-height must be within [0, 1) and --drop-static-iou within [0, 1]");
    }
    let (rec, read) = read_recording_with(&args.data, args.strict)
        .with_context(|| format!("reading training data {}", args.data.display()))?;
    let read_summary = format!(
        "{} boxes clipped at the image edge, {} broken boxes and {} broken lines skipped",
        read.clipped_boxes, read.skipped_boxes, read.skipped_lines
    );
    if read.skipped_boxes + read.skipped_lines > 0 {
        tracing::warn!(
            clipped = read.clipped_boxes,
            skipped_boxes = read.skipped_boxes,
            skipped_lines = read.skipped_lines,
            first = read.first_problem.as_deref().unwrap_or(""),
            "training data had broken boxes or lines (skipped; --strict aborts instead)"
        );
    }
    let mut set = TrainingSet::from_recording(&rec.without_ids(), MIN_FRAMES)
        .with_context(|| format!("training data {}", args.data.display()))?;
    let filter = args.box_filter();
    let removed = filter.apply(&mut set);
    if !filter.is_off() {
        tracing::info!(
            before = removed.before,
            small = removed.small,
            stationary = removed.stationary,
            kept = set.num_boxes(),
            "filtered training boxes"
        );
    }
    if set.num_boxes() == 0 {
        anyhow::bail!(
            "no training boxes left after --min-box-height {} / --drop-static-iou {}",
            args.min_box_height,
            args.drop_static_iou
        );
    }
    let cfg = TrainConfig {
        fourier_features: args.fourier_features,
        camera_dim: args.camera_dim,
        width: args.width,
        blocks: args.blocks,
        epochs: args.epochs,
        triplets_per_step: args.triplets_per_step,
        lr: args.lr,
        lr_drop_at: args.lr_drop_at,
        max_edges: args.max_edges,
        alpha: args.alpha,
        pair_fraction: args.pair_fraction,
        seed: args.seed,
        val_every: args.val_every,
        max_train_seconds: args.max_train_seconds,
    };
    let mut validator = match &args.val {
        Some(p) => {
            let v = read_recording(p)
                .with_context(|| format!("reading validation data {}", p.display()))?;
            if v.scene.cameras != rec.scene.cameras {
                anyhow::bail!(
                    "validation recording {} has other cameras than the training data",
                    p.display()
                );
            }
            Some(EvalValidator::new(v, candidate_thresholds(), args.alpha)?)
        }
        None => None,
    };
    tracing::info!(
        frames = set.num_frames(),
        cameras = set.num_cameras(),
        boxes = set.num_boxes(),
        ?cfg,
        "training"
    );
    let ckpt = CheckpointOptions {
        dir: args.checkpoint_dir.clone(),
        every: args.checkpoint_every,
        resume: args.resume,
    };
    let outcome = train(
        &set,
        &cfg,
        validator.as_mut().map(|v| v as &mut dyn Validator),
        &ckpt,
        !args.quiet,
    )?;
    let data_name = args.data_name.clone().unwrap_or_else(|| {
        args.data
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    });
    let mut meta = metadata(
        &rec.scene.cameras,
        &args,
        &cfg,
        &outcome,
        &data_name,
        &rec.scene.name,
    );
    // Label-free confidence: synchronized vs time-shifted pairs of the training frames.
    let mut exported = outcome.weights.clone();
    match calibrate(&mut exported, &set, args.seed) {
        Ok(cal) => {
            meta.calibration = Some(std::sync::Arc::new(cal));
            meta.match_threshold = Some(args.match_threshold);
        }
        Err(e) => tracing::warn!(error = %e, "no calibration stored: identities will use S"),
    }
    write_onnx(&args.out, &outcome.weights, &meta)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let curve = args
        .curve
        .clone()
        .unwrap_or_else(|| args.out.with_extension("svg"));
    write_svg(
        &curve,
        &outcome.history,
        &format!("crossview train on {data_name} (width {})", cfg.width),
    )?;
    let history = args.out.with_extension("history.json");
    std::fs::write(&history, serde_json::to_vec_pretty(&outcome.history)?)
        .with_context(|| format!("writing {}", history.display()))?;
    match outcome.best {
        Some(s) => println!(
            "wrote {} (epoch {}, {} steps, {:.0}s training): val ACC {:.2} IPAA-100 {:.2} P {:.2} R {:.2} threshold {:.1}; curve {}; data: {read_summary}",
            args.out.display(),
            outcome.best_epoch,
            outcome.steps,
            outcome.train_seconds,
            100.0 * s.acc,
            100.0 * s.ipaa100,
            100.0 * s.precision,
            100.0 * s.recall,
            s.threshold,
            curve.display()
        ),
        None => println!(
            "wrote {} ({} steps, {:.0}s training, threshold {:.1}); curve {}; data: {read_summary}",
            args.out.display(),
            outcome.steps,
            outcome.train_seconds,
            args.threshold,
            curve.display()
        ),
    }
    Ok(())
}

fn metadata(
    cameras: &[crate::core::CameraSpec],
    args: &TrainArgs,
    cfg: &TrainConfig,
    out: &TrainOutcome,
    data_name: &str,
    scene: &str,
) -> ModelMetadata {
    let mut meta = ModelMetadata::new(cameras.to_vec());
    meta.alpha = args.alpha;
    meta.threshold = out.best.map_or(args.threshold, |s| s.threshold);
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
        "crossview.train_box_filter".into(),
        serde_json::to_string(&args.box_filter()).unwrap_or_default(),
    );
    if let Some(s) = out.best {
        extra.insert(
            "crossview.validation".into(),
            format!(
                "{{\"data\":{:?},\"acc\":{:.4},\"ipaa100\":{:.4},\"precision\":{:.4},\"recall\":{:.4},\"threshold\":{:.1}}}",
                args.val
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

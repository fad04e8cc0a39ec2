//! `crossview train`: the flags, their presets and checks; the run itself is
//! `crossview_train::run` (self-supervised training, ONNX export with metadata, training
//! curve, optional validation on a labelled recording).
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::{Args, ValueEnum};

use crossview_train::clean::BoxFilter;
use crossview_train::distil::DistilOptions;
use crossview_train::population::{DEFAULT_ENSEMBLE, DEFAULT_MEMBERS, PopulationOptions};
use crossview_train::pseudo::PseudoOptions;
use crossview_train::run::{RunOptions, run as run_training};
use crossview_train::student::{DEFAULT_TOLERANCE, ExportMode, StudentOptions};
use crossview_train::trainer::{CheckpointOptions, LrSchedule, Select, TrainConfig};

/// Options of `crossview train`.
#[derive(Debug, Args)]
pub struct TrainArgs {
    /// Training recording (SPEC §7 JSONL); ids, if any, are ignored. A file or a directory
    /// (every `*.jsonl` file below it, e.g. a `serve --record` directory); repeatable, all
    /// read as one recording (same scene). A torn last line of a file is dropped and counted.
    #[arg(long, env = "CROSSVIEW_TRAIN_DATA", required = true)]
    pub data: Vec<PathBuf>,
    /// Labelled validation recording: periodic validation, best-model keeping and
    /// threshold selection.
    #[arg(long, env = "CROSSVIEW_TRAIN_VAL")]
    pub val: Option<PathBuf>,
    /// Start from this model file's encoder (same cameras; its shape overrides `--width`,
    /// `--fourier-features`, `--camera-dim` and `--blocks`) instead of a fresh one.
    #[arg(long)]
    pub init: Option<PathBuf>,
    /// Output ONNX model (SPEC §8).
    #[arg(long, env = "CROSSVIEW_TRAIN_OUT")]
    pub out: PathBuf,
    /// Training curve (SVG); default: the output path with `.svg`.
    #[arg(long)]
    pub curve: Option<PathBuf>,
    /// Starting point for every training knob below; a flag given explicitly overrides it.
    /// `default`: the recipe that learns from detector boxes in minutes (width 64, lr 1e-3
    /// after a short warm-up, 8 triplets per step, 16 edges, moving average of the weights,
    /// small and static boxes dropped, then a self-training stage on pseudo-identities). `paper`: the paper's settings (width 768,
    /// lr 1e-4 dropped ×0.1 at 3/4, one triplet per step, all edges, no box filter).
    #[arg(long, value_enum, default_value_t = Preset::Default, env = "CROSSVIEW_TRAIN_PRESET")]
    pub preset: Preset,
    /// Epochs (one epoch = every training frame once as an anchor) [default: 1100; paper 1200].
    #[arg(long)]
    pub epochs: Option<usize>,
    /// Triplets per optimiser step [default: 8; paper 1].
    #[arg(long)]
    pub triplets_per_step: Option<usize>,
    /// Adam learning rate, the peak of the schedule [default: 1e-3; paper 1e-4].
    #[arg(long)]
    pub lr: Option<f64>,
    /// [ours] Learning-rate schedule [default and paper: step].
    #[arg(long, value_enum)]
    pub schedule: Option<ScheduleArg>,
    /// [ours] Fraction of training with a linear learning-rate warm-up [default: 0.02; paper 0].
    #[arg(long)]
    pub warmup: Option<f64>,
    /// Fraction of the epochs after which the learning rate drops ×0.1 (`--schedule step`;
    /// 1 = never) [default: 1; paper 0.75].
    #[arg(long)]
    pub lr_drop_at: Option<f64>,
    /// [ours] Per-step decay of the moving average of the weights that is scored and exported
    /// (0 = off) [default: 0.999; paper 0].
    #[arg(long)]
    pub ema_decay: Option<f64>,
    /// [ours] Epochs of the self-training stage, after `--epochs`: training goes on from the
    /// best first-stage weights with a pseudo-identity loss on their confident, multi-view
    /// identities (0 = none) [default: 300; paper 0].
    #[arg(long)]
    pub self_train_epochs: Option<usize>,
    /// [ours] Peak learning rate of the self-training stage.
    #[arg(long, default_value_t = 3e-4)]
    pub self_train_lr: f64,
    /// [ours] An identity becomes a pseudo-label when every pair of its members has at least
    /// this calibrated probability P(same person | distance).
    #[arg(long, default_value_t = 0.5)]
    pub pseudo_confidence: f32,
    /// [ours] Fewest cameras a pseudo-labelled identity must span.
    #[arg(long, default_value_t = 3)]
    pub pseudo_views: usize,
    /// [ours] Recompute the pseudo-labels (and the kept boxes) from the current weights every
    /// this many self-training epochs (0 = once, from the first stage; measured, not better:
    /// BENCHMARKS.md, "Training") [default: 0].
    #[arg(long)]
    pub pseudo_refresh_every: Option<usize>,
    /// [ours] Self-training trains only on boxes that its identities place in at least this
    /// many cameras: boxes no other camera sees are mostly outside the shared area or false
    /// detections (0 = every box; measured, not better: BENCHMARKS.md, "Training")
    /// [default: 0].
    #[arg(long)]
    pub self_train_keep_views: Option<usize>,
    /// Block width G (an input projection is added when G != 4·F + C) [default: 64; paper 768].
    #[arg(long)]
    pub width: Option<usize>,
    /// Fourier features per corner (F) [default: 32; paper 128].
    #[arg(long)]
    pub fourier_features: Option<usize>,
    /// Camera embedding width (C) [default: 32; paper 256].
    #[arg(long)]
    pub camera_dim: Option<usize>,
    /// Residual blocks.
    #[arg(long, default_value_t = 3)]
    pub blocks: usize,
    /// Edge pairs per matching (0 = all unique unordered pairs) [default: 16; paper 0].
    #[arg(long)]
    pub max_edges: Option<usize>,
    /// [ours] Fraction of each image pair's Hungarian pairs (the most confident) used by the
    /// losses; 1.0 = the paper.
    #[arg(long, default_value_t = 1.0)]
    pub pair_fraction: f32,
    /// [ours] Fraction of the first stage during which the synchronization loss uses a soft
    /// assignment (entropy-regularised transport, its temperature falling to 0) instead of
    /// the Hungarian pairs; 0 = the paper's Hungarian throughout [default: 0].
    #[arg(long)]
    pub soft_assignment: Option<f64>,
    /// [ours] Starting temperature of the soft assignment (max-normalised distance units).
    #[arg(long, default_value_t = 0.1)]
    pub soft_temperature: f32,
    /// [ours] Drop training boxes shorter than this fraction of their image height
    /// (0 = keep all; far-away people rarely appear in another camera) [default: 0.08;
    /// paper 0].
    #[arg(long)]
    pub min_box_height: Option<f32>,
    /// [ours] Drop training boxes that overlap a box of the same camera `--static-offset`
    /// frames away with an IoU above this (0 = keep all; static boxes carry no
    /// synchronization signal) [default: 0.8; paper 0].
    #[arg(long)]
    pub drop_static_iou: Option<f32>,
    /// Frame distance (positions in the recording) at which `--drop-static-iou` looks.
    #[arg(long, default_value_t = 10)]
    pub static_offset: usize,
    /// [ours] Frames per second of the training recording [default: the rate its header
    /// declares (`crossview simulate` and `crossview import` write it), else 2]. The method's
    /// negatives lie 5–19 frames from their anchor at 2 frames per second (WILDTRACK's rate):
    /// a faster recording trains on one frame in round(fps / 2) so that they stay seconds
    /// apart.
    #[arg(long, env = "CROSSVIEW_TRAIN_FPS")]
    pub fps: Option<f64>,
    /// [ours] Fraction of the recording's frames, at its end, held out from training to
    /// score each epoch without labels (0 = no label-free scoring).
    #[arg(long, default_value_t = 0.1)]
    pub holdout: f64,
    /// What chooses the exported epoch and inference threshold: the label-free score on the
    /// held-out frames, or the labelled `--val` recording.
    #[arg(long, value_enum, default_value_t = SelectArg::LabelFree)]
    pub select: SelectArg,
    /// Inference threshold on `S` stored unless `--select labelled` chooses one on `--val`
    /// (the identities the server returns use the calibrated `--match-threshold` instead).
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
    /// Score (label-free and, with `--val`, labelled) every this many epochs (0 = only at
    /// the end).
    #[arg(long, alias = "val-every", default_value_t = 25)]
    pub score_every: usize,
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
    /// Cores the run uses (default: all): a population trains this many members at once.
    /// Each member computes on one thread: at these matrix sizes candle's threaded kernels
    /// cost more than they gain (BENCHMARKS.md, "Training").
    #[arg(long, env = "CROSSVIEW_THREADS")]
    pub threads: Option<usize>,
    /// [ours] Train this many members (the run's seed and seeds derived from it) side by
    /// side, one per thread, rank them by the label-free key and export the best
    /// `--ensemble` of them together. Default: one member per core and at least 6 when frames
    /// are held out (`--holdout`) or `--val` is given, else 1. 1 = a single run.
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub population: Option<u16>,
    /// [ours] Where in the first stage (fractions of its epochs, comma-separated, e.g.
    /// `0.25,0.5`) a population drops its worse half, down to one member per thread; `none`
    /// (the default) trains every member to the end.
    #[arg(long, default_value = "none", value_parser = parse_fractions)]
    pub halve_at: Fractions,
    /// [ours] Export the best this many finalists of the population (by the label-free key)
    /// together as one encoder: the embedding is theirs concatenated, so distances are the
    /// RMS of theirs. 1 = the winner alone (a sixth of the default encoder's width); more than the
    /// finalists = all of them.
    #[arg(long, default_value_t = DEFAULT_ENSEMBLE as u16, value_parser = clap::value_parser!(u16).range(1..=16))]
    pub ensemble: u16,
    /// [ours] What a population of more than one exported member writes: `ensemble` (the
    /// default) that; `student` one encoder distilled from it (`crossview model distil`);
    /// `auto` distils it and writes the student when, on the held-out frames, its label-free
    /// key and expected accuracy are within `--student-tolerance` of the ensemble's. Not the
    /// default: on WILDTRACK it let through a student 0.4 ACC points below its ensemble on the
    /// training and validation frames (BENCHMARKS.md, "One student").
    #[arg(long, default_value = "ensemble", env = "CROSSVIEW_TRAIN_EXPORT")]
    pub export: ExportMode,
    /// [ours] How far (a share: 0.003 = 0.3 points) the student's label-free key and expected
    /// decision accuracy may each be below the ensemble's for `--export auto` to write it.
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub student_tolerance: f64,
    /// [ours] The student's passes over the training frames.
    #[arg(long, default_value_t = DistilOptions::default().epochs)]
    pub student_epochs: usize,
    /// [ours] The student's width (default: one and a half times the members'; their depth).
    #[arg(long)]
    pub student_width: Option<usize>,
    /// [ours] Also write every finalist of the population as its own model file in this
    /// directory (`member-<i>.onnx`).
    #[arg(long)]
    pub members_out: Option<PathBuf>,
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
    /// Skip the check, after training, that the recording's cameras are in sync (each
    /// camera's clock offset estimated with the new model, as `crossview sync-check` does).
    #[arg(long)]
    pub no_sync_check: bool,
}

/// Starting points for the training knobs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Preset {
    /// [ours] The recipe that learns from detector boxes on one core in minutes.
    Default,
    /// The paper's settings.
    Paper,
}

/// `--schedule`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum ScheduleArg {
    /// Constant, ×0.1 after `--lr-drop-at`.
    Step,
    /// Warm-up, then cosine decay to 1/100.
    Cosine,
}

/// `--select`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SelectArg {
    /// The label-free score on the held-out frames.
    LabelFree,
    /// Labelled validation (`--val`).
    Labelled,
}

impl TrainArgs {
    /// The training configuration: the preset, overridden by the flags given.
    pub fn config(&self) -> TrainConfig {
        let base = match self.preset {
            Preset::Default => TrainConfig::recommended(),
            Preset::Paper => TrainConfig::default(),
        };
        TrainConfig {
            fourier_features: self.fourier_features.unwrap_or(base.fourier_features),
            camera_dim: self.camera_dim.unwrap_or(base.camera_dim),
            width: self.width.unwrap_or(base.width),
            blocks: self.blocks,
            epochs: self.epochs.unwrap_or(base.epochs),
            triplets_per_step: self.triplets_per_step.unwrap_or(base.triplets_per_step),
            lr: self.lr.unwrap_or(base.lr),
            lr_drop_at: self.lr_drop_at.unwrap_or(base.lr_drop_at),
            schedule: match self.schedule {
                Some(ScheduleArg::Step) => LrSchedule::Step,
                Some(ScheduleArg::Cosine) => LrSchedule::Cosine,
                None => base.schedule,
            },
            warmup: self.warmup.unwrap_or(base.warmup),
            ema_decay: self.ema_decay.unwrap_or(base.ema_decay),
            self_train_epochs: self.self_train_epochs.unwrap_or(base.self_train_epochs),
            self_train_lr: self.self_train_lr,
            pseudo: PseudoOptions {
                min_confidence: self.pseudo_confidence,
                min_views: self.pseudo_views,
                match_threshold: self.match_threshold,
                keep_views: self.self_train_keep_views.unwrap_or(base.pseudo.keep_views),
            },
            pseudo_refresh_every: self
                .pseudo_refresh_every
                .unwrap_or(base.pseudo_refresh_every),
            max_edges: self.max_edges.unwrap_or(base.max_edges),
            alpha: self.alpha,
            pair_fraction: self.pair_fraction,
            soft_assignment: self.soft_assignment.unwrap_or(base.soft_assignment),
            soft_temperature: self.soft_temperature,
            seed: self.seed,
            val_every: self.score_every,
            max_train_seconds: self.max_train_seconds,
        }
    }

    /// The training-box cleaning: the preset's, overridden by the flags given.
    pub fn box_filter(&self) -> BoxFilter {
        let (h, iou) = match self.preset {
            Preset::Default => (0.08, 0.8),
            Preset::Paper => (0.0, 0.0),
        };
        BoxFilter {
            min_height: self.min_box_height.unwrap_or(h),
            static_iou: self.drop_static_iou.unwrap_or(iou),
            static_offset: self.static_offset,
        }
    }
}

/// A flag that the first Ctrl-C sets (the run ends after its epoch in progress, scored and
/// checkpointed); a second Ctrl-C exits at once.
fn interrupt_on_ctrl_c() -> anyhow::Result<Arc<AtomicBool>> {
    let flag = Arc::new(AtomicBool::new(false));
    let f = flag.clone();
    ctrlc::set_handler(move || {
        if f.swap(true, Ordering::Relaxed) {
            std::process::exit(130);
        }
        eprintln!("\nstopping after the epoch in progress (Ctrl-C again to quit at once)");
    })
    .context("cannot install the Ctrl-C handler")?;
    Ok(flag)
}

/// A list of fractions in (0, 1), as `--halve-at` takes it.
#[derive(Debug, Clone, PartialEq)]
pub struct Fractions(pub Vec<f64>);

/// Parses `none` or comma-separated fractions, each within (0, 1).
fn parse_fractions(s: &str) -> Result<Fractions, String> {
    if s.trim().eq_ignore_ascii_case("none") {
        return Ok(Fractions(Vec::new()));
    }
    s.split(',')
        .map(|p| match p.trim().parse::<f64>() {
            Ok(f) if f > 0.0 && f < 1.0 => Ok(f),
            _ => Err(format!("{p:?} is not a fraction within (0, 1)")),
        })
        .collect::<Result<Vec<_>, _>>()
        .map(Fractions)
}

/// `--population` and `--threads` as the population's options.
fn population_options(args: &TrainArgs) -> PopulationOptions {
    let machine = PopulationOptions::for_machine();
    let threads = args.threads.unwrap_or(machine.threads).max(1);
    let rankable = args.holdout > 0.0 || args.val.is_some();
    let size = match args.population {
        Some(k) => usize::from(k),
        None if rankable => threads.max(DEFAULT_MEMBERS),
        None => 1,
    };
    if size <= 1 {
        return PopulationOptions::single();
    }
    PopulationOptions {
        size,
        threads,
        keep_at_least: threads,
        halve_at: args.halve_at.0.clone(),
        ensemble: usize::from(args.ensemble),
        ..machine
    }
}

/// Runs `crossview train`.
pub fn run(args: TrainArgs) -> anyhow::Result<()> {
    super::compute::one_compute_thread_per_model();
    if !(0.0..=1.0).contains(&args.threshold)
        || !(0.0..=1.0).contains(&args.alpha)
        || !(0.0..=1.0).contains(&args.match_threshold)
    {
        anyhow::bail!("--threshold, --match-threshold and --alpha must be within [0, 1]");
    }
    let filter = args.box_filter();
    if !(0.0..1.0).contains(&filter.min_height) || !(0.0..=1.0).contains(&filter.static_iou) {
        anyhow::bail!("--min-box-height must be within [0, 1) and --drop-static-iou within [0, 1]");
    }
    if !(0.0..0.5).contains(&args.holdout) {
        anyhow::bail!("--holdout must be within [0, 0.5)");
    }
    if args.population.is_some_and(|k| k > 1) && args.holdout == 0.0 && args.val.is_none() {
        anyhow::bail!("--population needs held-out frames to rank its members (--holdout > 0)");
    }
    if args.select == SelectArg::Labelled && args.val.is_none() {
        anyhow::bail!("--select labelled needs --val");
    }
    let interrupt = interrupt_on_ctrl_c()?;
    // Without --checkpoint-dir, an interrupted run still leaves a checkpoint to resume from
    // (beside the output); a run that completes removes it.
    let default_ckpt = args
        .checkpoint_dir
        .is_none()
        .then(|| args.out.with_extension("checkpoint"));
    let report = run_training(RunOptions {
        data: args.data.clone(),
        strict: args.strict,
        val: args.val.clone(),
        init: args.init.clone(),
        out: args.out.clone(),
        curve: args.curve.clone(),
        data_name: args.data_name.clone(),
        config: args.config(),
        filter,
        fps: args.fps,
        holdout: args.holdout,
        select: match args.select {
            SelectArg::LabelFree => Select::LabelFree,
            SelectArg::Labelled => Select::Labelled,
        },
        threshold: args.threshold,
        alpha: args.alpha,
        match_threshold: args.match_threshold,
        checkpoint: CheckpointOptions {
            dir: args.checkpoint_dir.clone().or_else(|| default_ckpt.clone()),
            every: args.checkpoint_every,
            resume: args.resume,
            interrupt: Some(interrupt.clone()),
        },
        progress: !args.quiet,
        population: population_options(&args),
        members_out: args.members_out.clone(),
        student: StudentOptions {
            export: args.export,
            distil: DistilOptions {
                epochs: args.student_epochs,
                width: args.student_width,
                seed: args.seed,
                ..DistilOptions::default()
            },
            tolerance: args.student_tolerance,
        },
    })
    .with_context(|| {
        let names: Vec<_> = args.data.iter().map(|p| p.display().to_string()).collect();
        format!("training on {}", names.join(", "))
    })?;
    println!(
        "wrote {} ({}); curve {}; data: {}",
        args.out.display(),
        report.summary,
        report.curve.display(),
        report.data
    );
    let ckpt = args.checkpoint_dir.as_ref().or(default_ckpt.as_ref());
    if interrupt.load(Ordering::Relaxed) {
        if let Some(dir) = ckpt {
            eprintln!(
                "interrupted: {} holds the best model so far; continue with the same command \
                 plus --checkpoint-dir {} --resume",
                args.out.display(),
                dir.display()
            );
        }
        return Ok(());
    }
    if let Some(dir) = &default_ckpt
        && let Err(e) = std::fs::remove_dir_all(dir)
    {
        tracing::warn!(dir = %dir.display(), error = %e, "could not remove the run's checkpoint");
    }
    if !args.no_sync_check {
        warn_if_out_of_sync(&args)?;
    }
    Ok(())
}

/// Warns loudly when the training recording's cameras look out of sync (training on them
/// teaches the wrong geometry).
fn warn_if_out_of_sync(args: &TrainArgs) -> anyhow::Result<()> {
    let warnings = super::sync_check::check_after_training(&args.out, &args.data)
        .context("checking the recording's camera clocks with the new model")?;
    if warnings.is_empty() {
        return Ok(());
    }
    for w in &warnings {
        tracing::warn!(warning = %w, "training recording out of sync");
    }
    eprintln!(
        "\nWARNING: the training recording's cameras look out of sync (estimated with the new \
         model):\n{}\nTraining on cameras out of sync teaches the model the wrong geometry. \
         Check each camera's clock with `crossview sync-check --model M --data ...` using a \
         model trained on cameras in sync, declare the offsets in the recording's header \
         (\"offset\": N) and train again (docs/clock-offsets.md).\n",
        warnings
            .iter()
            .map(|w| format!("  - {w}"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cmd {
        #[command(flatten)]
        args: TrainArgs,
    }

    fn parse(extra: &[&str]) -> TrainArgs {
        let base = ["train", "--data", "rec.jsonl", "--out", "m.onnx"];
        Cmd::try_parse_from(base.iter().chain(extra)).unwrap().args
    }

    #[test]
    fn defaults_are_the_recommended_recipe_with_the_box_filter() {
        let a = parse(&[]);
        assert_eq!(a.config(), TrainConfig::recommended());
        let f = a.box_filter();
        assert_eq!((f.min_height, f.static_iou), (0.08, 0.8));
        assert_eq!(
            (a.holdout, a.select, a.score_every),
            (0.1, SelectArg::LabelFree, 25)
        );
    }

    #[test]
    fn paper_preset_is_the_papers_settings_and_flags_override_presets() {
        let a = parse(&["--preset", "paper", "--score-every", "0"]);
        assert_eq!(a.config(), TrainConfig::default());
        assert!(a.box_filter().is_off());
        let b = parse(&["--preset", "paper", "--width", "64", "--lr", "1e-3"]);
        let c = b.config();
        assert_eq!((c.width, c.lr, c.fourier_features), (64, 1e-3, 128));
        let d = parse(&[
            "--min-box-height",
            "0",
            "--schedule",
            "step",
            "--val-every",
            "5",
        ]);
        assert_eq!(d.box_filter().min_height, 0.0);
        assert_eq!(d.config().schedule, LrSchedule::Step);
        assert_eq!(d.config().val_every, 5);
    }
}

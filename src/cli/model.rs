//! `crossview model`: create a random encoder file for a scene (`init`), inspect a model
//! file (`info`), give an existing model its label-free match calibration (`calibrate`), and
//! join model files into one ensemble encoder (`combine`).
use std::path::PathBuf;

use clap::{Args, Subcommand};

use crossview_core::SceneSpec;
use crossview_data::recording::RecordingReader;
use crossview_model::metadata::KEY_SCENE;
use crossview_model::{
    EncoderConfig, EncoderWeights, Ensemble, ModelMetadata, export, write_ensemble_onnx, write_onnx,
};
use crossview_train::prepare::prepare_as_trained;

/// Model file tools.
#[derive(Debug, Args)]
pub struct ModelArgs {
    #[command(subcommand)]
    pub command: ModelCommand,
}

/// `crossview model` subcommands.
#[derive(Debug, Subcommand)]
pub enum ModelCommand {
    /// Write a randomly initialised encoder for a recording's scene.
    Init(InitArgs),
    /// Print a model file's metadata, width, inputs and outputs.
    Info(InfoArgs),
    /// Fit the model's label-free match confidence P(same person | distance) on an
    /// unlabelled recording (synchronized vs time-shifted frames) and store it in a copy of
    /// the model file.
    Calibrate(CalibrateArgs),
    /// Join model files of the same cameras into one ensemble encoder: its embedding is
    /// theirs concatenated (each scaled by 1/√M), so its distances are the RMS of theirs.
    /// Calibrated on `--data` when given (else it carries no calibration).
    Combine(CombineArgs),
    /// Whether a candidate model should replace the serving one, judged without labels on a
    /// recording neither was chosen on (what `serve --auto-retrain` checks before a swap);
    /// exit status 3 when refused.
    Gate(super::gate::GateArgs),
    /// Train one encoder (the student) to reproduce an ensemble's cross-view distances on a
    /// recording, without labels, and write it as its own model file: one member to serve
    /// instead of many.
    Distil(super::distil::DistilArgs),
}

/// Options of `crossview model combine`.
#[derive(Debug, Args)]
pub struct CombineArgs {
    /// Model files (two or more; an ensemble file adds all its members). Thresholds and
    /// alpha come from the first.
    #[arg(required = true, num_args = 2..)]
    pub models: Vec<PathBuf>,
    /// Output model file.
    #[arg(long)]
    pub out: PathBuf,
    /// Unlabelled recording of the models' cameras to fit the ensemble's label-free match
    /// calibration on (e.g. the training recording).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Threshold on the calibrated confidence stored as `crossview.match_threshold`.
    #[arg(long, default_value_t = 0.2)]
    pub match_threshold: f32,
    /// Seed of the calibration's time-shift draws.
    #[arg(long, default_value_t = 0, env = "CROSSVIEW_SEED")]
    pub seed: u64,
}

/// Options of `crossview model calibrate`.
#[derive(Debug, Args)]
pub struct CalibrateArgs {
    /// Model file (SPEC §8 ONNX, written by crossview).
    #[arg(long, env = "CROSSVIEW_MODEL")]
    pub model: PathBuf,
    /// Unlabelled recording of the model's cameras (SPEC §7 JSONL; ids are ignored), e.g.
    /// the training recording.
    #[arg(long)]
    pub data: PathBuf,
    /// Output model file (may be the input file).
    #[arg(long)]
    pub out: PathBuf,
    /// Threshold on the calibrated confidence stored as `crossview.match_threshold`.
    #[arg(long, default_value_t = 0.2)]
    pub match_threshold: f32,
    /// Seed of the time-shift draws.
    #[arg(long, default_value_t = 0, env = "CROSSVIEW_SEED")]
    pub seed: u64,
    /// Frames per second of the recording (default: the rate its header declares, else the
    /// rate the model was trained at, else 2); a faster one is thinned as training thins it
    /// (`crossview train --fps`).
    #[arg(long)]
    pub fps: Option<f64>,
}

/// Options of `crossview model init`.
#[derive(Debug, Args)]
pub struct InitArgs {
    /// Recording (SPEC §7 JSONL) whose header line defines the scene's cameras.
    #[arg(long)]
    pub scene_from: PathBuf,
    /// Output ONNX file.
    #[arg(long)]
    pub out: PathBuf,
    /// Random seed.
    #[arg(long, default_value_t = 0, env = "CROSSVIEW_SEED")]
    pub seed: u64,
    /// Embedding width G.
    #[arg(long, default_value_t = 768)]
    pub width: usize,
    /// Number of Fourier features per corner.
    #[arg(long, default_value_t = 128)]
    pub fourier: usize,
    /// Camera embedding width.
    #[arg(long, default_value_t = 256)]
    pub camera_dim: usize,
    /// Number of residual blocks.
    #[arg(long, default_value_t = 3)]
    pub blocks: usize,
    /// Inference confidence threshold stored in the file.
    #[arg(long, default_value_t = 0.4)]
    pub threshold: f32,
    /// Appearance weight stored in the file.
    #[arg(long, default_value_t = 0.1)]
    pub alpha: f32,
}

/// Options of `crossview model info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// ONNX model file.
    pub model: PathBuf,
}

/// Runs `crossview model ...`.
pub fn run(args: ModelArgs) -> anyhow::Result<()> {
    match args.command {
        ModelCommand::Init(a) => init(a),
        ModelCommand::Info(a) => info(a),
        ModelCommand::Calibrate(a) => calibrate(a),
        ModelCommand::Combine(a) => combine(a),
        ModelCommand::Gate(a) => super::gate::run(a),
        ModelCommand::Distil(a) => super::distil::run(a),
    }
}

fn check_match_threshold(t: f32) -> anyhow::Result<()> {
    if !(0.0..=1.0).contains(&t) {
        anyhow::bail!("--match-threshold must be within [0, 1], got {t}");
    }
    Ok(())
}

fn calibrate(a: CalibrateArgs) -> anyhow::Result<()> {
    check_match_threshold(a.match_threshold)?;
    let (ensemble, mut meta) = export::read_ensemble(&a.model)?;
    fit_calibration(
        &ensemble,
        &mut meta,
        &a.data,
        a.match_threshold,
        a.seed,
        a.fps,
    )?;
    meta.validate(&a.out.display().to_string())?;
    write_ensemble_onnx(&a.out, &ensemble, &meta)?;
    println!(
        "wrote {} (crossview.match_threshold {})",
        a.out.display(),
        a.match_threshold
    );
    Ok(())
}

/// Fits `ensemble`'s label-free calibration on the recording `data` into `meta` and prints it.
fn fit_calibration(
    ensemble: &Ensemble,
    meta: &mut ModelMetadata,
    data: &PathBuf,
    match_threshold: f32,
    seed: u64,
    fps: Option<f64>,
) -> anyhow::Result<()> {
    let recording = crossview_data::recording::read_recording(data)?;
    super::eval::check_scene(&recording.scene, meta)?;
    let (set, stats) = prepare_as_trained(&recording, meta, fps, None)?;
    let mut encoder = ensemble.clone();
    let cal = crossview_train::calibrate::calibrate(&mut encoder, &set, seed)?;
    println!(
        "calibrated on {} ({} of {} boxes after the training filter): {} synchronized and {} time-shifted pairs, false share {:.2}",
        data.display(),
        set.num_boxes(),
        stats.before,
        cal.samples[0],
        cal.samples[1],
        cal.false_share
    );
    let probs: Vec<String> = cal
        .distances
        .iter()
        .zip(&cal.probabilities)
        .step_by(4)
        .map(|(d, p)| format!("{d:.2}:{p:.2}"))
        .collect();
    println!("P(same | distance): {}", probs.join(" "));
    meta.calibration = Some(std::sync::Arc::new(cal));
    meta.match_threshold = Some(match_threshold);
    Ok(())
}

fn combine(a: CombineArgs) -> anyhow::Result<()> {
    check_match_threshold(a.match_threshold)?;
    let mut members = Vec::new();
    let mut sources = Vec::new();
    let mut first_meta: Option<ModelMetadata> = None;
    for path in &a.models {
        let (e, m) = export::read_ensemble(path)?;
        if let Some(first) = &first_meta
            && first.cameras != m.cameras
        {
            anyhow::bail!(
                "{} is for other cameras than {}",
                path.display(),
                a.models[0].display()
            );
        }
        sources.push(serde_json::json!({
            "file": path.file_name().map(|n| n.to_string_lossy().into_owned()),
            "members": e.members().len(),
            "width": e.width(),
            "member": m.extra.get("crossview.member")
                .and_then(|v| serde_json::from_str::<serde_json::Value>(v).ok()),
        }));
        members.extend(e.members().iter().cloned());
        first_meta.get_or_insert(m);
    }
    let ensemble = Ensemble::new(members)?;
    let mut meta = first_meta.expect("clap requires two or more models");
    meta.calibration = None;
    meta.match_threshold = None;
    for key in [
        "crossview.member",
        "crossview.selection",
        "crossview.validation",
    ] {
        meta.extra.remove(key);
    }
    meta.extra.insert(
        "crossview.ensemble".into(),
        serde_json::Value::Array(sources).to_string(),
    );
    match &a.data {
        Some(data) => fit_calibration(&ensemble, &mut meta, data, a.match_threshold, a.seed, None)?,
        None => eprintln!(
            "no --data: the ensemble carries no calibration (identities use S); \
             `crossview model calibrate` can add it"
        ),
    }
    meta.validate(&a.out.display().to_string())?;
    write_ensemble_onnx(&a.out, &ensemble, &meta)?;
    println!(
        "wrote {} ({} encoders, width {})",
        a.out.display(),
        ensemble.members().len(),
        ensemble.width()
    );
    Ok(())
}

/// Reads and validates only the header line (`{"scene": {...}}`) of a SPEC §7 recording.
fn read_scene_header(path: &PathBuf) -> anyhow::Result<SceneSpec> {
    Ok(RecordingReader::open(path)?.scene().clone())
}

fn init(a: InitArgs) -> anyhow::Result<()> {
    let scene = read_scene_header(&a.scene_from)?;
    let config = EncoderConfig {
        fourier_features: a.fourier,
        camera_dim: a.camera_dim,
        width: a.width,
        blocks: a.blocks,
    };
    let weights = EncoderWeights::random(scene.cameras.len(), config, a.seed)?;
    let mut meta = ModelMetadata::new(scene.cameras.clone());
    meta.threshold = a.threshold;
    meta.alpha = a.alpha;
    meta.extra.insert(KEY_SCENE.into(), scene.name.clone());
    meta.extra
        .insert("crossview.init_seed".into(), a.seed.to_string());
    meta.extra
        .insert("crossview.trained".into(), "false".into());
    meta.validate(&a.out.display().to_string())?;
    write_onnx(&a.out, &weights, &meta)?;
    println!(
        "wrote {} (scene '{}', {} cameras, width {}, {} blocks, seed {})",
        a.out.display(),
        scene.name,
        scene.cameras.len(),
        a.width,
        a.blocks,
        a.seed
    );
    Ok(())
}

fn info(a: InfoArgs) -> anyhow::Result<()> {
    let m = crossview_model::inspect::inspect(&a.model)?;
    let meta = &m.metadata;
    println!("model:     {}", a.model.display());
    println!("producer:  {}", m.producer);
    println!("width G:   {}", m.dim);
    println!("version:   {}", meta.version);
    println!("threshold: {}", meta.threshold);
    println!("alpha:     {}", meta.alpha);
    match &meta.calibration {
        Some(c) => println!(
            "calibrated: yes ({} knots, false share {:.2}), match threshold {}",
            c.distances.len(),
            c.false_share,
            meta.identity_threshold()
        ),
        None => println!("calibrated: no (identities use S at the threshold)"),
    }
    println!("cameras:   {}", meta.cameras.len());
    for (i, c) in meta.cameras.iter().enumerate() {
        println!("  [{i}] {} {}x{}", c.name, c.width, c.height);
    }
    for (k, v) in &meta.extra {
        println!("{k} = {v}");
    }
    for v in &m.inputs {
        println!("input:     {v}");
    }
    for v in &m.outputs {
        println!("output:    {v}");
    }
    println!("nodes:     {}, parameters: {}", m.nodes, m.parameters);
    println!("onnxruntime: loaded (dim {})", m.runtime_dim);
    Ok(())
}

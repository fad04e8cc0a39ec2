//! `crossview eval` (SPEC §5 metrics of a model on a recording with ids, or recomputed from a
//! pair dump) and `crossview associate` (global identities per frame of a recording).
use std::io::Write;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use serde::Serialize;

use crate::core::association::{AssociationConfig, Mode, associate_frame, embed_frame};
use crate::core::{CameraSpec, SceneSpec};
use crate::eval::driver::evaluate_settings;
use crate::eval::dump::{read_dump, write_dump};
use crate::eval::metrics::compute_metrics;
use crate::eval::report::{EvalReport, TableRow, format_table};
use crate::io::recording::read_recording;
use crate::model::{ModelMetadata, OnnxEncoder};

/// Arguments of `crossview eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Model file (SPEC §8 ONNX).
    #[arg(long, env = "CROSSVIEW_MODEL", required_unless_present = "from_dump")]
    pub model: Option<PathBuf>,
    /// Recording with ground-truth ids on every box (SPEC §7 JSONL).
    #[arg(long, required_unless_present = "from_dump")]
    pub data: Option<PathBuf>,
    /// Confidence threshold (default: the model's `crossview.threshold`).
    #[arg(long)]
    pub threshold: Option<f32>,
    /// Appearance weight (default: the model's `crossview.alpha`; used only with appearance).
    #[arg(long)]
    pub alpha: Option<f32>,
    /// `pairwise` (SPEC §3) or `global` (matches derived from global identities).
    #[arg(long, default_value = "pairwise")]
    pub mode: Mode,
    /// Also evaluate the other mode on the same embeddings and print both rows.
    #[arg(long)]
    pub compare_modes: bool,
    /// Extra thresholds to sweep (comma-separated), each in every evaluated mode.
    #[arg(long, value_delimiter = ',')]
    pub sweep: Vec<f32>,
    /// Write a JSON report (rates as fractions in [0, 1]).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Write one JSON line per image pair (the primary setting), enough to recompute the table.
    #[arg(long)]
    pub dump_pairs: Option<PathBuf>,
    /// Recompute the table from a pair dump alone (no model, no data).
    #[arg(long, conflicts_with_all = ["model", "data", "dump_pairs", "compare_modes", "sweep"])]
    pub from_dump: Option<PathBuf>,
}

/// Arguments of `crossview associate`.
#[derive(Debug, Args)]
pub struct AssociateArgs {
    /// Model file (SPEC §8 ONNX).
    #[arg(long, env = "CROSSVIEW_MODEL")]
    pub model: PathBuf,
    /// Recording (SPEC §7 JSONL); ids, if present, are ignored.
    #[arg(long)]
    pub data: PathBuf,
    /// Output JSONL: one line per frame with its identities.
    #[arg(long)]
    pub out: PathBuf,
    /// Confidence threshold (default: the model's).
    #[arg(long)]
    pub threshold: Option<f32>,
    /// Appearance weight (default: the model's).
    #[arg(long)]
    pub alpha: Option<f32>,
    /// Which pairwise matches to write next to the identities.
    #[arg(long, default_value = "pairwise")]
    pub mode: Mode,
}

/// Checks that the recording's cameras are the model's, in the same order (the encoder's
/// camera embedding is indexed by position). Size differences only warn: boxes are
/// normalised by the recording's sizes.
fn check_scene(scene: &SceneSpec, meta: &ModelMetadata) -> anyhow::Result<()> {
    let names = |c: &[CameraSpec]| c.iter().map(|c| c.name.clone()).collect::<Vec<_>>();
    if names(&scene.cameras) != names(&meta.cameras) {
        bail!(
            "the recording's cameras {:?} differ from the model's {:?} (same names, same order needed)",
            names(&scene.cameras),
            names(&meta.cameras)
        );
    }
    for (s, m) in scene.cameras.iter().zip(&meta.cameras) {
        if (s.width, s.height) != (m.width, m.height) {
            tracing::warn!(
                camera = %s.name,
                recording = ?(s.width, s.height),
                model = ?(m.width, m.height),
                "image size differs between recording and model"
            );
        }
    }
    Ok(())
}

fn check_threshold(t: f32) -> anyhow::Result<f32> {
    if !t.is_finite() {
        bail!("--threshold must be finite, got {t}");
    }
    Ok(t)
}

fn check_alpha(a: f32) -> anyhow::Result<f32> {
    if !(0.0..=1.0).contains(&a) {
        bail!("--alpha must be within [0, 1], got {a}");
    }
    Ok(a)
}

fn label(mode: Mode, threshold: f32) -> String {
    format!("{mode} t={threshold:.2}")
}

/// Runs `crossview eval`.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    if let Some(dump) = &args.from_dump {
        let records = read_dump(dump)?;
        let metrics = compute_metrics(&records);
        let name = dump.display().to_string();
        print!(
            "{}",
            format_table(&[TableRow {
                label: name.clone(),
                metrics
            }])
        );
        if let Some(path) = &args.report {
            let mut report = EvalReport::new("", &name, &[]);
            report.runs.push(crate::eval::report::ReportRun {
                mode: "from-dump".into(),
                threshold: None,
                alpha: None,
                metrics,
            });
            report.write(path)?;
        }
        return Ok(());
    }
    let (Some(model), Some(data)) = (&args.model, &args.data) else {
        bail!("--model and --data are required (or --from-dump)");
    };
    let mut encoder = OnnxEncoder::load(model)?;
    let meta = encoder.metadata().clone();
    let recording = read_recording(data)?;
    check_scene(&recording.scene, &meta)?;
    let threshold = check_threshold(args.threshold.unwrap_or(meta.threshold))?;
    let alpha = check_alpha(args.alpha.unwrap_or(meta.alpha))?;
    let mut modes = vec![args.mode];
    if args.compare_modes {
        modes.push(match args.mode {
            Mode::Pairwise => Mode::Global,
            Mode::Global => Mode::Pairwise,
        });
    }
    let mut settings = Vec::new();
    for t in std::iter::once(threshold).chain(args.sweep.iter().copied()) {
        let t = check_threshold(t)?;
        for &m in &modes {
            if !settings.contains(&(m, t)) {
                settings.push((m, t));
            }
        }
    }
    tracing::info!(
        frames = recording.frames.len(),
        settings = settings.len(),
        "evaluating"
    );
    let runs = evaluate_settings(&mut encoder, &recording, alpha, &settings)?;
    let rows: Vec<TableRow> = runs
        .iter()
        .map(|r| TableRow {
            label: label(r.mode, r.threshold),
            metrics: r.metrics,
        })
        .collect();
    print!("{}", format_table(&rows));
    if let Some(path) = &args.report {
        EvalReport::new(
            &model.display().to_string(),
            &data.display().to_string(),
            &runs,
        )
        .write(path)?;
    }
    if let Some(path) = &args.dump_pairs {
        write_dump(path, &runs[0].records)?;
        tracing::info!(path = %path.display(), pairs = runs[0].records.len(), "pair dump written");
    }
    Ok(())
}

/// One member of an identity in the `associate` output.
#[derive(Debug, Serialize)]
struct MemberOut<'a> {
    camera: &'a str,
    detection: usize,
    bbox: [f32; 4],
}

/// One identity in the `associate` output.
#[derive(Debug, Serialize)]
struct IdentityOut<'a> {
    id: usize,
    confidence: f32,
    members: Vec<MemberOut<'a>>,
}

/// One camera pair's matches in the `associate` output.
#[derive(Debug, Serialize)]
struct PairOut<'a> {
    camera_a: &'a str,
    camera_b: &'a str,
    matches: Vec<(usize, usize, f32)>,
}

/// One line of the `associate` output.
#[derive(Debug, Serialize)]
struct FrameOut<'a> {
    frame_id: u64,
    mode: Mode,
    identities: Vec<IdentityOut<'a>>,
    pairs: Vec<PairOut<'a>>,
}

/// Runs `crossview associate`.
pub fn run_associate(args: AssociateArgs) -> anyhow::Result<()> {
    let mut encoder = OnnxEncoder::load(&args.model)?;
    let meta = encoder.metadata().clone();
    let recording = read_recording(&args.data)?;
    let scene = &recording.scene;
    check_scene(scene, &meta)?;
    let cfg = AssociationConfig {
        threshold: check_threshold(args.threshold.unwrap_or(meta.threshold))?,
        alpha: check_alpha(args.alpha.unwrap_or(meta.alpha))?,
        mode: args.mode,
    };
    let file = std::fs::File::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut out = std::io::BufWriter::new(file);
    for frame in &recording.frames {
        let embeddings = embed_frame(&mut encoder, scene, frame)?;
        let assoc = associate_frame(frame, embeddings, &cfg);
        let cam = |c: usize| scene.cameras[c].name.as_str();
        let line = FrameOut {
            frame_id: frame.frame_id,
            mode: cfg.mode,
            identities: assoc
                .identities
                .iter()
                .map(|i| IdentityOut {
                    id: i.id,
                    confidence: i.confidence,
                    members: i
                        .members
                        .iter()
                        .map(|&(c, d)| MemberOut {
                            camera: cam(c),
                            detection: d,
                            bbox: frame.views[c].as_ref().map_or([0.0; 4], |v| v[d].bbox),
                        })
                        .collect(),
                })
                .collect(),
            pairs: assoc
                .pairs
                .iter()
                .map(|p| PairOut {
                    camera_a: cam(p.cam_a),
                    camera_b: cam(p.cam_b),
                    matches: p
                        .matching
                        .matches
                        .iter()
                        .map(|m| (m.a, m.b, m.score))
                        .collect(),
                })
                .collect(),
        };
        serde_json::to_writer(&mut out, &line)?;
        out.write_all(b"\n")?;
    }
    out.flush()
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    tracing::info!(frames = recording.frames.len(), out = %args.out.display(), "associated");
    Ok(())
}

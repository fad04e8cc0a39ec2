//! `crossview eval` (SPEC §5 metrics of a model on a recording with ids, or recomputed from a
//! pair dump) and `crossview associate` (global identities per frame of a recording).
use std::io::Write;
use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use clap::Args;
use serde::Serialize;

use crossview_core::Encoder;
use crossview_core::association::{
    AssociationConfig, FrameAssociation, Mode, associate_frame, associate_frame_with, embed_frame,
};
use crossview_core::identity::IdentityMethod;
use crossview_core::matching::Match;
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::tracking::{Tracker, TrackerConfig};
use crossview_core::{CameraSpec, Frame, FrameEmbeddings, SceneSpec};
use crossview_data::Recording;
use crossview_data::recording::read_recordings;
use crossview_eval::driver::evaluate_settings_with;
use crossview_eval::dump::{read_dump, write_dump_on};
use crossview_eval::metrics::compute_metrics;
use crossview_eval::parallel::{DEFAULT_WINDOW, map_ordered, worker_count};
use crossview_eval::report::{EvalReport, TableRow, format_table};
use crossview_eval::tracking::{TrackScores, TrackingReport, evaluate_tracking};
use crossview_model::{EncoderOptions, ModelMetadata, OnnxEncoder};

/// Arguments of `crossview eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Model file (SPEC §8 ONNX).
    #[arg(long, env = "CROSSVIEW_MODEL", required_unless_present = "from_dump")]
    pub model: Option<PathBuf>,
    /// Recording with ground-truth ids on every box (SPEC §7 JSONL): a file, or a directory
    /// (every `*.jsonl` file below it, e.g. a `serve --record` directory); repeatable, all
    /// read as one recording (same scene). A torn last line of a file is dropped and counted.
    #[arg(long, required_unless_present = "from_dump")]
    pub data: Vec<PathBuf>,
    /// SPEC §3 threshold on `S` for the pairwise row (default: the model's
    /// `crossview.threshold`).
    #[arg(long)]
    pub threshold: Option<f32>,
    /// Threshold on the calibrated `P` for the calibrated row (default: the model's
    /// `crossview.match_threshold`, else its `crossview.threshold`).
    #[arg(long)]
    pub match_threshold: Option<f32>,
    /// Appearance weight (default: the model's `crossview.alpha`; used only with appearance).
    #[arg(long)]
    pub alpha: Option<f32>,
    /// Identity method (for studies): `clustering` (what ships) or `union-find` (the plain
    /// baseline).
    #[arg(long, default_value = "clustering")]
    pub identity_method: IdentityMethod,
    /// Identity parameters (for studies; default: the method's measured ones, see
    /// `core::identity`): the link threshold and the support per agreeing third camera.
    #[arg(long, num_args = 2, value_names = ["THRESHOLD", "SUPPORT"])]
    pub identity_params: Option<Vec<f32>>,
    /// Extra thresholds to sweep (comma-separated): pairwise rows on `S`, calibrated rows on
    /// `P`, identity rows on the link threshold.
    #[arg(long, value_delimiter = ',')]
    pub sweep: Vec<f32>,
    /// Write a JSON report (rates as fractions in [0, 1]).
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Write one JSON line per image pair (the primary setting), enough to recompute the table.
    #[arg(long)]
    pub dump_pairs: Option<PathBuf>,
    /// Recompute the table from a pair dump alone (no model, no data).
    #[arg(long, conflicts_with_all = ["model", "data", "dump_pairs", "sweep"])]
    pub from_dump: Option<PathBuf>,
    /// Worker threads, each with its own encoder session of one ONNX Runtime thread; frames
    /// are dealt to them and collected in order, so the results are the same for any number
    /// (default: the machine's available parallelism).
    #[arg(long, env = "CROSSVIEW_WORKERS")]
    pub workers: Option<NonZeroUsize>,
    /// [ours] Also link the identities over time (frame order) into track ids and score them
    /// against the recording's ids, which must be consistent over time: multi-camera and
    /// per-camera IDF1, ID switches, MOTA.
    #[arg(long, conflicts_with = "from_dump")]
    pub tracking: bool,
    /// Tracker gate: an identity continues a track only within this many times the frame's
    /// median distance between identities (see `crossview_core::tracking`).
    #[arg(long, default_value_t = TrackerConfig::default().gate)]
    pub track_gate: f32,
    /// Frames a track survives unseen before it is retired.
    #[arg(long, default_value_t = TrackerConfig::default().max_age)]
    pub track_max_age: u32,
    /// How fast a track's velocity follows its motion (0 = constant position).
    #[arg(long, default_value_t = TrackerConfig::default().velocity_weight)]
    pub track_velocity: f32,
    /// Weight of the image cue (box overlap with the track's last boxes, per camera).
    #[arg(long, default_value_t = TrackerConfig::default().iou_weight)]
    pub track_iou: f32,
    /// How fast a track's box velocity in each camera follows the box's motion (0 = the
    /// last box is the prediction).
    #[arg(long, default_value_t = TrackerConfig::default().box_velocity_weight)]
    pub track_box_velocity: f32,
    /// [ours] Identities with memory: the past frames' share of each pair's evidence, carried
    /// along each camera's tracks in frame order, as `crossview serve` streams do (0: every
    /// frame alone; docs/method.md, "Identities with memory").
    #[arg(long, env = "CROSSVIEW_MEMORY", default_value_t = MemoryConfig::default().carry)]
    pub memory: f32,
}

/// Arguments of `crossview associate`.
#[derive(Debug, Args)]
pub struct AssociateArgs {
    /// Model file (SPEC §8 ONNX).
    #[arg(long, env = "CROSSVIEW_MODEL")]
    pub model: PathBuf,
    /// Recording (SPEC §7 JSONL); ids, if present, are ignored. A file or a directory;
    /// repeatable, read as one recording (like `crossview eval --data`).
    #[arg(long, required = true)]
    pub data: Vec<PathBuf>,
    /// Output JSONL: one line per frame with its identities.
    #[arg(long)]
    pub out: PathBuf,
    /// SPEC §3 threshold on `S` for the pairwise matches (default: the model's).
    #[arg(long)]
    pub threshold: Option<f32>,
    /// Threshold on the identity confidence (default: the model's).
    #[arg(long)]
    pub match_threshold: Option<f32>,
    /// Appearance weight (default: the model's).
    #[arg(long)]
    pub alpha: Option<f32>,
    /// Which pairwise matches to write next to the identities: `pairwise` (SPEC §3),
    /// `calibrated` or `identities`.
    #[arg(long, default_value = "pairwise")]
    pub mode: Mode,
    /// Worker threads, each with its own encoder session of one ONNX Runtime thread; frames
    /// are dealt to them and written in order, so the output is byte-identical for any number
    /// (default: the machine's available parallelism).
    #[arg(long, env = "CROSSVIEW_WORKERS")]
    pub workers: Option<NonZeroUsize>,
    /// [ours] Link the identities over time (frame order) and write each one's `track_id`
    /// (`crossview_core::tracking`, default settings). The tracker runs on one thread after
    /// the workers, so it also serialises the output.
    #[arg(long)]
    pub tracking: bool,
    /// [ours] Identities with memory: the past frames' share of each pair's evidence (0: every
    /// frame alone), as `crossview eval --memory`.
    #[arg(long, env = "CROSSVIEW_MEMORY", default_value_t = MemoryConfig::default().carry)]
    pub memory: f32,
}

/// Checks that the recording's cameras are the model's, in the same order (the encoder's
/// camera embedding is indexed by position). Size differences only warn: boxes are
/// normalised by the recording's sizes.
pub(crate) fn check_scene(scene: &SceneSpec, meta: &ModelMetadata) -> anyhow::Result<()> {
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
    match mode {
        Mode::Pairwise => format!("pairwise S>={threshold:.2}"),
        Mode::Calibrated => format!("calibrated P>={threshold:.2}"),
        Mode::Identities => format!("identities t={threshold:.2}"),
    }
}

/// The association settings of `meta` with the command line's overrides.
fn config(
    meta: &ModelMetadata,
    threshold: Option<f32>,
    match_threshold: Option<f32>,
    alpha: Option<f32>,
) -> anyhow::Result<AssociationConfig> {
    let mut cfg = meta.association_config();
    cfg.threshold = check_threshold(threshold.unwrap_or(cfg.threshold))?;
    cfg.identity.threshold = check_threshold(match_threshold.unwrap_or(cfg.identity.threshold))?;
    cfg.alpha = check_alpha(alpha.unwrap_or(cfg.alpha))?;
    Ok(cfg)
}

/// Loads `workers` encoder sessions of `model` (one ONNX Runtime thread each), one thread
/// each, while this thread reads the recording `data`. A model error is reported before a
/// data error.
pub(crate) fn load_and_read(
    model: &Path,
    data: &[PathBuf],
    workers: usize,
) -> anyhow::Result<(Vec<OnnxEncoder>, Recording)> {
    std::thread::scope(|scope| {
        let loaders: Vec<_> = (0..workers.max(1))
            .map(|_| {
                scope.spawn(|| OnnxEncoder::load_with(model, EncoderOptions { intra_threads: 1 }))
            })
            .collect();
        let recording = read_recordings(data, true);
        let encoders = loaders
            .into_iter()
            .map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
            .collect::<crossview_core::Result<Vec<_>>>()?;
        let (recording, stats) = recording?;
        if stats.torn_lines > 0 {
            eprintln!(
                "note: dropped {} torn last line(s) of the recording's files (cut short by a crash)",
                stats.torn_lines
            );
        }
        Ok((encoders, recording))
    })
}

/// The recording's name in reports: its paths, comma-separated.
fn data_name(data: &[PathBuf]) -> String {
    data.iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(",")
}

/// Runs `crossview eval`.
pub fn run(args: EvalArgs) -> anyhow::Result<()> {
    if let Some(dump) = &args.from_dump {
        let records = read_dump(dump)?;
        let name = dump.display().to_string();
        let mut rows = vec![TableRow {
            label: name.clone(),
            metrics: compute_metrics(&records),
        }];
        let identity: Option<Vec<_>> = records.iter().map(|r| r.as_identities()).collect();
        if let Some(identity) = identity.filter(|r| !r.is_empty()) {
            rows.push(TableRow {
                label: format!("{name} (identities)"),
                metrics: compute_metrics(&identity),
            });
        }
        print!("{}", format_table(&rows));
        if let Some(path) = &args.report {
            let mut report = EvalReport::new("", &name, &[]);
            for (row, mode) in rows.iter().zip(["from-dump", "from-dump-identities"]) {
                report.runs.push(crossview_eval::report::ReportRun {
                    mode: mode.into(),
                    threshold: None,
                    alpha: None,
                    metrics: row.metrics,
                    identities: None,
                });
            }
            report.write(path)?;
        }
        return Ok(());
    }
    let (Some(model), data) = (&args.model, &args.data) else {
        bail!("--model and --data are required (or --from-dump)");
    };
    if data.is_empty() {
        bail!("--model and --data are required (or --from-dump)");
    }
    let memory = MemoryConfig::with_carry(args.memory)?;
    let workers = worker_count(args.workers);
    let (mut encoders, recording) = load_and_read(model, data, workers)?;
    let meta = encoders[0].metadata().clone();
    check_scene(&recording.scene, &meta)?;
    let mut base = config(&meta, args.threshold, args.match_threshold, args.alpha)?;
    let (link, support) = args.identity_method.defaults();
    base.identity.method = args.identity_method;
    (base.identity.link_threshold, base.identity.support) = (link, support);
    if let Some(w) = &args.identity_params {
        if w.iter().any(|v| !v.is_finite() || *v < 0.0) {
            bail!("--identity-params must be finite and non-negative, got {w:?}");
        }
        (base.identity.link_threshold, base.identity.support) = (w[0], w[1]);
    }
    // Rows: SPEC §3 pairwise (what the paper's metrics mean), pairwise on the calibrated
    // confidence when the model has one, and the identities the service returns.
    let modes: &[Mode] = if base.identity.calibration.is_some() {
        &[Mode::Pairwise, Mode::Calibrated, Mode::Identities]
    } else {
        &[Mode::Pairwise, Mode::Identities]
    };
    let mut settings: Vec<(Mode, f32)> = modes.iter().map(|&m| (m, base.threshold_of(m))).collect();
    for &t in &args.sweep {
        let t = check_threshold(t)?;
        for &m in modes {
            if !settings.contains(&(m, t)) {
                settings.push((m, t));
            }
        }
    }
    tracing::info!(
        frames = recording.frames.len(),
        settings = settings.len(),
        calibrated = base.identity.calibration.is_some(),
        workers,
        "evaluating"
    );
    let mut encoders: Vec<&mut dyn Encoder> =
        encoders.iter_mut().map(|e| e as &mut dyn Encoder).collect();
    let runs =
        evaluate_settings_with(&mut encoders, &recording, &base, &settings, memory.as_ref())?;
    let rows: Vec<TableRow> = runs
        .iter()
        .map(|r| TableRow {
            label: label(r.mode, r.threshold),
            metrics: r.metrics,
        })
        .collect();
    print!("{}", format_table(&rows));
    if let Some(r) = runs.iter().find(|r| r.mode == Mode::Identities) {
        if let Some(m) = &memory {
            println!(
                "identities remember the past frames in frame order, as served (--memory {}; 0: each frame alone)",
                m.carry
            );
        }
        print!("{}", r.identities.format());
        if args.tracking {
            let tracker = TrackerConfig {
                gate: args.track_gate,
                max_age: args.track_max_age,
                velocity_weight: args.track_velocity,
                iou_weight: args.track_iou,
                box_velocity_weight: args.track_box_velocity,
                ..TrackerConfig::default()
            };
            let cfg = base.with_mode(Mode::Identities, r.threshold);
            let t = evaluate_tracking(&mut encoders, &recording, &cfg, &tracker, memory.as_ref())?;
            print!("{}", format_tracking(&t));
        }
    }
    if let Some(path) = &args.report {
        EvalReport::new(&model.display().to_string(), &data_name(data), &runs).write(path)?;
    }
    if let Some(path) = &args.dump_pairs {
        write_dump_on(path, &runs[0].records, workers)?;
        tracing::info!(path = %path.display(), pairs = runs[0].records.len(), "pair dump written");
    }
    Ok(())
}

/// The `--tracking` block: the multi-camera row, then one row per camera.
fn format_tracking(t: &TrackingReport) -> String {
    let row = |name: &str, s: &TrackScores| {
        format!(
            "  {name:<14} IDF1 {:6.2}  MOTA {:6.2}  ID switches {:5}  ({} boxes, {} people, {} tracks)\n",
            100.0 * s.idf1,
            100.0 * s.mota,
            s.id_switches,
            s.boxes,
            s.people,
            s.tracks
        )
    };
    let mut out =
        String::from("tracking (identities linked over time, track ids vs ground-truth ids):\n");
    out.push_str(&row("multi-camera", &t.multi_camera));
    for (name, s) in &t.per_camera {
        out.push_str(&row(name, s));
    }
    out
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
    #[serde(skip_serializing_if = "Option::is_none")]
    track_id: Option<u64>,
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

/// Appends the `associate` output line of one associated frame (JSON and a newline) to `buf`.
fn frame_line(
    buf: &mut Vec<u8>,
    scene: &SceneSpec,
    frame: &Frame,
    assoc: &FrameAssociation,
    tracks: Option<&[u64]>,
    mode: Mode,
) -> serde_json::Result<()> {
    let cam = |c: usize| scene.cameras[c].name.as_str();
    let line = FrameOut {
        frame_id: frame.frame_id,
        mode,
        identities: assoc
            .identities
            .iter()
            .enumerate()
            .map(|(k, i)| IdentityOut {
                id: i.id,
                track_id: tracks.and_then(|t| t.get(k).copied()),
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
                matches: p.matching.matches.iter().map(Match::triple).collect(),
            })
            .collect(),
    };
    serde_json::to_writer(&mut *buf, &line)?;
    buf.push(b'\n');
    Ok(())
}

/// A frame as a worker leaves it for the sink.
enum Done {
    /// Its line, written as is.
    Line(Vec<u8>),
    /// Associated; the sink adds the track ids.
    Associated(FrameAssociation),
    /// Embedded; the sink associates it with the memory (frame order).
    Embedded(FrameEmbeddings),
}

/// Runs `crossview associate`: the frames are dealt to `--workers` threads (one encoder
/// session each) that embed, associate and format their frames' lines; this thread writes the
/// lines in frame order.
pub fn run_associate(args: AssociateArgs) -> anyhow::Result<()> {
    let mut memory = MemoryConfig::with_carry(args.memory)?.map(Memory::new);
    let workers = worker_count(args.workers);
    let t0 = Instant::now();
    let (mut encoders, recording) = load_and_read(&args.model, &args.data, workers)?;
    let loaded = t0.elapsed();
    let meta = encoders[0].metadata().clone();
    let scene = &recording.scene;
    check_scene(scene, &meta)?;
    let mut cfg = config(&meta, args.threshold, args.match_threshold, args.alpha)?;
    cfg.mode = args.mode;
    let file = std::fs::File::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut out = std::io::BufWriter::new(file);
    let write_err = |e: std::io::Error| anyhow::anyhow!("cannot write {}: {e}", args.out.display());
    let t1 = Instant::now();
    let mut tracker = args
        .tracking
        .then(|| Tracker::new(TrackerConfig::default()));
    let frames = &recording.frames;
    let (tracking, remember) = (tracker.is_some(), memory.is_some());
    map_ordered(
        frames,
        &mut encoders,
        DEFAULT_WINDOW,
        |encoder, _, frame| -> anyhow::Result<Done> {
            let embeddings = embed_frame(encoder, scene, frame)?;
            if remember {
                // Memory needs frame order: the sink associates this frame.
                return Ok(Done::Embedded(embeddings));
            }
            let assoc = associate_frame(frame, embeddings, &cfg);
            if tracking {
                // Track ids need frame order: the sink writes this frame's line.
                return Ok(Done::Associated(assoc));
            }
            let mut line = Vec::with_capacity(32 * 1024);
            frame_line(&mut line, scene, frame, &assoc, None, cfg.mode)?;
            Ok(Done::Line(line))
        },
        |i, done| {
            let frame = &frames[i];
            let assoc = match done {
                Done::Line(line) => return out.write_all(&line).map_err(write_err),
                Done::Associated(assoc) => assoc,
                Done::Embedded(e) => associate_frame_with(frame, e, &cfg, memory.as_mut()),
            };
            let tracks = tracker
                .as_mut()
                .map(|t| t.update(frame, &assoc.identities, &assoc.embeddings));
            let mut line = Vec::with_capacity(32 * 1024);
            frame_line(&mut line, scene, frame, &assoc, tracks.as_deref(), cfg.mode)?;
            out.write_all(&line).map_err(write_err)
        },
    )?;
    out.flush().map_err(write_err)?;
    tracing::info!(
        frames = recording.frames.len(),
        workers,
        load_read_seconds = loaded.as_secs_f64(),
        associate_write_seconds = t1.elapsed().as_secs_f64(),
        out = %args.out.display(),
        "associated"
    );
    Ok(())
}

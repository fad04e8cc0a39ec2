//! `crossview fit-check`: whether each camera still fits the model over a recording
//! (`crossview_core::fit`), look after look as the server's live watch takes them: a window of
//! the newest frames, every pair's shift profile, each pair's contrast over the newest of
//! them, each camera's score and state.
use std::num::NonZeroUsize;
use std::path::PathBuf;

use anyhow::bail;
use clap::Args;
use serde::Serialize;

use crossview_core::fit::{CameraFit, FitConfig, FitState, FitWatch, PairContrast, contrast};
use crossview_core::offsets::{CameraSeries, OffsetConfig, frame_step};
use crossview_eval::parallel::worker_count;

use super::eval::{check_scene, load_and_read};
use super::sync_check::{embed_series, profile_pairs};

/// Arguments of `crossview fit-check`.
#[derive(Debug, Args)]
pub struct FitCheckArgs {
    /// Model file (SPEC §8 ONNX) trained on this scene's cameras.
    #[arg(long, env = "CROSSVIEW_MODEL")]
    pub model: PathBuf,
    /// Recording (SPEC §7 JSONL; ids, if any, are ignored): a file or a directory; repeatable,
    /// read as one recording.
    #[arg(long, required = true)]
    pub data: Vec<PathBuf>,
    /// Frames each look profiles (the server's `--clock-watch-window`).
    #[arg(long, default_value_t = 300)]
    pub window: usize,
    /// Newest frames of the window the contrast is read on.
    #[arg(long, default_value_t = FitConfig::default().recent)]
    pub recent: usize,
    /// One look every this many frames (the server: one per `--clock-watch-interval`).
    #[arg(long, default_value_t = 20)]
    pub every: usize,
    /// Largest clock offset searched, in frame steps either way (the server's
    /// `--clock-watch-max-offset`).
    #[arg(long, default_value_t = 10)]
    pub max_offset: u32,
    /// Write every look as a JSON line (each camera's score and state, each pair's contrast)
    /// instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Worker threads (default: the machine's available parallelism).
    #[arg(long, env = "CROSSVIEW_WORKERS")]
    pub workers: Option<NonZeroUsize>,
}

/// One look, as the JSON lines write it.
#[derive(Serialize)]
struct Look<'a> {
    as_of_frame: i64,
    seconds: Option<f64>,
    frames: usize,
    cameras: Vec<CameraRow<'a>>,
    pairs: Vec<PairRow>,
}

#[derive(Serialize)]
struct CameraRow<'a> {
    name: &'a str,
    score: Option<f32>,
    state: FitState,
}

#[derive(Serialize)]
struct PairRow {
    a: usize,
    b: usize,
    #[serde(flatten)]
    contrast: Option<PairContrast>,
}

/// Runs `crossview fit-check`.
pub fn run(args: FitCheckArgs) -> anyhow::Result<()> {
    if args.window < 2 || args.recent == 0 || args.recent > args.window || args.every == 0 {
        bail!("--window must be at least 2, --recent within 1..=--window, --every at least 1");
    }
    if args.max_offset == 0 || args.max_offset > 100 {
        bail!(
            "--max-offset must be within 1..=100, got {}",
            args.max_offset
        );
    }
    let workers = worker_count(args.workers);
    let (mut encoders, recording) = load_and_read(&args.model, &args.data, 1)?;
    check_scene(&recording.scene, encoders[0].metadata())?;
    let scene = &recording.scene;
    let lags = vec![0; scene.cameras.len()];
    let series = embed_series(&mut encoders[0], &recording, &lags)?;
    let step = frame_step(series.iter().flat_map(CameraSeries::frame_ids));
    let offsets = OffsetConfig {
        max_offset: args.max_offset,
        ..OffsetConfig::default()
    };
    let fit = FitConfig {
        recent: args.recent,
        min_frames: FitConfig::default().min_frames.min(args.recent / 2).max(2),
        ..FitConfig::default()
    };
    let mut watch = FitWatch::new(scene.cameras.len(), fit);
    let mut ids: Vec<i64> = recording
        .frames
        .iter()
        .filter_map(|f| i64::try_from(f.frame_id).ok())
        .collect();
    ids.sort_unstable();
    ids.dedup();
    let first_id = ids.first().copied().unwrap_or(0);
    let seconds = |id: i64| {
        recording
            .fps
            .map(|fps| (id - first_id) as f64 / step as f64 / fps)
    };
    if !args.json {
        print!("{}", header(scene, &args));
    }
    // Looks start once the window is half full, as the server's.
    let first_look = (args.window / 2).max(args.recent).max(2);
    let mut at = first_look;
    // One look every `--every` frames, and one on the last frame.
    while at < ids.len() + args.every && ids.len() >= first_look {
        at = at.min(ids.len());
        let (last, first) = (ids[at - 1], ids[at.saturating_sub(args.window)]);
        let since = ids[at - args.recent.min(at)];
        let window: Vec<CameraSeries> = series.iter().map(|s| s.between(first, last)).collect();
        let recent: Vec<bool> = series
            .iter()
            .map(|s| s.between(since, last).is_empty())
            .collect();
        let profiles = profile_pairs(&window, step, &offsets, workers)?;
        let pairs: Vec<Option<PairContrast>> = profiles
            .iter()
            .map(|(_, _, p)| contrast(p, since, fit.min_frames))
            .collect();
        let fits = watch.look(&pairs, &recent);
        if args.json {
            let look = Look {
                as_of_frame: last,
                seconds: seconds(last),
                frames: at.min(args.window),
                cameras: fits
                    .iter()
                    .map(|f| CameraRow {
                        name: &scene.cameras[f.camera].name,
                        score: f.score,
                        state: f.state,
                    })
                    .collect(),
                pairs: profiles
                    .iter()
                    .zip(pairs)
                    .map(|((a, b, _), contrast)| PairRow {
                        a: *a,
                        b: *b,
                        contrast,
                    })
                    .collect(),
            };
            println!("{}", serde_json::to_string(&look)?);
        } else {
            println!("{}", row(last, seconds(last), &fits));
        }
        at += args.every;
    }
    Ok(())
}

fn header(scene: &crossview_core::SceneSpec, args: &FitCheckArgs) -> String {
    let mut out = format!(
        "scene '{}': a look every {} frames over the newest {} (contrast over the newest {}); \
         score 1 = fits as when first seen, below {} drifting, below {} twice: does not fit (!)\n",
        scene.name,
        args.every,
        args.window,
        args.recent,
        FitConfig::default().drifting,
        FitConfig::default().misfit
    );
    out.push_str(&format!("{:>12} {:>9}", "frame", "seconds"));
    for c in &scene.cameras {
        out.push_str(&format!(" {:>10}", truncate(&c.name, 10)));
    }
    out.push('\n');
    out
}

fn row(frame: i64, seconds: Option<f64>, fits: &[CameraFit]) -> String {
    let mut out = format!(
        "{frame:>12} {:>9}",
        seconds.map_or("-".into(), |s| format!("{s:.1}"))
    );
    for f in fits {
        let cell = match (f.state, f.score) {
            (FitState::Silent, _) => "silent".to_string(),
            (_, None) => "-".to_string(),
            (FitState::DoesNotFit, Some(s)) => format!("{s:.2} !"),
            (FitState::Drifting, Some(s)) => format!("{s:.2} ~"),
            (_, Some(s)) => format!("{s:.2}"),
        };
        out.push_str(&format!(" {cell:>10}"));
    }
    out
}

fn truncate(s: &str, n: usize) -> &str {
    s.char_indices().nth(n).map_or(s, |(i, _)| &s[..i])
}

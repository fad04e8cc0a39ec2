//! `crossview sync-check`: each camera's clock offset, estimated from a recording's detections
//! with the model (`crossview_core::offsets`), as a table or JSON.
use std::num::NonZeroUsize;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use serde::Serialize;

use crossview_core::association::embed_frame;
use crossview_core::capture::{PhaseTracker, Timing};
use crossview_core::offsets::{
    CameraSeries, OffsetConfig, OffsetEstimate, PairProfile, camera_pairs, frame_step, profile,
    solve,
};
use crossview_core::{Encoder, SceneSpec};
use crossview_data::Recording;
use crossview_eval::parallel::{map_ordered, worker_count};

use super::eval::{check_scene, load_and_read};

/// Largest `--max-offset` (frame steps): the work grows linearly with it.
const MAX_SEARCH: u32 = 500;

/// Arguments of `crossview sync-check`.
#[derive(Debug, Args)]
pub struct SyncCheckArgs {
    /// Model file (SPEC §8 ONNX) trained on this scene's cameras.
    #[arg(long, env = "CROSSVIEW_MODEL")]
    pub model: PathBuf,
    /// Recording (SPEC §7 JSONL; ids, if any, are ignored): a file or a directory; repeatable,
    /// read as one recording.
    #[arg(long, required = true)]
    pub data: Vec<PathBuf>,
    /// Frames per second of the recording (one frame is one frame step of ids, e.g. 2 for
    /// WILDTRACK, whose ids step by 5 every 0.5 s): offsets are also given in seconds
    /// [default: the rate the recording's header declares, if any].
    #[arg(long)]
    pub fps: Option<f64>,
    /// Largest offset searched, in frame steps either way (a step is the recording's gap
    /// between frame ids, e.g. 5 for WILDTRACK); at most 500.
    #[arg(long, default_value_t = OffsetConfig::default().max_offset)]
    pub max_offset: u32,
    /// Camera the offsets are relative to (default: the camera at the median offset, so
    /// that the cameras out of step with the majority are the ones shown shifted).
    #[arg(long)]
    pub reference: Option<String>,
    /// Write the estimate as JSON on standard output instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Shift a camera's frame ids by N frame steps before estimating, as if its clock ran
    /// late (`CAMERA:N`, N may be negative; repeatable): checks the estimate on a recording
    /// known to be in sync.
    #[arg(long, value_name = "CAMERA:N")]
    pub simulate_lag: Vec<String>,
    /// Worker threads (default: the machine's available parallelism).
    #[arg(long, env = "CROSSVIEW_WORKERS")]
    pub workers: Option<NonZeroUsize>,
}

/// The JSON form: the estimate with camera names and seconds.
#[derive(Serialize)]
struct Report<'a> {
    scene: &'a str,
    frames: usize,
    fps: Option<f64>,
    reference: &'a str,
    step: i64,
    cameras: Vec<CameraRow<'a>>,
    pairs: &'a [crossview_core::offsets::PairSummary],
}

#[derive(Serialize)]
struct CameraRow<'a> {
    name: &'a str,
    #[serde(flatten)]
    offset: &'a crossview_core::offsets::CameraOffset,
    seconds: Option<f64>,
    /// A camera whose batches carry capture times: its clock in milliseconds (the whole
    /// frames found, times the period, plus where within the period its captures fall), the
    /// drift and the jitter of its times ([`crossview_core::capture`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    capture: Option<CaptureClock>,
}

#[derive(Serialize, Clone, Copy)]
struct CaptureClock {
    offset_ms: Option<f64>,
    phase_ms: f64,
    drift_ms_per_min: Option<f64>,
    jitter_ms: f64,
    captures: usize,
}

/// Each camera's timing from its batches' capture times (none without times or a rate).
fn capture_timing(
    data: &[PathBuf],
    scene: &SceneSpec,
    fps: Option<f64>,
) -> anyhow::Result<Vec<Option<Timing>>> {
    let n = scene.cameras.len();
    let Some(period_ms) = fps.map(|f| 1e3 / f) else {
        return Ok(vec![None; n]);
    };
    let mut trackers = vec![PhaseTracker::new(period_ms); n];
    for file in crossview_data::recording_files(data)? {
        for batch in crossview_data::RecordingReader::open(&file)? {
            let batch = batch?;
            let (Some(t), Ok(c)) = (batch.time, scene.camera_index(&batch.camera)) else {
                continue;
            };
            // The residual from the nearest tick, as the reader placed the camera's first batch
            // (its phase follows on from that branch, as the reader's did).
            let ms = t.unix_nanos() as f64 / 1e6;
            trackers[c].observe(t.unix_nanos(), ms - period_ms * (ms / period_ms).round());
        }
    }
    Ok(trackers.iter().map(PhaseTracker::timing).collect())
}

/// Runs `crossview sync-check`.
pub fn run(args: SyncCheckArgs) -> anyhow::Result<()> {
    if args.max_offset == 0 || args.max_offset > MAX_SEARCH {
        bail!(
            "--max-offset must be within 1..={MAX_SEARCH}, got {}",
            args.max_offset
        );
    }
    if let Some(fps) = args.fps
        && !(fps.is_finite() && fps > 0.0)
    {
        bail!("--fps must be a positive number, got {fps}");
    }
    let workers = worker_count(args.workers);
    let (mut encoders, recording) = load_and_read(&args.model, &args.data, 1)?;
    let reference = args
        .reference
        .as_deref()
        .map(|name| recording.scene.camera_index(name))
        .transpose()?;
    let lags = parse_lags(&recording.scene, &args.simulate_lag)?;
    let cfg = OffsetConfig {
        max_offset: args.max_offset,
        ..OffsetConfig::default()
    };
    let (step, estimate) = estimate_recording(
        &mut encoders[0],
        &recording,
        &lags,
        reference,
        &cfg,
        workers,
    )?;
    let scene = &recording.scene;
    let fps = args.fps.or(recording.fps);
    let timing = capture_timing(&args.data, scene, fps)?;
    let reference_ms = timing[estimate.reference]
        .zip(fps)
        .map(|(t, fps)| scene.cameras[estimate.reference].offset as f64 * 1e3 / fps + t.phase_ms);
    let report = Report {
        scene: &scene.name,
        frames: recording.frames.len(),
        fps,
        reference: &scene.cameras[estimate.reference].name,
        step,
        cameras: estimate
            .cameras
            .iter()
            .map(|c| CameraRow {
                name: &scene.cameras[c.camera].name,
                offset: c,
                seconds: c
                    .refined
                    .zip(fps)
                    .map(|(r, fps)| f64::from(r) / step as f64 / fps),
                capture: timing[c.camera].zip(fps).map(|(t, fps)| CaptureClock {
                    // Relative to the reference camera, as the frame offsets are.
                    offset_ms: c.frames.zip(reference_ms).map(|(f, r)| {
                        let whole = scene.cameras[c.camera].offset + f / step.max(1);
                        whole as f64 * 1e3 / fps + t.phase_ms - r
                    }),
                    phase_ms: t.phase_ms,
                    drift_ms_per_min: t.drift_ms_per_min,
                    jitter_ms: t.jitter_ms,
                    captures: t.captures,
                }),
            })
            .collect(),
        pairs: &estimate.pairs,
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", table(&report, args.max_offset));
    }
    Ok(())
}

/// Every camera's offset in `recording` (its ids shifted by `lags` frame steps first), with the
/// frame step: the embeddings from `encoder` (their leading block, an ensemble's first member,
/// as the server's live watch), the pairs profiled on `workers` threads.
pub(crate) fn estimate_recording(
    encoder: &mut crossview_model::OnnxEncoder,
    recording: &Recording,
    lags: &[i64],
    reference: Option<usize>,
    cfg: &OffsetConfig,
    workers: usize,
) -> anyhow::Result<(i64, OffsetEstimate)> {
    check_scene(&recording.scene, encoder.metadata())?;
    let series = embed_series(encoder, recording, lags)?;
    let step = frame_step(series.iter().flat_map(CameraSeries::frame_ids));
    Ok((step, estimate(&series, step, reference, cfg, workers)?))
}

/// After `crossview train`: every camera's offset in the training recording `data`, estimated
/// with the model just written, as warnings (none when the cameras look in sync). A camera
/// out of sync shows as an offset, or — since training on it taught the model no consistent
/// geometry for it — as linked to no other camera while the others are.
pub(crate) fn check_after_training(
    model: &std::path::Path,
    data: &[PathBuf],
) -> anyhow::Result<Vec<String>> {
    let (mut encoders, recording) = load_and_read(model, data, 1)?;
    let lags = vec![0; recording.scene.cameras.len()];
    let cfg = OffsetConfig::default();
    let (step, found) = estimate_recording(
        &mut encoders[0],
        &recording,
        &lags,
        None,
        &cfg,
        worker_count(None),
    )?;
    Ok(out_of_sync(&recording.scene, step, &found))
}

/// The warnings for an estimate: each camera off the reference, and each camera linked to no
/// other while at least two are.
fn out_of_sync(scene: &SceneSpec, step: i64, found: &OffsetEstimate) -> Vec<String> {
    let known = found.cameras.iter().filter(|c| c.frames.is_some()).count();
    found
        .cameras
        .iter()
        .filter_map(|c| {
            let name = &scene.cameras[c.camera].name;
            match c.frames {
                Some(0) => None,
                Some(ids) => Some(format!(
                    "camera '{name}' is {ids:+} frame ids ({:+.1} frames) off the others",
                    f64::from(c.refined.unwrap_or(0.0)) / step.max(1) as f64
                )),
                None if known >= 2 => Some(format!(
                    "camera '{name}' is linked to no other camera by the new model (it overlaps \
                     with none, or its clock is off and its geometry was not learnt)"
                )),
                None => None,
            }
        })
        .collect()
}

/// `CAMERA:N` → per camera, a lag in frame steps.
fn parse_lags(scene: &SceneSpec, specs: &[String]) -> anyhow::Result<Vec<i64>> {
    let mut lags = vec![0i64; scene.cameras.len()];
    for spec in specs {
        let (name, n) = spec
            .rsplit_once(':')
            .with_context(|| format!("--simulate-lag wants CAMERA:N, got '{spec}'"))?;
        let n: i64 = n
            .trim_start_matches('+')
            .parse()
            .with_context(|| format!("--simulate-lag: '{n}' is not a whole number"))?;
        if n.unsigned_abs() > u64::from(MAX_SEARCH) {
            bail!("--simulate-lag: {n} is beyond ±{MAX_SEARCH} steps");
        }
        lags[scene.camera_index(name)?] = n;
    }
    Ok(lags)
}

/// Every camera's embeddings over time, frame ids shifted by `lags` (in frame steps of the
/// recording's unshifted ids).
pub(crate) fn embed_series(
    encoder: &mut dyn Encoder,
    recording: &Recording,
    lags: &[i64],
) -> anyhow::Result<Vec<CameraSeries>> {
    let scene = &recording.scene;
    let step = frame_step(
        recording
            .frames
            .iter()
            .filter_map(|f| i64::try_from(f.frame_id).ok()),
    );
    let mut series = vec![CameraSeries::new(); scene.cameras.len()];
    let mut skipped = 0usize;
    for frame in &recording.frames {
        let Ok(id) = i64::try_from(frame.frame_id) else {
            skipped += 1;
            continue;
        };
        // The leading block (an ensemble's first member), as the server's live watch keeps.
        let width = encoder.leading_width();
        let embeddings = embed_frame(encoder, scene, frame)?.leading(width);
        for (c, s) in series.iter_mut().enumerate() {
            if let Some(view) = embeddings.view(c) {
                let shifted = lags[c].checked_mul(step).and_then(|d| id.checked_add(d));
                match shifted {
                    Some(t) => s.insert(t, view.to_owned()),
                    None => skipped += 1,
                }
            }
        }
    }
    if skipped > 0 {
        tracing::warn!(skipped, "frame ids beyond 2^63 - 1 left out");
    }
    Ok(series)
}

/// Profiles of every camera pair (on `workers` threads), then the joint fit.
fn estimate(
    series: &[CameraSeries],
    step: i64,
    reference: Option<usize>,
    cfg: &OffsetConfig,
    workers: usize,
) -> anyhow::Result<OffsetEstimate> {
    let profiles = profile_pairs(series, step, cfg, workers)?;
    let frames: Vec<usize> = series.iter().map(CameraSeries::len).collect();
    Ok(solve(
        series.len(),
        &profiles,
        &frames,
        step,
        reference,
        cfg,
    ))
}

/// The profile of every camera pair `(a, b)`, `a < b`, in order, on `workers` threads.
pub(crate) fn profile_pairs(
    series: &[CameraSeries],
    step: i64,
    cfg: &OffsetConfig,
    workers: usize,
) -> anyhow::Result<Vec<(usize, usize, PairProfile)>> {
    let n = series.len();
    let pairs: Vec<(usize, usize)> = camera_pairs(n).collect();
    let mut states = vec![(); workers.clamp(1, pairs.len().max(1))];
    let mut profiles: Vec<(usize, usize, PairProfile)> = Vec::with_capacity(pairs.len());
    map_ordered(
        &pairs,
        &mut states,
        1,
        |_, _, &(a, b)| -> anyhow::Result<PairProfile> {
            Ok(profile(&series[a], &series[b], step, cfg))
        },
        |i, p| {
            profiles.push((pairs[i].0, pairs[i].1, p));
            Ok(())
        },
    )?;
    Ok(profiles)
}

/// The human-readable table.
fn table(r: &Report, max_offset: u32) -> String {
    let mut out = format!(
        "scene '{}': {} frames, frame step {}, searched ±{} steps; offsets relative to {}\n",
        r.scene, r.frames, r.step, max_offset, r.reference
    );
    out.push_str(&format!(
        "{:<16} {:>8} {:>9} {:>9} {:>10} {:>5} {:>7}\n",
        "camera", "offset", "refined", "seconds", "confidence", "pairs", "z"
    ));
    for c in &r.cameras {
        let o = c.offset;
        match (o.frames, o.refined) {
            (Some(f), Some(refined)) => out.push_str(&format!(
                "{:<16} {:>+8} {:>+9.2} {:>9} {:>10.2} {:>5} {:>7.1}\n",
                c.name,
                f,
                refined,
                c.seconds.map_or("-".into(), |s| format!("{s:+.2}")),
                o.confidence,
                o.pairs,
                o.z
            )),
            _ => out.push_str(&format!(
                "{:<16} {:>8} ({})\n",
                c.name,
                "unknown",
                match o.unknown {
                    Some(crossview_core::offsets::Unknown::TooFewFrames) => "too few frames",
                    _ => "no confident pair: no overlap with another camera, or nobody moved",
                }
            )),
        }
    }
    if r.cameras.iter().any(|c| c.capture.is_some()) {
        out.push_str(&format!(
            "capture times:\n{:<16} {:>10} {:>9} {:>11} {:>9}\n",
            "camera", "offset ms", "phase ms", "drift ms/min", "jitter ms"
        ));
        for c in &r.cameras {
            if let Some(k) = c.capture {
                out.push_str(&format!(
                    "{:<16} {:>10} {:>+9.1} {:>11} {:>9.1}\n",
                    c.name,
                    k.offset_ms.map_or("unknown".into(), |o| format!("{o:+.1}")),
                    k.phase_ms,
                    k.drift_ms_per_min
                        .map_or("-".into(), |d| format!("{d:+.1}")),
                    k.jitter_ms
                ));
            }
        }
    }
    let used = r.pairs.iter().filter(|p| p.used).count();
    out.push_str(&format!(
        "{used} of {} camera pairs confident and consistent\n",
        r.pairs.len()
    ));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::offsets::CameraOffset;
    use crossview_core::{CameraSpec, offsets::Unknown};

    fn camera(c: usize, frames: Option<i64>) -> CameraOffset {
        CameraOffset {
            camera: c,
            frames,
            refined: frames.map(|f| f as f32),
            pairs: 2,
            z: 8.0,
            residual: 0.0,
            confidence: 0.6,
            unknown: frames.is_none().then_some(Unknown::NoConfidentPair),
        }
    }

    #[test]
    fn out_of_sync_names_offsets_and_unlinked_cameras() {
        let scene = SceneSpec {
            name: "s".into(),
            cameras: (0..4)
                .map(|i| CameraSpec::new(format!("c{i}"), 640, 480))
                .collect(),
        };
        let estimate = |cams: Vec<CameraOffset>| OffsetEstimate {
            reference: 0,
            step: 5,
            cameras: cams,
            pairs: Vec::new(),
        };
        let in_sync = estimate((0..4).map(|c| camera(c, Some(0))).collect());
        assert!(out_of_sync(&scene, 5, &in_sync).is_empty());
        let off = estimate(vec![
            camera(0, Some(0)),
            camera(1, Some(10)),
            camera(2, None),
            camera(3, Some(0)),
        ]);
        let w = out_of_sync(&scene, 5, &off);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(
            w[0].contains("'c1' is +10 frame ids (+2.0 frames)"),
            "{w:?}"
        );
        assert!(w[1].contains("'c2' is linked to no other"), "{w:?}");
        // Nothing known (a model that learnt nothing, a static scene): no claim.
        let none = estimate((0..4).map(|c| camera(c, None)).collect());
        assert!(out_of_sync(&scene, 5, &none).is_empty());
    }
}

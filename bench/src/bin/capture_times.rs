//! Capture times through the real server: a recording's frames pushed with each camera's
//! capture time instead of a frame id — every camera with its own clock offset, jitter and
//! (optionally) drift — or, for the baseline, with frame ids. Reports what a client receives:
//! how many batches the server grouped with the other cameras' batches of the frame they were
//! captured in, and the served identities (SPEC §5 pairwise ACC / IPAA-100, scored as
//! `crossview eval` scores them against the recording's ground-truth ids).
//!
//! The real server in-process on 127.0.0.1:0 (`--record` on, to read back where each batch
//! went), batches pushed over HTTP camera by camera in shuffled order, results read over gRPC.
//! Frame `k` of the run (the recording looped `--loops` times) is captured at
//! `2026-12-06T00:00:00Z + k / fps`; camera `c` stamps it `+ offset_c + drift_c · t + jitter`,
//! jitter uniform in ±`--jitter` periods.
//!
//! "after" scores the frames from the first loop start after the last misplaced batch.
//!
//! Usage: capture_times --model M.onnx --data REC.jsonl [--offsets-ms CAM:MS,...]
//!        [--drift CAM:MS_PER_MIN] [--jitter 0.2] [--declare] [--auto-align] [--ids]
//!        [--loops N] [--rate FRAMES_PER_S] [--watch-window N] [--watch-interval-ms MS]
//! Prints one JSON line.
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use crossview::demo::score::pair_records;
use crossview_api::convert::identity_from_pb;
use crossview_api::pb;
use crossview_core::capture::{CaptureTime, Ticks};
use crossview_core::identity::Identity;
use crossview_core::{Batch, Frame};
use crossview_data::read_recording;
use crossview_eval::compute_metrics;
use crossview_serve::config::{ClockWatchConfig, SceneDecl};
use crossview_serve::{ModelSpec, RecordConfig, ServeConfig};
use futures::StreamExt;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};

/// 2026-12-06T00:00:00Z, in seconds.
const T0: f64 = 1_796_515_200.0;

#[derive(Parser)]
struct Args {
    #[arg(long)]
    model: PathBuf,
    /// A recording with ground-truth ids (its header's fps is the scene's rate).
    #[arg(long)]
    data: PathBuf,
    /// Camera clock offsets, `CAM:MS,...` (others 0).
    #[arg(long, value_delimiter = ',')]
    offsets_ms: Vec<String>,
    /// A camera whose clock drifts, `CAM:MS_PER_MIN`.
    #[arg(long)]
    drift: Option<String>,
    /// Jitter of each capture time, uniform in ± this many periods.
    #[arg(long, default_value_t = 0.0)]
    jitter: f64,
    /// Declare every camera's offset in the scene (`@±Nms`).
    #[arg(long)]
    declare: bool,
    /// `--auto-align` (whole-frame offsets from the clock watch).
    #[arg(long)]
    auto_align: bool,
    /// The baseline: push frame ids, no times.
    #[arg(long)]
    ids: bool,
    /// Play the recording this many times (capture time runs on).
    #[arg(long, default_value_t = 1)]
    loops: u64,
    /// Frames pushed per second of wall time.
    #[arg(long, default_value_t = 50.0)]
    rate: f64,
    #[arg(long, default_value_t = 300)]
    watch_window: usize,
    #[arg(long, default_value_t = 1000)]
    watch_interval_ms: u64,
}

/// Where one batch came from: the frame (run index) it was captured in.
type Origin = HashMap<(usize, i64), u64>;

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rec = read_recording(&args.data)?;
    let fps = rec.fps.context("the recording declares no fps")?;
    Ticks::new(fps).map_err(anyhow::Error::msg)?;
    let names: Vec<String> = rec.scene.cameras.iter().map(|c| c.name.clone()).collect();
    let n = names.len();
    let per_camera = |list: &[String]| -> anyhow::Result<Vec<f64>> {
        let mut v = vec![0.0; n];
        for item in list {
            let (cam, ms) = item.split_once(':').context("CAM:VALUE")?;
            v[rec.scene.camera_index(cam)?] = ms.parse()?;
        }
        Ok(v)
    };
    let offsets = per_camera(&args.offsets_ms)?;
    let drift = per_camera(args.drift.as_slice())?;
    let cams: Vec<String> = rec
        .scene
        .cameras
        .iter()
        .zip(&offsets)
        .map(|(c, &o)| {
            let declared = if args.declare && o != 0.0 {
                format!("@{:+}ms", o.round() as i64)
            } else {
                String::new()
            };
            format!("{}:{}x{}{declared}", c.name, c.width, c.height)
        })
        .collect();
    let decl = format!("{}={}@{fps}fps", rec.scene.name, cams.join(","));
    let rec_dir = tempfile::tempdir()?;
    let dir = rec_dir.path().to_path_buf();
    let record_dir = dir.clone();
    let spec = ModelSpec::parse(&format!("{}={}", rec.scene.name, args.model.display()))?;
    let (window, interval, align) = (
        args.watch_window,
        Duration::from_millis(args.watch_interval_ms),
        args.auto_align,
    );
    let server = crossview_testing::start_with(vec![spec], move |c: &mut ServeConfig| {
        c.sync_timeout = Duration::from_secs(5);
        c.limits.subscriber_buffer = 1_000_000;
        c.limits.clock_watch = ClockWatchConfig {
            window,
            interval,
            auto_align: align,
            ..ClockWatchConfig::default()
        };
        c.scenes = vec![SceneDecl::parse(&decl).expect("scene")];
        c.record = Some(RecordConfig::new(&record_dir));
    })
    .await;
    // Read while pushing: a subscriber that stops reading is dropped by the server.
    let mut results = server.subscribe(&rec.scene.name).await;
    let reader = tokio::spawn(async move {
        let mut got: BTreeMap<u64, pb::FrameResult> = BTreeMap::new();
        while let Ok(Some(r)) = tokio::time::timeout(Duration::from_secs(8), results.next()).await {
            let r = r?;
            got.insert(r.frame_id, r);
        }
        anyhow::Ok(got)
    });
    let http = reqwest::Client::new();
    let url = server.url(&format!("/v1/scenes/{}/batches", rec.scene.name));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let pace = Duration::from_secs_f64(1.0 / args.rate.max(0.1));
    let period_ms = 1e3 / fps;
    let frames: Vec<&Frame> = (0..args.loops).flat_map(|_| rec.frames.iter()).collect();
    let mut origin = Origin::new();
    let (mut refused, mut refusals) = (0usize, BTreeMap::<String, usize>::new());
    for (k, frame) in frames.iter().enumerate() {
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut rng);
        for c in order {
            let Some(view) = &frame.views[c] else {
                continue;
            };
            let mut detections = view.clone();
            detections.iter_mut().for_each(|d| d.id = None);
            let t = T0 + k as f64 / fps;
            let ms = offsets[c]
                + drift[c] * (k as f64 / fps) / 60.0
                + rng.random_range(-1.0..=1.0) * args.jitter * period_ms;
            let ns = ((t + ms / 1e3) * 1e9).round() as i64;
            origin.insert((c, ns), k as u64);
            let batch = Batch {
                camera: names[c].clone(),
                frame_id: if args.ids { k as u64 } else { 0 },
                time: (!args.ids).then(|| CaptureTime::from_unix_nanos(ns).expect("a time")),
                detections,
            };
            let r = http.post(&url).json(&batch).send().await?;
            if r.status() != 202 {
                refused += 1;
                let body: serde_json::Value = r.json().await.unwrap_or_default();
                let kind = body["error"]["kind"].as_str().unwrap_or("?").to_string();
                *refusals.entry(kind).or_default() += 1;
            }
        }
        tokio::time::sleep(pace).await;
    }
    // Every frame's result (the last ones after the sync timeout).
    let got = reader.await??;
    let aligned = server
        .get_json(&format!("/v1/scenes/{}", rec.scene.name))
        .await;
    server
        .shutdown()
        .await
        .map_err(|e| anyhow::anyhow!("shutdown: {e:?}"))?;
    let placed = recorded_frames(&dir, &names)?;
    let report = score(
        &frames,
        &names,
        &origin,
        &placed,
        &got,
        args.ids,
        rec.frames.len(),
    )?;
    println!(
        "{}",
        serde_json::json!({
            "fps": fps, "frames": frames.len(), "ids": args.ids, "declare": args.declare,
            "auto_align": args.auto_align, "jitter_periods": args.jitter, "offsets_ms": offsets,
            "drift_ms_per_min": drift, "refused": refused, "refusals": refusals,
            "results": got.len(), "report": report, "clock": aligned["clock"],
            "offsets_applied": aligned["cameras"],
        })
    );
    Ok(())
}

/// Where the server put each accepted batch, from its recording: per (frame, camera), the
/// batch's capture time (ns; for frame ids, the id) — frame ids less each file's offsets.
fn recorded_frames(dir: &Path, names: &[String]) -> anyhow::Result<HashMap<(u64, usize), i64>> {
    let mut out = HashMap::new();
    for file in crossview_data::recording_files(&[dir.to_path_buf()])? {
        let text = std::fs::read_to_string(&file)?;
        let mut lines = text.lines();
        let Some(header) = lines.next() else { continue };
        let header: serde_json::Value = serde_json::from_str(header)?;
        let offset: Vec<i64> = header["scene"]["cameras"]
            .as_array()
            .context("header")?
            .iter()
            .map(|c| c["offset"].as_i64().unwrap_or(0))
            .collect();
        for line in lines {
            let b: Batch = serde_json::from_str(line)?;
            let c = names
                .iter()
                .position(|n| *n == b.camera)
                .context("camera")?;
            let frame = b
                .frame_id
                .checked_add_signed(-offset[c])
                .context("offset")?;
            let stamp = b.time.map_or(b.frame_id as i64, CaptureTime::unix_nanos);
            out.insert((frame, c), stamp);
        }
    }
    Ok(out)
}

/// Grouping and identity scores of the served frames.
fn score(
    frames: &[&Frame],
    names: &[String],
    origin: &Origin,
    placed: &HashMap<(u64, usize), i64>,
    got: &BTreeMap<u64, pb::FrameResult>,
    ids: bool,
    loop_len: usize,
) -> anyhow::Result<serde_json::Value> {
    // Per served frame and camera, the run frame its batch was captured in.
    let mut from: HashMap<(u64, usize), u64> = HashMap::new();
    for (&(f, c), &stamp) in placed {
        let k = if ids {
            Some(stamp as u64)
        } else {
            origin.get(&(c, stamp)).copied()
        };
        if let Some(k) = k {
            from.insert((f, c), k);
        }
    }
    // The shift between served frame and capture frame most batches share.
    let mut shifts: HashMap<i64, usize> = HashMap::new();
    for (&(f, _), &k) in &from {
        *shifts.entry(f as i64 - k as i64).or_default() += 1;
    }
    let shift = shifts
        .iter()
        .max_by_key(|&(_, &v)| v)
        .map_or(0, |(&s, _)| s);
    let misplaced: Vec<u64> = {
        let mut v: Vec<u64> = from
            .iter()
            .filter(|&(&(f, _), &k)| f as i64 - k as i64 != shift)
            .map(|(_, &k)| k)
            .collect();
        v.sort_unstable();
        v
    };
    // Scored after the last misplaced batch, from a loop's start (whole loops compare with one
    // loop of the frame-id path).
    let settled = misplaced.last().map_or(0, |&k| {
        if frames.len() > loop_len {
            (k + 1).div_ceil(loop_len as u64) * loop_len as u64
        } else {
            k + 1
        }
    });
    let mut unlabelled = 1u64 << 62;
    let (mut records, mut after) = (Vec::new(), Vec::new());
    for (&f, r) in got {
        let truth: Vec<Option<Vec<u64>>> = (0..names.len())
            .map(|c| {
                let k = *from.get(&(f, c))?;
                let view = frames[k as usize].views[c].as_ref()?;
                Some(
                    view.iter()
                        .map(|d| {
                            d.id.unwrap_or_else(|| {
                                unlabelled += 1;
                                unlabelled
                            })
                        })
                        .collect(),
                )
            })
            .collect();
        let served: Vec<Identity> = r.identities.iter().map(identity_from_pb).collect();
        let pairs = pair_records(f, names, &truth, &served)?;
        let first = (0..names.len()).filter_map(|c| from.get(&(f, c))).min();
        if first.is_some_and(|&k| k >= settled) {
            after.extend(pairs.iter().cloned());
        }
        records.extend(pairs);
    }
    let (m, a) = (compute_metrics(&records), compute_metrics(&after));
    Ok(serde_json::json!({
        "batches_placed": from.len(), "shift": shift, "misplaced": misplaced.len(),
        "last_misplaced_capture_frame": misplaced.last(),
        "first_misplaced_capture_frame": misplaced.first(),
        "acc": m.acc, "ipaa_100": m.ipaa_100, "pairs": records.len(), "frames": got.len(),
        "settled_from_capture_frame": settled,
        "after": {"acc": a.acc, "ipaa_100": a.ipaa_100, "pairs": after.len()},
    }))
}

//! Healing as a client of the real server lives it: a recording in which one camera moves is
//! streamed at its frame rate to the server with `--record` and `--auto-retrain`; the server
//! notices, fences, retrains in a child process (the release `crossview` given by
//! `--program`), gates and swaps. Reported: when the fence came up and the swap happened (in
//! seconds of stream after the move), the served identities (every camera, SPEC §5 pairwise
//! ACC / IPAA-100 as `crossview eval` scores them) before the move, between move and swap and
//! after the swap, batches refused, frames not complete, and the latency from a frame's last
//! batch to its result (p50 / p99) before the move (idle) and while the retrain ran.
//!
//! Usage: heal_served --model M.onnx --data REC.jsonl --camera cam1 --moved-at FRAME_ID
//!        --program target/release/crossview [--after-s 300] [--epochs 150] [--rate 10]
//! Prints one JSON line. The server's defaults otherwise (clock watch every 10 s).
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Parser;
use crossview::demo::score::{TruthIds, pair_records};
use crossview_api::convert::identity_from_pb;
use crossview_bench::{MovedCamera, push_frame};
use crossview_core::identity::Identity;
use crossview_data::read_recording;
use crossview_eval::compute_metrics;
use crossview_serve::config::SceneDecl;
use crossview_serve::{HealConfig, ModelSpec, RecordConfig, ServeConfig};
use futures::StreamExt;
use rand::SeedableRng;

/// A moved camera healed by the real server, as its client lives it (see the file's header).
#[derive(Parser)]
struct Args {
    /// The model, the recording and the camera that moves.
    #[command(flatten)]
    run: MovedCamera,
    /// The `crossview` executable the server retrains with.
    #[arg(long)]
    program: PathBuf,
    /// `--retrain-after`, seconds.
    #[arg(long, default_value_t = 300)]
    after_s: u64,
    /// `--retrain-epochs`.
    #[arg(long, default_value_t = 150)]
    epochs: usize,
    /// Frames pushed per second (the recording's rate).
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// Where the server records and writes its retrained models (kept).
    #[arg(long)]
    work: PathBuf,
    /// `--retrain-reference-every`, seconds (a reference stretch must be complete before the
    /// move for the gate to use one).
    #[arg(long, default_value_t = 300)]
    reference_every_s: u64,
}

/// What the reader saw of one frame: its result and when it arrived.
type Seen = BTreeMap<u64, (crossview_api::pb::FrameResult, Instant)>;

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let rec = read_recording(&args.run.data)?;
    let names: Vec<String> = rec.scene.cameras.iter().map(|c| c.name.clone()).collect();
    let spec = ModelSpec::parse(&format!("{}={}", rec.scene.name, args.run.model.display()))?;
    let decl = SceneDecl {
        spec: rec.scene.clone(),
        fps: Some(args.rate),
    };
    let heal = HealConfig {
        after: Duration::from_secs(args.after_s),
        epochs: args.epochs,
        reference_every: Duration::from_secs(args.reference_every_s),
        ..HealConfig::new(&args.program, args.work.join("retrained"))
    };
    let record = RecordConfig::new(args.work.join("rec"));
    let server = crossview_testing::start_with(vec![spec], move |c: &mut ServeConfig| {
        c.scenes = vec![decl];
        c.limits.subscriber_buffer = 100_000;
        c.record = Some(record);
        c.heal = Some(heal);
    })
    .await;
    let mut results = server.subscribe(&rec.scene.name).await;
    let seen: Arc<Mutex<Seen>> = Arc::default();
    let seen2 = seen.clone();
    let reader = tokio::spawn(async move {
        while let Some(Ok(r)) = results.next().await {
            seen2
                .lock()
                .unwrap()
                .insert(r.frame_id, (r, Instant::now()));
        }
    });
    let http = reqwest::Client::new();
    let url = server.url(&format!("/v1/scenes/{}/batches", rec.scene.name));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let period = Duration::from_secs_f64(1.0 / args.rate.max(0.1));
    let start = Instant::now();
    let mut pushed: BTreeMap<u64, Instant> = BTreeMap::new();
    // Per frame pushed: whether a retrain was running then.
    let mut retraining: BTreeMap<u64, bool> = BTreeMap::new();
    let mut refused = 0usize;
    for (k, frame) in rec.frames.iter().enumerate() {
        tokio::time::sleep_until((start + period * k as u32).into()).await;
        refused += push_frame(&http, &url, &names, frame, &mut rng, None)
            .await?
            .len();
        pushed.insert(frame.frame_id, Instant::now());
        if k % 10 == 0 {
            let d = server
                .get_json(&format!("/v1/scenes/{}", rec.scene.name))
                .await;
            let state = d["retrain"]["state"].as_str().unwrap_or("").to_string();
            retraining.insert(frame.frame_id, state == "training" || state == "gating");
            if k % 600 == 0 {
                eprintln!(
                    "{:.0}s frame {} retrain {}",
                    start.elapsed().as_secs_f64(),
                    frame.frame_id,
                    d["retrain"]
                );
            }
        }
    }
    let last = rec.frames.last().map_or(0, |f| f.frame_id);
    tokio::time::timeout(Duration::from_secs(60), async {
        while !seen.lock().unwrap().contains_key(&last) {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
    .context("the last result never came")?;
    reader.abort();
    let status = server
        .get_json(&format!("/v1/scenes/{}", rec.scene.name))
        .await["retrain"]
        .clone();
    let report = {
        let seen = seen.lock().unwrap();
        score(&args, &rec, &names, &seen, &pushed, &retraining, refused)?
    };
    println!(
        "{}",
        serde_json::json!({"report": report, "retrain": status})
    );
    server
        .shutdown()
        .await
        .map_err(|e| anyhow::anyhow!("shutdown: {e:?}"))?;
    Ok(())
}

/// The JSON report of one run.
fn score(
    args: &Args,
    rec: &crossview_data::Recording,
    names: &[String],
    seen: &Seen,
    pushed: &BTreeMap<u64, Instant>,
    retraining: &BTreeMap<u64, bool>,
    refused: usize,
) -> anyhow::Result<serde_json::Value> {
    let (moved, moved_at) = (rec.scene.camera_index(&args.run.camera)?, args.run.moved_at);
    let first_version = seen.values().next().map(|(r, _)| r.model_version.clone());
    let swapped_at = seen
        .values()
        .find(|(r, _)| Some(&r.model_version) != first_version.as_ref())
        .map(|(r, _)| r.frame_id);
    let fenced_from = seen
        .values()
        .find(|(r, _)| r.fenced_cameras.contains(&args.run.camera))
        .map(|(r, _)| r.frame_id);
    let (mut before, mut between, mut after) = (Vec::new(), Vec::new(), Vec::new());
    let (mut idle_lat, mut busy_lat) = (Vec::new(), Vec::new());
    let mut partial = 0usize;
    let mut running = false;
    // A false detection (no id) is a person of its own: a link to it is wrong.
    let mut truth_ids = TruthIds::new();
    for frame in &rec.frames {
        let Some((r, at)) = seen.get(&frame.frame_id) else {
            partial += 1;
            continue;
        };
        partial += usize::from(
            !r.complete || r.status != crossview_api::pb::ResultStatus::Associated as i32,
        );
        running = retraining.get(&frame.frame_id).copied().unwrap_or(running);
        let latency = pushed[&frame.frame_id].elapsed().as_secs_f64() - at.elapsed().as_secs_f64();
        if frame.frame_id < moved_at {
            idle_lat.push(latency * 1000.0);
        } else if running {
            busy_lat.push(latency * 1000.0);
        }
        let truth = truth_ids.of_frame(frame);
        let all: Vec<Identity> = r.identities.iter().map(identity_from_pb).collect();
        let records = pair_records(frame.frame_id, names, &truth, &all)?;
        if frame.frame_id < moved_at {
            before.extend(records);
        } else if swapped_at.is_none_or(|s| frame.frame_id < s) {
            between.extend(records);
        } else {
            after.extend(records);
        }
    }
    let metrics = |r: &[_]| {
        let m = compute_metrics(r);
        serde_json::json!({"acc": m.acc, "ipaa_100": m.ipaa_100, "pairs": r.len()})
    };
    let pct = |v: &mut Vec<f64>, q: f64| {
        v.sort_by(f64::total_cmp);
        v.get(((v.len() as f64 - 1.0) * q).round().max(0.0) as usize)
            .copied()
    };
    let seconds = |f: Option<u64>| f.map(|f| (f.saturating_sub(moved_at)) as f64 / args.rate);
    Ok(serde_json::json!({
        "moved": moved, "moved_at": moved_at,
        "fenced_after_s": seconds(fenced_from), "swapped_after_s": seconds(swapped_at),
        "before_move": metrics(&before), "moved_before_swap": metrics(&between),
        "after_swap": metrics(&after),
        "batches_refused": refused, "frames_not_complete": partial,
        "latency_ms_idle": {"p50": pct(&mut idle_lat, 0.5), "p99": pct(&mut idle_lat, 0.99), "n": idle_lat.len()},
        "latency_ms_retraining": {"p50": pct(&mut busy_lat, 0.5), "p99": pct(&mut busy_lat, 0.99), "n": busy_lat.len()},
    }))
}

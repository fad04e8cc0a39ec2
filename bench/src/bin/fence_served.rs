//! What a client of the real server receives when one camera moves: the other cameras'
//! identities (SPEC §5 pairwise ACC / IPAA-100, scored as `crossview eval` scores them, the
//! moved camera left out of the score) over a recording in which it moves, with the fence on or
//! off, or with the camera silent. The real server in-process on 127.0.0.1:0, batches pushed
//! over HTTP camera by camera in shuffled order, results read over gRPC.
//!
//! Usage: fence_served --model M.onnx --data REC.jsonl --camera CVLab2 --moved-at FRAME_ID
//!        [--fence true|false] [--silent] [--rate FRAMES_PER_S] [--watch-interval-ms 1000]
//! Prints one JSON line: the other cameras' scores over the frames before the move, after it,
//! and after the first fenced result; every camera's after the move; the frame the fence came
//! up.
use std::collections::BTreeMap;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use crossview::demo::score::pair_records;
use crossview_api::convert::identity_from_pb;
use crossview_api::pb;
use crossview_bench::{MovedCamera, push_frame};
use crossview_core::identity::Identity;
use crossview_data::read_recording;
use crossview_eval::compute_metrics;
use crossview_eval::driver::frame_ids;
use crossview_serve::{ModelSpec, ServeConfig};
use futures::StreamExt;
use rand::SeedableRng;

/// What a client of the real server receives when one camera moves (see the file's header).
#[derive(Parser)]
struct Args {
    /// The model, the recording and the camera that moves (left out of the score).
    #[command(flatten)]
    run: MovedCamera,
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    fence: bool,
    /// Send the camera's batches empty (the reference: the camera silent).
    #[arg(long)]
    silent: bool,
    /// Frames pushed per second (the watch's interval should scale with it).
    #[arg(long, default_value_t = 20.0)]
    rate: f64,
    /// The clock watch's interval, milliseconds.
    #[arg(long, default_value_t = 1000)]
    watch_interval_ms: u64,
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let MovedCamera {
        model,
        data,
        camera,
        moved_at,
    } = &args.run;
    let rec = read_recording(data)?;
    let names: Vec<String> = rec.scene.cameras.iter().map(|c| c.name.clone()).collect();
    let moved = rec.scene.camera_index(camera)?;
    let spec = ModelSpec::parse(&format!("{}={}", rec.scene.name, model.display()))?;
    let (fence, interval) = (args.fence, Duration::from_millis(args.watch_interval_ms));
    let server = crossview_testing::start_with(vec![spec], move |c: &mut ServeConfig| {
        c.sync_timeout = Duration::from_secs(5);
        c.limits.subscriber_buffer = 100_000;
        c.limits.clock_watch.interval = interval;
        c.limits.clock_watch.fence = fence;
    })
    .await;
    let mut results = server.subscribe(&rec.scene.name).await;
    let http = reqwest::Client::new();
    let url = server.url(&format!("/v1/scenes/{}/batches", rec.scene.name));
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let pace = Duration::from_secs_f64(1.0 / args.rate.max(0.1));
    let silent = args.silent.then_some(moved);
    for frame in &rec.frames {
        let refused = push_frame(&http, &url, &names, frame, &mut rng, silent).await?;
        anyhow::ensure!(refused.is_empty(), "refused: {refused:?}");
        tokio::time::sleep(pace).await;
    }
    let mut got: BTreeMap<u64, pb::FrameResult> = BTreeMap::new();
    while got.len() < rec.frames.len() {
        let r = tokio::time::timeout(Duration::from_secs(30), results.next())
            .await
            .context("results stopped")?
            .context("result stream ended")??;
        got.insert(r.frame_id, r);
    }
    let fenced_from = got
        .values()
        .find(|r| r.fenced_cameras.contains(camera))
        .map(|r| r.frame_id);
    let (mut before, mut after, mut fenced) = (Vec::new(), Vec::new(), Vec::new());
    // Every camera's pairs, the moved one's included, after the move (what the whole scene's
    // identities are worth).
    let mut whole = Vec::new();
    for frame in &rec.frames {
        let r = &got[&frame.frame_id];
        let mut truth = frame_ids(&rec.scene, frame)?;
        if frame.frame_id >= *moved_at {
            let all: Vec<Identity> = r.identities.iter().map(identity_from_pb).collect();
            whole.extend(pair_records(frame.frame_id, &names, &truth, &all)?);
        }
        truth[moved] = None;
        // The other cameras' identities: the moved camera's members taken out.
        let served: Vec<Identity> = r
            .identities
            .iter()
            .map(identity_from_pb)
            .filter_map(|mut i| {
                i.members.retain(|&(c, _)| c != moved);
                (!i.members.is_empty()).then_some(i)
            })
            .collect();
        let records = pair_records(frame.frame_id, &names, &truth, &served)?;
        if frame.frame_id < *moved_at {
            before.extend(records);
        } else {
            if fenced_from.is_some_and(|f| frame.frame_id >= f) {
                fenced.extend(records.iter().cloned());
            }
            after.extend(records);
        }
    }
    let score = |r: &[_]| {
        let m = compute_metrics(r);
        serde_json::json!({"acc": m.acc, "precision": m.precision, "recall": m.recall, "ipaa_100": m.ipaa_100, "pairs": r.len()})
    };
    println!(
        "{}",
        serde_json::json!({
            "fence": args.fence, "silent": args.silent, "fenced_from": fenced_from,
            "before_move": score(&before), "after_move": score(&after),
            "after_fence": score(&fenced), "all_cameras_after_move": score(&whole),
        })
    );
    server
        .shutdown()
        .await
        .map_err(|e| anyhow::anyhow!("shutdown: {e:?}"))?;
    Ok(())
}

//! Camera clock offsets, end to end: a camera whose frame ids run late is measured by the
//! server's live clock watch (scene description over HTTP and gRPC, metric) and, once its
//! offset is declared (`CAMERA:WxH@+N`), its batches are grouped with the frames they belong
//! to and the identities a client receives are right again. Real server on 127.0.0.1:0, the
//! shipped `models/demo.onnx`, simulated `square4` frames with the ground truth kept in the
//! client, cameras of one frame pushed in a shuffled order.
use std::collections::HashMap;
use std::time::Duration;

use crossview::demo::pair_records;
use crossview_api::convert::identity_from_pb;
use crossview_api::pb;
use crossview_core::{Batch, SceneSpec};
use crossview_data::sim::{SimConfig, Simulator};
use crossview_eval::compute_metrics;
use crossview_serve::RecordConfig;
use crossview_serve::ServeConfig;
use crossview_serve::config::ClockWatchConfig;
use crossview_serve::config::SceneDecl;
use crossview_testing::*;
use futures::StreamExt;
use rand::SeedableRng;
use rand::seq::SliceRandom;

const FRAMES: u64 = 300;
/// Frames the lagging camera runs late (1 s at the simulator's 10 fps).
const LAG: u64 = 10;
const LAGGING: usize = 2;

fn configure(c: &mut ServeConfig, declared: Option<SceneSpec>) {
    c.sync_timeout = Duration::from_millis(300);
    // The results are read after the push (a long auto-align stream stays within it).
    c.limits.subscriber_buffer = 20_000;
    c.limits.clock_watch = ClockWatchConfig {
        window: 250,
        interval: Duration::ZERO,
        max_offset: 12,
        auto_align: false,
        fence: true,
    };
    c.scenes = declared
        .into_iter()
        .map(|spec| SceneDecl { spec, fps: None })
        .collect();
}

/// What the client sent: per camera and frame id, the ground-truth id of each box.
/// (`None`: a false detection, the same person as nobody.)
type Sent = HashMap<(usize, u64), Vec<Option<u64>>>;

/// What one run pushed and received.
struct Run {
    sent: Sent,
    /// Per camera and frame id, the boxes the client sent.
    boxes: HashMap<(usize, u64), Vec<[f32; 4]>>,
    results: Vec<pb::FrameResult>,
    /// Batches refused (late or duplicate ones while `--auto-align` moves a camera).
    refused: usize,
    /// The first frame pushed after the scene said camera `LAGGING`'s offset had changed
    /// (checked every 25 frames).
    changed_at: Option<u64>,
}

/// Pushes simulated `frames` over HTTP, camera `LAGGING`'s ids `lag(frame)` late, the cameras
/// of each frame in a shuffled order; collects the results over gRPC.
async fn run(server: &TestServer, frames: std::ops::Range<u64>, lag: impl Fn(u64) -> u64) -> Run {
    run_until(server, frames, lag, None).await
}

/// [`run`], stopping `after_change` frames after camera `LAGGING`'s offset changed (if given).
async fn run_until(
    server: &TestServer,
    frames: std::ops::Range<u64>,
    lag: impl Fn(u64) -> u64,
    after_change: Option<u64>,
) -> Run {
    let mut results = server.subscribe("demo").await;
    let mut cfg = SimConfig::preset("square4").unwrap();
    cfg.frames = frames.end;
    cfg.seed = 21;
    let mut sim = Simulator::new(&cfg).unwrap();
    let names: Vec<String> = sim.scene().cameras.iter().map(|c| c.name.clone()).collect();
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/demo/batches");
    let mut rng = rand::rngs::StdRng::seed_from_u64(5);
    let mut sent = Sent::new();
    let mut boxes = HashMap::new();
    let mut refused = 0;
    let mut changed_at = None;
    let mut end = frames.end;
    while let Some(frame) = sim.next_frame() {
        if frame.frame_id < frames.start {
            continue;
        }
        if let (Some(c), Some(n)) = (changed_at, after_change)
            && frame.frame_id >= c + n
        {
            end = frame.frame_id;
            break;
        }
        if changed_at.is_none() && frame.frame_id % 25 == 0 {
            let d = server.get_json("/v1/scenes/demo").await;
            if d["cameras"][LAGGING]["offset"].as_i64().unwrap_or(0) != 0 {
                changed_at = Some(frame.frame_id);
            }
        }
        let mut order: Vec<usize> = (0..names.len()).collect();
        order.shuffle(&mut rng);
        for c in order {
            let mut dets = frame.views[c].clone().unwrap_or_default();
            let frame_id = frame.frame_id + if c == LAGGING { lag(frame.frame_id) } else { 0 };
            sent.insert((c, frame_id), dets.iter().map(|d| d.id).collect());
            boxes.insert((c, frame_id), dets.iter().map(|d| d.bbox).collect());
            dets.iter_mut().for_each(|d| d.id = None);
            let batch = Batch {
                camera: names[c].clone(),
                frame_id,
                time: None,
                detections: dets,
            };
            let r = http.post(&url).json(&batch).send().await.unwrap();
            if r.status() != 202 {
                let body = r.text().await.unwrap();
                // The moved camera's batches for frames already published (late) or already
                // holding its batch under the old offset (duplicate).
                assert!(
                    body.contains("\"late\"") || body.contains("\"duplicate\""),
                    "{body}"
                );
                refused += 1;
            }
        }
    }
    // Every frame id the cameras sent comes out (the last ones partial, after the timeout).
    let mut got = Vec::new();
    while let Some(r) = guard("result", results.next()).await {
        let r = r.unwrap();
        let last = r.frame_id;
        got.push(r);
        if last + 1 >= end {
            break;
        }
    }
    Run {
        sent,
        boxes,
        results: got,
        refused,
        changed_at,
    }
}

/// SPEC §5 pairwise ACC and IPAA-100 of the identities in `results` (scored as `crossview
/// eval` scores them), against the ground truth the client kept; `offset[c]` maps a result's
/// frame to camera `c`'s id. A false detection is a person of its own.
fn score(sent: &Sent, results: &[pb::FrameResult], offset: &[u64]) -> (f64, f64) {
    let names: Vec<String> = (0..offset.len()).map(|c| format!("cam{c}")).collect();
    let mut unlabelled = 1u64 << 62;
    let mut records = Vec::new();
    for r in results {
        let truth: Vec<Option<Vec<u64>>> = (0..offset.len())
            .map(|c| {
                if r.missing_cameras.contains(&names[c]) {
                    return None;
                }
                let ids = sent.get(&(c, r.frame_id + offset[c]))?;
                Some(
                    ids.iter()
                        .map(|id| {
                            id.unwrap_or_else(|| {
                                unlabelled += 1;
                                unlabelled
                            })
                        })
                        .collect(),
                )
            })
            .collect();
        let served: Vec<_> = r.identities.iter().map(identity_from_pb).collect();
        records.extend(pair_records(r.frame_id, &names, &truth, &served).unwrap());
    }
    let m = compute_metrics(&records);
    (m.acc, m.ipaa_100)
}

/// Waits for the live estimate of the frames before `end` and returns the scene description
/// (HTTP JSON).
async fn clock_of(server: &TestServer, end: u64) -> serde_json::Value {
    guard("clock estimate", async {
        loop {
            let d = server.get_json("/v1/scenes/demo").await;
            if d["clock"]["as_of_frame"]
                .as_u64()
                .is_some_and(|f| f + 10 >= end)
            {
                return d;
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    })
    .await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_late_camera_is_measured_live_and_corrected_by_its_declared_offset() {
    // Undeclared: the watch finds the lag.
    let server = start_with(demo_model(), |c| configure(c, None)).await;
    let lagged = run(&server, 0..FRAMES, |_| LAG).await;
    assert_eq!(lagged.refused, 0);
    let lagged_acc = score(&lagged.sent, &lagged.results, &[0; 4]);
    let d = clock_of(&server, FRAMES).await;
    let cams = d["clock"]["cameras"].as_array().unwrap();
    for (c, cam) in cams.iter().enumerate() {
        let want = if c == LAGGING { LAG as i64 } else { 0 };
        assert_eq!(cam["offset_ids"].as_i64(), Some(want), "{d}");
        assert!(cam["confidence"].as_f64().unwrap() > 0.0, "{d}");
    }
    let frames = cams[LAGGING]["offset_frames"].as_f64().unwrap();
    assert!((frames - LAG as f64).abs() < 0.5, "{d}");
    // The same over gRPC and in the metrics.
    let scene = server.scene("demo").await;
    let clock = scene.clock.expect("clock estimate over gRPC");
    assert!(clock.cameras[LAGGING].known);
    assert_eq!(clock.cameras[LAGGING].offset_ids, LAG as i64);
    let m = server.metrics().await;
    let gauge = metric(
        &m,
        "crossview_camera_offset_frames{scene=\"demo\",camera=\"cam2\"}",
    );
    assert!((gauge - LAG as f64).abs() < 0.5, "{gauge}");
    assert!(metric(&m, "crossview_clock_estimate_seconds_count{scene=\"demo\"}") >= 1.0);
    server.shutdown().await.unwrap();

    // Declared `cam2:1280x720@+10`: grouped right, the watch sees it in sync, identities better.
    let mut spec = Simulator::new(&SimConfig::preset("square4").unwrap())
        .unwrap()
        .scene()
        .clone();
    spec.name = "demo".into();
    spec.cameras[LAGGING].offset = LAG as i64;
    let server = start_with(demo_model(), |c| configure(c, Some(spec))).await;
    let declared = run(&server, 0..FRAMES, |_| LAG).await;
    assert_eq!(declared.refused, 0);
    let complete = declared.results.iter().filter(|r| r.complete).count() as u64;
    assert!(complete + 1 >= FRAMES - LAG, "{complete} complete frames");
    let mut offsets = [0; 4];
    offsets[LAGGING] = LAG;
    let declared_acc = score(&declared.sent, &declared.results, &offsets);
    let d = clock_of(&server, FRAMES).await;
    for cam in d["clock"]["cameras"].as_array().unwrap() {
        assert_eq!(cam["offset_ids"].as_i64(), Some(0), "{d}");
    }
    assert_eq!(d["cameras"][LAGGING]["offset"], LAG, "{d}");
    server.shutdown().await.unwrap();

    // The same frames in sync: what the corrected stream should score.
    let server = start_with(demo_model(), |c| configure(c, None)).await;
    let in_sync = run(&server, 0..FRAMES, |_| 0).await;
    server.shutdown().await.unwrap();
    let sync_acc = score(&in_sync.sent, &in_sync.results, &[0; 4]);
    eprintln!(
        "served ACC / IPAA-100: in sync {:.2} / {:.2}, 1 s late {:.2} / {:.2}, declared @+{LAG} {:.2} / {:.2}",
        100.0 * sync_acc.0,
        100.0 * sync_acc.1,
        100.0 * lagged_acc.0,
        100.0 * lagged_acc.1,
        100.0 * declared_acc.0,
        100.0 * declared_acc.1
    );
    assert!(lagged_acc.0 < sync_acc.0 - 0.05, "the lag costs");
    assert!(
        (declared_acc.0 - sync_acc.0).abs() <= 0.01,
        "within 1 point"
    );
}

/// A camera whose lag grows mid-stream (in sync, then 4 frames late): the live estimate
/// says 0 during the first half and follows the camera to 4 once the window holds the new lag.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_live_estimate_follows_a_drifting_camera() {
    let server = start_with(demo_model(), |c| {
        configure(c, None);
    })
    .await;
    let half = 260;
    run(&server, 0..half, |_| 0).await;
    let d = clock_of(&server, half).await;
    for cam in d["clock"]["cameras"].as_array().unwrap() {
        assert_eq!(cam["offset_ids"].as_i64(), Some(0), "{d}");
    }
    run(&server, half..2 * half, |_| 4).await;
    let d = clock_of(&server, 2 * half).await;
    let cams = d["clock"]["cameras"].as_array().unwrap();
    assert_eq!(cams[LAGGING]["offset_ids"].as_i64(), Some(4), "{d}");
    server.shutdown().await.unwrap();
}

/// An ensemble model: the watch keeps only its first member's block of the embedding (one
/// encoder's memory, whatever the ensemble's width) and still finds a camera 1 s late. The
/// ensemble is `models/demo.onnx` followed by an untrained member, which only widens it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_ensemble_is_watched_by_its_leading_member() {
    use crossview_core::Encoder;
    let dir = tempfile::tempdir().unwrap();
    let path = demo_with_untrained_member(dir.path(), "wide");
    let onnx = crossview_model::OnnxEncoder::load(&path).unwrap();
    assert_eq!(2 * onnx.leading_width(), onnx.dim());
    let spec = crossview_serve::ModelSpec::parse(&format!("demo={}", path.display())).unwrap();
    let server = start_with(vec![spec], |c| configure(c, None)).await;
    run(&server, 0..FRAMES, |_| LAG).await;
    let d = clock_of(&server, FRAMES).await;
    let cams = d["clock"]["cameras"].as_array().unwrap();
    for (c, cam) in cams.iter().enumerate() {
        let want = if c == LAGGING { LAG as i64 } else { 0 };
        assert_eq!(cam["offset_ids"].as_i64(), Some(want), "{d}");
    }
    server.shutdown().await.unwrap();
}

/// `--auto-align`: a camera 1 s late, undeclared, is corrected mid-stream once two estimates
/// over full windows agree (one change, logged and counted); its batches for frames already
/// published are refused as late while it catches up, and the identities after the change
/// score like those of a declared offset.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn auto_align_corrects_a_late_camera_once() {
    let record = tempfile::tempdir().unwrap();
    let server = start_with(demo_model(), |c| {
        configure(c, None);
        c.limits.clock_watch.auto_align = true;
        c.record = Some(RecordConfig::new(record.path()));
    })
    .await;
    // Streams until 200 frames after the change (at most 10,000 frames).
    let stream = run_until(&server, 0..10_000, |_| LAG, Some(200)).await;
    let changed = stream.changed_at.expect("no auto-align change");
    assert!(
        stream.refused <= LAG as usize + 2,
        "{} refused",
        stream.refused
    );
    // Frames after the change: cam2's batch `k + LAG` is grouped into frame `k`.
    let mut offsets = [0; 4];
    offsets[LAGGING] = LAG;
    let tail: Vec<_> = stream
        .results
        .into_iter()
        .filter(|r| r.frame_id >= changed + LAG)
        .collect();
    let aligned = score(&stream.sent, &tail, &offsets);
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_clock_alignments_total{scene=\"demo\",camera=\"cam2\"}"
        ),
        1.0
    );
    server.shutdown().await.unwrap();
    recording_groups_as_served(record.path(), &stream.boxes, changed);
    // The same frames in sync.
    let server = start_with(demo_model(), |c| configure(c, None)).await;
    let end = tail.last().map_or(0, |r| r.frame_id + 1);
    let in_sync = run(&server, 0..end, |_| 0).await;
    server.shutdown().await.unwrap();
    let sync_tail: Vec<_> = in_sync
        .results
        .into_iter()
        .filter(|r| r.frame_id >= changed + LAG)
        .collect();
    let sync_acc = score(&in_sync.sent, &sync_tail, &[0; 4]);
    eprintln!(
        "auto-align at frame {changed}, {} batches refused; served ACC / IPAA-100 after it: \
         {:.2} / {:.2} (in sync: {:.2} / {:.2})",
        stream.refused,
        100.0 * aligned.0,
        100.0 * aligned.1,
        100.0 * sync_acc.0,
        100.0 * sync_acc.1
    );
    assert!((aligned.0 - sync_acc.0).abs() <= 0.01, "within 1 point");
}

/// The recording of an auto-aligned stream reads back grouped as the server grouped it: a new
/// file began with camera `LAGGING`'s new offset, so its batch `k + LAG` is in frame `k` once
/// the change is well past (before it, `k`), and every other camera's batch `k` in frame `k`.
fn recording_groups_as_served(
    dir: &std::path::Path,
    boxes: &HashMap<(usize, u64), Vec<[f32; 4]>>,
    changed: u64,
) {
    let files = crossview_data::recording_files(&[dir.join("demo")]).unwrap();
    assert!(files.len() >= 2, "a new file at the change: {files:?}");
    let last = crossview_data::RecordingReader::open(files.last().unwrap()).unwrap();
    assert_eq!(last.scene().cameras[LAGGING].offset, LAG as i64);
    let rec = crossview_data::read_recording(dir.join("demo")).unwrap();
    let (mut before, mut after) = (0, 0);
    for f in &rec.frames {
        for (c, view) in f.views.iter().enumerate() {
            let Some(view) = view else { continue };
            let got: Vec<[f32; 4]> = view.iter().map(|d| d.bbox).collect();
            let sent_at = |o: u64| boxes.get(&(c, f.frame_id + o));
            let lag = if c != LAGGING {
                0
            } else if f.frame_id + 25 < changed {
                before += 1;
                0
            } else if f.frame_id >= changed + LAG {
                after += 1;
                LAG
            } else {
                // Around the change: either grouping, as the server applied it then.
                assert!(
                    [0, LAG].iter().any(|&o| sent_at(o) == Some(&got)),
                    "frame {}",
                    f.frame_id
                );
                continue;
            };
            assert_eq!(sent_at(lag), Some(&got), "camera {c}, frame {}", f.frame_id);
        }
    }
    assert!(
        before > 0 && after > 100,
        "{before} before, {after} after the change"
    );
}

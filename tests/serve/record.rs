//! `--record DIR`: every accepted batch, pushed over gRPC or HTTP, is in the recording exactly
//! once and rejected ones are not; files rotate by size, each a valid recording with its
//! header; the total-size bound removes the oldest files; a full queue drops (counted) instead
//! of holding anything up; start-up cuts the torn tail a crash left. Files are read back with
//! `crossview_data`'s reader.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::time::Duration;

use crossview_data::{read_recording, read_recordings};
use crossview_serve::RecordConfig;
use crossview_testing::*;
use futures::StreamExt;

/// The recording files of scene `lab` under `dir`, in name order.
fn files(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir.join("lab"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "jsonl"))
        .collect();
    v.sort();
    v
}

/// The (camera, frame id) of every batch of a recording, asserting none appears twice.
fn batches_of(rec: &crossview_data::Recording) -> BTreeSet<(String, u64)> {
    let mut seen = BTreeSet::new();
    for b in rec.batches() {
        assert!(
            seen.insert((b.camera.clone(), b.frame_id)),
            "twice: {} {}",
            b.camera,
            b.frame_id
        );
    }
    seen
}

/// Waits until the server says `n` batches of `lab` reached the recording files.
async fn wait_recorded(server: &TestServer, n: f64) {
    guard("recorded batches", async {
        loop {
            let m = server.metrics().await;
            if metric(&m, "crossview_record_batches_total{scene=\"lab\"}") >= n {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
}

/// Pushes frames `frames` of all three cameras over one gRPC `Push` stream; asserts each is
/// accepted.
async fn push_grpc(server: &TestServer, frames: std::ops::RangeInclusive<u64>, n: usize) {
    let mut client = server.grpc().await;
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut acks = client
        .push(tokio_stream::wrappers::ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    for f in frames {
        for c in 0..3 {
            tx.send(batch(c, f, n)).await.unwrap();
            let ack = guard("ack", acks.next()).await.unwrap().unwrap();
            assert_eq!(ack.code, 0, "{ack:?}");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_accepted_batch_is_recorded_once_and_rejected_ones_are_not() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        c.sync_timeout = Duration::from_secs(600);
        c.record = Some(RecordConfig::new(&dir));
    })
    .await;
    let mut expected = BTreeSet::new();
    // gRPC: frames 1..=10, complete, so emitted.
    push_grpc(&server, 1..=10, 2).await;
    for f in 1..=10 {
        for c in CAMERAS {
            expected.insert((c.to_string(), f));
        }
    }
    // HTTP, one batch per request: frames 11 and 12.
    let http = reqwest::Client::new();
    let url = server.url("/v1/scenes/lab/batches");
    let post = async |body: serde_json::Value| http.post(&url).json(&body).send().await.unwrap();
    for f in 11..=12 {
        for (c, name) in CAMERAS.iter().enumerate() {
            assert_eq!(post(batch_json(c, f, 3)).await.status(), 202);
            expected.insert((name.to_string(), f));
        }
    }
    // Rejected: late, duplicate, invalid box, unknown camera.
    assert_eq!(post(batch_json(1, 3, 1)).await.status(), 409, "late");
    assert_eq!(post(batch_json(0, 40, 1)).await.status(), 202);
    expected.insert(("c0".to_string(), 40));
    assert_eq!(post(batch_json(0, 40, 2)).await.status(), 409, "duplicate");
    let inverted = serde_json::json!({"camera": "c1", "frame_id": 41, "detections": [{"bbox": [50, 10, 40, 90]}]});
    assert_eq!(post(inverted).await.status(), 422);
    let unknown = serde_json::json!({"camera": "zz", "frame_id": 41, "detections": []});
    assert_eq!(post(unknown).await.status(), 404);
    // HTTP JSON Lines: frames 13..=14, with a late and a duplicate line among them.
    let mut lines = Vec::new();
    for f in 13..=14 {
        for (c, name) in CAMERAS.iter().enumerate() {
            lines.push(batch_json(c, f, 1).to_string());
            expected.insert((name.to_string(), f));
        }
    }
    lines.push(batch_json(2, 2, 1).to_string()); // late
    lines.push(batch_json(0, 40, 1).to_string()); // duplicate
    let r: serde_json::Value = http
        .post(&url)
        .header("content-type", "application/x-ndjson")
        .body(lines.join("\n"))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(
        (r["accepted"].as_u64(), r["rejected"].as_u64()),
        (Some(6), Some(2)),
        "{r}"
    );

    let n = expected.len() as f64;
    wait_recorded(&server, n).await;
    let m = server.metrics().await;
    assert_eq!(metric(&m, "crossview_batches_total{scene=\"lab\"}"), n);
    assert!(metric(&m, "crossview_record_bytes_total{scene=\"lab\"}") > 0.0);
    assert_eq!(metric(&m, "crossview_record_dropped_total"), 0.0, "{m}");
    server.shutdown().await.unwrap();

    let (rec, stats) = read_recordings(&[&dir], true).unwrap();
    assert_eq!(stats.torn_lines, 0);
    assert_eq!(rec.scene.name, "lab");
    assert_eq!(rec.scene.cameras, cameras());
    assert_eq!(batches_of(&rec), expected);
    // The kept duplicate is the first batch (one box), recorded as accepted.
    let f40 = rec.frames.iter().find(|f| f.frame_id == 40).unwrap();
    assert_eq!(f40.views[0].as_ref().unwrap().len(), 1);
    // Boxes as pushed.
    let f12 = rec.frames.iter().find(|f| f.frame_id == 12).unwrap();
    let b = dets(1, 12, 3)[2].bbox.unwrap();
    assert_eq!(
        f12.views[1].as_ref().unwrap()[2].bbox,
        [b.x1, b.y1, b.x2, b.y2]
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn files_rotate_by_size_each_with_its_header() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        c.record = Some(RecordConfig {
            max_file_bytes: 3000,
            ..RecordConfig::new(&dir)
        });
    })
    .await;
    push_grpc(&server, 1..=30, 2).await;
    wait_recorded(&server, 90.0).await;
    server.shutdown().await.unwrap();

    let files = files(&dir);
    assert!(files.len() >= 3, "{files:?}");
    let mut total = 0;
    let mut split_frames = 0;
    let mut last_frames: BTreeSet<u64> = BTreeSet::new();
    for f in &files {
        assert!(std::fs::metadata(f).unwrap().len() <= 3000, "{f:?}");
        let text = std::fs::read_to_string(f).unwrap();
        assert!(text.starts_with("{\"scene\":"), "{f:?}");
        // Each file is a recording on its own.
        let part = read_recording(f).unwrap();
        assert_eq!(part.scene.name, "lab");
        total += part.batches().count();
        let frames: BTreeSet<u64> = part.frame_ids().into_iter().collect();
        split_frames += frames.intersection(&last_frames).count();
        last_frames = frames;
    }
    assert_eq!(total, 90);
    // Read as one: every frame whole, also those split across a rotation.
    let (rec, _) = read_recordings(&[&dir], true).unwrap();
    assert_eq!(rec.frame_ids(), (1..=30).collect::<Vec<_>>());
    assert!(
        rec.frames
            .iter()
            .all(|f| f.views.iter().all(Option::is_some))
    );
    eprintln!(
        "{} files, {split_frames} frames split across a rotation",
        files.len()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_total_size_bound_removes_the_oldest_files() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        c.record = Some(RecordConfig {
            max_file_bytes: 2000,
            max_bytes: 6000,
            ..RecordConfig::new(&dir)
        });
    })
    .await;
    push_grpc(&server, 1..=60, 2).await;
    wait_recorded(&server, 180.0).await;
    let m = server.metrics().await;
    assert!(
        metric(&m, "crossview_record_files_removed_total") > 0.0,
        "{m}"
    );
    assert!(metric(&m, "crossview_record_disk_bytes") <= 6000.0, "{m}");
    server.shutdown().await.unwrap();

    let files = files(&dir);
    let sizes: u64 = files
        .iter()
        .map(|f| std::fs::metadata(f).unwrap().len())
        .sum();
    assert!(sizes <= 6000, "{sizes}");
    // What is left is the newest files: consecutive sequence numbers, the last frames.
    let seqs: Vec<u64> = files
        .iter()
        .map(|f| {
            f.file_name().unwrap().to_str().unwrap()[..10]
                .parse()
                .unwrap()
        })
        .collect();
    assert!(seqs[0] > 1, "{seqs:?}");
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1), "{seqs:?}");
    let (rec, _) = read_recordings(&[&dir], true).unwrap();
    let ids = rec.frame_ids();
    assert_eq!(*ids.last().unwrap(), 60);
    assert!(ids[0] > 1, "{ids:?}");
    // Contiguous: only whole old files went.
    assert_eq!(ids, (ids[0]..=60).collect::<Vec<_>>());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_drops_and_counts_without_holding_up_association() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        c.record = Some(RecordConfig {
            queue_bytes: 1,
            ..RecordConfig::new(&dir)
        });
    })
    .await;
    let mut client = server.grpc().await;
    let mut results = client
        .subscribe(crossview_api::pb::SubscribeRequest {
            scene: "lab".into(),
        })
        .await
        .unwrap()
        .into_inner();
    push_grpc(&server, 1..=5, 1).await;
    for f in 1..=5 {
        let r = guard("result", results.next()).await.unwrap().unwrap();
        assert_eq!((r.frame_id, r.complete), (f, true));
    }
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_record_dropped_total{scene=\"lab\",reason=\"queue_full\"}"
        ),
        15.0,
        "{m}"
    );
    assert_eq!(metric(&m, "crossview_record_batches_total"), 0.0);
    server.shutdown().await.unwrap();
    // Nothing was written: no file was even started.
    assert!(files(&dir).is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn start_up_cuts_a_torn_tail_and_starts_a_new_file() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| c.record = Some(RecordConfig::new(&dir))).await;
    push_grpc(&server, 1..=3, 1).await;
    wait_recorded(&server, 9.0).await;
    server.shutdown().await.unwrap();
    let first = files(&dir);
    assert_eq!(first.len(), 1);
    // What a crash in the middle of a write leaves, and a file with only a torn header.
    let whole = std::fs::read(&first[0]).unwrap();
    let mut torn = whole.clone();
    torn.extend_from_slice(br#"{"camera": "c0", "frame_id": 4, "detec"#);
    std::fs::write(&first[0], &torn).unwrap();
    let headless = dir.join("lab/0000000002-20260101T000000Z.jsonl");
    std::fs::write(&headless, br#"{"scene": {"name": "la"#).unwrap();
    // Readers drop both, with a count.
    let (rec, stats) = read_recordings(&[&dir], true).unwrap();
    assert_eq!(stats.torn_lines, 2);
    assert_eq!(rec.frame_ids(), vec![1, 2, 3]);

    let server = start(|c| c.record = Some(RecordConfig::new(&dir))).await;
    assert_eq!(std::fs::read(&first[0]).unwrap(), whole, "torn tail cut");
    assert!(!headless.exists());
    push_grpc(&server, 4..=5, 1).await;
    wait_recorded(&server, 6.0).await;
    server.shutdown().await.unwrap();
    let now = files(&dir);
    assert_eq!(now.len(), 2, "{now:?}");
    assert!(
        now[1]
            .file_name()
            .unwrap()
            .to_str()
            .unwrap()
            .starts_with("0000000002-")
    );
    let (rec, stats) = read_recordings(&[&dir], true).unwrap();
    assert_eq!(stats.torn_lines, 0);
    assert_eq!(rec.frame_ids(), vec![1, 2, 3, 4, 5]);
}

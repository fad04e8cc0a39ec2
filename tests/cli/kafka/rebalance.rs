//! Replicas joining, dying (SIGKILL) and coming back, and a rolling restart (SIGTERM each in
//! turn), while camera batches stream in, each
//! frame's cameras spread over time (and stamped with their capture times), and while a
//! replica catches up a backlog; every replica with `--sync-timeout` [`SYNC_TIMEOUT`]. Asserted, by
//! reading the output and dead-letter topics from the beginning: every camera batch sent is in
//! a result of its frame; no result is partial (a rebalance in the middle of a frame neither
//! publishes the half it has nor rejects the rest as late); nothing is dead-lettered; the only
//! duplicates are frames published again after a takeover, each copy by another producer or
//! epoch.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use rdkafka::config::ClientConfig;
use rdkafka::consumer::{Consumer, StreamConsumer};
use rdkafka::producer::{FutureProducer, FutureRecord};

use super::*;

/// A sent camera batch: (scene, camera, frame).
pub(super) type Sent = (String, String, u64);

/// Scene `i` lives on partition `i` (sent to explicit partitions).
pub(super) fn scenes(n: usize) -> Vec<String> {
    (0..n).map(|i| format!("scene{i}")).collect()
}

/// Produces `line` of scene `i` to partition `i` of `topic`, stamped `ts` (ms).
pub(super) async fn send_scene(
    p: &FutureProducer,
    topic: &str,
    i: usize,
    scene: &str,
    line: &str,
    ts: i64,
) {
    let r = FutureRecord::to(topic)
        .partition(i as i32)
        .key(scene)
        .payload(line)
        .timestamp(ts);
    guard("produce", p.send(r, Duration::from_secs(20)))
        .await
        .unwrap();
}

/// Sends frames `from..to` of every scene: one camera at a time (all scenes at once), `gap`
/// after each camera, so a frame's cameras arrive over 4 × `gap`; each record stamped with
/// its camera's capture time by `capture`.
pub(super) async fn stream(
    p: &FutureProducer,
    topic: &str,
    lines: &[Line],
    scenes: &[String],
    frames: std::ops::Range<u64>,
    gap: Duration,
    capture: Capture,
) -> Vec<Sent> {
    let mut sent = Vec::new();
    for (cam, frame, line) in lines.iter().filter(|(_, f, _)| frames.contains(f)) {
        let ts = capture.stamp(cam, *frame);
        let sends = scenes
            .iter()
            .enumerate()
            .map(|(i, s)| send_scene(p, topic, i, s, line, ts));
        futures::future::join_all(sends).await;
        sent.extend(scenes.iter().map(|s| (s.clone(), cam.clone(), *frame)));
        if !gap.is_zero() {
            tokio::time::sleep(gap).await;
        }
    }
    sent
}

/// Streams frames `frames` of `scenes` live, in the background: each frame's 4 cameras 25 ms
/// apart, each batch stamped with its camera's capture time. The task returns what it sent.
pub(super) fn stream_live(
    s: &Setup,
    p: &Arc<FutureProducer>,
    scenes: &[String],
    frames: std::ops::Range<u64>,
) -> tokio::task::JoinHandle<Vec<Sent>> {
    let (p, topic, lines, scenes) = (
        p.clone(),
        s.topics.batches.clone(),
        s.lines.clone(),
        scenes.to_vec(),
    );
    let gap = Duration::from_millis(25);
    tokio::spawn(async move {
        stream(&p, &topic, &lines, &scenes, frames, gap, Capture::live(25)).await
    })
}

/// The replicas' `--sync-timeout` in these tests: 1 s. Stream time makes a rebalance, a pause
/// or a backlog cut no frame whatever the timeout (`bench/kafka_takeover.sh` measures the
/// 200 ms default), but a partition that is caught up and quiet that long by the wall clock
/// is an idle scene: on a loaded 2-core machine the tests' own producer can pause longer than
/// 200 ms in the middle of a frame.
pub(super) const SYNC_TIMEOUT: &str = "1s";

pub(super) fn replica_args(s: &Setup, scenes: &[String], id: &str) -> Vec<String> {
    let mut args = model_args(scenes);
    args.extend(kafka_args(s.broker, &s.topics, "replicas", id));
    args.extend(["--sync-timeout".into(), SYNC_TIMEOUT.into()]);
    args
}

/// Every batch of `sent` in a result, no partial result, duplicates only by another producer
/// or epoch, nothing dead-lettered. Returns how many frames were published more than once.
pub(super) async fn check_exact(results: &mut Results, sent: &[Sent], s: &Setup) -> usize {
    results.wait_cover(sent).await;
    results.read_for(Duration::from_secs(1)).await;
    let partial = results.partial();
    assert!(
        partial.is_empty(),
        "{} partial results, e.g. {}",
        partial.len(),
        partial[0]
    );
    let dups = results.duplicates();
    for (frame, copies) in &dups {
        let distinct: BTreeSet<&(String, u64)> = copies.iter().collect();
        assert_eq!(
            distinct.len(),
            copies.len(),
            "{frame:?} published twice by one producer and epoch: {copies:?}"
        );
    }
    // The dead-letter topic stays empty: its high watermark is 0.
    let dead: StreamConsumer = ClientConfig::new()
        .set("bootstrap.servers", &s.broker.addr)
        .create()
        .unwrap();
    let (_, high) = dead
        .fetch_watermarks(&s.topics.dead, 0, Duration::from_secs(10))
        .unwrap();
    assert_eq!(high, 0, "{high} batches were dead-lettered");
    eprintln!(
        "{} batches sent, {} results, {} frames published more than once",
        sent.len(),
        results.seen.len(),
        dups.len()
    );
    dups.len()
}

/// The (producer) ids that published results of `scene` with frame ids in `frames`.
fn producers_of(results: &Results, frames: std::ops::Range<u64>) -> BTreeSet<String> {
    results
        .seen
        .iter()
        .filter(|r| r["frame_id"].as_u64().is_some_and(|f| frames.contains(&f)))
        .filter_map(|r| r["producer"]["id"].as_str().map(String::from))
        .collect()
}

pub(super) fn rebalance_setup(frames: u32) -> Option<(Setup, Vec<String>)> {
    Some((setup(8, frames)?, scenes(8)))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_joining_mid_frame_loses_no_camera_batch() {
    joining_mid_frame("consumer").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_joining_mid_frame_loses_no_camera_batch_with_the_classic_protocol() {
    joining_mid_frame("classic").await;
}

/// A replica joins while frames are half sent, both in group protocol `protocol`.
async fn joining_mid_frame(protocol: &str) {
    let Some((s, scenes)) = rebalance_setup(60) else {
        return;
    };
    let args = |id: &str| {
        let mut a = replica_args(&s, &scenes, id);
        a.extend(["--kafka-group-protocol".into(), protocol.into()]);
        a
    };
    let (_a, _) = serve(s.bin, &args("a")).await;
    let p = Arc::new(producer(s.broker));
    let mut results = Results::new(s.broker, &s.topics.results);
    // 60 frames, each one's 4 cameras over 100 ms; B joins 1 s in, so the group rebalances
    // while frames are half sent.
    let streaming = stream_live(&s, &p, &scenes, 0..60);
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (_b, _) = serve(s.bin, &args("b")).await;
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &s).await;
    assert_eq!(
        producers_of(&results, 40..60),
        BTreeSet::from(["a".to_string(), "b".to_string()]),
        "after the rebalance both replicas own scenes"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_killed_and_restarted_mid_stream_loses_no_camera_batch() {
    let Some((s, scenes)) = rebalance_setup(200) else {
        return;
    };
    let (mut a, _) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let (_b, _) = serve(s.bin, &replica_args(&s, &scenes, "b")).await;
    let p = Arc::new(producer(s.broker));
    let mut results = Results::new(s.broker, &s.topics.results);
    // 200 frames over about 20 s; A is killed 2 s in and comes back (as a2) 16 s in, well
    // after B took its scenes over (about 6 s session timeout plus the broker's rebalance
    // delay after the kill; more on a loaded machine).
    let streaming = stream_live(&s, &p, &scenes, 0..200);
    tokio::time::sleep(Duration::from_secs(2)).await;
    signal(&a, "KILL");
    let _ = a.wait();
    tokio::time::sleep(Duration::from_secs(14)).await;
    let (_a2, _) = serve(s.bin, &replica_args(&s, &scenes, "a2")).await;
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &s).await;
    // B took every scene over while A was dead (about 2..16 s: frames 20..160).
    let last_b: BTreeSet<&str> = results
        .seen
        .iter()
        .filter(|r| r["producer"]["id"] == "b" && r["frame_id"].as_u64() > Some(20))
        .filter_map(|r| r["scene"].as_str())
        .collect();
    assert_eq!(
        last_b.len(),
        scenes.len(),
        "B published every scene: {last_b:?}"
    );
    assert!(
        producers_of(&results, 190..200).contains("a2"),
        "the restarted replica owns scenes again"
    );
}

/// A rolling restart while frames stream in: each replica in turn gets SIGTERM (mid-frame: it
/// leaves its incomplete frames to the next owner instead of cutting them), exits, starts
/// again and rejoins before the next one goes.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_rolling_restart_loses_no_camera_batch() {
    let Some((s, scenes)) = rebalance_setup(150) else {
        return;
    };
    let (a, _) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let (b, _) = serve(s.bin, &replica_args(&s, &scenes, "b")).await;
    let p = Arc::new(producer(s.broker));
    let mut results = Results::new(s.broker, &s.topics.results);
    let streaming = stream_live(&s, &p, &scenes, 0..150);
    tokio::time::sleep(Duration::from_millis(2_030)).await;
    let mut restarted = Vec::new();
    for (mut old, id) in [(a, "a2"), (b, "b2")] {
        signal(&old, "TERM");
        guard("replica exit", async {
            while old.try_wait().unwrap().is_none() {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        })
        .await;
        restarted.push(serve(s.bin, &replica_args(&s, &scenes, id)).await);
    }
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &s).await;
    let last = producers_of(&results, 140..150);
    assert!(
        !last.is_empty() && last.iter().all(|p| p == "a2" || p == "b2"),
        "after the roll the restarted replicas publish: {last:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_rebalance_while_catching_up_a_backlog_loses_no_camera_batch() {
    let Some((s, scenes)) = rebalance_setup(80) else {
        return;
    };
    // The whole backlog first (captured from 30 s ago on, as by a replica that comes back
    // that far behind), then two replicas one after the other: the second joins while the
    // first reads the backlog.
    let p = producer(s.broker);
    let capture = Capture::from_ms_ago(30_000, 25);
    let sent = stream(
        &p,
        &s.topics.batches,
        &s.lines,
        &scenes,
        0..80,
        Duration::ZERO,
        capture,
    )
    .await;
    let mut results = Results::new(s.broker, &s.topics.results);
    let (_a, _) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let (_b, _) = serve(s.bin, &replica_args(&s, &scenes, "b")).await;
    check_exact(&mut results, &sent, &s).await;
}

/// A backlog read with a 1 ms sync timeout, each frame's cameras captured at the same instant:
/// on the reader's clock the backlog's frames would be cut while it is read (the old
/// wall-clock wait held them only until the partition's end); on stream time a frame is cut
/// only when the stream has moved past it, so every frame comes out whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_backlog_is_read_whole_whatever_the_sync_timeout() {
    let Some((s, scenes)) = rebalance_setup(48) else {
        return;
    };
    let p = producer(s.broker);
    let capture = Capture::from_ms_ago(10_000, 0);
    let sent = stream(
        &p,
        &s.topics.batches,
        &s.lines,
        &scenes,
        0..48,
        Duration::ZERO,
        capture,
    )
    .await;
    let mut results = Results::new(s.broker, &s.topics.results);
    let mut args = replica_args(&s, &scenes, "a");
    let at = args.iter().position(|a| a == "--sync-timeout").unwrap();
    args[at + 1] = "1ms".into();
    let (_a, _) = serve(s.bin, &args).await;
    check_exact(&mut results, &sent, &s).await;
}

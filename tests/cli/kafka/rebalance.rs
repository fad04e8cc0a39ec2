//! Replicas joining, dying (SIGKILL) and coming back while camera batches stream in, each
//! frame's cameras spread over time, and while a replica catches up a backlog. Asserted, by
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
type Sent = (String, String, u64);

/// Scene `i` lives on partition `i` (sent to explicit partitions).
fn scenes(n: usize) -> Vec<String> {
    (0..n).map(|i| format!("scene{i}")).collect()
}

/// Produces `line` of scene `i` to partition `i` of `batches`.
async fn send_scene(p: &FutureProducer, i: usize, scene: &str, line: &str) {
    let r = FutureRecord::to("batches")
        .partition(i as i32)
        .key(scene)
        .payload(line);
    guard("produce", p.send(r, Duration::from_secs(20)))
        .await
        .unwrap();
}

/// Sends frames `from..to` of every scene: one camera at a time (all scenes at once), `gap`
/// after each camera, so a frame's cameras arrive over 4 × `gap`.
async fn stream(
    p: &FutureProducer,
    lines: &[Line],
    scenes: &[String],
    frames: std::ops::Range<u64>,
    gap: Duration,
) -> Vec<Sent> {
    let mut sent = Vec::new();
    for (cam, frame, line) in lines.iter().filter(|(_, f, _)| frames.contains(f)) {
        let sends = scenes
            .iter()
            .enumerate()
            .map(|(i, s)| send_scene(p, i, s, line));
        futures::future::join_all(sends).await;
        sent.extend(scenes.iter().map(|s| (s.clone(), cam.clone(), *frame)));
        if !gap.is_zero() {
            tokio::time::sleep(gap).await;
        }
    }
    sent
}

/// Streams in the background; the task returns what it sent.
fn stream_in_background(
    p: Arc<FutureProducer>,
    lines: Vec<Line>,
    scenes: Vec<String>,
    frames: std::ops::Range<u64>,
    gap: Duration,
) -> tokio::task::JoinHandle<Vec<Sent>> {
    tokio::spawn(async move { stream(&p, &lines, &scenes, frames, gap).await })
}

fn replica_args(broker: &Broker, scenes: &[String], id: &str) -> Vec<String> {
    let mut args = model_args(scenes);
    args.extend(kafka_args(broker, "replicas", id));
    args.extend(["--kafka-dead-letter-topic".into(), "dead".into()]);
    args
}

/// Every batch of `sent` in a result, no partial result, duplicates only by another producer
/// or epoch, nothing dead-lettered. Returns how many frames were published more than once.
async fn check_exact(results: &mut Results, sent: &[Sent], broker: &Broker) -> usize {
    results.wait_cover(sent).await;
    results.read_for(Duration::from_secs(1)).await;
    let partial: Vec<&Value> = results
        .seen
        .iter()
        .filter(|r| {
            r["missing_cameras"]
                .as_array()
                .is_some_and(|a| !a.is_empty())
        })
        .collect();
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
        .set("bootstrap.servers", &broker.addr)
        .create()
        .unwrap();
    let (_, high) = dead
        .fetch_watermarks("dead", 0, Duration::from_secs(10))
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

fn rebalance_setup(frames: u32) -> Option<(Setup, Vec<String>)> {
    let s = setup(8, frames)?;
    s.broker.create_topic("dead", 1);
    Some((s, scenes(8)))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_joining_mid_frame_loses_no_camera_batch() {
    let Some((Setup { broker, bin, lines }, scenes)) = rebalance_setup(60) else {
        return;
    };
    let (_a, _) = serve(bin, &replica_args(&broker, &scenes, "a")).await;
    let p = Arc::new(producer(&broker));
    let mut results = Results::new(&broker, "results");
    // 60 frames, each one's 4 cameras over 100 ms; B joins 1 s in, so the group rebalances
    // while frames are half sent.
    let streaming = stream_in_background(
        p.clone(),
        lines.clone(),
        scenes.clone(),
        0..60,
        Duration::from_millis(25),
    );
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (_b, _) = serve(bin, &replica_args(&broker, &scenes, "b")).await;
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &broker).await;
    assert_eq!(
        producers_of(&results, 40..60),
        BTreeSet::from(["a".to_string(), "b".to_string()]),
        "after the rebalance both replicas own scenes"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_killed_and_restarted_mid_stream_loses_no_camera_batch() {
    let Some((Setup { broker, bin, lines }, scenes)) = rebalance_setup(200) else {
        return;
    };
    let (mut a, _) = serve(bin, &replica_args(&broker, &scenes, "a")).await;
    let (_b, _) = serve(bin, &replica_args(&broker, &scenes, "b")).await;
    let p = Arc::new(producer(&broker));
    let mut results = Results::new(&broker, "results");
    // 200 frames over about 20 s; A is killed 2 s in and comes back (as a2) 16 s in, well
    // after B took its scenes over (about 6 s session timeout plus the broker's rebalance
    // delay after the kill; more on a loaded machine).
    let streaming = stream_in_background(
        p.clone(),
        lines.clone(),
        scenes.clone(),
        0..200,
        Duration::from_millis(25),
    );
    tokio::time::sleep(Duration::from_secs(2)).await;
    signal(&a, "KILL");
    let _ = a.wait();
    tokio::time::sleep(Duration::from_secs(14)).await;
    let (_a2, _) = serve(bin, &replica_args(&broker, &scenes, "a2")).await;
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &broker).await;
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

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_rebalance_while_catching_up_a_backlog_loses_no_camera_batch() {
    let Some((Setup { broker, bin, lines }, scenes)) = rebalance_setup(80) else {
        return;
    };
    // The whole backlog first, then two replicas one after the other: the second joins while
    // the first reads the backlog.
    let p = producer(&broker);
    let sent = stream(&p, &lines, &scenes, 0..80, Duration::ZERO).await;
    let mut results = Results::new(&broker, "results");
    let (_a, _) = serve(bin, &replica_args(&broker, &scenes, "a")).await;
    let (_b, _) = serve(bin, &replica_args(&broker, &scenes, "b")).await;
    check_exact(&mut results, &sent, &broker).await;
}

/// A backlog read with a 1 ms sync timeout. Each frame's cameras lie far apart in the
/// partition (per block of 16 frames: every frame's first camera, then every frame's second,
/// …), as they do when cameras send in bursts; counted while the backlog is read, the timeout
/// would publish most frames partial and refuse their last cameras as late. The replica holds
/// the timeouts until each partition's end: every frame comes out whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_backlog_is_read_whole_whatever_the_sync_timeout() {
    let Some((Setup { broker, bin, lines }, scenes)) = rebalance_setup(48) else {
        return;
    };
    let mut ordered = lines.clone();
    ordered.sort_by_key(|(cam, frame, _)| (frame / 16, cam.clone(), *frame));
    let p = producer(&broker);
    let sent = stream(&p, &ordered, &scenes, 0..48, Duration::ZERO).await;
    let mut results = Results::new(&broker, "results");
    let mut args = replica_args(&broker, &scenes, "a");
    let at = args.iter().position(|a| a == "--sync-timeout").unwrap();
    args[at + 1] = "1ms".into();
    let (_a, _) = serve(bin, &args).await;
    check_exact(&mut results, &sent, &broker).await;
}

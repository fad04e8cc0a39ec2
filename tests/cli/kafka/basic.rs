//! One replica: every accepted batch appears in a published result (its camera reported in a
//! result of its scene and frame); a malformed record is counted and skipped without stalling
//! its partition; a replica restarted in the same group resumes from the committed offsets
//! (nothing already published is published again after a graceful stop); protobuf batches in
//! and protobuf results out.

use std::time::Duration;

use rdkafka::config::ClientConfig;
use rdkafka::consumer::{Consumer, StreamConsumer};
use serde_json::Value;

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_replica_publishes_every_batch_skips_malformed_and_resumes_after_restart() {
    let Some(Setup {
        broker,
        topics,
        bin,
        lines,
    }) = setup(4, 20)
    else {
        return;
    };
    let scenes: Vec<String> = vec!["north".into(), "south".into()];
    let mut args = model_args(&scenes);
    args.extend(kafka_args(broker, &topics, "replicas", "r1"));
    // Records go out one at a time, stamped when sent: a generous wait, as this test is not
    // about synchronization.
    args.extend(["--sync-timeout".into(), "5s".into()]);
    let (child, base) = serve(bin, &args).await;
    let p = producer(broker);
    let mut results = Results::new(broker, &topics.results);

    // The first 10 frames of both scenes, with malformed records in the middle of `north`'s
    // partition (not JSON, not a batch, no key) and a rejected one (a scene nobody serves).
    let mut expected = Vec::new();
    for (i, (cam, frame, line)) in lines.iter().enumerate() {
        if *frame >= 10 {
            continue;
        }
        for s in &scenes {
            send(&p, &topics.batches, Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
        if i == 8 {
            send(&p, &topics.batches, Some("north"), "{not json").await;
            send(&p, &topics.batches, Some("north"), r#"{"scene":"north"}"#).await;
            send(&p, &topics.batches, None, &lines[0].2).await;
            send(&p, &topics.batches, Some("nowhere"), &lines[0].2).await;
        }
    }
    results.wait_cover(&expected).await;
    let m = records_counted(&base, expected.len(), 3).await;
    assert!(m.contains("crossview_kafka_assigned{"), "{m}");
    // Consumer lag is exported per owned partition that holds records (librdkafka
    // statistics, every 2 s) and falls to 0 once everything is consumed and committed.
    let mut lags = Vec::new();
    for _ in 0..150 {
        let m = metrics_text(&base).await;
        lags = m
            .lines()
            .filter(|l| {
                l.starts_with(&format!(
                    "crossview_kafka_consumer_lag{{topic=\"{}\"",
                    topics.batches
                ))
            })
            .map(String::from)
            .collect();
        if !lags.is_empty() && lags.iter().all(|l| l.ends_with(" 0")) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert!(
        !lags.is_empty() && lags.iter().all(|l| l.ends_with(" 0")),
        "consumer lag never reached 0: {lags:?}"
    );
    assert_eq!(
        metric(&m, "crossview_kafka_records_total{outcome=\"rejected\"}"),
        1.0,
        "{m}"
    );
    // The rejected record's unknown scene is counted once, however many statistics reports
    // (every 100 ms, over the wait for the lag above) the replica handled since.
    let m = metrics_text(&base).await;
    assert_eq!(
        metric(&m, "crossview_errors_total{kind=\"unknown_scene\"}"),
        1.0,
        "{m}"
    );
    // The refused records went to the dead-letter topic, each saying why.
    let dead: StreamConsumer = ClientConfig::new()
        .set("bootstrap.servers", &broker.addr)
        .set("group.id", format!("checker-{}", topics.dead))
        .set("auto.offset.reset", "earliest")
        .create()
        .unwrap();
    dead.subscribe(&[&topics.dead]).unwrap();
    let mut reasons = Vec::new();
    while reasons.len() < 4 {
        let m = guard("dead letters", dead.recv()).await.unwrap();
        let why = header(&m, "crossview-error").expect("crossview-error header");
        reasons.push(why);
    }
    assert!(reasons.iter().any(|r| r.contains("nowhere")), "{reasons:?}");
    assert!(
        results.duplicates().is_empty(),
        "{:?}",
        results.duplicates()
    );
    // Everything published has its offsets committed: a graceful stop, then a new replica in
    // the same group resumes after them.
    signal(&child, "TERM");
    let mut child = child;
    guard("replica exit", async {
        while child.try_wait().unwrap().is_none() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    let before = results.seen.len();
    let mut args = model_args(&scenes);
    args.extend(kafka_args(broker, &topics, "replicas", "r2"));
    args.extend(["--sync-timeout".into(), "5s".into()]);
    let (_child, _base) = serve(bin, &args).await;
    for (cam, frame, line) in &lines {
        if *frame < 10 {
            continue;
        }
        for s in &scenes {
            send(&p, &topics.batches, Some(s), line).await;
            expected.push((s.clone(), cam.clone(), *frame));
        }
    }
    results.wait_cover(&expected).await;
    results.read_for(Duration::from_secs(1)).await;
    let after: Vec<&Value> = results.seen[before..].iter().collect();
    assert!(
        after
            .iter()
            .all(|r| r["frame_id"].as_u64().unwrap() >= 10 && r["producer"]["id"] == "r2"),
        "the restarted replica re-published a frame already committed"
    );
    assert!(
        results.duplicates().is_empty(),
        "{:?}",
        results.duplicates()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn protobuf_batches_in_and_protobuf_results_out() {
    let Some(Setup {
        broker,
        topics,
        bin,
        lines,
    }) = setup(2, 6)
    else {
        return;
    };
    let scenes: Vec<String> = vec!["east".into()];
    let mut args = model_args(&scenes);
    args.extend(kafka_args(broker, &topics, "proto", "p1"));
    args.extend(["--sync-timeout".into(), "5s".into()]);
    args.extend(["--kafka-output-format".into(), "protobuf".into()]);
    let (_child, base) = serve(bin, &args).await;
    let p = producer(broker);
    let mut results = Results::new(broker, &topics.results);
    // Even frames as protobuf `Batch` (named by the header), odd ones as JSON lines without
    // a header (the default input format); one record with a content type nobody reads.
    let mut expected = Vec::new();
    for (cam, frame, line) in &lines {
        let batch: crossview_core::Batch = serde_json::from_str(line).unwrap();
        if frame % 2 == 0 {
            use prost::Message as _;
            let pb = crossview_api::convert::batch_to_pb("east", &batch).encode_to_vec();
            send_with(
                &p,
                &topics.batches,
                Some("east"),
                &pb,
                Some("application/x-protobuf"),
            )
            .await;
        } else {
            send(&p, &topics.batches, Some("east"), line).await;
        }
        expected.push(("east".to_string(), cam.clone(), *frame));
        if expected.len() == 3 {
            send_with(
                &p,
                &topics.batches,
                Some("east"),
                line.as_bytes(),
                Some("text/csv"),
            )
            .await;
        }
    }
    results.wait_cover(&expected).await;
    assert!(
        results
            .seen
            .iter()
            .all(|r| r["identities"].as_u64() > Some(0)),
        "every frame of the clean simulation associates someone"
    );
    records_counted(&base, expected.len(), 1).await;
}

//! Capture times through Kafka: one replica, two scenes declared at 10 frames/s; `north`'s
//! cameras put their capture time in the value (`"time"`), `south`'s only in the record's
//! timestamp (`--kafka-timestamp record`); no frame ids, cameras jittering ±20 ms and one of
//! them 35 ms late. Every batch appears in the result of the tick it was captured at.

use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn batches_stamped_in_the_value_or_the_record_go_to_their_capture_tick() {
    let Some(Setup {
        broker,
        topics,
        bin,
        lines,
    }) = setup(2, 20)
    else {
        return;
    };
    let scenes: Vec<String> = vec!["north".into(), "south".into()];
    let mut args = model_args(&scenes);
    for s in &scenes {
        let cams: Vec<String> = SQUARE4.iter().map(|c| format!("{c}:1280x720")).collect();
        args.extend(["--scene".into(), format!("{s}={}@10fps", cams.join(","))]);
    }
    args.extend(kafka_args(broker, &topics, "replicas", "r1"));
    args.extend(["--kafka-timestamp".into(), "record".into()]);
    args.extend(["--sync-timeout".into(), "5s".into()]);
    let (child, base) = serve(bin, &args).await;
    let p = producer(broker);
    let mut results = Results::new(broker, &topics.results);
    // Frame f of camN captured at start + f × 100 ms (+ 35 ms for cam2), ±20 ms.
    let capture = Capture::from_ms_ago(10_000, 0);
    let start_tick = (capture.start_ms + 99) / 100;
    let jitter = [0, 15, -20, 10, -5, 20, -15, 5];
    let mut expected = Vec::new();
    for (i, (cam, frame, line)) in lines.iter().enumerate() {
        let late = if cam == "cam2" { 35 } else { 0 };
        let ms = (start_tick + *frame as i64) * 100 + late + jitter[i % jitter.len()];
        let tick = (start_tick + *frame as i64) as u64;
        let mut v: Value = serde_json::from_str(line).unwrap();
        v.as_object_mut().unwrap().remove("frame_id");
        let south = v.to_string();
        v["time"] = serde_json::json!(ms as f64 / 1e3);
        send(&p, &topics.batches, Some("north"), &v.to_string()).await;
        let r = FutureRecord::<str, str>::to(&topics.batches)
            .key("south")
            .payload(&south)
            .timestamp(ms);
        guard("produce", p.send(r, Duration::from_secs(20)))
            .await
            .unwrap();
        for s in &scenes {
            expected.push((s.clone(), cam.clone(), tick));
        }
    }
    results.wait_cover(&expected).await;
    records_counted(&base, expected.len(), 0).await;
    // Whole frames: every result of these ticks is complete and carries its tick time.
    for r in &results.seen {
        assert_eq!(r["complete"], true, "{r}");
        let tick = r["frame_id"].as_u64().unwrap();
        let t = crossview_core::capture::Ticks::new(10.0)
            .unwrap()
            .time_of(tick);
        assert_eq!(r["time"], t.to_rfc3339(), "{r}");
    }
    drop(child);
}

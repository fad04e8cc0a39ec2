//! A frame waits on the stream, not the wall clock (docs/kafka.md, "Stream time"), with
//! `--sync-timeout 1s` ([`super::rebalance::SYNC_TIMEOUT`]): a replica whose delivery stops
//! for 2 s in the middle of frames (the whole process stopped, as a long pause or a starved
//! machine does) cuts none of them; a camera that really stops still yields partial frames, each missing only that
//! camera, cut by the stream moving on and, at the end, by the quiet; producers whose clocks
//! run 5 s ahead or behind cut nothing. Every camera batch sent is accounted for in the output
//! topic read from the beginning.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use super::rebalance::{
    check_exact, rebalance_setup, replica_args, send_scene, stream, stream_live,
};
use super::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_replica_stopped_for_two_seconds_mid_frame_cuts_no_frame() {
    let Some((s, scenes)) = rebalance_setup(60) else {
        return;
    };
    let scenes = scenes[..2].to_vec();
    let (mut a, base) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let p = Arc::new(producer(s.broker));
    let mut results = Results::new(s.broker, &s.topics.results);
    let streaming = stream_live(&s, &p, &scenes, 0..60);
    // Stopped 1 s in (frames half sent), for 2 s: twice the sync timeout.
    tokio::time::sleep(Duration::from_millis(1_030)).await;
    signal(&a, "STOP");
    tokio::time::sleep(Duration::from_secs(2)).await;
    signal(&a, "CONT");
    let sent = streaming.await.unwrap();
    check_exact(&mut results, &sent, &s).await;
    let m = metrics_text(&base).await;
    assert_eq!(
        metric(&m, "crossview_late_batches_total{scene=\"scene0\"}"),
        0.0,
        "{m}"
    );
    assert!(
        m.contains("crossview_kafka_stream_time_seconds{"),
        "stream time is exported: {m}"
    );
    signal(&a, "KILL");
    let _ = a.wait();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_camera_that_stops_still_yields_partial_frames() {
    let Some((s, scenes)) = rebalance_setup(60) else {
        return;
    };
    let scenes = scenes[..2].to_vec();
    let (_a, base) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let p = producer(s.broker);
    let mut results = Results::new(s.broker, &s.topics.results);
    // cam3 stops after frame 19; the others go on to frame 59.
    let lines: Vec<Line> = s
        .lines
        .iter()
        .filter(|(cam, f, _)| cam != "cam3" || *f < 20)
        .cloned()
        .collect();
    let sent = stream(
        &p,
        &s.topics.batches,
        &lines,
        &scenes,
        0..60,
        Duration::from_millis(25),
        Capture::live(25),
    )
    .await;
    results.wait_cover(&sent).await;
    let by_frame = results.covered();
    for scene in &scenes {
        for f in 0..60u64 {
            let cams = &by_frame[&(scene.clone(), f)];
            let want: BTreeSet<String> = SQUARE4
                .iter()
                .filter(|c| f < 20 || **c != "cam3")
                .map(|c| c.to_string())
                .collect();
            assert_eq!(cams, &want, "{scene} frame {f}");
        }
    }
    let m = metrics_text(&base).await;
    for scene in &scenes {
        let moved_on = metric(
            &m,
            &format!(
                "crossview_frames_partial_total{{scene=\"{scene}\",cause=\"camera_missing\"}}"
            ),
        );
        let idle = metric(
            &m,
            &format!("crossview_frames_partial_total{{scene=\"{scene}\",cause=\"idle\"}}"),
        );
        // Frames 20..59: those the stream moved 1 s past (to about 49) are cut by it; the
        // last ones, which it never passed, by the quiet at the end.
        assert_eq!(moved_on + idle, 40.0, "{scene}: {m}");
        assert!(
            moved_on >= 25.0,
            "{scene}: {moved_on} cut by the stream: {m}"
        );
        assert!(
            idle >= 1.0,
            "{scene}: the last frame waits for the quiet: {m}"
        );
    }
    assert_eq!(
        metric(&m, "crossview_late_batches_total{scene=\"scene0\"}"),
        0.0,
        "{m}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn producer_clocks_five_seconds_off_cut_nothing() {
    let Some((s, scenes)) = rebalance_setup(30) else {
        return;
    };
    let scenes = scenes[..2].to_vec();
    let (_a, _) = serve(s.bin, &replica_args(&s, &scenes, "a")).await;
    let p = producer(s.broker);
    let mut results = Results::new(s.broker, &s.topics.results);
    // cam1's producer runs 5 s ahead, cam2's 5 s behind; the others keep true time.
    let capture = Capture::live(25);
    let mut sent = Vec::new();
    for (cam, frame, line) in &s.lines {
        let skew = match cam.as_str() {
            "cam1" => 5_000,
            "cam2" => -5_000,
            _ => 0,
        };
        let ts = capture.stamp(cam, *frame) + skew;
        for (i, scene) in scenes.iter().enumerate() {
            send_scene(&p, &s.topics.batches, i, scene, line, ts).await;
            sent.push((scene.clone(), cam.clone(), *frame));
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    check_exact(&mut results, &sent, &s).await;
}

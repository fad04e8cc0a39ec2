//! The run itself: subscribe, then push the workload on a clock-driven schedule (open loop)
//! or as fast as the in-flight window allows, inject soak faults, drain, and build the report.
use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use crossview_core::Batch;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::{Semaphore, oneshot};
use tokio::task::JoinHandle;

use crate::args::{Args, FrameIds, Transport};
use crate::grpc::{self, GrpcSlot};
use crate::http::{self, HttpSlot};
use crate::kafka::{self, KafkaSlot};
use crate::promtext::{self, Sample};
use crate::recording::Workload;
use crate::report::{Comparison, Latency, Report, SoakCounts};
use crate::tracker::Tracker;
use crate::transport::Outgoing;
use crate::{rss, target};

/// A connection of any transport.
enum Slot {
    Grpc(GrpcSlot),
    Http(HttpSlot),
    /// Kafka: one producer serves every slot.
    Kafka(Arc<KafkaSlot>),
}

impl Slot {
    async fn connect(args: &Args, tracker: &Arc<Tracker>) -> anyhow::Result<Self> {
        Ok(match args.transport {
            Transport::Grpc => Slot::Grpc(GrpcSlot::connect(&args.target, tracker.clone()).await?),
            Transport::Http => Slot::Http(HttpSlot::new(
                &args.target,
                args.http1,
                args.request_timeout,
                tracker.clone(),
            )?),
            Transport::Kafka => Slot::Kafka(Arc::new(KafkaSlot::new(args, tracker.clone()).await?)),
        })
    }

    fn send(&self, out: Outgoing) {
        match self {
            Slot::Grpc(s) => s.send(out),
            Slot::Http(s) => s.send(out),
            Slot::Kafka(s) => s.send(out),
        }
    }
}

/// Shared pieces every send needs.
struct Sender {
    tracker: Arc<Tracker>,
    window: Arc<Semaphore>,
    closed_loop: bool,
}

impl Sender {
    /// Hands one batch to `slot`, honouring the in-flight window.
    async fn send(&self, slot: &Slot, scene_idx: usize, scene: &Arc<str>, batch: Batch) {
        let permit = if self.closed_loop {
            self.window
                .clone()
                .acquire_owned()
                .await
                .expect("the window semaphore is never closed")
        } else {
            match self.window.clone().try_acquire_owned() {
                Ok(p) => p,
                Err(_) => {
                    // Never handed over, so neither sent nor in flight.
                    self.tracker.error("client_backlog");
                    return;
                }
            }
        };
        let key = (scene_idx, batch.frame_id);
        self.tracker.sent(key, Instant::now());
        slot.send(Outgoing {
            key,
            scene: scene.clone(),
            batch,
            permit,
        });
    }
}

/// Soak-mode fault injection state.
struct Soak {
    rng: ChaCha8Rng,
    /// Per slot: the frame index from which the camera is back (slot is `None` while down).
    down_until: Vec<u64>,
    /// Late batches waiting: (due frame index, seq) -> (slot, scene index, batch).
    deferred: BTreeMap<(u64, u64), (usize, usize, Batch)>,
    late_frames: u64,
    seq: u64,
    counts: SoakCounts,
}

/// Runs the load test described by `args` and returns its report.
pub async fn run(args: &Args) -> anyhow::Result<Report> {
    args.validate()?;
    // Kafka: the replicas are behind the broker; --target is only a replica to wait for.
    let via_kafka = args.transport == Transport::Kafka;
    if via_kafka {
        kafka::check_brokers(args).await?;
    }
    if !via_kafka || args.wait_ready.is_some() {
        target::check_target(&args.target, &args.allow_host).await?;
    }
    let workload = Arc::new(Workload::load(&args.recording)?);
    if let Some(w) = args.wait_ready {
        target::wait_ready(&args.target, w).await?;
    }
    let scenes: Vec<Arc<str>> = args
        .scene_names(&workload.scene.name)
        .into_iter()
        .map(Arc::from)
        .collect();
    if !via_kafka {
        for scene in &scenes {
            target::check_scene(&args.target, scene, &workload.scene).await?;
        }
    }
    let ncam = workload.scene.cameras.len();
    let tracker = Arc::new(Tracker::new().latency_after(args.latency_after));
    let metrics_before = server_metrics(args).await;
    let rss = args
        .server_pid
        .map(|pid| rss::spawn_sampler(pid, Duration::from_secs(1)));

    let (subscribers, kafka_start) = subscribe_all(args, &scenes, &tracker).await?;
    // The server registers a subscriber right after answering; give it a moment.
    tokio::time::sleep(Duration::from_millis(200)).await;

    let nslots = if args.soak {
        scenes.len() * ncam
    } else if via_kafka {
        1
    } else {
        args.connections
    };
    let mut slots: Vec<Option<Slot>> = Vec::with_capacity(nslots);
    for _ in 0..nslots {
        slots.push(Some(Slot::connect(args, &tracker).await?));
    }
    let sender = Sender {
        tracker: tracker.clone(),
        window: Arc::new(Semaphore::new(args.max_in_flight)),
        closed_loop: args.rate == 0.0,
    };
    let mut soak = args.soak.then(|| Soak {
        rng: ChaCha8Rng::seed_from_u64(args.seed),
        down_until: vec![0; nslots],
        deferred: BTreeMap::new(),
        late_frames: (args.late_delay.as_secs_f64() * args.rate).ceil().max(1.0) as u64,
        seq: 0,
        counts: SoakCounts::default(),
    });

    tracing::info!(
        scenes = scenes.len(),
        cameras = ncam,
        frames = workload.frames.len(),
        batches_per_pass = workload.num_batches(),
        slots = nslots,
        "sending"
    );
    let len = workload.frames.len() as u64;
    let span = workload.loop_span();
    let base = frame_id_base(args.frame_ids, args.rate);
    let t0 = Instant::now();
    let mut max_lag = Duration::ZERO;
    let mut k: u64 = 0;
    loop {
        if args.frames.is_some_and(|n| k >= n) {
            break;
        }
        let pass = k / len;
        // Soak runs are bounded by --duration/--frames and always loop.
        if pass > 0 && !(args.repeat || args.soak) {
            break;
        }
        if args.rate > 0.0 {
            let offset = Duration::from_secs_f64(k as f64 / args.rate);
            if args.duration.is_some_and(|d| offset >= d) {
                break;
            }
            let due = t0 + offset;
            tokio::time::sleep_until(due.into()).await;
            max_lag = max_lag.max(Instant::now().saturating_duration_since(due));
        } else {
            if args.duration.is_some_and(|d| t0.elapsed() >= d) {
                break;
            }
            // Closed loop: at most `window` frames per scene awaiting their results.
            tracker
                .wait_in_flight_below(args.window * scenes.len())
                .await;
        }
        if let Some(s) = soak.as_mut() {
            send_deferred(s, k, &slots, &scenes, &sender).await;
        }
        let frame = &workload.frames[(k % len) as usize];
        for (si, scene) in scenes.iter().enumerate() {
            for (cam, batch) in &frame.batches {
                let slot_idx = (si * ncam + cam) % nslots;
                let mut batch = batch.clone();
                batch.frame_id = match args.frame_ids {
                    FrameIds::Times => base.saturating_add(k),
                    _ => match pass
                        .checked_mul(span)
                        .and_then(|o| o.checked_add(base))
                        .and_then(|o| o.checked_add(frame.frame_id))
                    {
                        Some(id) => id,
                        None => anyhow::bail!("frame ids overflow u64 after {k} frames"),
                    },
                };
                if args.frame_ids == FrameIds::Times {
                    batch.time = Some(tick_time(batch.frame_id, args.rate)?);
                }
                let mut copies = 1;
                if let Some(s) = soak.as_mut() {
                    match soak_decide(s, args, k, slot_idx, &mut slots, &tracker).await {
                        SoakAction::Skip => continue,
                        SoakAction::Defer => {
                            s.seq += 1;
                            s.deferred
                                .insert((k + s.late_frames, s.seq), (slot_idx, si, batch));
                            continue;
                        }
                        SoakAction::Send(n) => copies = n,
                    }
                }
                let Some(slot) = slots[slot_idx].as_ref() else {
                    continue;
                };
                for _ in 1..copies {
                    sender.send(slot, si, scene, batch.clone()).await;
                }
                sender.send(slot, si, scene, batch).await;
            }
        }
        k += 1;
    }
    if let Some(s) = soak.as_mut() {
        send_deferred(s, u64::MAX, &slots, &scenes, &sender).await;
    }
    let send_elapsed = t0.elapsed();
    tracing::info!(
        frames = k,
        seconds = send_elapsed.as_secs_f64(),
        "sent; draining"
    );

    // Drain: every batch answered and every accepted frame's result in, or the timeout.
    let drain_until = Instant::now() + args.drain_timeout;
    if let Some(Some(Slot::Kafka(k))) = slots.first() {
        let k = k.clone();
        let wait = args.drain_timeout;
        let _ = tokio::task::spawn_blocking(move || k.flush(wait)).await;
    }
    while Instant::now() < drain_until {
        if sender.window.available_permits() == args.max_in_flight && tracker.in_flight() == 0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(slots);
    for s in &subscribers {
        s.abort();
    }
    // Kafka: a frame that seems lost may be in the topic all the same (a broker whose live
    // reads skipped a record); look for it from where the run began.
    if let Some(start) = kafka_start {
        let lost = tracker.snapshot().lost;
        if !lost.is_empty() {
            match kafka::reread(args, &start, &scenes).await {
                Ok(found) => {
                    for key in lost.into_iter().filter(|k| found.contains(k)) {
                        tracker.found_on_reread(key);
                    }
                }
                Err(e) => tracing::warn!(error = %e, "kafka: re-reading the results failed"),
            }
        }
    }
    let metrics_after = server_metrics(args).await;
    let rss = rss.map(|r| r.lock().unwrap_or_else(|e| e.into_inner()).clone());
    Ok(build_report(
        args,
        &scenes,
        ncam,
        nslots,
        k,
        send_elapsed,
        max_lag,
        &tracker,
        soak.map(|s| s.counts),
        metrics_before.zip(metrics_after),
        rss,
    ))
}

/// The server's `/metrics`, to compare our counts with; none over Kafka (several replicas
/// may share the scenes: no single server's counters to compare with).
async fn server_metrics(args: &Args) -> Option<Vec<Sample>> {
    if args.transport == Transport::Kafka {
        return None;
    }
    promtext::scrape(&args.target).await.ok()
}

/// The offset added to every frame id: 0 for `original`; for `fresh`, the current Unix time in
/// ms times 1000, which grows faster than any run can use ids; for `times`, the tick of `rate`
/// after now.
fn frame_id_base(mode: FrameIds, rate: f64) -> u64 {
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    match mode {
        FrameIds::Original => 0,
        FrameIds::Fresh => (now.as_millis() as u64).saturating_mul(1000),
        FrameIds::Times => (now.as_secs_f64() * rate).ceil() as u64,
    }
}

/// The time of tick `tick` at `rate` frames per second.
fn tick_time(tick: u64, rate: f64) -> anyhow::Result<crossview_core::capture::CaptureTime> {
    let ticks = crossview_core::capture::Ticks::new(rate)
        .map_err(|e| anyhow::anyhow!("--frame-ids times needs --rate: {e}"))?;
    Ok(ticks.time_of(tick))
}

/// Opens one result subscription per scene (Kafka: one reader of the output topic, and the
/// offsets it started from) and waits until all are open.
async fn subscribe_all(
    args: &Args,
    scenes: &[Arc<str>],
    tracker: &Arc<Tracker>,
) -> anyhow::Result<(Vec<JoinHandle<()>>, Option<kafka::PartitionOffsets>)> {
    let mut handles = Vec::new();
    if args.transport == Transport::Kafka {
        // One reader of the output topic serves every scene.
        let (tx, rx) = oneshot::channel();
        let a = Arc::new(args.clone());
        handles.push(tokio::spawn(kafka::subscribe(
            a,
            scenes.to_vec(),
            tracker.clone(),
            tx,
        )));
        let start = rx
            .await
            .context("result reader ended before opening")?
            .context("cannot read the Kafka output topic")?;
        return Ok((handles, Some(start)));
    }
    for (i, scene) in scenes.iter().enumerate() {
        let (tx, rx) = oneshot::channel();
        let (t, s) = (tracker.clone(), scene.clone());
        let h = if args.transport == Transport::Http {
            tokio::spawn(http::subscribe(args.target.clone(), s, i, t, tx))
        } else {
            tokio::spawn(grpc::subscribe(args.target.clone(), s, i, t, tx))
        };
        rx.await
            .context("subscriber ended before opening")?
            .with_context(|| format!("cannot subscribe to scene '{scene}'"))?;
        handles.push(h);
    }
    Ok((handles, None))
}

enum SoakAction {
    Skip,
    Defer,
    Send(u32),
}

/// Decides what happens to one batch in soak mode: camera dropout (closing its connection)
/// and reconnection, late hold-back, or duplication.
async fn soak_decide(
    s: &mut Soak,
    args: &Args,
    k: u64,
    slot_idx: usize,
    slots: &mut [Option<Slot>],
    tracker: &Arc<Tracker>,
) -> SoakAction {
    if s.down_until[slot_idx] > k {
        s.counts.batches_skipped_while_down += 1;
        return SoakAction::Skip;
    }
    if slots[slot_idx].is_none() {
        match Slot::connect(args, tracker).await {
            Ok(slot) => {
                slots[slot_idx] = Some(slot);
                s.counts.reconnects += 1;
            }
            Err(e) => {
                tracing::warn!(error = %e, "reconnect failed");
                tracker.error("reconnect");
                return SoakAction::Skip;
            }
        }
    }
    if s.rng.random_bool(args.dropout_prob) {
        s.down_until[slot_idx] = k + s.rng.random_range(1..=args.dropout_frames.max(1));
        slots[slot_idx] = None;
        s.counts.dropouts += 1;
        s.counts.batches_skipped_while_down += 1;
        return SoakAction::Skip;
    }
    if s.rng.random_bool(args.late_prob) {
        s.counts.late_sent += 1;
        return SoakAction::Defer;
    }
    if s.rng.random_bool(args.duplicate_prob) {
        s.counts.duplicates_sent += 1;
        return SoakAction::Send(2);
    }
    SoakAction::Send(1)
}

/// Sends the held-back batches due by frame index `k` (skipped if their camera is down).
async fn send_deferred(
    s: &mut Soak,
    k: u64,
    slots: &[Option<Slot>],
    scenes: &[Arc<str>],
    sender: &Sender,
) {
    while let Some(entry) = s.deferred.first_entry() {
        if entry.key().0 > k {
            break;
        }
        let (slot_idx, si, batch) = entry.remove();
        if let Some(slot) = slots[slot_idx].as_ref() {
            sender.send(slot, si, &scenes[si], batch).await;
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn build_report(
    args: &Args,
    scenes: &[Arc<str>],
    ncam: usize,
    nslots: usize,
    frames: u64,
    send_elapsed: Duration,
    max_lag: Duration,
    tracker: &Tracker,
    soak_counts: Option<SoakCounts>,
    metrics: Option<(Vec<Sample>, Vec<Sample>)>,
    server_rss: Option<rss::RssSummary>,
) -> Report {
    let snap = tracker.snapshot();
    let names: Vec<String> = scenes.iter().map(|s| s.to_string()).collect();
    let mut failures = Vec::new();
    if !snap.lost.is_empty() {
        failures.push(format!("{} frames lost", snap.lost.len()));
    }
    if snap.results == 0 {
        failures.push("no results at all".to_string());
    }
    if !snap.errors_by_kind.is_empty() {
        failures.push(format!("client errors {:?}", snap.errors_by_kind));
    }
    // Under overload the server sheds whole frames: refusals as `overloaded` are its
    // backpressure, expected; a frame cut by it (some batches taken, some refused) is not.
    let expected_rejections: &[&str] = if args.soak {
        &["late", "duplicate", "overloaded"]
    } else {
        &["overloaded"]
    };
    if snap.frames_cut_by_overload > 0 {
        failures.push(format!(
            "{} frames cut by the overload (batches both taken and refused)",
            snap.frames_cut_by_overload
        ));
    }
    let unexpected: BTreeMap<_, _> = snap
        .rejected_by_kind
        .iter()
        .filter(|(k, _)| !expected_rejections.contains(&k.as_str()))
        .collect();
    if !unexpected.is_empty() {
        failures.push(format!("rejected batches {unexpected:?}"));
    }
    let server_comparison = metrics
        .map(|(before, after)| compare(&before, &after, &names, &snap))
        .unwrap_or_default();
    for c in server_comparison.iter().filter(|c| !c.matches) {
        failures.push(format!(
            "{}: ours {} vs server {}",
            c.metric,
            c.ours,
            c.server.unwrap_or(0)
        ));
    }
    let secs = send_elapsed.as_secs_f64().max(1e-9);
    Report {
        target: args.target.clone(),
        transport: args.transport,
        scenes: names.clone(),
        cameras: ncam,
        connections: nslots,
        rate_fps_per_scene: (args.rate > 0.0).then_some(args.rate),
        soak: args.soak,
        frames_scheduled_per_scene: frames,
        send_seconds: send_elapsed.as_secs_f64(),
        max_schedule_lag_ms: max_lag.as_secs_f64() * 1e3,
        batches_sent: snap.sent,
        batches_accepted: snap.accepted,
        batches_rejected: snap.rejected_by_kind.clone(),
        errors: snap.errors_by_kind.clone(),
        offered_batches_per_s: snap.sent as f64 / secs,
        frames_accepted: snap.frames_accepted,
        results: snap.results,
        results_complete: snap.results_complete,
        results_shed: snap.results_shed,
        partial_all_accepted: snap.partial_all_accepted,
        frames_cut_by_overload: snap.frames_cut_by_overload,
        results_per_s: snap.results as f64 / snap.active.as_secs_f64().max(1e-9),
        unexpected_results: snap.unexpected_results,
        duplicate_results: snap.duplicate_results,
        results_missed_live: snap.missed_live,
        frames_lost: snap.lost.len() as u64,
        lost_examples: snap
            .lost
            .iter()
            .take(20)
            .map(|(s, f)| (names[*s].clone(), *f))
            .collect(),
        latency_complete: Latency::from_micros(&snap.latency_complete),
        latency_partial: Latency::from_micros(&snap.latency_partial),
        server_comparison,
        soak_counts,
        server_rss,
        passed: failures.is_empty(),
        failures,
    }
}

/// Our counts against the server's counter deltas for our scenes.
fn compare(
    before: &[Sample],
    after: &[Sample],
    scenes: &[String],
    snap: &crate::tracker::Snapshot,
) -> Vec<Comparison> {
    let delta = |name: &str| {
        let f = |s: &[Sample]| promtext::sum(s, name, Some(("scene", scenes)), &[]);
        (f(after) - f(before)).max(0.0).round() as u64
    };
    let mut out = vec![
        ("crossview_batches_total", snap.accepted),
        ("crossview_frames_total", snap.results),
    ];
    let late = snap.rejected_by_kind.get("late").copied().unwrap_or(0);
    let dup = snap.rejected_by_kind.get("duplicate").copied().unwrap_or(0);
    out.push(("crossview_late_batches_total", late));
    out.push(("crossview_frames_shed_total", snap.results_shed));
    out.push(("crossview_duplicate_batches_total", dup));
    out.into_iter()
        // A counter the server never exposed cannot be compared (it may not count that);
        // a zero on both sides says nothing either.
        .filter(|(name, ours)| *ours > 0 || after.iter().any(|s| s.name == *name))
        .map(|(name, ours)| {
            let exposed = after.iter().any(|s| s.name == name);
            let server = exposed.then(|| delta(name));
            Comparison {
                metric: name.to_string(),
                ours,
                server,
                matches: server.is_none_or(|v| v == ours),
            }
        })
        .collect()
}

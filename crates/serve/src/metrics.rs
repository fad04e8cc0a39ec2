//! Prometheus metrics of one server instance. Each [`Metrics`] owns its own recorder (no global
//! state), so several servers in one process (tests) keep separate counts.
use std::sync::Arc;
use std::time::Duration;

use crate::error::Error;
use metrics::{Key, Label, Metadata, Recorder};
use metrics_exporter_prometheus::{PrometheusBuilder, PrometheusHandle, PrometheusRecorder};

const BUCKETS: &[f64] = &[
    0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0,
];

static META: Metadata<'static> =
    Metadata::new(module_path!(), metrics::Level::INFO, Some(module_path!()));

/// Marks a response whose error was produced outside the service (so not yet counted); the
/// request-accounting middleware counts it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct UncountedError(pub &'static str);

/// Counters, gauges and histograms of the service, rendered at `/metrics`.
#[derive(Clone)]
pub struct Metrics {
    recorder: Arc<PrometheusRecorder>,
    handle: PrometheusHandle,
    /// Series (rendered name and labels) no longer exported: the lag of revoked partitions.
    hidden: Arc<std::sync::Mutex<std::collections::BTreeSet<String>>>,
}

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Metrics")
    }
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

/// The rendered series of one partition's consumer lag, up to the value.
fn lag_series(topic: &str, partition: i32) -> String {
    format!("crossview_kafka_consumer_lag{{topic=\"{topic}\",partition=\"{partition}\"}} ")
}

fn key(name: &'static str, labels: &[(&'static str, &str)]) -> Key {
    let labels: Vec<Label> = labels
        .iter()
        .map(|(k, v)| Label::new(*k, v.to_string()))
        .collect();
    Key::from_parts(name, labels)
}

impl Metrics {
    /// A fresh, empty registry.
    pub fn new() -> Self {
        let recorder = PrometheusBuilder::new()
            .set_buckets(BUCKETS)
            .expect("static buckets are non-empty")
            .build_recorder();
        let handle = recorder.handle();
        Metrics {
            recorder: Arc::new(recorder),
            handle,
            hidden: Arc::default(),
        }
    }

    fn inc(&self, name: &'static str, labels: &[(&'static str, &str)]) {
        self.recorder
            .register_counter(&key(name, labels), &META)
            .increment(1);
    }

    fn set(&self, name: &'static str, labels: &[(&'static str, &str)], v: f64) {
        self.recorder
            .register_gauge(&key(name, labels), &META)
            .set(v);
    }

    fn observe(&self, name: &'static str, labels: &[(&'static str, &str)], d: Duration) {
        self.recorder
            .register_histogram(&key(name, labels), &META)
            .record(d.as_secs_f64());
    }

    /// One API request (`transport` = grpc | http, `method` its route) and its duration to the
    /// response head. Every label value must come from a closed set (the caller maps client
    /// input onto known names or `other`), or the registry grows without bound.
    pub fn request(&self, transport: &str, method: &str, status: &str, took: Duration) {
        let l = [
            ("transport", transport),
            ("method", method),
            ("status", status),
        ];
        self.inc("crossview_requests_total", &l);
        self.observe(
            "crossview_request_duration_seconds",
            &[("transport", transport), ("method", method)],
            took,
        );
    }

    /// Counts one error by its [`Error::kind`]: the one counter of `crossview_errors_total`,
    /// for both transports and the inference worker.
    pub fn error(&self, e: &Error) {
        self.error_kind(e.kind());
    }

    /// Counts an error already turned into a response (its kind from [`Error::kind`]).
    pub(crate) fn error_kind(&self, kind: &'static str) {
        self.inc("crossview_errors_total", &[("kind", kind)]);
    }

    /// One accepted batch.
    pub fn batch(&self, scene: &str) {
        self.inc("crossview_batches_total", &[("scene", scene)]);
    }

    /// One frame published unassociated: its scene has no model yet.
    pub fn unassociated(&self, scene: &str) {
        self.inc("crossview_frames_unassociated_total", &[("scene", scene)]);
    }

    /// One model reload of `scene` with its outcome (`swapped`, `unchanged`, `missing`,
    /// `refused`).
    pub fn model_reload(&self, scene: &str, outcome: &str) {
        self.inc(
            "crossview_model_reloads_total",
            &[("scene", scene), ("outcome", outcome)],
        );
    }

    /// One late batch (its frame was already emitted).
    pub fn late(&self, scene: &str) {
        self.inc("crossview_late_batches_total", &[("scene", scene)]);
    }

    /// One duplicate batch.
    pub fn duplicate(&self, scene: &str) {
        self.inc("crossview_duplicate_batches_total", &[("scene", scene)]);
    }

    /// One batch refused as out of the frame-id window.
    pub fn out_of_range(&self, scene: &str) {
        self.inc("crossview_out_of_range_batches_total", &[("scene", scene)]);
    }

    /// `n` boxes clipped to their image (they overlapped its edge).
    pub fn clipped(&self, scene: &str, n: usize) {
        self.recorder
            .register_counter(
                &key("crossview_clipped_boxes_total", &[("scene", scene)]),
                &META,
            )
            .increment(n as u64);
    }

    /// Open connections of the shared port.
    pub fn connections(&self, n: usize) {
        self.recorder
            .register_gauge(&key("crossview_connections", &[]), &META)
            .set(n as f64);
    }

    /// One connection refused at the connection cap (every open one had a request in flight).
    pub(crate) fn connection_refused(&self) {
        self.inc("crossview_connections_refused_total", &[]);
    }

    /// One idle connection closed to make room for a new one at the connection cap.
    pub(crate) fn connection_evicted(&self) {
        self.inc("crossview_connections_evicted_total", &[]);
    }

    /// One frame emitted by the synchronizer.
    pub fn frame(&self, scene: &str, complete: bool) {
        let c = if complete { "complete" } else { "partial" };
        self.inc("crossview_frames_total", &[("scene", scene), ("state", c)]);
    }

    /// One frame shed at intake left the synchronizer (`crossview_frames_total{state="shed"}`).
    pub(crate) fn frame_shed(&self, scene: &str) {
        self.inc(
            "crossview_frames_total",
            &[("scene", scene), ("state", "shed")],
        );
    }

    /// One frame published partial, by `cause`: `camera_missing` (the clock moved on past its
    /// timeout without it), `idle` (Kafka: its partition caught up and quiet that long),
    /// `frame_cap` (--max-pending-frames), `restart`, `shutdown`.
    pub(crate) fn partial(&self, scene: &str, cause: &'static str) {
        self.inc(
            "crossview_frames_partial_total",
            &[("scene", scene), ("cause", cause)],
        );
    }

    /// A Kafka input partition's stream time (ms since the Unix epoch) and how far it trails
    /// the wall clock.
    pub(crate) fn kafka_stream_time(&self, topic: &str, partition: i32, ms: u64, now_ms: u64) {
        let p = partition.to_string();
        let labels = [("topic", topic), ("partition", p.as_str())];
        self.set(
            "crossview_kafka_stream_time_seconds",
            &labels,
            ms as f64 / 1e3,
        );
        self.set(
            "crossview_kafka_stream_behind_seconds",
            &labels,
            now_ms.saturating_sub(ms) as f64 / 1e3,
        );
    }

    /// A Kafka record without a usable timestamp: its arrival time stands in for it.
    pub(crate) fn kafka_untimed(&self) {
        self.inc("crossview_kafka_records_untimed_total", &[]);
    }

    /// Frames currently waiting in the synchronizer.
    pub fn pending(&self, scene: &str, n: usize) {
        self.recorder
            .register_gauge(&key("crossview_pending_frames", &[("scene", scene)]), &META)
            .set(n as f64);
    }

    /// One Kafka input record and what became of it (`accepted`, `malformed`: not a batch
    /// line keyed by a scene; `rejected`: refused by the scene, e.g. unknown scene or late).
    pub(crate) fn kafka_record(&self, outcome: &'static str) {
        self.inc("crossview_kafka_records_total", &[("outcome", outcome)]);
    }

    /// One frame result produced to the Kafka output topic (or a failed attempt).
    pub(crate) fn kafka_produced(&self, ok: bool) {
        let outcome = if ok { "ok" } else { "error" };
        self.inc("crossview_kafka_results_total", &[("outcome", outcome)]);
    }

    /// Whether this replica owns input partition `partition` (1) or not (0).
    pub(crate) fn kafka_assigned(&self, topic: &str, partition: i32, owned: bool) {
        let p = partition.to_string();
        self.recorder
            .register_gauge(
                &key(
                    "crossview_kafka_assigned",
                    &[("topic", topic), ("partition", &p)],
                ),
                &META,
            )
            .set(if owned { 1.0 } else { 0.0 });
    }

    /// The next offset committed for an input partition.
    pub(crate) fn kafka_committed(&self, topic: &str, partition: i32, offset: i64) {
        let p = partition.to_string();
        self.recorder
            .register_gauge(
                &key(
                    "crossview_kafka_committed_offset",
                    &[("topic", topic), ("partition", &p)],
                ),
                &META,
            )
            .set(offset as f64);
    }

    /// Consumer lag of an owned input partition (librdkafka's statistics: high watermark
    /// minus the consumer's position).
    pub(crate) fn kafka_lag(&self, topic: &str, partition: i32, lag: i64) {
        crate::locks::lock(&self.hidden).remove(&lag_series(topic, partition));
        let p = partition.to_string();
        self.recorder
            .register_gauge(
                &key(
                    "crossview_kafka_consumer_lag",
                    &[("topic", topic), ("partition", &p)],
                ),
                &META,
            )
            .set(lag.max(0) as f64);
    }

    /// Result subscribers disconnected to keep a bound (`reason`: `budget`).
    pub(crate) fn subscribers_dropped(&self, reason: &'static str, n: u64) {
        self.recorder
            .register_counter(
                &key("crossview_subscribers_dropped_total", &[("reason", reason)]),
                &META,
            )
            .increment(n);
    }

    /// The lag gauge of an input partition this replica no longer owns: no longer exported.
    pub(crate) fn kafka_lag_forget(&self, topic: &str, partition: i32) {
        let line = lag_series(topic, partition);
        crate::locks::lock(&self.hidden).insert(line);
    }

    /// One input record read again after a rebalance whose frame was already produced
    /// (dropped: not a loss).
    pub(crate) fn kafka_redelivered(&self) {
        self.inc("crossview_kafka_redelivered_total", &[]);
    }

    /// Frames with consumed batches dropped because their input partition left this replica
    /// (the next owner publishes them).
    pub(crate) fn kafka_revoked_frames(&self, n: usize) {
        self.recorder
            .register_counter(&key("crossview_kafka_revoked_frames_total", &[]), &META)
            .increment(n as u64);
    }

    /// Live result subscribers (gRPC Subscribe/Stream and SSE) of a scene.
    pub fn subscribers(&self, scene: &str, n: usize) {
        self.recorder
            .register_gauge(&key("crossview_subscribers", &[("scene", scene)]), &META)
            .set(n as f64);
    }

    /// Frame latency: first batch to result published.
    pub(crate) fn frame_latency(&self, scene: &str, d: Duration) {
        self.observe("crossview_frame_latency_seconds", &[("scene", scene)], d);
    }

    /// A camera's live clock offset in frame intervals (NaN while unknown) and its confidence.
    pub(crate) fn camera_offset(
        &self,
        scene: &str,
        camera: &str,
        frames: Option<f32>,
        confidence: f32,
    ) {
        let labels = [("scene", scene), ("camera", camera)];
        self.recorder
            .register_gauge(&key("crossview_camera_offset_frames", &labels), &META)
            .set(frames.map_or(f64::NAN, f64::from));
        self.recorder
            .register_gauge(&key("crossview_camera_offset_confidence", &labels), &META)
            .set(f64::from(confidence));
    }

    /// A camera's live fit score (NaN while unknown or silent) and its state: one
    /// `crossview_camera_fit_state{state}` series per state, 1 for the camera's.
    pub(crate) fn camera_fit(&self, scene: &str, camera: &str, score: Option<f32>, state: &str) {
        let labels = [("scene", scene), ("camera", camera)];
        self.recorder
            .register_gauge(&key("crossview_camera_fit", &labels), &META)
            .set(score.map_or(f64::NAN, f64::from));
        for s in ["fits", "drifting", "does_not_fit", "silent", "unknown"] {
            let labels = [("scene", scene), ("camera", camera), ("state", s)];
            self.recorder
                .register_gauge(&key("crossview_camera_fit_state", &labels), &META)
                .set(if s == state { 1.0 } else { 0.0 });
        }
    }

    /// A camera fenced (left out of association) or its fence lifted:
    /// `crossview_camera_fenced{scene,camera}` 1 or 0, and each fencing counted in
    /// `crossview_camera_fences_total{scene,camera}`.
    pub(crate) fn camera_fenced(&self, scene: &str, camera: &str, fenced: bool) {
        let labels = [("scene", scene), ("camera", camera)];
        self.recorder
            .register_gauge(&key("crossview_camera_fenced", &labels), &META)
            .set(if fenced { 1.0 } else { 0.0 });
        if fenced {
            self.inc("crossview_camera_fences_total", &labels);
        }
    }

    /// A retrain (`--auto-retrain`) ended: `crossview_retrains_total{scene,outcome}`.
    pub(crate) fn retrain_done(&self, scene: &str, outcome: &str) {
        self.inc(
            "crossview_retrains_total",
            &[("scene", scene), ("outcome", outcome)],
        );
    }

    /// Whether a retrain of `scene` is running: `crossview_retrain_running{scene}` 1 or 0.
    pub(crate) fn retrain_running(&self, scene: &str, running: bool) {
        self.set(
            "crossview_retrain_running",
            &[("scene", scene)],
            if running { 1.0 } else { 0.0 },
        );
    }

    /// `--auto-align` changed a camera's clock offset.
    pub(crate) fn clock_aligned(&self, scene: &str, camera: &str) {
        self.inc(
            "crossview_clock_alignments_total",
            &[("scene", scene), ("camera", camera)],
        );
    }

    /// Time one live clock estimate took (its sum over uptime is the watch's CPU share).
    pub(crate) fn clock_estimate(&self, scene: &str, d: Duration) {
        self.observe("crossview_clock_estimate_seconds", &[("scene", scene)], d);
    }

    /// One frame shed under overload (`stage`: `intake`, refused before any batch was taken,
    /// or `queue`, taken whole but waited past `--max-queue-delay`).
    pub(crate) fn shed(&self, scene: &str, stage: &'static str) {
        self.inc(
            "crossview_frames_shed_total",
            &[("scene", scene), ("stage", stage)],
        );
    }

    /// How long a job of the scene waited in the inference queue before it ran (or was shed).
    pub(crate) fn queue_delay(&self, scene: &str, d: Duration) {
        self.observe("crossview_queue_delay_seconds", &[("scene", scene)], d);
    }

    /// Time spent in the encoder and matcher for one frame.
    pub fn inference(&self, scene: &str, d: Duration) {
        self.observe("crossview_inference_seconds", &[("scene", scene)], d);
    }

    /// `n` accepted batches not recorded (`reason`: `queue_full` or `write_error`).
    pub(crate) fn record_dropped(&self, scene: &str, reason: &'static str, n: u64) {
        if n == 0 {
            return;
        }
        self.recorder
            .register_counter(
                &key(
                    "crossview_record_dropped_total",
                    &[("scene", scene), ("reason", reason)],
                ),
                &META,
            )
            .increment(n);
    }

    /// `lines` batches (`bytes` bytes) written to a scene's recording files.
    pub(crate) fn record_written(&self, scene: &str, lines: u64, bytes: u64) {
        let l = [("scene", scene)];
        self.recorder
            .register_counter(&key("crossview_record_batches_total", &l), &META)
            .increment(lines);
        self.recorder
            .register_counter(&key("crossview_record_bytes_total", &l), &META)
            .increment(bytes);
    }

    /// One failed write to a scene's recording file.
    pub(crate) fn record_write_error(&self, scene: &str) {
        self.inc("crossview_record_write_errors_total", &[("scene", scene)]);
    }

    /// One recording file removed to keep within `--record-max-bytes`.
    pub(crate) fn record_file_removed(&self) {
        self.inc("crossview_record_files_removed_total", &[]);
    }

    /// Bytes of all recording files (on disk and buffered).
    pub(crate) fn record_disk_bytes(&self, bytes: u64) {
        self.recorder
            .register_gauge(&key("crossview_record_disk_bytes", &[]), &META)
            .set(bytes as f64);
    }

    /// The Prometheus text exposition.
    pub fn render(&self) -> String {
        self.handle.run_upkeep();
        let text = self.handle.render();
        let hidden = crate::locks::lock(&self.hidden);
        if hidden.is_empty() {
            return text;
        }
        let mut out = String::with_capacity(text.len());
        for line in text.lines() {
            if !hidden.iter().any(|h| line.starts_with(h.as_str())) {
                out.push_str(line);
                out.push('\n');
            }
        }
        out
    }
}

//! The live clock watch: each camera's clock offset, estimated from the embeddings the worker
//! computed anyway ([`crossview_core::offsets`]), off the hot path.
//!
//! After publishing a frame, the worker moves its embeddings to the scene's own watch thread
//! ([`ClockWatch::observe`]: no copy, no lock, never blocks; for an ensemble only its first
//! member's columns, [`crossview_core::Encoder::leading_width`], so the window costs what one
//! encoder's would), which keeps the last `window` frames per camera (a few kilobytes per
//! frame) and, once per `interval`, estimates every
//! camera's offset from them if they changed: the worker never waits for an estimate and the
//! work is bounded by one estimate per interval. The thread publishes the estimate in the
//! scene description, as the `crossview_camera_offset_frames{scene,camera}` and
//! `crossview_camera_offset_confidence` gauges, and logs a warning when a camera's offset
//! leaves ±0.5 frame while known (and a note when it comes back).
//!
//! Offsets are measured on the frames as the synchronizer grouped them, after the offsets the
//! scene declares: a correctly declared camera shows 0.
//!
//! With `--auto-align` the thread also corrects: when two successive estimates over full
//! windows agree that a camera is a whole number of frames off (at least 0.75 frame, within
//! 0.35 of the whole number), it adds that to the camera's offset ([`Offsets`]), logs and
//! counts the change (`crossview_clock_alignments_total`) and starts a new window, so there is
//! at most one change per window. Batches of the changed camera for frames already published
//! are refused as late (counted, as any late batch) while it catches up.
use std::collections::VecDeque;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossview_api::types::{CameraClock, ClockEstimate, FitEstimate};
use crossview_core::offsets::{
    CameraSeries, OffsetConfig, OffsetEstimate, frame_step, profiles, solve,
};
use crossview_core::{CameraSpec, FrameEmbeddings, SceneSpec};

use super::fit::FitReporter;
use super::lock;
use crate::config::ClockWatchConfig;
use crate::metrics::Metrics;

/// Each camera's clock offset as the synchronizer applies it now: the declared one (`@±N`),
/// changed by `--auto-align`.
pub(crate) type Offsets = Arc<[AtomicI64]>;

/// Where the watch thread leaves its latest estimate for the scene description.
pub(super) type Latest<T> = Arc<Mutex<Option<T>>>;

/// An `--auto-align` proposal for a camera needs its estimate this close to a whole number of
/// steps and at least this far from 0 (hysteresis: a camera near ±0.5 frame is left alone).
const ALIGN_ROUNDING: f32 = 0.35;
const ALIGN_FRAMES: f32 = 0.75;

/// A camera whose offset is known (confident pairs link it to the reference) and beyond this
/// many frames is logged as out of sync.
const WARN_FRAMES: f32 = 0.5;

/// Poll period of the watch thread when the interval is shorter.
const MIN_POLL: Duration = Duration::from_millis(50);

/// How often the watch thread takes the frames queued for it. It polls a lock-free queue
/// instead of blocking on a channel: the inference thread that hands it a frame must never
/// wait on a lock the watch thread (at background priority, possibly without a core for a
/// while) holds.
const TAKE_EVERY: Duration = Duration::from_millis(50);

/// Frames queued for the watch thread at most (it takes them in microseconds, except while
/// estimating: ~0.6 s for 7 cameras; beyond, frames are left out of the window, never waited
/// for). Bounds its memory: 512 frames of 7 cameras × 35 boxes × 64 floats is 32 MiB (the
/// worker hands over only the model's leading block, an ensemble's first member).
const QUEUE: usize = 512;

/// A frame for the watch thread: the worker's epoch (bumped on a model swap), its id and its
/// embeddings (moved, not copied).
type Observed = (u64, u64, FrameEmbeddings);

/// The rolling window of the watch thread.
struct Window {
    series: Vec<CameraSeries>,
    /// Frame ids held, oldest first.
    ids: VecDeque<i64>,
    capacity: usize,
    /// Newest frame id seen.
    as_of: u64,
    /// Epoch of the frames held.
    epoch: u64,
    /// Changed since the last estimate.
    changed: bool,
}

impl Window {
    fn new(cameras: usize, capacity: usize) -> Self {
        Window {
            series: vec![CameraSeries::new(); cameras],
            ids: VecDeque::new(),
            capacity,
            as_of: 0,
            epoch: 0,
            changed: false,
        }
    }

    fn clear(&mut self) {
        self.series
            .iter_mut()
            .for_each(|s| *s = CameraSeries::new());
        self.ids.clear();
        self.changed = true;
    }

    /// Adds a frame, dropping the oldest beyond the capacity; a frame not newer than the
    /// window (a restarted stream) is left out, so the window stays ordered. True when the
    /// frame came from a new model (the window was cleared for it).
    fn insert(&mut self, (epoch, frame_id, embeddings): Observed) -> bool {
        let new_model = epoch != self.epoch;
        if new_model {
            self.clear();
            self.epoch = epoch;
        }
        let Ok(id) = i64::try_from(frame_id) else {
            return new_model;
        };
        if self.ids.back().is_some_and(|&last| id <= last) {
            return new_model;
        }
        for (c, series) in self.series.iter_mut().enumerate() {
            if let Some(view) = embeddings.view(c) {
                series.insert(id, view.to_owned());
            }
        }
        self.ids.push_back(id);
        if self.ids.len() > self.capacity {
            self.ids.pop_front();
            if let Some(&oldest) = self.ids.front() {
                self.series.iter_mut().for_each(|s| s.retain_from(oldest));
            }
        }
        self.as_of = frame_id;
        self.changed = true;
        new_model
    }
}

/// The worker's side of the watch: hands frames to the watch thread; dropping it stops the
/// thread.
pub(super) struct ClockWatch {
    feed: Arc<Feed>,
    epoch: u64,
}

/// The frames handed to the watch thread, and whether the worker still hands any.
struct Feed {
    frames: crossbeam_queue::ArrayQueue<Observed>,
    closed: std::sync::atomic::AtomicBool,
}

impl Drop for ClockWatch {
    fn drop(&mut self) {
        self.feed.closed.store(true, Ordering::Release);
    }
}

impl ClockWatch {
    /// Starts the watch thread of scene `spec`; it writes each estimate into `state` and each
    /// look at the cameras' fit into `fit`. `None` when the watch is off (window 0) or its
    /// thread could not start (logged).
    pub(super) fn start(
        spec: &SceneSpec,
        config: ClockWatchConfig,
        metrics: Metrics,
        state: Latest<ClockEstimate>,
        fit: Latest<FitEstimate>,
        offsets: Offsets,
        fence: super::fit::Fence,
    ) -> Option<Self> {
        if config.window == 0 {
            return None;
        }
        let feed = Arc::new(Feed {
            frames: crossbeam_queue::ArrayQueue::new(QUEUE),
            closed: std::sync::atomic::AtomicBool::new(false),
        });
        let rx = feed.clone();
        let watched = spec.clone();
        let spawned = std::thread::Builder::new()
            .name(format!("clock-{}", spec.name))
            .spawn(move || {
                super::run_in_background();
                let shared = Shared {
                    metrics,
                    state,
                    offsets,
                };
                let fence = config.fence.then_some(fence);
                let mut fit = FitReporter::new(watched.cameras.len(), fit, fence);
                watch(&watched, config, &shared, &mut fit, &rx);
            });
        if let Err(e) = spawned {
            tracing::error!(scene = %spec.name, error = %e, "clock watch not started");
            return None;
        }
        Some(ClockWatch { feed, epoch: 0 })
    }

    /// Hands frame `frame_id`'s embeddings to the watch thread (moved: no copy, no lock, never
    /// blocks; a frame is left out while the thread's queue is full).
    pub(super) fn observe(&mut self, frame_id: u64, embeddings: FrameEmbeddings) {
        let _ = self.feed.frames.push((self.epoch, frame_id, embeddings));
    }

    /// Forgets the window (a new model's embeddings are not comparable with the old one's).
    pub(super) fn reset(&mut self) {
        self.epoch += 1;
    }
}

/// What the watch thread shares with the scene.
struct Shared {
    metrics: Metrics,
    state: Arc<Mutex<Option<ClockEstimate>>>,
    offsets: Offsets,
}

/// Held while a watch computes its look (see [`watch`]).
static LOOK: Mutex<()> = Mutex::new(());

/// The watch thread: takes the worker's frames into its window and, once per interval, makes
/// an estimate of the window if it changed and holds enough frames; ends when the worker
/// drops its [`ClockWatch`].
fn watch(
    spec: &SceneSpec,
    config: ClockWatchConfig,
    shared: &Shared,
    fit: &mut FitReporter,
    rx: &Feed,
) {
    let offsets = OffsetConfig {
        max_offset: config.max_offset,
        ..OffsetConfig::default()
    };
    let period = config.interval.max(MIN_POLL);
    let enough = (config.window / 2).max(offsets.min_frames);
    let mut window = Window::new(spec.cameras.len(), config.window);
    let mut flagged = vec![false; spec.cameras.len()];
    let mut proposed: Option<Vec<i64>> = None;
    let mut due = Instant::now() + period;
    loop {
        if rx.closed.load(Ordering::Acquire) {
            return;
        }
        // Everything queued meanwhile (frames wait here while an estimate runs).
        while let Some(frame) = rx.frames.pop() {
            // A new model: its contrasts are not comparable with the old one's.
            if window.insert(frame) {
                fit.reset();
            }
        }
        let now = Instant::now();
        if now < due {
            std::thread::sleep(TAKE_EVERY.min(due - now));
            continue;
        }
        if !window.changed || window.ids.len() < enough {
            due = Instant::now() + period;
            continue;
        }
        window.changed = false;
        // One look at a time across the server: with many scenes the watch's share of the
        // cores stays that of one background thread (the interval stretches instead).
        let _turn = lock(&LOOK);
        let t = Instant::now();
        let step = frame_step(window.series.iter().flat_map(CameraSeries::frame_ids));
        let pairs = profiles(&window.series, step, &offsets);
        let counts: Vec<usize> = window.series.iter().map(CameraSeries::len).collect();
        let found = solve(window.series.len(), &pairs, &counts, step, None, &offsets);
        let ids = window.ids.make_contiguous();
        let in_doubt = fit.look(spec, &shared.metrics, &window.series, ids, &pairs);
        shared.metrics.clock_estimate(&spec.name, t.elapsed());
        let mut report = describe(spec, &found, window.ids.len(), window.as_of);
        // A camera that moved is never reported (nor auto-aligned) as a clock offset.
        for (camera, doubt) in report.cameras.iter_mut().zip(in_doubt) {
            if doubt {
                camera.offset_frames = None;
                camera.offset_ids = None;
                camera.confidence = 0.0;
            }
        }
        report_changes(spec, &report, &shared.metrics, &mut flagged);
        if config.auto_align && window.ids.len() >= config.window {
            let now = proposal(&report);
            if now.iter().any(|&k| k != 0) && proposed.as_ref() == Some(&now) {
                align(spec, shared, &now);
                // The frames held were grouped with the old offsets.
                window.clear();
                proposed = None;
            } else {
                proposed = Some(now);
            }
        }
        *lock(&shared.state) = Some(report);
        // The next estimate one interval after this one ended.
        due = Instant::now() + period;
    }
}

/// Per camera, the correction `--auto-align` would apply (in frame ids; 0: none).
fn proposal(report: &ClockEstimate) -> Vec<i64> {
    let step = report.step as f32;
    report
        .cameras
        .iter()
        .map(|c| match (c.offset_frames, c.offset_ids) {
            (Some(f), Some(ids))
                if f.abs() >= ALIGN_FRAMES && (f - ids as f32 / step).abs() <= ALIGN_ROUNDING =>
            {
                ids
            }
            _ => 0,
        })
        .collect()
}

/// Applies `corrections` to the scene's offsets, logs and counts each.
fn align(spec: &SceneSpec, shared: &Shared, corrections: &[i64]) {
    for ((camera, offset), &k) in spec
        .cameras
        .iter()
        .zip(shared.offsets.iter())
        .zip(corrections)
    {
        if k == 0 {
            continue;
        }
        let from = offset.load(Ordering::Acquire);
        let to = from
            .saturating_add(k)
            .clamp(-CameraSpec::MAX_OFFSET, CameraSpec::MAX_OFFSET);
        offset.store(to, Ordering::Release);
        shared.metrics.clock_aligned(&spec.name, &camera.name);
        tracing::warn!(
            scene = %spec.name,
            camera = %camera.name,
            from,
            to,
            "auto-align: camera clock offset changed (its batches now go to frame id - {to})"
        );
    }
}

/// Sets the gauges and logs each camera that went out of sync or came back.
fn report_changes(
    spec: &SceneSpec,
    report: &ClockEstimate,
    metrics: &Metrics,
    flagged: &mut [bool],
) {
    for (camera, was) in report.cameras.iter().zip(flagged) {
        metrics.camera_offset(
            &spec.name,
            &camera.camera,
            camera.offset_frames,
            camera.confidence,
        );
        let off = camera.offset_frames.is_some_and(|f| f.abs() > WARN_FRAMES);
        if off && !*was {
            tracing::warn!(
                scene = %spec.name,
                camera = %camera.camera,
                offset_frames = camera.offset_frames.unwrap_or_default(),
                offset_ids = camera.offset_ids.unwrap_or_default(),
                confidence = camera.confidence,
                "camera clock out of sync with the scene: declare its offset ({}:WxH@{:+}) \
                 or fix the camera's clock",
                camera.camera,
                camera.offset_ids.unwrap_or_default()
            );
        } else if !off && *was {
            tracing::info!(scene = %spec.name, camera = %camera.camera, "camera clock back in sync");
        }
        *was = off;
    }
}

/// The published form of an estimate.
fn describe(spec: &SceneSpec, found: &OffsetEstimate, frames: usize, as_of: u64) -> ClockEstimate {
    let step = found.step.max(1);
    ClockEstimate {
        frames,
        as_of_frame: as_of,
        step,
        reference: spec.cameras[found.reference].name.clone(),
        cameras: found
            .cameras
            .iter()
            .map(|c| CameraClock {
                camera: spec.cameras[c.camera].name.clone(),
                offset_frames: c.refined.map(|r| r / step as f32),
                offset_ids: c.frames,
                confidence: c.confidence,
                // Capture times: filled by the scene ([`super::timing::Timing::fill`]).
                offset_ms: None,
                drift_ms_per_min: None,
                jitter_ms: None,
            })
            .collect(),
    }
}

//! Capture times: which frame a timestamped batch belongs to ([`crossview_core::capture`]).
//!
//! A scene is fed either frame ids or capture times, never both: its first accepted batch
//! decides ([`Stamps`]), since the two number frames differently (a timed scene's frame id is
//! its tick: `round(time · fps)`, ticks counted from the Unix epoch). A timestamped batch of
//! camera `c` goes to the camera's own tick `round((time − phase_c) · fps)`, less the camera's
//! whole-frame offset (`@±N`, `--auto-align`) like any frame id, where `phase_c` is the
//! camera's sub-frame clock offset:
//! - declared (`CAMERA:WxH@+120ms`): fixed;
//! - otherwise followed from the camera's own capture times ([`PhaseTracker`]): where within
//!   the period its captures fall, so a camera whose captures sit near half a period from the
//!   scene's ticks (a free-running camera, a clock a fraction of a frame off, a clock that
//!   drifts) is not split between two frames by its jitter. The whole frames are the clock
//!   watch's to find (geometry), the fraction the timestamps'.
//!
//! Refused, changing nothing: a time in a scene without a frame rate, a scene fed the other
//! kind of stamp, a time further than the tolerance from its tick, a frame id given with a
//! time that is not the time's tick, a time that goes backwards on its camera.
use crossview_api::types::ClockEstimate;
use crossview_core::capture::{CameraPhase, CaptureTime, Placement, Ticks};
use crossview_core::{CameraSpec, SceneSpec};

use crate::error::{Error, Result};

/// The refusal of a capture time in scene `scene`, which declared no frame rate.
pub(super) fn no_rate(scene: &str) -> Error {
    Error::invalid(
        "time",
        format!(
            "scene '{scene}' has no frame rate: declare it (--scene {scene}=CAMERA:WxH,...@10fps, \
             or a recording header's \"fps\") to send capture times"
        ),
    )
}

/// How a scene's batches are stamped (fixed by its first accepted batch).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Stamps {
    /// Nothing accepted yet.
    Unknown,
    /// Frame ids.
    Ids,
    /// Capture times.
    Times,
}

/// One camera's clock, for capture times.
#[derive(Debug, Clone)]
struct CameraClock {
    phase: CameraPhase,
    /// The camera's own tick of its last accepted batch.
    last_tick: Option<u64>,
}

/// The scene's clock and its cameras' (see the module docs). Lives under the intake lock.
#[derive(Debug)]
pub(super) struct Timing {
    ticks: Option<Ticks>,
    tolerance_ms: f64,
    stamps: Stamps,
    cameras: Vec<CameraClock>,
}

impl Timing {
    /// The clock of `spec` at `fps` (none: the scene takes no capture times) with `tolerance`
    /// (none: half a period).
    pub(super) fn new(
        spec: &SceneSpec,
        fps: Option<f64>,
        tolerance: Option<std::time::Duration>,
    ) -> Self {
        let ticks = fps.and_then(|f| Ticks::new(f).ok());
        let half = ticks.map_or(0.0, |t| t.period_ns() / 2e6);
        let tolerance_ms = tolerance.map_or(half, |d| d.as_secs_f64() * 1e3);
        Timing {
            ticks,
            tolerance_ms,
            stamps: Stamps::Unknown,
            cameras: spec
                .cameras
                .iter()
                .map(|c| CameraClock {
                    phase: CameraPhase::new(c.offset_ms),
                    last_tick: None,
                })
                .collect(),
        }
    }

    /// The scene's clock, if it declared a rate.
    pub(super) fn ticks(&self) -> Option<Ticks> {
        self.ticks
    }

    /// Whether the scene is fed capture times.
    pub(super) fn timed(&self) -> bool {
        self.stamps == Stamps::Times
    }

    /// Camera `cam`'s own frame id of a batch stamped `frame_id` and `time`: `frame_id`, or the
    /// time's tick (with what [`Self::accepted`] records), or why the batch is refused.
    pub(super) fn place(
        &self,
        scene: &str,
        camera: &CameraSpec,
        cam: usize,
        frame_id: u64,
        time: Option<CaptureTime>,
    ) -> Result<(u64, Option<Placement>)> {
        let Some(time) = time else {
            if self.stamps == Stamps::Times {
                return Err(Error::invalid(
                    "time",
                    format!(
                        "scene '{scene}' is fed capture times (its first batch had one): the \
                         batch of camera '{}' has only a frame_id",
                        camera.name
                    ),
                ));
            }
            return Ok((frame_id, None));
        };
        if self.stamps == Stamps::Ids {
            return Err(Error::invalid(
                "time",
                format!(
                    "scene '{scene}' is fed frame ids (its first batch had no time): send \
                     frame_id only, or restart the scene to feed capture times"
                ),
            ));
        }
        let ticks = self.ticks.ok_or_else(|| no_rate(scene))?;
        let clock = &self.cameras[cam];
        let period_ms = ticks.period_ns() / 1e6;
        self.check_agrees(&ticks, camera, frame_id, time)?;
        let Some(near) = clock.phase.place(&ticks, time) else {
            return Err(Error::invalid(
                "time",
                format!(
                    "time {time} of camera '{}' less its clock offset {:.1} ms is before 1970",
                    camera.name,
                    clock.phase.offset_ms()
                ),
            ));
        };
        // A camera's first capture places its phase (unless declared): no tolerance yet.
        if clock.phase.known() && near.residual_ms.abs() > self.tolerance_ms {
            return Err(Error::invalid(
                "time",
                format!(
                    "time {time} of camera '{}' is {:+.1} ms from its nearest tick (frame {}, \
                     period {period_ms:.1} ms) after its clock offset {:.1} ms; the scene's \
                     tolerance is {:.1} ms (--time-tolerance)",
                    camera.name,
                    near.residual_ms,
                    near.tick,
                    clock.phase.offset_ms(),
                    self.tolerance_ms
                ),
            ));
        }
        if let Some(last) = clock.last_tick
            && near.tick < last
        {
            return Err(Error::invalid(
                "time",
                format!(
                    "time {time} of camera '{}' goes backwards: it falls on tick {} but the \
                     camera already sent tick {last} ({})",
                    camera.name,
                    near.tick,
                    ticks.time_of(last)
                ),
            ));
        }
        Ok((near.tick, Some(near)))
    }

    /// A frame id given beside a capture time must be the time's tick on the camera's own
    /// clock, within the tolerance.
    fn check_agrees(
        &self,
        ticks: &Ticks,
        camera: &CameraSpec,
        frame_id: u64,
        time: CaptureTime,
    ) -> Result<()> {
        if frame_id == 0 {
            return Ok(());
        }
        let off_ms = (time.unix_nanos() as f64 - frame_id as f64 * ticks.period_ns()) / 1e6;
        if off_ms.abs() > self.tolerance_ms {
            return Err(Error::invalid(
                "frame_id",
                format!(
                    "frame_id {frame_id} of camera '{}' disagrees with its time {time} by \
                     {off_ms:+.1} ms: tick {frame_id} is at {} ({} frames/s, tolerance {:.1} \
                     ms)",
                    camera.name,
                    ticks.time_of(frame_id),
                    ticks.fps(),
                    self.tolerance_ms
                ),
            ));
        }
        Ok(())
    }

    /// Records an accepted batch of camera `cam` (`placed`: timestamped): fixes the scene's
    /// stamps and follows the camera's phase.
    pub(super) fn accepted(&mut self, cam: usize, placed: Option<Placement>) {
        let Some(p) = placed else {
            self.stamps = Stamps::Ids;
            return;
        };
        self.stamps = Stamps::Times;
        let clock = &mut self.cameras[cam];
        clock.last_tick = Some(p.tick);
        clock.phase.accept(&p);
    }

    /// Forgets where each camera's ticks were (the scene's frames restarted), keeping the
    /// phases.
    pub(super) fn restart(&mut self) {
        self.cameras.iter_mut().for_each(|c| c.last_tick = None);
    }

    /// Adds each camera's clock in milliseconds to the watch's `estimate`, for a scene fed
    /// capture times (`applied`: the whole-frame offsets applied now): the offset, relative to
    /// the estimate's reference camera as the frame offsets are, is the whole frames applied
    /// and found by the watch, times the period, plus where within the period the camera's
    /// captures fall; with its drift and jitter. A camera with too few captures yet is left as
    /// it is; one whose whole frames the watch does not know gets no offset.
    pub(super) fn fill(&self, estimate: &mut ClockEstimate, applied: &[i64]) {
        let (Some(ticks), true) = (self.ticks, self.timed()) else {
            return;
        };
        let period_ms = ticks.period_ns() / 1e6;
        let total = |c: usize, found: Option<i64>| {
            let t = self.cameras[c].phase.timing()?;
            let frames = applied.get(c)?.saturating_add(found?);
            Some(frames as f64 * period_ms + t.phase_ms)
        };
        let reference = estimate
            .cameras
            .iter()
            .position(|c| c.camera == estimate.reference)
            .and_then(|r| total(r, Some(0)));
        for (c, out) in estimate.cameras.iter_mut().enumerate() {
            let Some(t) = self.cameras.get(c).and_then(|k| k.phase.timing()) else {
                continue;
            };
            out.offset_ms = total(c, out.offset_ids)
                .zip(reference)
                .map(|(own, r)| own - r);
            out.drift_ms_per_min = t.drift_ms_per_min;
            out.jitter_ms = Some(t.jitter_ms);
        }
    }
}

//! Capture times: when a camera took a frame, and how a scene's clock turns them into frames.
//! **[ours]**
//!
//! Real cameras (RTSP readers, GStreamer, DeepStream, OpenCV pipelines) stamp every frame with
//! its capture time; separate cameras share no frame counter, jitter by tens of milliseconds
//! and run at slightly different rates. A scene that declares its rate has a clock: **tick `k`
//! is `k` periods after the Unix epoch** (1970-01-01T00:00:00Z), so a frame id of a timed scene
//! *is* a time (`k / fps` seconds), the same on every replica, every restart and every
//! recording, and a client that once turned times into ids by hand (`round(t · fps)`) agrees
//! with it. A camera's batch goes to the tick nearest its capture time less the camera's clock
//! offset ([`Ticks::nearest`]), within a tolerance (half a period by default).
//!
//! [`PhaseTracker`] follows one camera's timing from its capture times alone: where within the
//! period its captures fall (its *phase*, a sub-frame clock offset), how fast that moves (a
//! clock that gains or loses: *drift*) and how much single captures scatter (*jitter*): a
//! line through the circular means of its recent captures.
use std::collections::VecDeque;

use serde::de::{self, Deserializer, Visitor};
use serde::{Deserialize, Serialize, Serializer};

/// Highest frame rate a recording or a simulation may declare, in frames per second.
pub const MAX_FPS: f64 = 1000.0;

/// Checks a declared frame rate: finite, above 0 and at most [`MAX_FPS`]. The error says why.
pub fn check_fps(fps: f64) -> std::result::Result<(), String> {
    if fps.is_finite() && fps > 0.0 && fps <= MAX_FPS {
        Ok(())
    } else {
        Err(format!(
            "fps must be a frame rate in (0, {MAX_FPS}] frames per second, got {fps}"
        ))
    }
}

/// A capture time: nanoseconds since the Unix epoch, within `1970-01-01T00:00:00Z ..=
/// 2262-04-11T23:47:16.854775807Z` (what a signed 64-bit count of nanoseconds holds).
///
/// Its JSON form is an RFC 3339 string (`"2026-12-06T09:50:00.125Z"`, any offset) or a number
/// of seconds since the Unix epoch (`1796550600.125`); it is written as an RFC 3339 string in
/// UTC with nanoseconds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct CaptureTime(i64);

impl CaptureTime {
    /// Seconds since the Unix epoch that [`Self::from_unix_seconds`] accepts at most.
    pub const MAX_SECONDS: f64 = 9_223_372_036.0;

    /// From nanoseconds since the Unix epoch (negative: before 1970, refused).
    pub fn from_unix_nanos(ns: i64) -> Result<Self, String> {
        if ns < 0 {
            return Err(format!(
                "{ns} ns is before 1970-01-01T00:00:00Z (the Unix epoch)"
            ));
        }
        Ok(CaptureTime(ns))
    }

    /// From seconds since the Unix epoch (finite, `0..=`[`Self::MAX_SECONDS`]).
    pub fn from_unix_seconds(s: f64) -> Result<Self, String> {
        if !s.is_finite() {
            return Err(format!("{s} is not a time"));
        }
        if !(0.0..=Self::MAX_SECONDS).contains(&s) {
            return Err(format!(
                "{s} s is outside 1970-01-01..2262-04-11 (0..={} seconds since the Unix epoch)",
                Self::MAX_SECONDS
            ));
        }
        // Whole seconds and the fraction apart: a f64 of ~1.8e9 s keeps ~0.2 µs.
        let whole = s.trunc();
        let ns = (whole as i64)
            .checked_mul(1_000_000_000)
            .and_then(|n| n.checked_add(((s - whole) * 1e9).round() as i64))
            .ok_or_else(|| format!("{s} s is beyond 2262-04-11"))?;
        Ok(CaptureTime(ns))
    }

    /// From an RFC 3339 date-time (`2026-12-06T09:50:00.125Z`, `...+01:00`).
    pub fn parse_rfc3339(s: &str) -> Result<Self, String> {
        let shown: String = s.chars().take(40).collect();
        let t = time::OffsetDateTime::parse(s, &time::format_description::well_known::Rfc3339)
            .map_err(|e| format!("'{shown}' is not an RFC 3339 date-time: {e}"))?;
        let ns = i64::try_from(t.unix_timestamp_nanos())
            .map_err(|_| format!("'{shown}' is beyond 2262-04-11"))?;
        Self::from_unix_nanos(ns).map_err(|_| format!("'{shown}' is before 1970"))
    }

    /// Nanoseconds since the Unix epoch.
    pub fn unix_nanos(self) -> i64 {
        self.0
    }

    /// The time as RFC 3339 in UTC with nanoseconds (`2026-12-06T09:50:00.125000000Z`).
    pub fn to_rfc3339(self) -> String {
        let t = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(self.0))
            .expect("0..=i64::MAX ns is a valid date-time");
        let (y, mo, d) = (t.year(), u8::from(t.month()), t.day());
        let (h, mi, s, n) = (t.hour(), t.minute(), t.second(), t.nanosecond());
        format!("{y:04}-{mo:02}-{d:02}T{h:02}:{mi:02}:{s:02}.{n:09}Z")
    }
}

impl std::fmt::Display for CaptureTime {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.to_rfc3339())
    }
}

impl Serialize for CaptureTime {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(&self.to_rfc3339())
    }
}

struct TimeVisitor;

impl Visitor<'_> for TimeVisitor {
    type Value = CaptureTime;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("an RFC 3339 date-time string or seconds since the Unix epoch")
    }

    fn visit_str<E: de::Error>(self, v: &str) -> Result<CaptureTime, E> {
        CaptureTime::parse_rfc3339(v).map_err(|e| E::custom(format!("capture time: {e}")))
    }

    fn visit_f64<E: de::Error>(self, v: f64) -> Result<CaptureTime, E> {
        CaptureTime::from_unix_seconds(v).map_err(|e| E::custom(format!("capture time: {e}")))
    }

    fn visit_u64<E: de::Error>(self, v: u64) -> Result<CaptureTime, E> {
        self.visit_f64(v as f64)
    }

    fn visit_i64<E: de::Error>(self, v: i64) -> Result<CaptureTime, E> {
        self.visit_f64(v as f64)
    }
}

impl<'de> Deserialize<'de> for CaptureTime {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(TimeVisitor)
    }
}

/// A scene's clock: ticks of `1 / fps` seconds counted from the Unix epoch (see the module
/// docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ticks {
    fps: f64,
    period_ns: f64,
}

/// Where a capture time falls on a scene's clock.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    /// The nearest tick.
    pub tick: u64,
    /// The time less the tick's, in nanoseconds (within half a period either way).
    pub residual_ns: f64,
}

impl Ticks {
    /// The clock of a scene at `fps` frames per second (checked by [`check_fps`]).
    pub fn new(fps: f64) -> Result<Self, String> {
        check_fps(fps)?;
        Ok(Ticks {
            fps,
            period_ns: 1e9 / fps,
        })
    }

    /// Frames per second.
    pub fn fps(&self) -> f64 {
        self.fps
    }

    /// One period in nanoseconds.
    pub fn period_ns(&self) -> f64 {
        self.period_ns
    }

    /// The tick nearest `t_ns` nanoseconds since the Unix epoch, and how far from it; `None`
    /// before the first tick's half period (a negative time after an offset).
    pub fn nearest(&self, t_ns: f64) -> Option<Nearest> {
        let k = (t_ns / self.period_ns).round();
        if !k.is_finite() || k < 0.0 || k >= u64::MAX as f64 {
            return None;
        }
        Some(Nearest {
            tick: k as u64,
            residual_ns: t_ns - k * self.period_ns,
        })
    }

    /// The time of tick `tick` (saturating at the last representable time).
    pub fn time_of(&self, tick: u64) -> CaptureTime {
        let ns = (tick as f64 * self.period_ns).round();
        CaptureTime(if ns >= i64::MAX as f64 {
            i64::MAX
        } else {
            ns as i64
        })
    }
}

/// One camera's timing, followed from its capture times (see the module docs).
///
/// Each capture gives a phase modulo the period. The tracker never unwraps single captures
/// against its own running estimate: with a jitter near half a period that feeds back (an
/// estimate a little off wraps the far captures to the wrong side, which pulls it further
/// off). It takes [`Self::BLOCK`] captures at a time and places them on the circle where they
/// gather most tightly (the cut of the circle that gives them the least variance: their
/// intrinsic mean, whatever any estimate says), unwraps those block means (consecutive blocks
/// differ by a drift of milliseconds, never by half a period) and fits a line through the last
/// [`Self::BLOCKS`] of them: the phase now, its drift and, from each block's spread, the jitter.
#[derive(Debug, Clone)]
pub struct PhaseTracker {
    period_ms: f64,
    /// The block being filled: (capture time in seconds since `origin`, phase in `[0, P)`).
    block: Vec<(f64, f64)>,
    /// Completed blocks, oldest first, their phases unwrapped.
    blocks: VecDeque<BlockMean>,
    /// The first capture time seen (nanoseconds), the origin of the blocks' times.
    origin: Option<i64>,
    /// The first capture's phase as given: the branch the phase is unwrapped near.
    anchor: f64,
    /// The newest capture time, seconds since `origin`.
    newest: f64,
}

#[derive(Debug, Clone, Copy)]
struct BlockMean {
    t: f64,
    phase: f64,
    /// Variance of its captures' phases about `phase`, ms².
    var: f64,
}

/// What a [`PhaseTracker`] knows of its camera now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// Where the camera's captures fall within the period at the newest capture, in ms (its
    /// sub-frame offset; not wrapped: a drifting clock's phase runs on past the period).
    pub phase_ms: f64,
    /// How fast the phase moves, in ms per minute (a clock that gains: positive); `None`
    /// before [`PhaseTracker::LINE_BLOCKS`] blocks (a shorter span says nothing of drift).
    pub drift_ms_per_min: Option<f64>,
    /// Standard deviation of single captures about it, in ms.
    pub jitter_ms: f64,
    /// Captures it rests on.
    pub captures: usize,
}

impl PhaseTracker {
    /// Captures per block.
    pub const BLOCK: usize = 32;
    /// Blocks the line is fitted to (2,048 captures: at 10 frames/s, 3.4 min; a step in a
    /// camera's clock is followed within about half that).
    pub const BLOCKS: usize = 64;
    /// Blocks needed before the phase follows a line (a drift) rather than their mean.
    pub const LINE_BLOCKS: usize = 4;

    /// A tracker for a scene of period `period_ms` that has seen nothing.
    pub fn new(period_ms: f64) -> Self {
        PhaseTracker {
            period_ms,
            block: Vec::with_capacity(Self::BLOCK),
            blocks: VecDeque::new(),
            origin: None,
            anchor: 0.0,
            newest: 0.0,
        }
    }

    /// Records a capture at `t_ns` whose phase is `phase_ms` (any branch: it is taken modulo
    /// the period). Captures older than the newest are left out.
    pub fn observe(&mut self, t_ns: i64, phase_ms: f64) {
        if !phase_ms.is_finite() || self.period_ms.is_nan() || self.period_ms <= 0.0 {
            return;
        }
        let origin = *self.origin.get_or_insert_with(|| {
            self.anchor = phase_ms;
            t_ns
        });
        let t = t_ns.saturating_sub(origin) as f64 / 1e9;
        if (!self.block.is_empty() || !self.blocks.is_empty()) && t < self.newest {
            return;
        }
        self.newest = t;
        self.block.push((t, phase_ms.rem_euclid(self.period_ms)));
        if self.block.len() == Self::BLOCK {
            let mean = self.block_mean(&self.block);
            self.blocks.push_back(mean);
            if self.blocks.len() > Self::BLOCKS {
                self.blocks.pop_front();
            }
            self.block.clear();
        }
    }

    /// The captures' intrinsic mean on the circle (see the type's docs), unwrapped near the
    /// last block's phase (or the anchor), with their mean time and variance.
    fn block_mean(&self, captures: &[(f64, f64)]) -> BlockMean {
        let p = self.period_ms;
        let n = captures.len().max(1) as f64;
        let mut phases: Vec<f64> = captures.iter().map(|&(_, ph)| ph).collect();
        phases.sort_by(f64::total_cmp);
        // Cutting the circle before sorted capture `j` puts the ones before it a period up.
        let (sum, sq): (f64, f64) = phases
            .iter()
            .fold((0.0, 0.0), |(a, b), &x| (a + x, b + x * x));
        let (mut best_mean, mut best_var) = (sum / n, sq / n - (sum / n).powi(2));
        let (mut s, mut q) = (sum, sq);
        for &x in &phases[..phases.len().saturating_sub(1)] {
            s += p;
            q += 2.0 * x * p + p * p;
            let mean = s / n;
            let var = q / n - mean * mean;
            if var < best_var {
                (best_mean, best_var) = (mean, var);
            }
        }
        let t = captures.iter().map(|&(t, _)| t).sum::<f64>() / n;
        // Near where the earlier blocks' line puts it (one stray block cannot carry the branch
        // off), or the last block's, or the first capture's.
        let near = if self.blocks.len() >= Self::LINE_BLOCKS {
            let (slope, at) = line(&self.blocks);
            at + slope * (t - self.blocks.back().map_or(t, |m| m.t))
        } else {
            self.blocks.back().map_or(self.anchor, |m| m.phase)
        };
        BlockMean {
            t,
            phase: best_mean + p * ((near - best_mean) / p).round(),
            var: best_var.max(0.0) * n / (n - 1.0).max(1.0),
        }
    }

    /// True before the first capture.
    pub fn is_empty(&self) -> bool {
        self.origin.is_none()
    }

    /// Forgets every capture (the camera's clock changed).
    pub fn reset(&mut self) {
        *self = PhaseTracker::new(self.period_ms);
    }

    /// The camera's timing now, once it sent a capture.
    pub fn timing(&self) -> Option<Timing> {
        if self.is_empty() {
            return None;
        }
        let captures = self.blocks.len() * Self::BLOCK + self.block.len();
        let (phase, slope) = if self.blocks.len() >= Self::LINE_BLOCKS {
            let (slope, at) = line(&self.blocks);
            let last = self.blocks.back().map_or(0.0, |m| m.t);
            (at + slope * (self.newest - last), Some(slope))
        } else {
            // Too few blocks for a line: the mean of every capture so far (the blocks' and
            // the partial one's, weighted by their captures).
            let partial = (!self.block.is_empty()).then(|| self.block_mean(&self.block).phase);
            let full = self.blocks.iter().map(|m| (m.phase, Self::BLOCK as f64));
            let part = partial.map(|b| (b, self.block.len() as f64));
            let (sum, w) = full
                .chain(part)
                .fold((0.0, 0.0), |(s, w), (p, n)| (s + p * n, w + n));
            (if w > 0.0 { sum / w } else { self.anchor }, None)
        };
        let vars: Vec<f64> = self
            .blocks
            .iter()
            .map(|m| m.var)
            .chain((self.block.len() >= 2).then(|| self.block_mean(&self.block).var))
            .collect();
        let jitter = (vars.iter().sum::<f64>() / vars.len().max(1) as f64).sqrt();
        Some(Timing {
            phase_ms: phase,
            drift_ms_per_min: slope.map(|s| s * 60.0),
            jitter_ms: jitter,
            captures,
        })
    }
}

/// Least-squares line through the blocks' phases: (slope in ms per second, the line's value
/// at the newest block).
fn line(blocks: &VecDeque<BlockMean>) -> (f64, f64) {
    let n = blocks.len() as f64;
    let (mt, mp) = blocks
        .iter()
        .fold((0.0, 0.0), |(a, b), m| (a + m.t / n, b + m.phase / n));
    let (mut stt, mut stp) = (0.0, 0.0);
    for m in blocks {
        stt += (m.t - mt) * (m.t - mt);
        stp += (m.t - mt) * (m.phase - mp);
    }
    let slope = if stt > 0.0 { stp / stt } else { 0.0 };
    let newest = blocks.back().map_or(mt, |m| m.t);
    (slope, mp + slope * (newest - mt))
}

/// One camera's clock offset in milliseconds, for capture times: declared (fixed), or followed
/// from its captures by a [`PhaseTracker`] (its first capture places it). The one placement
/// rule the server and the recording reader share, so a recording reads back as it was served.
#[derive(Debug, Clone)]
pub struct CameraPhase {
    declared_ms: Option<f64>,
    phase_ms: f64,
    /// Made at the first capture (it needs the scene's period).
    tracker: Option<PhaseTracker>,
}

/// A capture placed on a scene's clock by [`CameraPhase::place`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Placement {
    /// The tick nearest the capture time less the camera's offset.
    pub tick: u64,
    /// How far from that tick, ms.
    pub residual_ms: f64,
    /// The capture's own phase (the applied offset plus the residual), what
    /// [`CameraPhase::accept`] follows.
    observed_ms: f64,
    time_ns: i64,
    period_ms: f64,
}

impl CameraPhase {
    /// A camera whose offset is `declared_ms` (0: none declared, followed from its times).
    pub fn new(declared_ms: i64) -> Self {
        let declared_ms = (declared_ms != 0).then_some(declared_ms as f64);
        CameraPhase {
            declared_ms,
            phase_ms: declared_ms.unwrap_or(0.0),
            tracker: None,
        }
    }

    /// The offset applied now, ms.
    pub fn offset_ms(&self) -> f64 {
        self.phase_ms
    }

    /// Whether the offset is known: declared, or placed by a first capture. Before, a
    /// capture's distance from its tick says nothing (it places the phase).
    pub fn known(&self) -> bool {
        self.declared_ms.is_some() || self.tracker.is_some()
    }

    /// The tick of a capture at `time` on `ticks`, less the offset applied now; `None` before
    /// the first tick.
    pub fn place(&self, ticks: &Ticks, time: CaptureTime) -> Option<Placement> {
        let t = time.unix_nanos();
        let near = ticks.nearest(t as f64 - self.phase_ms * 1e6)?;
        let residual_ms = near.residual_ns / 1e6;
        Some(Placement {
            tick: near.tick,
            residual_ms,
            observed_ms: self.phase_ms + residual_ms,
            time_ns: t,
            period_ms: ticks.period_ns() / 1e6,
        })
    }

    /// Follows an accepted capture: an undeclared offset moves to the tracker's phase.
    pub fn accept(&mut self, p: &Placement) {
        let tracker = self
            .tracker
            .get_or_insert_with(|| PhaseTracker::new(p.period_ms));
        tracker.observe(p.time_ns, p.observed_ms);
        if self.declared_ms.is_none()
            && let Some(t) = tracker.timing()
        {
            self.phase_ms = t.phase_ms;
        }
    }

    /// What the captures say of the camera's clock (its measured phase, drift and jitter).
    pub fn timing(&self) -> Option<Timing> {
        self.tracker.as_ref()?.timing()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_parse_both_ways_and_refuse_junk() {
        let a = CaptureTime::parse_rfc3339("2026-12-06T09:50:00.125Z").unwrap();
        let b: CaptureTime = serde_json::from_str("1796550600.125").unwrap();
        assert_eq!(a, b);
        let c: CaptureTime = serde_json::from_str("\"2026-12-06T10:50:00.125+01:00\"").unwrap();
        assert_eq!(a, c);
        assert_eq!(a.to_rfc3339(), "2026-12-06T09:50:00.125000000Z");
        let back: CaptureTime = serde_json::from_str(&serde_json::to_string(&a).unwrap()).unwrap();
        assert_eq!(back, a);
        for bad in [
            "-1",
            "1e300",
            "\"yesterday\"",
            "\"1969-12-31T23:59:59Z\"",
            "\"9999-01-01T00:00:00Z\"",
            "null",
            "true",
        ] {
            assert!(serde_json::from_str::<CaptureTime>(bad).is_err(), "{bad}");
        }
        assert!(CaptureTime::from_unix_seconds(f64::NAN).is_err());
        assert!(CaptureTime::from_unix_seconds(f64::INFINITY).is_err());
    }

    #[test]
    fn ticks_count_from_the_unix_epoch() {
        let t = Ticks::new(10.0).unwrap();
        let n = t.nearest(1_000_049_000.0).unwrap();
        assert_eq!(n.tick, 10);
        assert!((n.residual_ns - 49_000.0).abs() < 1.0);
        assert_eq!(t.time_of(10).unix_nanos(), 1_000_000_000);
        assert!(t.nearest(-60_000_000.0).is_none());
        assert!(t.nearest(f64::NAN).is_none());
        // Now-ish at 1,000 frames/s: the tick and residual keep microseconds.
        let t = Ticks::new(1000.0).unwrap();
        let now = 1_796_550_600_000_400_000.0;
        let n = t.nearest(now).unwrap();
        assert_eq!(n.tick, 1_796_550_600_000);
        assert!((n.residual_ns - 400_000.0).abs() < 1_000.0);
        assert!(Ticks::new(0.0).is_err() && Ticks::new(f64::NAN).is_err());
    }

    #[test]
    fn the_tracker_follows_phase_drift_and_jitter() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        let mut tr = PhaseTracker::new(100.0);
        assert!(tr.timing().is_none());
        // 10 frames/s, phase 30 ms drifting 20 ms/min (200 ms, two periods, in 10 min),
        // jitter uniform ±40 ms (sd 23 ms); each capture's phase given wrapped to ±50 ms, as
        // a camera's residual from its nearest tick comes.
        let wrap = |p: f64| (p + 50.0).rem_euclid(100.0) - 50.0;
        for k in 0..6000i64 {
            let t = k * 100_000_000;
            let phase = 30.0 + 20.0 * (t as f64 / 60e9) + rng.random_range(-40.0..40.0);
            tr.observe(t, wrap(phase));
            if k % 500 == 499 {
                // Followed all along, never run away (the branch is the first capture's).
                let tm = tr.timing().unwrap();
                let truth = 30.0 + 20.0 * (k as f64 * 0.1 / 60.0);
                assert!(
                    wrap(tm.phase_ms - truth).abs() < 10.0,
                    "{k}: {tm:?} vs {truth}"
                );
                if k >= 1999 {
                    let drift = tm.drift_ms_per_min.unwrap();
                    assert!((drift - 20.0).abs() < 5.0, "{k}: {tm:?}");
                }
            }
        }
        let tm = tr.timing().unwrap();
        let truth = 30.0 + 20.0 * (5999.0 * 0.1 / 60.0);
        assert!(wrap(tm.phase_ms - truth).abs() < 3.0, "{tm:?} vs {truth}");
        // Unwrapped: two periods later, the phase ran on continuously.
        assert!((tm.phase_ms - tr.timing().unwrap().phase_ms).abs() < 1e-9);
        assert!((tm.jitter_ms - 23.1).abs() < 2.0, "{tm:?}");
        assert_eq!(
            tm.captures,
            PhaseTracker::BLOCK * PhaseTracker::BLOCKS + 6000 % PhaseTracker::BLOCK
        );
        tr.reset();
        assert!(tr.timing().is_none());
    }
}

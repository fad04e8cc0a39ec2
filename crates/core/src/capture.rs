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
//! circular mean of its first captures, then an average of its captures' distances from it.
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
/// Each capture gives a phase modulo the period. For its first [`TrackerSettings::warmup`]
/// captures the phase is their circular mean (unbiased wherever it starts); then it follows
/// each capture's distance from it, wrapped to half a period, with a small gain
/// ([`TrackerSettings::gain`]: an exponential average over the last ~50 captures). That is
/// stable for any jitter short of half a period: with jitter uniform in ±J and the phase `e`
/// off, the far captures wrap to the other side, but the captures' mean distance still points
/// back (by `e` while `e < P/2 − J`, less beyond, never away) — unlike a line fitted through
/// captures unwrapped against it and extrapolated, which ran away. The drift is a
/// least-squares line through the last [`Self::HISTORY`] captures' unwrapped phases (reported,
/// after a minute); the jitter is the captures' standard deviation about the phase.
#[derive(Debug, Clone)]
pub struct PhaseTracker {
    period_ms: f64,
    settings: TrackerSettings,
    /// Captures seen.
    n: usize,
    /// Warm-up: the sums of the captures' unit vectors on the circle.
    cos: f64,
    sin: f64,
    /// The phase now, ms (continuous: not wrapped).
    phase: f64,
    /// Mean squared distance of captures from the phase, ms².
    sq: f64,
    /// (capture time in seconds since `origin`, the capture's unwrapped phase), newest last.
    history: VecDeque<(f64, f64)>,
    /// The first capture time seen (nanoseconds).
    origin: Option<i64>,
}

/// How a [`PhaseTracker`] follows a camera (the defaults are its associated constants).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerSettings {
    /// Captures whose circular mean places the phase.
    pub warmup: usize,
    /// The weight of each later capture.
    pub gain: f64,
}

impl Default for TrackerSettings {
    fn default() -> Self {
        TrackerSettings {
            warmup: PhaseTracker::WARMUP,
            gain: PhaseTracker::GAIN,
        }
    }
}

/// What a [`PhaseTracker`] knows of its camera now.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// Where the camera's captures fall within the period, in ms (its sub-frame offset; not
    /// wrapped: a drifting clock's phase runs on past the period).
    pub phase_ms: f64,
    /// How fast the phase moves, in ms per minute (a clock that gains: positive); `None`
    /// before a minute of captures.
    pub drift_ms_per_min: Option<f64>,
    /// Standard deviation of single captures about the phase, in ms.
    pub jitter_ms: f64,
    /// Captures seen.
    pub captures: usize,
}

impl PhaseTracker {
    /// Captures whose circular mean places the phase.
    pub const WARMUP: usize = 32;
    /// The weight of each capture after the warm-up (or 1/n while that is larger).
    pub const GAIN: f64 = 0.02;
    /// Captures the drift is fitted to (at 10 frames/s, 3.4 min).
    pub const HISTORY: usize = 2048;

    /// A tracker for a scene of period `period_ms` that has seen nothing.
    pub fn new(period_ms: f64) -> Self {
        Self::with_settings(period_ms, TrackerSettings::default())
    }

    /// [`Self::new`] with other settings (what the benchmarks vary ±50 %).
    pub fn with_settings(period_ms: f64, settings: TrackerSettings) -> Self {
        PhaseTracker {
            period_ms,
            settings: TrackerSettings {
                warmup: settings.warmup.max(1),
                gain: settings.gain.clamp(1e-4, 1.0),
            },
            n: 0,
            cos: 0.0,
            sin: 0.0,
            phase: 0.0,
            sq: 0.0,
            history: VecDeque::new(),
            origin: None,
        }
    }

    /// `x` less the phase, wrapped to half a period either way.
    fn off(&self, x: f64) -> f64 {
        let d = x - self.phase;
        d - self.period_ms * (d / self.period_ms).round()
    }

    /// Records a capture at `t_ns` whose phase is `phase_ms` (any branch: it is taken modulo
    /// the period; the first capture's branch is the phase's). Captures older than the newest
    /// are left out.
    pub fn observe(&mut self, t_ns: i64, phase_ms: f64) {
        if !phase_ms.is_finite() || self.period_ms.is_nan() || self.period_ms <= 0.0 {
            return;
        }
        let origin = *self.origin.get_or_insert(t_ns);
        let t = t_ns.saturating_sub(origin) as f64 / 1e9;
        if self.history.back().is_some_and(|&(last, _)| t < last) {
            return;
        }
        if self.n == 0 {
            self.phase = phase_ms;
        }
        self.n += 1;
        let r = self.off(phase_ms);
        if self.n <= self.settings.warmup {
            let angle = std::f64::consts::TAU * phase_ms / self.period_ms;
            self.cos += angle.cos();
            self.sin += angle.sin();
            let mean = self.sin.atan2(self.cos) * self.period_ms / std::f64::consts::TAU;
            self.phase += self.off(mean);
            self.sq += (r * r - self.sq) / self.n as f64;
        } else {
            let g = self.settings.gain.max(1.0 / self.n as f64);
            self.phase += g * r;
            self.sq += g * (r * r - self.sq);
        }
        let unwrapped = self.phase + self.off(phase_ms);
        self.history.push_back((t, unwrapped));
        if self.history.len() > Self::HISTORY {
            self.history.pop_front();
        }
    }

    /// True before the first capture.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Forgets every capture (the camera's clock changed).
    pub fn reset(&mut self) {
        *self = PhaseTracker::with_settings(self.period_ms, self.settings);
    }

    /// The camera's timing now, once it sent a capture.
    pub fn timing(&self) -> Option<Timing> {
        if self.is_empty() {
            return None;
        }
        let span = match (self.history.front(), self.history.back()) {
            (Some(a), Some(b)) => b.0 - a.0,
            _ => 0.0,
        };
        Some(Timing {
            phase_ms: self.phase,
            drift_ms_per_min: (span >= 60.0).then(|| slope(&self.history) * 60.0),
            jitter_ms: self.sq.max(0.0).sqrt(),
            captures: self.n,
        })
    }
}

/// Least-squares slope of `(t, y)` points, per unit of `t`.
fn slope(points: &VecDeque<(f64, f64)>) -> f64 {
    let n = points.len().max(1) as f64;
    let (mt, my) = points
        .iter()
        .fold((0.0, 0.0), |(a, b), &(t, y)| (a + t / n, b + y / n));
    let (mut stt, mut sty) = (0.0, 0.0);
    for &(t, y) in points {
        stt += (t - mt) * (t - mt);
        sty += (t - mt) * (y - my);
    }
    if stt > 0.0 { sty / stt } else { 0.0 }
}

/// One camera's clock offset in milliseconds, for capture times: declared (fixed), or followed
/// from its captures by a [`PhaseTracker`] (its first capture places it). The one placement
/// rule the server and the recording reader share, so a recording reads back as it was served.
#[derive(Debug, Clone)]
pub struct CameraPhase {
    declared_ms: Option<f64>,
    phase_ms: f64,
    settings: TrackerSettings,
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
        Self::with_settings(declared_ms, TrackerSettings::default())
    }

    /// [`Self::new`] whose tracker has other settings (what the benchmarks vary).
    pub fn with_settings(declared_ms: i64, settings: TrackerSettings) -> Self {
        let declared_ms = (declared_ms != 0).then_some(declared_ms as f64);
        CameraPhase {
            declared_ms,
            phase_ms: declared_ms.unwrap_or(0.0),
            settings,
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
            .get_or_insert_with(|| PhaseTracker::with_settings(p.period_ms, self.settings));
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
        assert_eq!(tm.captures, 6000);
        tr.reset();
        assert!(tr.timing().is_none());
    }
}

//! Whether each camera still fits the model, from the detections alone (no labels, no
//! calibration): the synchronisation signal that trained the encoder, read back live.
//!
//! For two cameras that see the same people, the mean matched embedding distance between
//! frames shown at the same moment is well below the distance between frames shown at other
//! moments: the pair's shift profile ([`crate::offsets::profile`]) has a deep minimum. How deep,
//! relative to the far shifts, is the pair's **contrast** `1 − cost(best) / median(cost(far))`
//! (0: flat, no sign that the two cameras see one geometry; toward 1: a sharp minimum). A
//! camera whose clock is off moves the minimum, not its depth, so the contrast is read at the
//! minimum wherever it lies: an offset is never taken for a move. A camera that was bumped,
//! re-aimed or zoomed no longer maps its boxes to the geometry the encoder learnt: the matched
//! distances at the minimum rise toward those of unrelated moments and the contrast of every
//! pair it is in falls, while the pairs of the other cameras keep theirs.
//!
//! A camera's **fit** is the contrast of its pairs over the newest frames, read against the
//! same pairs' contrast when the camera last fitted (the baseline: pairs differ by how much
//! the two cameras overlap, so one global level cannot tell). Pure and single-threaded.
use serde::Serialize;

use crate::offsets::{PairProfile, column_means};

/// A pair's contrast over the newest frames of a profile.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PairContrast {
    /// `1 − cost(best) / median(cost(far))`, in `[0, 1]`.
    pub contrast: f32,
    /// Mean matched distance at the minimum.
    pub low: f32,
    /// Median over the far shifts (two steps or more from the minimum) of their mean matched
    /// distance.
    pub far: f32,
    /// The shift of the minimum over these frames, in frame ids.
    pub delta: i64,
    /// Frames scored at the minimum.
    pub frames: usize,
}

/// The contrast of `profile` over its rows for frames `since` and later (the newest frames of
/// the profile's window), each shift needing at least `min_frames` frames; `None` when too
/// few frames or nothing to compare the minimum with (every shift within one step of it).
pub fn contrast(profile: &PairProfile, since: i64, min_frames: usize) -> Option<PairContrast> {
    let first = profile.frames.partition_point(|&t| t < since);
    let rows = profile.values.slice(ndarray::s![first.., ..]);
    let costs = column_means(rows, min_frames);
    let (best, low, frames) = costs
        .iter()
        .enumerate()
        .filter_map(|(j, &(mean, n))| mean.map(|m| (j, m, n)))
        .min_by(|x, y| x.1.total_cmp(&y.1))?;
    let mut far: Vec<f32> = costs
        .iter()
        .enumerate()
        .filter(|(j, _)| j.abs_diff(best) >= 2)
        .filter_map(|(_, c)| c.0)
        .collect();
    let median = upper_median(&mut far)?;
    let contrast = if median > 0.0 {
        (1.0 - low / median).clamp(0.0, 1.0)
    } else {
        0.0
    };
    Some(PairContrast {
        contrast,
        low,
        far: median,
        delta: profile.shifts[best],
        frames,
    })
}

/// The upper median of `values` (the middle one, or the higher of the two middle ones);
/// `None` when empty. Sorts `values`.
pub fn upper_median(values: &mut [f32]) -> Option<f32> {
    values.sort_unstable_by(f32::total_cmp);
    values.get(values.len() / 2).copied()
}

/// Settings of the fit (chosen on the WILDTRACK training frames and the simulator:
/// BENCHMARKS.md, "Camera fit").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitConfig {
    /// Newest frames the contrast is read on (a move shows once they are mostly after it).
    pub recent: usize,
    /// Frames a shift needs among them to be scored.
    pub min_frames: usize,
    /// A pair whose contrast was below this when its cameras fitted carries no signal (the two
    /// cameras hardly overlap) and is left out.
    pub min_baseline: f32,
    /// A camera whose score is below this is drifting.
    pub drifting: f32,
    /// A camera whose score is below this in `confirm` looks in a row does not fit; it fits
    /// again after `confirm` looks at or above `drifting`.
    pub misfit: f32,
    /// Looks in a row that confirm a change to or from "does not fit".
    pub confirm: usize,
}

impl Default for FitConfig {
    /// 60 frames, 20 per shift, pairs above 0.15, drifting below 0.8, does not fit below
    /// 0.7 twice in a row.
    fn default() -> Self {
        FitConfig {
            recent: 60,
            min_frames: 20,
            min_baseline: 0.15,
            drifting: 0.8,
            misfit: 0.7,
            confirm: 2,
        }
    }
}

/// Whether a camera fits the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FitState {
    /// Its pairs' contrast is what it was.
    Fits,
    /// Its pairs' contrast is falling: a small move, or a passing change of the scene.
    Drifting,
    /// Its pairs' contrast has fallen and stayed down: it moved, was re-aimed or zoomed.
    DoesNotFit,
    /// It sent no boxes in the newest frames.
    Silent,
    /// Nothing to tell yet: no look has linked it to another camera (it overlaps with none,
    /// or nobody has moved since the model was loaded).
    Unknown,
}

impl FitState {
    /// The state's name as the API and the metrics write it.
    pub fn as_str(self) -> &'static str {
        match self {
            FitState::Fits => "fits",
            FitState::Drifting => "drifting",
            FitState::DoesNotFit => "does_not_fit",
            FitState::Silent => "silent",
            FitState::Unknown => "unknown",
        }
    }
}

/// One camera's fit after a look.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CameraFit {
    /// Camera index in the scene.
    pub camera: usize,
    /// Its pairs' contrast against their baseline, relative to the whole scene's (1: as it
    /// was; toward 0: it no longer fits); `None` when unknown or silent.
    pub score: Option<f32>,
    /// The state the score puts it in (with the confirmation of [`FitConfig::confirm`]).
    pub state: FitState,
}

/// The fit of every camera of a scene, look after look: each pair's baseline contrast (from
/// the first look that measured it) and each camera's recent scores. Pure: the caller makes
/// the looks ([`contrast`] on each pair's profile over the newest frames).
#[derive(Debug, Clone)]
pub struct FitWatch {
    cfg: FitConfig,
    cameras: usize,
    /// Per pair `(a, b)`, `a < b`, in [`crate::offsets::camera_pairs`] order.
    baseline: Vec<Option<f32>>,
    /// Per camera, its newest scores (at most `confirm`).
    scores: Vec<Vec<f32>>,
    states: Vec<FitState>,
}

impl FitWatch {
    /// A watch of `cameras` cameras with nothing seen yet.
    pub fn new(cameras: usize, cfg: FitConfig) -> Self {
        FitWatch {
            cfg,
            cameras,
            baseline: vec![None; cameras * cameras.saturating_sub(1) / 2],
            scores: vec![Vec::new(); cameras],
            states: vec![FitState::Unknown; cameras],
        }
    }

    /// The settings.
    pub fn config(&self) -> &FitConfig {
        &self.cfg
    }

    /// Forgets everything (a new model's contrasts are not comparable with the old one's).
    pub fn reset(&mut self) {
        *self = FitWatch::new(self.cameras, self.cfg);
    }

    /// Takes one look: `pairs` holds each pair's contrast over the newest frames (in
    /// [`crate::offsets::camera_pairs`] order, `None` where unmeasured), `silent` the cameras
    /// that sent no boxes in them. Returns every camera's fit.
    pub fn look(&mut self, pairs: &[Option<PairContrast>], silent: &[bool]) -> Vec<CameraFit> {
        let index: Vec<(usize, usize)> = crate::offsets::camera_pairs(self.cameras).collect();
        // A pair's baseline is its first measure while both its cameras fit (or are unknown).
        for (k, &(a, b)) in index.iter().enumerate() {
            let fits = |c: usize| matches!(self.states[c], FitState::Fits | FitState::Unknown);
            if let (None, Some(Some(p))) = (self.baseline[k], pairs.get(k))
                && fits(a)
                && fits(b)
                && !silent.get(a).copied().unwrap_or(false)
                && !silent.get(b).copied().unwrap_or(false)
            {
                self.baseline[k] = Some(p.contrast);
            }
        }
        // Each usable pair's contrast against its baseline, and the scene's median ratio.
        let ratios: Vec<Option<(f32, f32)>> = index
            .iter()
            .enumerate()
            .map(
                |(k, _)| match (self.baseline[k], pairs.get(k).copied().flatten()) {
                    (Some(base), Some(p)) if base >= self.cfg.min_baseline => {
                        Some((p.contrast / base, base))
                    }
                    _ => None,
                },
            )
            .collect();
        let scores = self.scores_without_outliers(&index, &ratios);
        (0..self.cameras)
            .map(|c| {
                let silent = silent.get(c).copied().unwrap_or(false);
                let state = self.step(c, scores[c], silent);
                CameraFit {
                    camera: c,
                    score: scores[c].filter(|_| !silent),
                    state,
                }
            })
            .collect()
    }

    /// Each camera's score: the baseline-weighted mean of its pairs' ratios over the scene's
    /// median ratio. A camera that does not fit drags down the pair it shares with each other
    /// camera, so the worst camera below [`FitConfig::misfit`] is set aside and the others
    /// scored again without its pairs, one camera at a time while one is below (at most half
    /// of them: the majority defines what fitting is).
    fn scores_without_outliers(
        &self,
        index: &[(usize, usize)],
        ratios: &[Option<(f32, f32)>],
    ) -> Vec<Option<f32>> {
        let mut aside = vec![false; self.cameras];
        let mut scores = vec![None; self.cameras];
        for _ in 0..=self.cameras / 2 {
            let mut all: Vec<f32> = index
                .iter()
                .zip(ratios)
                .filter(|((a, b), _)| !aside[*a] && !aside[*b])
                .filter_map(|(_, r)| r.map(|r| r.0))
                .collect();
            let scene = upper_median(&mut all).filter(|g| *g > 0.0);
            for (c, score) in scores.iter_mut().enumerate() {
                if aside[c] {
                    continue;
                }
                let (sum, weight) = index
                    .iter()
                    .zip(ratios)
                    .filter(|((a, b), _)| *a == c || *b == c)
                    .filter(|((a, b), _)| !aside[*a] && !aside[*b])
                    .filter_map(|(_, r)| *r)
                    .fold((0.0, 0.0), |(s, w), (r, base)| (s + r * base, w + base));
                *score = scene.filter(|_| weight > 0.0).map(|g| sum / weight / g);
            }
            let worst = scores
                .iter()
                .enumerate()
                .filter(|(c, s)| !aside[*c] && s.is_some_and(|s| s < self.cfg.misfit))
                .min_by(|x, y| x.1.unwrap_or(0.0).total_cmp(&y.1.unwrap_or(0.0)));
            match worst {
                Some((c, _)) if aside.iter().filter(|&&x| x).count() < self.cameras / 2 => {
                    aside[c] = true;
                }
                _ => break,
            }
        }
        scores
    }

    /// Camera `c`'s next state from its score.
    fn step(&mut self, c: usize, score: Option<f32>, silent: bool) -> FitState {
        let cfg = self.cfg;
        let next = match (silent, score) {
            (true, _) => FitState::Silent,
            (false, None) => FitState::Unknown,
            (false, Some(s)) => {
                let history = &mut self.scores[c];
                history.push(s);
                if history.len() > cfg.confirm.max(1) {
                    history.remove(0);
                }
                let full = history.len() >= cfg.confirm.max(1);
                let all_below = |t: f32| full && history.iter().all(|&x| x < t);
                let all_above = |t: f32| full && history.iter().all(|&x| x >= t);
                match self.states[c] {
                    FitState::DoesNotFit if !all_above(cfg.drifting) => FitState::DoesNotFit,
                    _ if all_below(cfg.misfit) => FitState::DoesNotFit,
                    _ if s < cfg.drifting => FitState::Drifting,
                    _ => FitState::Fits,
                }
            }
        };
        // Silence keeps the history (a camera that comes back is judged on what it sends).
        self.states[c] = next;
        next
    }
}

#[cfg(test)]
mod tests {
    use ndarray::Array2;

    use super::*;

    /// A profile of `rows` frames (ids 0, 1, …) over shifts −3..=3 whose costs are `far`
    /// everywhere but `low` at shift `at`.
    fn profile(rows: usize, at: i64, low: f32, far: f32) -> PairProfile {
        let shifts: Vec<i64> = (-3..=3).collect();
        let mut values = Array2::from_elem((rows, shifts.len()), far);
        let j = shifts.iter().position(|&s| s == at).unwrap();
        values.column_mut(j).fill(low);
        PairProfile {
            shifts,
            costs: Vec::new(),
            counts: Vec::new(),
            best: None,
            refined: None,
            z: 0.0,
            frames: (0..rows as i64).collect(),
            values,
        }
    }

    #[test]
    fn contrast_is_read_at_the_minimum_wherever_it_lies() {
        let c = contrast(&profile(30, 0, 0.5, 1.0), 0, 20).unwrap();
        assert!((c.contrast - 0.5).abs() < 1e-6, "{c:?}");
        // A clock offset moves the minimum, not its depth.
        let shifted = contrast(&profile(30, 2, 0.5, 1.0), 0, 20).unwrap();
        assert_eq!((shifted.contrast, shifted.delta), (c.contrast, 2));
        // Only the frames from `since` on count; too few of them: nothing to say.
        assert!(contrast(&profile(30, 0, 0.5, 1.0), 15, 20).is_none());
        assert_eq!(
            contrast(&profile(30, 0, 0.5, 1.0), 10, 20).unwrap().frames,
            20
        );
        // Flat: 0. NaN rows (frames the other camera lacks) are skipped.
        assert_eq!(
            contrast(&profile(30, 0, 1.0, 1.0), 0, 20).unwrap().contrast,
            0.0
        );
        let mut p = profile(40, 0, 0.5, 1.0);
        p.values.row_mut(0).fill(f32::NAN);
        assert_eq!(contrast(&p, 0, 20).unwrap().frames, 39);
    }

    fn pc(contrast: f32) -> Option<PairContrast> {
        Some(PairContrast {
            contrast,
            low: 1.0 - contrast,
            far: 1.0,
            delta: 0,
            frames: 30,
        })
    }

    /// Contrasts of the 6 pairs of 4 cameras: `base` for each, scaled by `scene`, the pairs
    /// of camera `moved` by `by`.
    fn look(scene: f32, moved: Option<usize>, by: f32) -> Vec<Option<PairContrast>> {
        crate::offsets::camera_pairs(4)
            .map(|(a, b)| {
                let base = 0.2 + 0.1 * (a + b) as f32;
                let f = if moved == Some(a) || moved == Some(b) {
                    by
                } else {
                    1.0
                };
                pc(base * scene * f)
            })
            .collect()
    }

    fn states(fits: &[CameraFit]) -> Vec<FitState> {
        fits.iter().map(|f| f.state).collect()
    }

    #[test]
    fn a_camera_whose_pairs_fall_is_drifting_then_does_not_fit_then_fits_again() {
        use FitState::*;
        let quiet = [false; 4];
        let mut w = FitWatch::new(4, FitConfig::default());
        assert_eq!(states(&w.look(&look(1.0, None, 1.0), &quiet)), [Fits; 4]);
        // The whole scene's contrast falls (fewer people walking): nobody is blamed.
        let calm = w.look(&look(0.5, None, 1.0), &quiet);
        assert_eq!(states(&calm), [Fits; 4]);
        assert!(calm.iter().all(|f| (f.score.unwrap() - 1.0).abs() < 1e-4));
        // Camera 2's pairs fall to half: drifting at once, does not fit when confirmed.
        assert_eq!(
            states(&w.look(&look(1.0, Some(2), 0.5), &quiet))[2],
            Drifting
        );
        let moved = w.look(&look(1.0, Some(2), 0.5), &quiet);
        assert_eq!(states(&moved), [Fits, Fits, DoesNotFit, Fits]);
        assert!(moved[2].score.unwrap() < 0.7, "{moved:?}");
        // Back: it stays fenced until it scores well twice in a row.
        assert_eq!(
            states(&w.look(&look(1.0, None, 1.0), &quiet))[2],
            DoesNotFit
        );
        assert_eq!(states(&w.look(&look(1.0, None, 1.0), &quiet))[2], Fits);
    }

    #[test]
    fn silent_and_unlinked_cameras_get_their_own_states() {
        use FitState::*;
        let mut w = FitWatch::new(4, FitConfig::default());
        let mut pairs = look(1.0, None, 1.0);
        // Camera 3 is linked to nobody: its pairs were never measured.
        for (k, (a, b)) in crate::offsets::camera_pairs(4).enumerate() {
            if a == 3 || b == 3 {
                pairs[k] = None;
            }
        }
        assert_eq!(
            states(&w.look(&pairs, &[false; 4])),
            [Fits, Fits, Fits, Unknown]
        );
        let silent = w.look(&pairs, &[false, true, false, false]);
        assert_eq!(states(&silent)[1], Silent);
        assert_eq!(silent[1].score, None);
        // A look with nothing measured at all: unknown, never a false alarm.
        assert_eq!(states(&w.look(&[None; 6], &[false; 4])), [Unknown; 4]);
        w.reset();
        assert_eq!(
            states(&w.look(&look(0.3, None, 1.0), &[false; 4])),
            [Fits; 4]
        );
    }
}

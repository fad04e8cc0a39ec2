//! The live camera fit: after each clock estimate, the watch thread reads the same pairs'
//! profiles over the newest frames ([`crossview_core::fit`]) and tells, per camera, whether it
//! still fits the model — published in the scene description, as the
//! `crossview_camera_fit{scene,camera}` and `crossview_camera_fit_state{scene,camera,state}`
//! gauges, and as one log line per change of state (a warning when a camera stops fitting).
//! No extra matching: the profiles keep their per-frame costs.
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use crossview_api::types::{CameraFitState, FitEstimate};
use crossview_core::SceneSpec;
use crossview_core::fit::{CameraFit, FitConfig, FitState, FitWatch, contrast};
use crossview_core::offsets::{CameraSeries, PairProfile};

use super::lock;
use crate::metrics::Metrics;

/// Per camera, whether it is fenced: left out of association because it does not fit. The
/// watch thread writes it, the worker reads it for each frame.
pub(super) type Fence = Arc<[AtomicBool]>;

/// A fence of `cameras` cameras, none fenced.
pub(super) fn fence(cameras: usize) -> Fence {
    (0..cameras).map(|_| AtomicBool::new(false)).collect()
}

/// The cameras fenced now.
pub(super) fn fenced(fence: &Fence) -> Vec<bool> {
    fence.iter().map(|f| f.load(Ordering::Acquire)).collect()
}

/// The fit side of a scene's watch thread.
pub(super) struct FitReporter {
    watch: FitWatch,
    state: Arc<Mutex<Option<FitEstimate>>>,
    /// Where the cameras that do not fit are fenced (`None`: `--fence-moved-cameras false`).
    fence: Option<Fence>,
    /// Each camera's state as last published.
    published: Vec<FitState>,
}

impl FitReporter {
    /// A reporter for `cameras` cameras that writes each look into `state` and, with `fence`,
    /// fences the cameras that do not fit.
    pub(super) fn new(
        cameras: usize,
        state: Arc<Mutex<Option<FitEstimate>>>,
        fence: Option<Fence>,
    ) -> Self {
        FitReporter {
            watch: FitWatch::new(cameras, FitConfig::default()),
            state,
            fence,
            published: vec![FitState::Unknown; cameras],
        }
    }

    /// Forgets the baselines (a new model) and lifts every fence: the new model is judged
    /// afresh (nothing is published until its first look).
    pub(super) fn reset(&mut self) {
        self.watch.reset();
        *lock(&self.state) = None;
        if let Some(fence) = &self.fence {
            fence.iter().for_each(|f| f.store(false, Ordering::Release));
        }
    }

    /// One look at the window `series` (frame ids `ids`, oldest first) from the pairs'
    /// `profiles` just computed for the clock estimate. Returns, per camera, whether its fit
    /// is in doubt (drifting or does not fit): its clock offset is then not to be trusted (a
    /// camera that moved can put its profiles' minimum anywhere).
    pub(super) fn look(
        &mut self,
        spec: &SceneSpec,
        metrics: &Metrics,
        series: &[CameraSeries],
        ids: &[i64],
        profiles: &[(usize, usize, PairProfile)],
    ) -> Vec<bool> {
        let cfg = *self.watch.config();
        let Some(&since) = ids.get(ids.len().saturating_sub(cfg.recent)) else {
            return vec![false; spec.cameras.len()];
        };
        let pairs: Vec<_> = profiles
            .iter()
            .map(|(_, _, p)| contrast(p, since, cfg.min_frames))
            .collect();
        let silent: Vec<bool> = series
            .iter()
            .map(|s| s.frame_ids().next_back().is_none_or(|t| t < since))
            .collect();
        let fits = self.watch.look(&pairs, &silent);
        self.report(spec, metrics, &fits);
        let as_of = ids.last().and_then(|&t| u64::try_from(t).ok()).unwrap_or(0);
        *lock(&self.state) = Some(describe(spec, &fits, ids.len().min(cfg.recent), as_of));
        fits.iter()
            .map(|f| matches!(f.state, FitState::Drifting | FitState::DoesNotFit))
            .collect()
    }

    /// Sets the gauges and logs each change of state.
    fn report(&mut self, spec: &SceneSpec, metrics: &Metrics, fits: &[CameraFit]) {
        for (f, was) in fits.iter().zip(&mut self.published) {
            let camera = &spec.cameras[f.camera].name;
            metrics.camera_fit(&spec.name, camera, f.score, f.state.as_str());
            if let Some(fence) = &self.fence {
                let fenced = f.state == FitState::DoesNotFit;
                if fence[f.camera].swap(fenced, Ordering::AcqRel) != fenced {
                    metrics.camera_fenced(&spec.name, camera, fenced);
                    if fenced {
                        tracing::warn!(scene = %spec.name, camera = %camera,
                            "camera fenced: left out of association until it fits again");
                    } else {
                        tracing::info!(scene = %spec.name, camera = %camera, "camera fence lifted");
                    }
                }
            }
            if f.state == *was {
                continue;
            }
            let score = f.score.unwrap_or(f32::NAN);
            match f.state {
                FitState::DoesNotFit => tracing::warn!(
                    scene = %spec.name, camera = %camera, score, from = was.as_str(),
                    "camera no longer fits the model: it moved, was re-aimed or zoomed \
                     (retrain on new recordings, or put it back)"
                ),
                FitState::Drifting => tracing::warn!(
                    scene = %spec.name, camera = %camera, score, from = was.as_str(),
                    "camera fit drifting"
                ),
                _ => tracing::info!(
                    scene = %spec.name, camera = %camera, score, from = was.as_str(),
                    to = f.state.as_str(), "camera fit changed"
                ),
            }
            *was = f.state;
        }
    }
}

/// The published form of a look.
fn describe(spec: &SceneSpec, fits: &[CameraFit], frames: usize, as_of: u64) -> FitEstimate {
    FitEstimate {
        frames,
        as_of_frame: as_of,
        cameras: fits
            .iter()
            .map(|f| CameraFitState {
                camera: spec.cameras[f.camera].name.clone(),
                score: f.score,
                state: f.state.as_str().to_string(),
            })
            .collect(),
    }
}

//! Healing (`serve --auto-retrain`): a camera that stopped fitting the model (it was bumped,
//! re-aimed or zoomed, [`crate::scene`]'s fit watch) is fenced at once; when it has not fitted
//! for [`HealConfig::after`], the server retrains the scene's model on what it recorded since,
//! gates the result without labels and swaps it in live, as a reload does.
//!
//! One retrain at a time per server, at most one per scene every [`HealConfig::interval`]:
//! 1. the moment a camera stops fitting, the scene's recording is cut ([`SceneRecorder::mark`]):
//!    what follows is the new view;
//! 2. after [`HealConfig::after`] it is cut again and `crossview train --init <serving model>`
//!    fine-tunes every member of the serving model on the files between the two cuts, in a
//!    child process at the lowest CPU priority (`--nice 19`, `--threads`) for a fixed number
//!    of epochs ([`HealConfig::epochs`]), its time bounded by [`HealConfig::timeout`];
//! 3. `crossview model gate` judges candidate and serving model on the files recorded after
//!    the second cut (frames neither was trained or chosen on): the candidate must have the
//!    higher label-free key and make every camera fit, and bring the scene back to how it was
//!    on a reference — a stretch recorded while every camera fitted (the recording is cut every
//!    [`HealConfig::reference_every`] while they do; the older of the last two stretches, so
//!    that the change is not in it);
//! 4. an accepted candidate is swapped in ([`crate::reload::Reloader::adopt`]); it becomes the
//!    scene's model file (a `SIGHUP` re-reads it; the old file is left as it was). A refused
//!    or failed one is deleted, its log kept.
//!
//! Status in `GetScene` (`retrain`), `crossview_retrains_total{scene,outcome}`,
//! `crossview_retrain_running{scene}` and a log line per step.
pub mod config;
mod job;

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossview_api::types::RetrainStatus;
use crossview_core::fit::FitState;

use crate::locks::lock;
use crate::scene::Scene;
use crate::service::Service;
pub use config::HealConfig;
use job::{Job, Outcome};

/// One scene's healing state.
struct SceneHeal {
    scene: Arc<Scene>,
    phase: Phase,
    status: Arc<Mutex<RetrainStatus>>,
    last_start: Option<Instant>,
    /// The model the reference stretches were recorded under.
    version: Option<String>,
    /// The stretch being recorded while every camera fits: since when, and its first file.
    fitting: Option<(Instant, u64)>,
    /// The last two complete stretches (first file, first file after), oldest first.
    good: Vec<(u64, u64)>,
}

enum Phase {
    /// Every camera fits (or nothing is known).
    Idle,
    /// A camera does not fit since `since`; its new view is recorded from file `from` on.
    Waiting { since: Instant, from: u64 },
    /// This scene's retrain is running.
    Running,
}

/// Starts healing every scene of `service` that is recorded; ends with the service. A retrain
/// running at shutdown is stopped (its child process killed).
pub(crate) fn spawn(service: Arc<Service>, cfg: HealConfig) {
    let stop = service.shutting_down();
    tokio::spawn(async move {
        let mut scenes: BTreeMap<String, SceneHeal> = BTreeMap::new();
        for scene in service.scene_list() {
            if scene.recorder().is_none() {
                continue;
            }
            let heal = SceneHeal {
                status: Arc::new(Mutex::new(idle())),
                scene: scene.clone(),
                phase: Phase::Idle,
                last_start: None,
                version: None,
                fitting: None,
                good: Vec::new(),
            };
            scene.set_retrain(idle());
            scenes.insert(scene.name().to_string(), heal);
        }
        tracing::info!(scenes = scenes.len(), after = ?cfg.after, dir = %cfg.dir.display(), "healing on: cameras that stop fitting get a retrained model");
        let mut running: Option<(String, tokio::task::JoinHandle<Outcome>)> = None;
        let mut tick = tokio::time::interval(Duration::from_secs(1));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        tokio::pin!(stop);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = &mut stop => break,
            }
            finish(&mut running, &mut scenes, &service).await;
            for heal in scenes.values_mut() {
                step(heal, &mut running, &service, &cfg).await;
            }
        }
        if let Some((_, handle)) = running {
            handle.abort();
        }
    });
}

fn idle() -> RetrainStatus {
    RetrainStatus {
        state: "idle".into(),
        ..RetrainStatus::default()
    }
}

/// The cameras of `scene` that do not fit now, by name, and whether every camera fits (or is
/// silent, two at least fitting).
fn misfits(scene: &Scene) -> (Vec<String>, bool) {
    let Some(fit) = scene.fit() else {
        return (Vec::new(), false);
    };
    let state = |s: FitState| fit.cameras.iter().filter(|c| c.state == s.as_str()).count();
    let fits = state(FitState::Fits);
    let all_fit = fits >= 2 && fits + state(FitState::Silent) == fit.cameras.len();
    let bad = fit
        .cameras
        .into_iter()
        .filter(|c| c.state == FitState::DoesNotFit.as_str())
        .map(|c| c.camera)
        .collect();
    (bad, all_fit)
}

/// Keeps the reference stretches of a scene whose cameras all fit: its recording cut every
/// [`HealConfig::reference_every`]; stretches of another model, or one cut short by a camera
/// that stopped fitting, are dropped.
async fn keep_reference(heal: &mut SceneHeal, all_fit: bool, cfg: &HealConfig) {
    let version = heal.scene.serving().map(|i| i.version);
    if version != heal.version {
        heal.version = version;
        heal.good.clear();
        heal.fitting = None;
    }
    if !all_fit {
        heal.fitting = None;
        return;
    }
    if heal
        .fitting
        .is_some_and(|(t, _)| t.elapsed() < cfg.reference_every)
    {
        return;
    }
    let Some(seq) = heal.scene.recorder().map(|r| r.mark()) else {
        return;
    };
    let Some(seq) = seq.await else {
        return;
    };
    if let Some((_, from)) = heal.fitting {
        heal.good.push((from, seq));
        if heal.good.len() > 2 {
            heal.good.remove(0);
        }
    }
    heal.fitting = Some((Instant::now(), seq));
}

/// Publishes `heal`'s status after `change`.
fn update(heal: &SceneHeal, change: impl FnOnce(&mut RetrainStatus)) {
    let mut s = lock(&heal.status);
    change(&mut s);
    heal.scene.set_retrain(s.clone());
}

/// Moves one scene on: notices a camera that stopped fitting, gives up waiting when it fits
/// again, starts its retrain when it is due and no other runs.
async fn step(
    heal: &mut SceneHeal,
    running: &mut Option<(String, tokio::task::JoinHandle<Outcome>)>,
    service: &Arc<Service>,
    cfg: &HealConfig,
) {
    let (bad, all_fit) = misfits(&heal.scene);
    let name = heal.scene.name().to_string();
    match heal.phase {
        Phase::Running => {}
        Phase::Idle if bad.is_empty() => keep_reference(heal, all_fit, cfg).await,
        Phase::Idle => {
            let Some(rec) = heal.scene.recorder() else {
                return;
            };
            let Some(from) = rec.mark().await else {
                return;
            };
            tracing::warn!(scene = %name, cameras = ?bad, after = ?cfg.after,
                "a camera does not fit: recording its new view to retrain on");
            heal.phase = Phase::Waiting {
                since: Instant::now(),
                from,
            };
            // The stretch being recorded holds the change: not a reference.
            heal.fitting = None;
            update(heal, |s| {
                s.state = "waiting".into();
                s.cameras = bad;
            });
        }
        Phase::Waiting { .. } if bad.is_empty() => {
            tracing::info!(scene = %name, "every camera fits again: no retrain");
            heal.phase = Phase::Idle;
            update(heal, |s| {
                s.state = "idle".into();
                s.cameras.clear();
            });
        }
        Phase::Waiting { since, from } => {
            let due = since.elapsed() >= cfg.after
                && heal.last_start.is_none_or(|t| t.elapsed() >= cfg.interval);
            if !due || running.is_some() {
                update(heal, |s| s.cameras = bad);
                return;
            }
            heal.last_start = Some(Instant::now());
            heal.phase = Phase::Running;
            update(heal, |s| {
                s.state = "training".into();
                s.cameras = bad.clone();
                s.attempts += 1;
            });
            service.metrics().retrain_running(&name, true);
            tracing::warn!(scene = %name, cameras = ?bad, "retraining the scene's model on its recording since the camera stopped fitting");
            let job = Job {
                service: service.clone(),
                scene: heal.scene.clone(),
                cfg: cfg.clone(),
                from,
                reference: heal.good.first().copied(),
                cameras: bad,
                status: heal.status.clone(),
            };
            *running = Some((name, tokio::spawn(job.run())));
        }
    }
}

/// Collects the running retrain once it has ended: its outcome published and counted.
async fn finish(
    running: &mut Option<(String, tokio::task::JoinHandle<Outcome>)>,
    scenes: &mut BTreeMap<String, SceneHeal>,
    service: &Service,
) {
    if !running.as_ref().is_some_and(|(_, h)| h.is_finished()) {
        return;
    }
    let Some((name, handle)) = running.take() else {
        return;
    };
    let outcome = handle
        .await
        .unwrap_or_else(|e| Outcome::Failed(format!("the retrain task ended abnormally: {e}")));
    service.metrics().retrain_running(&name, false);
    service.metrics().retrain_done(&name, outcome.label());
    let Some(heal) = scenes.get_mut(&name) else {
        return;
    };
    heal.phase = Phase::Idle;
    match &outcome {
        Outcome::Swapped { model, .. } => {
            tracing::info!(scene = %name, model = %model.display(), "retrained model swapped in")
        }
        other => {
            tracing::warn!(scene = %name, outcome = other.label(), reason = %other.reason(), "retrain not swapped in; the serving model stays")
        }
    }
    update(heal, |s| {
        s.state = "idle".into();
        s.last_outcome = Some(outcome.label().into());
        s.last_reason = Some(outcome.reason());
        if let Outcome::Swapped { model, .. } = &outcome {
            s.swapped += 1;
            s.last_model = Some(model.display().to_string());
            s.cameras.clear();
        }
    });
}

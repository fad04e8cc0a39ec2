//! Live model swaps: re-reads every scene's model file (on `SIGHUP`, or the admin route),
//! loads and checks it off the hot path (ONNX Runtime session creation on a blocking thread),
//! and queues the swap behind the frames already waiting ([`crate::Scene::swap`]): no
//! accepted batch is lost or associated twice, and every result names the version that
//! produced it. A file that is missing, corrupt or made for other cameras is refused with a
//! log line and `crossview_model_reloads_total{outcome="refused"}`; the old model keeps
//! serving. Healing ([`crate::heal`]) swaps a retrained file in the same way and makes it the
//! scene's file from then on ([`Reloader::adopt`]).
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use crate::config::{Limits, ModelSpec};
use crate::error::{Error, Result};
use crate::locks::lock;
use crate::metrics::Metrics;
use crate::registry;
use crate::scene::Scene;

pub use crossview_api::types::ReloadOutcome;

/// The model files a server reloads, by scene.
#[derive(Debug, Clone)]
pub(crate) struct Reloader {
    /// Each scene's model file (a healed scene's is its retrained file).
    models: Arc<Mutex<Vec<ModelSpec>>>,
    limits: Limits,
    /// One reload at a time: a second waits for the first.
    running: Arc<tokio::sync::Mutex<()>>,
}

impl Reloader {
    pub(crate) fn new(models: Vec<ModelSpec>, limits: Limits) -> Self {
        Reloader {
            models: Arc::new(Mutex::new(models)),
            limits,
            running: Arc::default(),
        }
    }

    /// Re-reads every scene's model file and swaps in those that changed; `scene_of` finds a
    /// served scene by name.
    pub(crate) async fn reload(
        &self,
        scene_of: impl Fn(&str) -> Result<Arc<Scene>>,
        metrics: &Metrics,
    ) -> Vec<ReloadOutcome> {
        let _one = self.running.lock().await;
        let models = lock(&self.models).clone();
        let mut out = Vec::with_capacity(models.len());
        for spec in &models {
            let outcome = self.reload_one(scene_of(&spec.name), spec).await;
            log_outcome(&outcome, spec, metrics);
            out.push(outcome);
        }
        out
    }

    /// The model file scene `scene` is served from, when it has one.
    pub(crate) fn path_of(&self, scene: &str) -> Option<PathBuf> {
        let models = lock(&self.models);
        models
            .iter()
            .find(|m| m.name == scene)
            .map(|m| m.path.clone())
    }

    /// Swaps the model file `path` into `scene` as a reload does and, when it is swapped in,
    /// makes it the scene's file (later reloads re-read it). Outcome `superseded` when the
    /// scene is not served from `expected` any more (an operator's reload came first).
    pub(crate) async fn adopt(
        &self,
        scene: Result<Arc<Scene>>,
        path: &Path,
        expected: &Path,
        metrics: &Metrics,
    ) -> ReloadOutcome {
        let _one = self.running.lock().await;
        let Some(mut spec) = lock(&self.models)
            .iter()
            .find(|m| scene.as_ref().is_ok_and(|s| s.name() == m.name))
            .cloned()
        else {
            let e = Error::NoModel("the scene has no model file to replace".into());
            let spec = ModelSpec {
                name: scene.as_ref().map_or("?", |s| s.name()).to_string(),
                path: path.to_path_buf(),
            };
            return refused(&spec, None, &e);
        };
        if spec.path != expected {
            let e = Error::Unavailable(format!(
                "the scene's model file changed to {} meanwhile",
                spec.path.display()
            ));
            return ReloadOutcome {
                outcome: "superseded".into(),
                ..refused(&spec, None, &e)
            };
        }
        spec.path = path.to_path_buf();
        let outcome = self.reload_one(scene, &spec).await;
        log_outcome(&outcome, &spec, metrics);
        if outcome.outcome == "swapped" {
            let mut models = lock(&self.models);
            if let Some(m) = models.iter_mut().find(|m| m.name == spec.name) {
                m.path = spec.path;
            }
        }
        outcome
    }

    async fn reload_one(&self, scene: Result<Arc<Scene>>, spec: &ModelSpec) -> ReloadOutcome {
        let scene = match scene {
            Ok(s) => s,
            Err(e) => return refused(spec, None, &e),
        };
        let current = scene.serving().map(|i| i.version);
        let result = |outcome: &str, version| ReloadOutcome {
            scene: spec.name.clone(),
            outcome: outcome.to_string(),
            version,
            error: None,
        };
        // The file is read once: its content hash first (an unchanged file costs no
        // session), then the same bytes make the session.
        let limits = self.limits;
        let (spec2, serving) = (spec.clone(), current.clone());
        let read = tokio::task::spawn_blocking(move || {
            let Ok(bytes) = std::fs::read(&spec2.path) else {
                return Read::Missing;
            };
            let hash = registry::model_version("", &bytes);
            if serving.as_deref().is_some_and(|v| v.ends_with(&hash)) {
                return Read::Unchanged;
            }
            Read::Loaded(registry::load_model_bytes(&spec2, &bytes, &limits))
        })
        .await
        .unwrap_or_else(|e| Read::Loaded(Err(Error::internal_from("model loading panicked", e))));
        let model = match read {
            Read::Missing => return result("missing", current),
            Read::Unchanged => return result("unchanged", current),
            Read::Loaded(m) => m,
        };
        let (info, encoder) = match model {
            Ok(m) => m,
            Err(e) => return refused(spec, current, &e),
        };
        let version = info.version.clone();
        match scene.swap(info, encoder).await {
            Ok(()) => result("swapped", Some(version)),
            Err(e) => refused(spec, current, &e),
        }
    }
}

/// What re-reading one model file found.
enum Read {
    /// The file is gone or unreadable.
    Missing,
    /// Its bytes are those of the model serving now.
    Unchanged,
    /// Different bytes, loaded (or refused).
    Loaded(Result<(crate::registry::SceneInfo, Box<dyn crossview_core::Encoder>)>),
}

/// Counts and logs one reload's outcome.
fn log_outcome(outcome: &ReloadOutcome, spec: &ModelSpec, metrics: &Metrics) {
    metrics.model_reload(&outcome.scene, &outcome.outcome);
    match &outcome.error {
        Some(e) => {
            tracing::warn!(scene = %outcome.scene, path = %spec.path.display(), error = %e, "model refused; the old one keeps serving")
        }
        None => {
            tracing::info!(scene = %outcome.scene, outcome = %outcome.outcome, version = outcome.version.as_deref().unwrap_or("none"), "model reload")
        }
    }
}

fn refused(spec: &ModelSpec, version: Option<String>, e: &Error) -> ReloadOutcome {
    ReloadOutcome {
        scene: spec.name.clone(),
        outcome: "refused".to_string(),
        version,
        error: Some(crate::echo::truncate_echo(&e.report()).into_owned()),
    }
}

/// Starts listening for `SIGHUP`: from this call on the signal no longer ends the process,
/// and one that arrives before [`crate::service::spawn_reload_on_sighup`] runs is delivered
/// to it then.
#[cfg(unix)]
pub(crate) fn listen_sighup() -> Result<tokio::signal::unix::Signal> {
    use tokio::signal::unix::{SignalKind, signal};
    signal(SignalKind::hangup()).map_err(|e| Error::internal_from("cannot listen for SIGHUP", e))
}

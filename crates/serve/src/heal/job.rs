//! One retrain: cut the recording, train in a child process, gate in another, swap (see the
//! module docs of [`super`]).
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crossview_api::types::RetrainStatus;
use tokio::io::AsyncReadExt;
use tokio::process::Command;

use super::HealConfig;
use crate::locks::lock;
use crate::scene::Scene;
use crate::service::Service;

/// Exit status of `crossview model gate` for a refused candidate.
const GATE_REFUSED: i32 = 3;

/// Most bytes of a child's standard output read (the gate's verdict is one short line).
const MAX_STDOUT: u64 = 1 << 20;

/// How a retrain ended.
#[derive(Debug)]
pub(super) enum Outcome {
    /// The candidate passed the gate and serves now.
    Swapped { model: PathBuf, reason: String },
    /// The gate refused the candidate.
    Refused(String),
    /// Training, the gate or the swap failed.
    Failed(String),
    /// It ran past [`HealConfig::timeout`].
    TimedOut,
    /// The scene's model file changed meanwhile (an operator's reload).
    Superseded(String),
}

impl Outcome {
    /// The `outcome` label of `crossview_retrains_total`.
    pub(super) fn label(&self) -> &'static str {
        match self {
            Outcome::Swapped { .. } => "swapped",
            Outcome::Refused(_) => "refused",
            Outcome::Failed(_) => "failed",
            Outcome::TimedOut => "timed_out",
            Outcome::Superseded(_) => "superseded",
        }
    }

    /// Why, in words.
    pub(super) fn reason(&self) -> String {
        match self {
            Outcome::Swapped { reason, .. }
            | Outcome::Refused(reason)
            | Outcome::Failed(reason)
            | Outcome::Superseded(reason) => reason.clone(),
            Outcome::TimedOut => "stopped after --retrain-timeout".into(),
        }
    }
}

/// What one retrain needs.
pub(super) struct Job {
    pub(super) service: Arc<Service>,
    pub(super) scene: Arc<Scene>,
    pub(super) cfg: HealConfig,
    /// The first recording file of the new view.
    pub(super) from: u64,
    /// Files recorded while every camera fitted (first, first after), if any.
    pub(super) reference: Option<(u64, u64)>,
    /// The cameras that do not fit.
    pub(super) cameras: Vec<String>,
    pub(super) status: Arc<Mutex<RetrainStatus>>,
}

impl Job {
    /// Runs the retrain within [`HealConfig::timeout`]; the candidate and its training files
    /// are removed unless it was swapped in.
    pub(super) async fn run(self) -> Outcome {
        let name = self.scene.name().to_string();
        let started = unix_seconds();
        let candidate = self.cfg.dir.join(format!("{name}-{started}.onnx"));
        let outcome = match tokio::time::timeout(self.cfg.timeout, self.steps(&candidate)).await {
            Ok(o) => o,
            Err(_) => Outcome::TimedOut,
        };
        if !matches!(outcome, Outcome::Swapped { .. }) {
            remove_model(&candidate);
        }
        let _ = std::fs::remove_dir_all(candidate.with_extension("checkpoint"));
        let serving = self.service.model_path(self.scene.name());
        prune(&self.cfg.dir, &name, serving.as_deref());
        outcome
    }

    async fn steps(&self, candidate: &Path) -> Outcome {
        let Some(serving) = self.service.model_path(self.scene.name()) else {
            return Outcome::Failed("the scene has no model file to start from".into());
        };
        let Some(rec) = self.scene.recorder() else {
            return Outcome::Failed("the scene is not recorded".into());
        };
        let Some(to) = rec.mark().await else {
            return Outcome::Failed("the recorder has stopped".into());
        };
        let cut = Instant::now();
        let data: Vec<PathBuf> = rec
            .files_from(self.from)
            .into_iter()
            .filter(|(seq, _)| *seq < to)
            .map(|(_, p)| p)
            .collect();
        if data.is_empty() {
            return Outcome::Failed("nothing was recorded since the camera stopped fitting".into());
        }
        if let Err(e) = std::fs::create_dir_all(&self.cfg.dir) {
            return Outcome::Failed(format!("cannot create {}: {e}", self.cfg.dir.display()));
        }
        let members = match members_of(&serving).await {
            Ok(m) => m,
            Err(e) => return Outcome::Failed(e),
        };
        let log = candidate.with_extension("log");
        let train = self.train_args(&serving, candidate, &data, members);
        if let Err(e) = run_child(&self.cfg.program, &train, &log)
            .await
            .and_then(|o| {
                (o.code == Some(0))
                    .then_some(())
                    .ok_or_else(|| format!("training failed: {}", o.tail))
            })
        {
            return Outcome::Failed(e);
        }
        // The gate reads only what was recorded after the training data, at least
        // `gate_after` of it.
        self.set_state("gating");
        let wait = self.cfg.gate_after.saturating_sub(cut.elapsed());
        tokio::time::sleep(wait).await;
        let fresh: Vec<PathBuf> = rec.files_from(to).into_iter().map(|(_, p)| p).collect();
        let verdict = match self.gate(&serving, candidate, &fresh, &log).await {
            Ok(v) => v,
            Err(o) => return o,
        };
        let swap = self
            .service
            .adopt_model(self.scene.name(), candidate, &serving)
            .await;
        match (swap.outcome.as_str(), swap.error) {
            ("swapped", _) => Outcome::Swapped {
                model: candidate.to_path_buf(),
                reason: verdict,
            },
            ("superseded", e) => Outcome::Superseded(e.unwrap_or_default()),
            (o, e) => Outcome::Failed(format!("swap {o}: {}", e.unwrap_or_default())),
        }
    }

    /// Publishes the retrain's state.
    fn set_state(&self, state: &str) {
        let mut st = lock(&self.status);
        st.state = state.into();
        self.scene.set_retrain(st.clone());
    }

    /// `crossview train`'s arguments: every member of the serving model fine-tuned on `data`
    /// (the first stage only: the self-training stage needs more frames than a retrain has).
    fn train_args(
        &self,
        serving: &Path,
        candidate: &Path,
        data: &[PathBuf],
        members: usize,
    ) -> Vec<String> {
        let mut args: Vec<String> = vec!["--nice".into(), self.cfg.nice.to_string()];
        args.extend(["train", "--quiet", "--no-sync-check"].map(String::from));
        for d in data {
            args.extend(["--data".into(), d.display().to_string()]);
        }
        let members = members.clamp(1, 16).to_string();
        args.extend([
            "--init".into(),
            serving.display().to_string(),
            "--out".into(),
            candidate.display().to_string(),
            "--epochs".into(),
            self.cfg.epochs.to_string(),
            "--self-train-epochs".into(),
            "0".into(),
            // Training ends by itself before the retrain's timeout would kill it.
            "--max-train-seconds".into(),
            (self.cfg.timeout.as_secs_f64() * 0.8).max(1.0).to_string(),
            "--threads".into(),
            self.cfg.threads.to_string(),
            "--population".into(),
            members.clone(),
            "--ensemble".into(),
            members,
            // The retrained model keeps the serving model's form (no student of it).
            "--export".into(),
            "ensemble".into(),
            "--data-name".into(),
            format!("{} (retrained by serve)", self.scene.name()),
        ]);
        args
    }

    /// Runs `crossview model gate` on `fresh`: the verdict's reason when accepted, else the
    /// retrain's outcome.
    async fn gate(
        &self,
        serving: &Path,
        candidate: &Path,
        fresh: &[PathBuf],
        log: &Path,
    ) -> Result<String, Outcome> {
        if fresh.is_empty() {
            return Err(Outcome::Failed(
                "nothing was recorded after the training data to gate on".into(),
            ));
        }
        let mut args: Vec<String> = vec!["--nice".into(), self.cfg.nice.to_string()];
        args.extend(["model", "gate", "--json"].map(String::from));
        args.extend(["--tolerance".into(), self.cfg.tolerance.to_string()]);
        args.extend(["--serving".into(), serving.display().to_string()]);
        args.extend(["--candidate".into(), candidate.display().to_string()]);
        for f in fresh {
            args.extend(["--data".into(), f.display().to_string()]);
        }
        for c in &self.cameras {
            args.extend(["--camera".into(), c.clone()]);
        }
        if let (Some((a, b)), Some(rec)) = (self.reference, self.scene.recorder()) {
            for (seq, f) in rec.files_from(a) {
                if seq < b {
                    args.extend(["--reference".into(), f.display().to_string()]);
                }
            }
        }
        let out = run_child(&self.cfg.program, &args, log)
            .await
            .map_err(Outcome::Failed)?;
        let reason = serde_json::from_str::<serde_json::Value>(out.stdout.trim())
            .ok()
            .and_then(|v| v.get("reason")?.as_str().map(String::from));
        match (out.code, reason) {
            (Some(0), Some(r)) => Ok(r),
            (Some(GATE_REFUSED), Some(r)) => Err(Outcome::Refused(r)),
            _ => Err(Outcome::Failed(format!("the gate failed: {}", out.tail))),
        }
    }
}

/// Retrained models of scene `scene` kept in `dir` besides the serving one, and retrain logs.
const KEEP_MODELS: usize = 3;
const KEEP_LOGS: usize = 20;

/// Bounds what retrains of `scene` leave in `dir`: its newest [`KEEP_MODELS`] models (with
/// their curves) and the serving one, its newest [`KEEP_LOGS`] logs.
fn prune(dir: &Path, scene: &str, serving: Option<&Path>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let prefix = format!("{scene}-");
    let mut files: Vec<PathBuf> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            // `<scene>-<unix seconds>.<ext>` (not another scene's whose name extends this one)
            p.file_name()
                .and_then(|n| n.to_str()?.strip_prefix(&prefix))
                .and_then(|rest| rest.split_once('.'))
                .is_some_and(|(stamp, _)| {
                    !stamp.is_empty() && stamp.bytes().all(|b| b.is_ascii_digit())
                })
        })
        .collect();
    // Names carry the start time (seconds): newest first.
    files.sort_unstable_by(|a, b| b.cmp(a));
    let of = |ext: &'static str| {
        files
            .iter()
            .filter(move |p| p.extension().is_some_and(|e| e == ext))
    };
    for old in of("onnx")
        .filter(|p| Some(p.as_path()) != serving)
        .skip(KEEP_MODELS)
    {
        remove_model(old);
    }
    for old in of("log").skip(KEEP_LOGS) {
        let _ = std::fs::remove_file(old);
    }
}

/// Removes a model file and what its training wrote beside it (curve, history).
fn remove_model(path: &Path) {
    let _ = std::fs::remove_file(path);
    let _ = std::fs::remove_file(path.with_extension("svg"));
    let _ = std::fs::remove_file(path.with_extension("history.json"));
}

/// The number of members of the model file `path`.
async fn members_of(path: &Path) -> Result<usize, String> {
    let p = path.to_path_buf();
    tokio::task::spawn_blocking(move || {
        crossview_model::read_ensemble(&p)
            .map(|(e, _)| e.members().len())
            .map_err(|e| format!("cannot read the serving model: {e}"))
    })
    .await
    .unwrap_or_else(|e| Err(format!("reading the serving model panicked: {e}")))
}

/// What a child process left.
struct ChildOutput {
    code: Option<i32>,
    stdout: String,
    /// The last line it logged.
    tail: String,
}

/// Runs `program args`, its log (standard error) appended to `log`; killed when the retrain
/// is dropped (timeout, shutdown).
async fn run_child(program: &Path, args: &[String], log: &Path) -> Result<ChildOutput, String> {
    let log_file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(log)
        .map_err(|e| format!("cannot write {}: {e}", log.display()))?;
    let mut child = Command::new(program)
        .args(args)
        .env("CROSSVIEW_LOG_FORMAT", "text")
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::from(log_file))
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| format!("cannot start {}: {e}", program.display()))?;
    let mut stdout = String::new();
    if let Some(out) = child.stdout.take() {
        let _ = out.take(MAX_STDOUT).read_to_string(&mut stdout).await;
    }
    let status = child
        .wait()
        .await
        .map_err(|e| format!("waiting for {}: {e}", program.display()))?;
    Ok(ChildOutput {
        code: status.code(),
        stdout,
        tail: last_line(log),
    })
}

/// The last non-empty line of the file `path` (at most its last 4 KiB), for error messages.
fn last_line(path: &Path) -> String {
    let Ok(bytes) = std::fs::read(path) else {
        return String::new();
    };
    let tail = &bytes[bytes.len().saturating_sub(4096)..];
    String::from_utf8_lossy(tail)
        .lines()
        .rev()
        .find(|l| !l.trim().is_empty())
        .map(|l| crate::echo::truncate_echo(l.trim()).into_owned())
        .unwrap_or_default()
}

/// Seconds since the Unix epoch, for candidate file names (they sort in time).
fn unix_seconds() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d: Duration| d.as_secs())
}

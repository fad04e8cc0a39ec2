//! `crossview model gate`: whether a candidate model should replace the serving one, judged
//! without labels on a recording neither was chosen on — the check `serve --auto-retrain`
//! runs before it swaps a retrained model in, and one an operator can run by hand.
//!
//! Both models are scored on the same frames: the label-free key (cycle consistency of the
//! cross-view assignments, [`crossview_train::label_free`]) and each camera's **relative
//! contrast**: the mean contrast of its camera pairs' shift profiles ([`crossview_core::fit`])
//! over the scene's median camera (1: like the others; a camera that does not fit the model
//! falls toward 0). The candidate is accepted when its key is higher, the cameras that did not
//! fit (`--camera`) reach the fit level ([`FitConfig::misfit`]) or better their serving score,
//! and no other camera falls below the lower of the fit level and its serving score.
//!
//! Contrasts of two models are not comparable (each has its own scale of distances), and a
//! model that learnt little can look alike on every camera. So, given `--reference` (frames of
//! the scene from when every camera fitted the serving model), the candidate must also bring
//! the scene back to how it was: its key on the new frames within `--tolerance` of the serving
//! model's key on the reference, and every camera pair that carried a signal there (contrast
//! at least [`FitConfig::min_baseline`]) carrying one under the candidate.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use serde::Serialize;

use crossview_core::fit::{FitConfig, contrast, upper_median};
use crossview_core::offsets::{CameraSeries, OffsetConfig, frame_step};
use crossview_data::Recording;
use crossview_model::read_ensemble;
use crossview_train::label_free::{LabelFreeScorer, LabelFreeScores};
use crossview_train::prepare::prepare_as_trained;

use super::eval::check_scene;
use super::sync_check::{embed_series, profile_pairs};

/// Exit status of a refused candidate (0: accepted; 1: the check itself failed).
pub const REFUSED: i32 = 3;

/// Options of `crossview model gate`.
#[derive(Debug, Args)]
pub struct GateArgs {
    /// The model serving now.
    #[arg(long)]
    pub serving: PathBuf,
    /// The model that would replace it (same cameras).
    #[arg(long)]
    pub candidate: PathBuf,
    /// Unlabelled recording of the scene (a file or a directory, repeatable, read as one),
    /// recorded after the candidate's training data: frames neither model was chosen on.
    #[arg(long, required = true)]
    pub data: Vec<PathBuf>,
    /// A camera that did not fit the serving model (repeatable): the candidate must make it
    /// fit (or fit better than it did).
    #[arg(long)]
    pub camera: Vec<String>,
    /// Frames of the scene from when every camera fitted the serving model (a file or a
    /// directory, repeatable): the candidate must bring the scene back to how it was then.
    #[arg(long)]
    pub reference: Vec<PathBuf>,
    /// How far below the serving model's key on `--reference` the candidate's key on `--data`
    /// may be (crowds differ from one stretch of time to another).
    #[arg(long, default_value_t = 0.05)]
    pub tolerance: f64,
    /// Write the verdict as one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Seed of the label-free key's time-shift draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// One model's label-free scores on the gate's frames.
#[derive(Debug, Serialize)]
struct Judged {
    key: f64,
    scores: LabelFreeScores,
    /// Per camera, its relative contrast (`None`: no pair of it could be measured).
    cameras: Vec<Option<f32>>,
    /// Per camera pair `(a, b)`, its contrast.
    pairs: Vec<(usize, usize, Option<f32>)>,
}

/// What `gate` found.
#[derive(Debug, Serialize)]
struct Verdict {
    accepted: bool,
    reason: String,
    frames: usize,
    cameras: Vec<String>,
    serving: Judged,
    candidate: Judged,
    /// The serving model on `--reference`, when given.
    reference: Option<Judged>,
}

/// Runs `crossview model gate`; exits with [`REFUSED`] when the candidate is refused.
pub fn run(args: GateArgs) -> anyhow::Result<()> {
    let recording = crossview_data::recording::read_recordings(&args.data, false)
        .context("reading --data")?
        .0;
    let mut watched = Vec::new();
    for name in &args.camera {
        match recording.scene.cameras.iter().position(|c| &c.name == name) {
            Some(i) => watched.push(i),
            None => bail!(
                "--camera {name}: not a camera of scene '{}'",
                recording.scene.name
            ),
        }
    }
    if !(0.0..=1.0).contains(&args.tolerance) {
        bail!("--tolerance must be within [0, 1]");
    }
    let serving = judge(&args.serving, &recording, args.seed)?;
    let candidate = judge(&args.candidate, &recording, args.seed)?;
    let reference = if args.reference.is_empty() {
        None
    } else {
        let r = crossview_data::recording::read_recordings(&args.reference, false)
            .context("reading --reference")?
            .0;
        if r.scene.cameras != recording.scene.cameras {
            bail!("--reference holds other cameras than --data");
        }
        Some(judge(&args.serving, &r, args.seed)?)
    };
    let (mut accepted, mut reason) = decide(&serving, &candidate, &watched, &recording);
    if accepted && let Some(r) = &reference {
        (accepted, reason) = as_it_was(r, &candidate, args.tolerance, &recording);
    }
    let verdict = Verdict {
        accepted,
        reason,
        frames: recording.frames.len(),
        cameras: recording
            .scene
            .cameras
            .iter()
            .map(|c| c.name.clone())
            .collect(),
        serving,
        candidate,
        reference,
    };
    if args.json {
        println!("{}", serde_json::to_string(&verdict)?);
    } else {
        print!("{}", table(&verdict));
    }
    if !verdict.accepted {
        std::process::exit(REFUSED);
    }
    Ok(())
}

/// The scores of the model file `path` on `recording`.
fn judge(path: &PathBuf, recording: &Recording, seed: u64) -> anyhow::Result<Judged> {
    let (ensemble, meta) = read_ensemble(path).with_context(|| format!("{}", path.display()))?;
    check_scene(&recording.scene, &meta)?;
    let (set, _) = prepare_as_trained(recording, &meta, None, None)?;
    let scorer = LabelFreeScorer::new(set, vec![meta.threshold], seed)?;
    // One read of the file: its ensemble scores the key and embeds the fit's series.
    let mut encoder = ensemble;
    let (scores, _) = scorer.score(&mut encoder)?;
    let pairs = pair_contrasts(&mut encoder, recording)?;
    Ok(Judged {
        key: scores.key(),
        scores,
        cameras: relative_contrast(recording.scene.cameras.len(), &pairs),
        pairs,
    })
}

/// Each camera pair's contrast over the whole recording.
fn pair_contrasts(
    encoder: &mut dyn crossview_core::Encoder,
    recording: &Recording,
) -> anyhow::Result<Vec<(usize, usize, Option<f32>)>> {
    let n = recording.scene.cameras.len();
    let series = embed_series(encoder, recording, &vec![0; n])?;
    let step = frame_step(series.iter().flat_map(CameraSeries::frame_ids));
    let profiles = profile_pairs(&series, step, &OffsetConfig::default(), 1)?;
    let min_frames = FitConfig::default().min_frames;
    Ok(profiles
        .iter()
        .map(|(a, b, p)| {
            (
                *a,
                *b,
                contrast(p, i64::MIN, min_frames).map(|c| c.contrast),
            )
        })
        .collect())
}

/// Each camera's mean pair contrast, over the median camera's.
fn relative_contrast(n: usize, pairs: &[(usize, usize, Option<f32>)]) -> Vec<Option<f32>> {
    let mut sums = vec![(0.0f32, 0usize); n];
    for &(a, b, c) in pairs {
        if let Some(c) = c {
            for k in [a, b] {
                sums[k].0 += c;
                sums[k].1 += 1;
            }
        }
    }
    let means: Vec<Option<f32>> = sums
        .iter()
        .map(|&(s, k)| (k > 0).then(|| s / k as f32))
        .collect();
    let mut known: Vec<f32> = means.iter().flatten().copied().collect();
    let median = upper_median(&mut known).filter(|m| *m > 0.0);
    means
        .iter()
        .map(|m| m.zip(median).map(|(m, g)| m / g))
        .collect()
}

/// Whether `candidate` replaces `serving`, and why.
fn decide(
    serving: &Judged,
    candidate: &Judged,
    watched: &[usize],
    recording: &Recording,
) -> (bool, String) {
    if candidate.key.is_nan() || candidate.key <= serving.key {
        return (
            false,
            format!(
                "label-free key {:.4} not above the serving model's {:.4}",
                candidate.key, serving.key
            ),
        );
    }
    let level = FitConfig::default().misfit;
    for (c, cam) in recording.scene.cameras.iter().enumerate() {
        let (old, new) = (serving.cameras[c], candidate.cameras[c]);
        let Some(new) = new else {
            if watched.contains(&c) {
                return (
                    false,
                    format!("camera {}: unmeasured under the candidate", cam.name),
                );
            }
            continue;
        };
        let floor = if watched.contains(&c) {
            old.map_or(level, |o| level.min(o + f32::EPSILON))
        } else {
            old.map_or(0.0, |o| level.min(o))
        };
        if new < floor {
            return (
                false,
                format!(
                    "camera {} fits worse under the candidate: {new:.2} (needs {floor:.2})",
                    cam.name
                ),
            );
        }
    }
    (
        true,
        format!(
            "label-free key {:.4} above {:.4}; every camera fits",
            candidate.key, serving.key
        ),
    )
}

/// Whether `candidate` brings the scene back to how the serving model saw it on the reference.
fn as_it_was(
    reference: &Judged,
    candidate: &Judged,
    tolerance: f64,
    recording: &Recording,
) -> (bool, String) {
    if candidate.key < reference.key - tolerance {
        return (
            false,
            format!(
                "label-free key {:.4} below the scene's {:.4} before the change (tolerance {tolerance})",
                candidate.key, reference.key
            ),
        );
    }
    let min = FitConfig::default().min_baseline;
    let names = &recording.scene.cameras;
    for ((a, b, before), (_, _, now)) in reference.pairs.iter().zip(&candidate.pairs) {
        if before.is_some_and(|c| c >= min) && !now.is_some_and(|c| c >= min) {
            return (
                false,
                format!(
                    "cameras {} and {} no longer match under the candidate (contrast {} < {min})",
                    names[*a].name,
                    names[*b].name,
                    now.map_or("-".into(), |c| format!("{c:.3}"))
                ),
            );
        }
    }
    (
        true,
        format!(
            "label-free key {:.4} (the scene's before the change: {:.4}); every camera fits",
            candidate.key, reference.key
        ),
    )
}

fn table(v: &Verdict) -> String {
    let cell = |x: Option<f32>| x.map_or("-".to_string(), |x| format!("{x:.2}"));
    let mut out = format!(
        "{} frames\n{:<12} {:>9} {:>9}\n",
        v.frames, "", "serving", "candidate"
    );
    out.push_str(&format!(
        "{:<12} {:>9.4} {:>9.4}\n",
        "key", v.serving.key, v.candidate.key
    ));
    for (c, name) in v.cameras.iter().enumerate() {
        out.push_str(&format!(
            "{:<12} {:>9} {:>9}\n",
            name,
            cell(v.serving.cameras[c]),
            cell(v.candidate.cameras[c])
        ));
    }
    if let Some(r) = &v.reference {
        out.push_str(&format!(
            "{:<12} {:>9.4}  (serving, --reference)\n",
            "key before", r.key
        ));
    }
    let word = if v.accepted { "accepted" } else { "refused" };
    out.push_str(&format!("{word}: {}\n", v.reason));
    out
}

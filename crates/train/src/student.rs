//! **[ours]** What a population run exports: its ensemble, or the student distilled from it
//! ([`crate::distil`]) when the student is about as accurate.
//!
//! Both are scored without labels on the frames held out of training
//! ([`crate::label_free`]). The student must be within the tolerance of the ensemble on two
//! scores: the selection key (cycle consistency) and the **expected decision accuracy** (the
//! share of right keep/drop decisions over the Hungarian pairs, read off each model's own
//! calibration). Neither suffices alone: on WILDTRACK's training frames a single member 8 ACC
//! points below its ensemble has the higher cycle key, while the expected accuracy falls with
//! the labelled accuracy (BENCHMARKS.md, "One student"); and an encoder that learnt nothing
//! has a high expected accuracy (its calibration drops every pair, rightly) and a low key.
use serde::{Deserialize, Serialize};

use crate::data::TrainingSet;
use crate::distil::{DistilOptions, distil};
use crate::label_free::{LabelFreeScorer, LabelFreeScores};
use crossview_core::{Error, Result};
use crossview_model::Ensemble;

/// Which encoder `crossview train` writes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ExportMode {
    /// The student when its key and expected accuracy are both within
    /// [`StudentOptions::tolerance`] of the ensemble's, else the ensemble.
    Auto,
    /// The ensemble of the population's best members (the default: `Auto` is not yet
    /// reliable enough, BENCHMARKS.md "One student").
    #[default]
    Ensemble,
    /// The student, however it scores.
    Student,
}

impl std::str::FromStr for ExportMode {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(ExportMode::Auto),
            "ensemble" => Ok(ExportMode::Ensemble),
            "student" => Ok(ExportMode::Student),
            _ => Err(Error::invalid(
                "export",
                format!("{s:?} is not auto, ensemble or student"),
            )),
        }
    }
}

/// How a population run makes and judges its student.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StudentOptions {
    /// What is exported.
    pub export: ExportMode,
    /// The student's training.
    pub distil: DistilOptions,
    /// How far (a share, 0.003 = 0.3 points) the student's key and expected decision accuracy
    /// may each be below the ensemble's for [`ExportMode::Auto`] to write it.
    pub tolerance: f64,
}

impl Default for StudentOptions {
    fn default() -> Self {
        StudentOptions {
            export: ExportMode::Ensemble,
            distil: DistilOptions::default(),
            tolerance: DEFAULT_TOLERANCE,
        }
    }
}

/// Default of [`StudentOptions::tolerance`]: the 0.3 ACC points a student may lose.
pub const DEFAULT_TOLERANCE: f64 = 0.003;

/// What [`choose`] decided, for the model file (`crossview.export`) and the run's summary.
#[derive(Debug, Clone, Serialize)]
pub struct Choice {
    /// `ensemble` or `student`.
    pub exported: &'static str,
    /// Why, in words.
    pub why: String,
    /// The ensemble's label-free scores on the held-out frames, when measured.
    pub ensemble_scores: Option<LabelFreeScores>,
    /// The student's, when measured.
    pub student_scores: Option<LabelFreeScores>,
    /// The student's training (width, kept epoch, losses, seconds), when one was trained.
    pub student: Option<serde_json::Value>,
}

/// Distils `ensemble` on `train` and decides which of the two to export as `opts` says,
/// scoring both with `scorer` (frames neither trained on) when there is one.
pub fn choose(
    ensemble: Ensemble,
    train: &TrainingSet,
    scorer: Option<&LabelFreeScorer>,
    opts: &StudentOptions,
) -> Result<(Ensemble, Choice)> {
    let keep = |why: &str| Choice {
        exported: "ensemble",
        why: why.into(),
        ensemble_scores: None,
        student_scores: None,
        student: None,
    };
    if ensemble.members().len() < 2 {
        return Ok((ensemble, keep("one member: nothing to distil")));
    }
    if opts.export == ExportMode::Ensemble {
        return Ok((ensemble, keep("--export ensemble")));
    }
    if opts.export == ExportMode::Auto && scorer.is_none() {
        return Ok((
            ensemble,
            keep("no held-out frames to compare a student with"),
        ));
    }
    tracing::info!(
        members = ensemble.members().len(),
        epochs = opts.distil.epochs,
        "distilling the ensemble into one student"
    );
    let out = distil(&ensemble, train, &opts.distil, &mut |epoch, train, held| {
        tracing::debug!(epoch, train, held_out = held, "distillation epoch");
    })?;
    let student = Ensemble::single(out.weights);
    let record = serde_json::json!({
        "width": student.width(),
        "epoch": out.epoch,
        "held_out_loss": out.held_out_loss.get(out.epoch - 1),
        "seconds": out.seconds,
        "options": opts.distil,
    });
    let scores = match scorer {
        Some(s) => Some((
            s.score(&mut ensemble.clone())?.0,
            s.score(&mut student.clone())?.0,
        )),
        None => None,
    };
    let (exported, why) = verdict(opts, scores);
    let choice = Choice {
        exported,
        why,
        ensemble_scores: scores.map(|s| s.0),
        student_scores: scores.map(|s| s.1),
        student: Some(record),
    };
    Ok((
        if exported == "student" {
            student
        } else {
            ensemble
        },
        choice,
    ))
}

/// Which to write, and why, from the (ensemble, student) scores.
fn verdict(
    opts: &StudentOptions,
    scores: Option<(LabelFreeScores, LabelFreeScores)>,
) -> (&'static str, String) {
    let Some((e, s)) = scores else {
        return match opts.export {
            ExportMode::Student => ("student", "--export student".into()),
            _ => (
                "ensemble",
                "no held-out frames to compare the student with".into(),
            ),
        };
    };
    let words = format!(
        "key {:.2} % and expected accuracy {:.2} % against the ensemble's {:.2} % and {:.2} % on the held-out frames",
        100.0 * s.key(),
        100.0 * s.expected_acc,
        100.0 * e.key(),
        100.0 * e.expected_acc
    );
    let within =
        s.key() >= e.key() - opts.tolerance && s.expected_acc >= e.expected_acc - opts.tolerance;
    match opts.export {
        ExportMode::Student => ("student", format!("--export student; {words}")),
        _ if within => (
            "student",
            format!("{words} (within {:.2} points)", 100.0 * opts.tolerance),
        ),
        _ => (
            "ensemble",
            format!(
                "the student's {words}: one more than {:.2} points below",
                100.0 * opts.tolerance
            ),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scores(expected_acc: f64) -> LabelFreeScores {
        keyed(0.4, expected_acc)
    }

    fn keyed(cycle: f64, expected_acc: f64) -> LabelFreeScores {
        LabelFreeScores {
            sync_acc: 0.9,
            cycle,
            expected_acc,
            threshold: 0.4,
            consistent: 0.1,
        }
    }

    fn opts(export: ExportMode) -> StudentOptions {
        StudentOptions {
            export,
            ..StudentOptions::default()
        }
    }

    #[test]
    fn auto_writes_the_student_only_within_the_tolerance() {
        let auto = opts(ExportMode::Auto);
        let (e, s_close, s_far) = (scores(0.775), scores(0.7725), scores(0.7708));
        assert_eq!(verdict(&auto, Some((e, s_close))).0, "student");
        let (what, why) = verdict(&auto, Some((e, s_far)));
        assert_eq!(what, "ensemble");
        assert!(why.contains("77.08 %") && why.contains("77.50 %"), "{why}");
        // A student above its teacher is written.
        assert_eq!(verdict(&auto, Some((e, scores(0.8)))).0, "student");
        // A student whose key fell is not, however its expected accuracy reads (an encoder
        // that learnt nothing drops every pair and expects to be right).
        assert_eq!(verdict(&auto, Some((e, keyed(0.19, 0.98)))).0, "ensemble");
        // Its key 0.4: 0.396 is more than 0.3 points below, 0.3975 within.
        assert_eq!(verdict(&auto, Some((e, keyed(0.396, 0.775)))).0, "ensemble");
        assert_eq!(verdict(&auto, Some((e, keyed(0.3975, 0.775)))).0, "student");
        // Nothing to compare on: the ensemble.
        assert_eq!(verdict(&auto, None).0, "ensemble");
        // The tolerance is the user's.
        let wide = StudentOptions {
            tolerance: 0.01,
            ..auto
        };
        assert_eq!(verdict(&wide, Some((e, s_far))).0, "student");
    }

    #[test]
    fn student_mode_writes_the_student_whatever_it_scores() {
        let st = opts(ExportMode::Student);
        assert_eq!(verdict(&st, Some((scores(0.9), scores(0.1)))).0, "student");
        assert_eq!(verdict(&st, None).0, "student");
        assert_eq!(
            "student".parse::<ExportMode>().unwrap(),
            ExportMode::Student
        );
        assert!("both".parse::<ExportMode>().is_err());
    }
}

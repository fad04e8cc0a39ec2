//! `crossview model distil`: one encoder (the student) trained, without labels, to reproduce an
//! ensemble model's cross-view distances on a recording ([`crossview_train::distil`]), and
//! written as a model file of its own: one member to serve instead of many.
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crossview_model::{Ensemble, read_ensemble, write_ensemble_onnx};
use crossview_train::distil::{DistilLoss, DistilOptions, distil, held_out_frames};
use crossview_train::label_free::LabelFreeScorer;
use crossview_train::prepare::prepare_as_trained;
use crossview_train::validate::candidate_thresholds;

use super::eval::check_scene;

/// Options of `crossview model distil`.
#[derive(Debug, Args)]
pub struct DistilArgs {
    /// The teacher: a model file (an ensemble of several members is what this is for).
    #[arg(long)]
    pub teacher: PathBuf,
    /// Unlabelled recording of the teacher's cameras (ids are ignored), e.g. its training
    /// recording; thinned and filtered as the teacher's training was.
    #[arg(long)]
    pub data: PathBuf,
    /// Output model file (the student, with its own label-free calibration).
    #[arg(long)]
    pub out: PathBuf,
    /// Passes over the recording's frames.
    #[arg(long, default_value_t = DistilOptions::default().epochs)]
    pub epochs: usize,
    /// Student width (default: one and a half times the teacher's member width).
    #[arg(long)]
    pub width: Option<usize>,
    /// Student residual blocks (default: the teacher's members').
    #[arg(long)]
    pub blocks: Option<usize>,
    /// Adam learning rate.
    #[arg(long, default_value_t = DistilOptions::default().lr)]
    pub lr: f64,
    /// Frames per optimiser step.
    #[arg(long, default_value_t = DistilOptions::default().frames_per_step)]
    pub frames_per_step: usize,
    /// How the student's distances are compared with the teacher's.
    #[arg(long, default_value = "relative")]
    pub loss: DistilLoss,
    /// Distil on every box of the recording, not only those the teacher's training filter
    /// kept (small and static boxes are served too).
    #[arg(long)]
    pub all_boxes: bool,
    /// Threshold on the calibrated confidence stored as `crossview.match_threshold`.
    #[arg(long, default_value_t = 0.2)]
    pub match_threshold: f32,
    /// Frames per second of the recording (default: its header's, else the teacher's
    /// training rate).
    #[arg(long)]
    pub fps: Option<f64>,
    /// Seed of the student's frame order (and initialisation at another width).
    #[arg(long, default_value_t = 0, env = "CROSSVIEW_SEED")]
    pub seed: u64,
}

/// Runs `crossview model distil`.
pub fn run(a: DistilArgs) -> anyhow::Result<()> {
    super::compute::one_compute_thread_per_model();
    anyhow::ensure!(
        (0.0..=1.0).contains(&a.match_threshold),
        "--match-threshold must be within [0, 1], got {}",
        a.match_threshold
    );
    let (teacher, mut meta) = read_ensemble(&a.teacher)?;
    let recording = crossview_data::recording::read_recording(&a.data)?;
    check_scene(&recording.scene, &meta)?;
    let all_boxes = a.all_boxes.then(crossview_train::clean::BoxFilter::default);
    let (set, _) = prepare_as_trained(&recording.without_ids(), &meta, a.fps, all_boxes)?;
    let opts = DistilOptions {
        epochs: a.epochs,
        frames_per_step: a.frames_per_step,
        lr: a.lr,
        width: a.width,
        blocks: a.blocks,
        seed: a.seed,
        loss: a.loss,
        ..DistilOptions::default()
    };
    let out = distil(&teacher, &set, &opts, &mut |epoch, train, held| {
        tracing::info!(epoch, train, held_out = held, "distillation epoch");
    })
    .context("distillation failed")?;
    let student = Ensemble::single(out.weights);
    for key in ["crossview.population", "crossview.ensemble"] {
        meta.extra.remove(key);
    }
    meta.extra.insert(
        "crossview.distilled".into(),
        serde_json::json!({
            "teacher": a.teacher.file_name().map(|n| n.to_string_lossy().into_owned()),
            "teacher_members": teacher.members().len(),
            "teacher_width": teacher.width(),
            "options": opts,
            "epoch": out.epoch,
            "held_out_loss": out.held_out_loss.get(out.epoch - 1),
            "seconds": out.seconds,
        })
        .to_string(),
    );
    compare(
        &teacher,
        &student,
        &held_out_frames(&set, opts.holdout_every),
        a.seed,
    );
    // Calibrated on the frames and boxes it was distilled on (SPEC §3's P(same | distance)).
    let cal = crossview_train::calibrate::calibrate(&mut student.clone(), &set, a.seed)?;
    meta.calibration = Some(std::sync::Arc::new(cal));
    meta.match_threshold = Some(a.match_threshold);
    meta.validate(&a.out.display().to_string())?;
    write_ensemble_onnx(&a.out, &student, &meta)?;
    println!(
        "wrote {} (one member of width {}, epoch {} of {} kept by the held-out loss {:.3e}, {:.0} s)",
        a.out.display(),
        student.width(),
        out.epoch,
        a.epochs,
        out.held_out_loss
            .get(out.epoch - 1)
            .copied()
            .unwrap_or(f32::NAN),
        out.seconds
    );
    Ok(())
}

/// Prints the teacher's and the student's label-free scores on the held-out frames (what
/// `crossview train --export auto` compares), or why they cannot be scored.
fn compare(teacher: &Ensemble, student: &Ensemble, held: &crossview_train::TrainingSet, seed: u64) {
    let scored = LabelFreeScorer::new(held.clone(), candidate_thresholds(), seed).and_then(|s| {
        Ok((
            s.score(&mut teacher.clone())?.0,
            s.score(&mut student.clone())?.0,
        ))
    });
    match scored {
        Ok((t, s)) => println!(
            "on {} held-out frames: expected accuracy {:.2} % (teacher {:.2} %), cycle key {:.4} (teacher {:.4})",
            held.num_frames(),
            100.0 * s.expected_acc,
            100.0 * t.expected_acc,
            s.key(),
            t.key()
        ),
        Err(e) => println!("the held-out frames cannot be scored: {e}"),
    }
}

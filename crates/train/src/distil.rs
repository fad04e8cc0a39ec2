//! **[ours]** Label-free distillation: one encoder (the student) taught to reproduce an
//! ensemble's (the teacher's) cross-view distances on the training recording, so that one
//! member serves what six learnt.
//!
//! The loss is relational: for every frame of a step, the distances between boxes of
//! *different* cameras (the only ones matching compares), each divided by its frame's mean, of
//! the student against the teacher's (squared error). Dividing by the mean leaves the
//! student its own scale, which matching ignores (SPEC §3 normalises per image pair). No labels
//! are involved; the weights kept are those with the lowest loss on held-out frames.
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;

use crate::adam::Adam;
use crate::data::TrainingSet;
use crate::model::{TrainModel, ce};
use crossview_core::{Error, Result};
use crossview_model::{EncoderConfig, EncoderWeights, Ensemble};

/// How a student is trained.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DistilOptions {
    /// Passes over the training frames.
    pub epochs: usize,
    /// Frames per optimiser step.
    pub frames_per_step: usize,
    /// Adam learning rate (cosine decay to a hundredth over the epochs).
    pub lr: f64,
    /// Student width; `None`: one and a half times the teacher's member width (96 for
    /// width-64 members: within 0.3 ACC of its teacher for each of five teachers on the
    /// WILDTRACK training frames, where width 64 with twice the depth was for three;
    /// BENCHMARKS.md, "One student"). A student of its members' shape starts from the first
    /// (best) member, any other from a fresh encoder.
    pub width: Option<usize>,
    /// Student residual blocks; `None`: the teacher's members'.
    #[serde(default)]
    pub blocks: Option<usize>,
    /// One frame in this many is held out to choose the epoch (0: none, the last is kept).
    pub holdout_every: usize,
    /// Initialisation and frame order.
    pub seed: u64,
    /// How distances are compared.
    #[serde(default)]
    pub loss: DistilLoss,
}

/// How the student's distances are compared with the teacher's.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DistilLoss {
    /// Each distance over its frame's mean; squared difference.
    #[default]
    Relative,
    /// The logarithm of each distance less its frame's mean logarithm; squared difference
    /// (every ratio counts alike, so near pairs weigh as much as far ones).
    Log,
}

impl std::str::FromStr for DistilLoss {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "relative" => Ok(DistilLoss::Relative),
            "log" => Ok(DistilLoss::Log),
            _ => Err(Error::invalid(
                "loss",
                format!("{s:?} is not relative or log"),
            )),
        }
    }
}

impl Default for DistilOptions {
    fn default() -> Self {
        DistilOptions {
            epochs: 120,
            frames_per_step: 4,
            lr: 3e-3,
            width: None,
            blocks: None,
            holdout_every: 10,
            seed: 0,
            loss: DistilLoss::Relative,
        }
    }
}

/// Widest student [`distil`] trains (the default members are 64 wide).
pub const MAX_WIDTH: usize = 4096;
/// Deepest student [`distil`] trains.
pub const MAX_BLOCKS: usize = 64;

/// A trained student.
#[derive(Debug, Clone)]
pub struct DistilOutcome {
    /// The kept weights.
    pub weights: EncoderWeights,
    /// Training loss per epoch.
    pub train_loss: Vec<f32>,
    /// Held-out loss per epoch (empty without held-out frames).
    pub held_out_loss: Vec<f32>,
    /// The kept epoch (1-based).
    pub epoch: usize,
    /// Wall seconds of the training.
    pub seconds: f64,
}

/// One frame's boxes, cameras and teacher embeddings, ready for a step.
struct FrameBatch {
    boxes: Vec<[f32; 4]>,
    cams: Vec<u32>,
    /// `[n, teacher width]`.
    teacher: Tensor,
    /// Number of cross-camera ordered pairs.
    pairs: f64,
}

impl FrameBatch {
    /// `[n, n]`: 1 where the two boxes are of different cameras (built per step: stored for
    /// every frame it would cost a square of the boxes each).
    fn mask(&self) -> candle_core::Result<Tensor> {
        let n = self.cams.len();
        let cams = &self.cams;
        let mask: Vec<f32> = (0..n * n)
            .map(|k| f32::from(cams[k / n] != cams[k % n]))
            .collect();
        Tensor::from_vec(mask, (n, n), &Device::Cpu)
    }
}

/// Trains a student of `teacher` on `set`'s frames (see the module documentation);
/// `on_epoch(epoch, train, held_out)` after every epoch.
pub fn distil(
    teacher: &Ensemble,
    set: &TrainingSet,
    opts: &DistilOptions,
    on_epoch: &mut dyn FnMut(usize, f32, Option<f32>),
) -> Result<DistilOutcome> {
    let start = Instant::now();
    if opts.epochs == 0 || opts.frames_per_step == 0 || !(opts.lr > 0.0 && opts.lr.is_finite()) {
        return Err(Error::invalid(
            "distil",
            format!("epochs, frames per step and the learning rate must be positive, got {opts:?}"),
        ));
    }
    let shape_ok = |v: Option<usize>, max: usize| v.is_none_or(|v| (1..=max).contains(&v));
    if !shape_ok(opts.width, MAX_WIDTH) || !shape_ok(opts.blocks, MAX_BLOCKS) {
        return Err(Error::invalid(
            "distil",
            format!(
                "the student's width must be within 1..={MAX_WIDTH} and its blocks within \
                 1..={MAX_BLOCKS}, got {:?} and {:?}",
                opts.width, opts.blocks
            ),
        ));
    }
    let frames = frame_batches(teacher, set)?;
    let (held, train): (Vec<usize>, Vec<usize>) = (0..frames.len())
        .filter(|&i| frames[i].is_some())
        .partition(|&i| is_held_out(i, opts.holdout_every));

    if train.is_empty() {
        return Err(Error::Training(
            "no frame with boxes of two cameras to distil on".into(),
        ));
    }
    let model = student(teacher, opts)?;
    let mut adam = Adam::new(model.named_vars(), opts.lr)?;
    let mut order = train.clone();
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let (mut train_loss, mut held_out_loss) = (Vec::new(), Vec::new());
    let mut best: Option<(f32, usize, EncoderWeights)> = None;
    for epoch in 1..=opts.epochs {
        adam.lr = cosine(opts.lr, epoch - 1, opts.epochs);
        order.shuffle(&mut rng);
        let (mut sum, mut n) = (0f64, 0usize);
        for chunk in order.chunks(opts.frames_per_step) {
            let loss = step_loss(
                &model,
                chunk.iter().filter_map(|&i| frames[i].as_ref()),
                opts.loss,
            )?;
            let value = loss.to_scalar::<f32>().map_err(ce)?;
            if !value.is_finite() {
                return Err(Error::Training(format!(
                    "distillation loss became {value} at epoch {epoch}; lower the learning rate"
                )));
            }
            adam.step(&loss.backward().map_err(ce)?)?;
            sum += value as f64;
            n += 1;
        }
        let tl = (sum / n.max(1) as f64) as f32;
        train_loss.push(tl);
        let hl = held_loss(&model, &frames, &held, opts.loss)?;
        if let Some(h) = hl {
            held_out_loss.push(h);
        }
        on_epoch(epoch, tl, hl);
        let key = hl.unwrap_or(tl);
        if best.as_ref().is_none_or(|(b, _, _)| key <= *b) || held.is_empty() {
            best = Some((key, epoch, model.to_weights()?));
        }
    }
    let (_, epoch, weights) = best.expect("at least one epoch ran");
    Ok(DistilOutcome {
        weights,
        train_loss,
        held_out_loss,
        epoch,
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The frames of `set` [`distil`] holds out (one in `every`; none for 0), as a set of their own.
pub fn held_out_frames(set: &TrainingSet, every: usize) -> TrainingSet {
    fn held<T: Clone>(v: &[T], every: usize) -> Vec<T> {
        let kept = v.iter().enumerate().filter(|&(i, _)| is_held_out(i, every));
        kept.map(|(_, x)| x.clone()).collect()
    }
    TrainingSet {
        scene: set.scene.clone(),
        frame_ids: held(&set.frame_ids, every),
        images: held(&set.images, every),
    }
}

/// Whether frame `i` of a set is held out when one in `every` is (none for 0).
fn is_held_out(i: usize, every: usize) -> bool {
    every != 0 && i % every == 1
}

/// The student before training: the teacher's first member when the shapes agree, else a
/// fresh encoder of the members' Fourier and camera dimensions.
fn student(teacher: &Ensemble, opts: &DistilOptions) -> Result<TrainModel> {
    let first = &teacher.members()[0];
    let config = EncoderConfig {
        width: opts.width.unwrap_or(first.config.width * 3 / 2),
        blocks: opts.blocks.unwrap_or(first.config.blocks),
        ..first.config
    };
    if config == first.config {
        TrainModel::from_weights(first, opts.seed)
    } else {
        TrainModel::new(config, first.num_cameras, opts.seed)
    }
}

/// Cosine decay from `lr` to `lr / 100` over `epochs`.
fn cosine(lr: f64, epoch: usize, epochs: usize) -> f64 {
    let f = epoch as f64 / epochs.max(1) as f64;
    lr * (0.01 + 0.99 * 0.5 * (1.0 + (std::f64::consts::PI * f).cos()))
}

/// Each frame of `set` with the teacher's embeddings; `None` without boxes of two cameras.
fn frame_batches(teacher: &Ensemble, set: &TrainingSet) -> Result<Vec<Option<FrameBatch>>> {
    let dev = Device::Cpu;
    let mut out = Vec::new();
    for images in &set.images {
        let mut boxes = Vec::new();
        let mut cams = Vec::new();
        for (c, img) in images.iter().enumerate() {
            boxes.extend_from_slice(&img.boxes);
            cams.extend(std::iter::repeat_n(c as u32, img.boxes.len()));
        }
        let n = boxes.len() as f64;
        let same: f64 = images.iter().map(|i| (i.boxes.len() as f64).powi(2)).sum();
        let pairs = n * n - same;
        if pairs == 0.0 {
            out.push(None);
            continue;
        }
        let wide: Vec<i64> = cams.iter().map(|&c| c as i64).collect();
        let t = teacher.forward(&boxes, &wide)?;
        let teacher = Tensor::from_iter(t.iter().copied(), &dev)
            .and_then(|x| x.reshape(t.dim()))
            .map_err(ce)?;
        out.push(Some(FrameBatch {
            boxes,
            cams,
            teacher,
            pairs,
        }));
    }
    Ok(out)
}

/// Pairwise Euclidean distances of the rows of `x` (`[n, g]` → `[n, n]`).
fn distances(x: &Tensor) -> candle_core::Result<Tensor> {
    let sq = x.sqr()?.sum_keepdim(1)?; // [n, 1]
    let gram = x.matmul(&x.t()?)?;
    let d2 = sq.broadcast_add(&sq.t()?)?.sub(&(gram * 2.0)?)?.relu()?;
    (d2 + 1e-8)?.sqrt()
}

/// Cross-camera distances made scale-free as `kind` says (zero where `mask` is).
fn relative(
    d: &Tensor,
    mask: &Tensor,
    pairs: f64,
    kind: DistilLoss,
) -> candle_core::Result<Tensor> {
    match kind {
        DistilLoss::Relative => {
            let masked = d.mul(mask)?;
            let mean = (masked.sum_all()? / pairs)?;
            masked.broadcast_div(&(mean + 1e-8)?)
        }
        DistilLoss::Log => {
            let masked = d.log()?.mul(mask)?;
            let mean = (masked.sum_all()? / pairs)?;
            masked.broadcast_sub(&mean)?.mul(mask)
        }
    }
}

/// The mean relational loss over `frames` (differentiable in the student's parameters).
fn step_loss<'f>(
    model: &TrainModel,
    frames: impl Iterator<Item = &'f FrameBatch>,
    kind: DistilLoss,
) -> Result<Tensor> {
    let mut total: Option<Tensor> = None;
    let mut k = 0usize;
    for f in frames {
        let s = model.forward(&f.boxes, &f.cams)?.embedding;
        let run = || -> candle_core::Result<Tensor> {
            let mask = f.mask()?;
            let ds = relative(&distances(&s)?, &mask, f.pairs, kind)?;
            let dt = relative(&distances(&f.teacher)?, &mask, f.pairs, kind)?.detach();
            (ds - dt)?.sqr()?.sum_all()? / f.pairs
        };
        let l = run().map_err(ce)?;
        total = Some(match total {
            None => l,
            Some(t) => (t + l).map_err(ce)?,
        });
        k += 1;
    }
    let total = total.unwrap_or(Tensor::zeros((), DType::F32, &Device::Cpu).map_err(ce)?);
    (total / k.max(1) as f64).map_err(ce)
}

/// The mean loss over the held-out frames; `None` without any. Each frame's loss is read out
/// as it is computed, so no frame's graph outlives it (nothing here is differentiated). The
/// sum and the division are [`step_loss`]'s, in the same order and precision.
fn held_loss(
    model: &TrainModel,
    frames: &[Option<FrameBatch>],
    held: &[usize],
    kind: DistilLoss,
) -> Result<Option<f32>> {
    if held.is_empty() {
        return Ok(None);
    }
    let (mut sum, mut k) = (0f32, 0usize);
    for f in held.iter().filter_map(|&i| frames[i].as_ref()) {
        let loss = step_loss(model, std::iter::once(f), kind)?;
        sum += loss.to_scalar::<f32>().map_err(ce)?;
        k += 1;
    }
    Ok(Some(sum * (1.0 / k.max(1) as f64) as f32))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::testing::cameras;
    use crossview_core::{Detection, Frame, SceneSpec};
    use crossview_data::Recording;

    /// `cams` cameras that see three walkers (each camera its own affine view of the place),
    /// for `frames` frames.
    fn walkers(cams: usize, frames: u64) -> TrainingSet {
        let scene = SceneSpec {
            name: "s".into(),
            cameras: cameras(cams, 100, 100),
        };
        let frames = (0..frames)
            .map(|t| {
                let mut f = Frame::new(t, cams);
                for (c, view) in f.views.iter_mut().enumerate() {
                    let boxes = (0..3)
                        .map(|k| {
                            let x = ((t as f32 * (1.5 + k as f32)) + 30.0 * k as f32) % 70.0;
                            let x = x * (1.0 - 0.1 * c as f32) + 5.0 * c as f32;
                            Detection::new([x, 10.0 + c as f32, x + 12.0, 55.0])
                        })
                        .collect();
                    *view = Some(boxes);
                }
                f
            })
            .collect();
        let rec = Recording {
            scene,
            frames,
            fps: None,
        };
        TrainingSet::from_recording(&rec, 1).unwrap()
    }

    fn teacher(cams: usize) -> Ensemble {
        let config = EncoderConfig {
            width: 16,
            fourier_features: 4,
            camera_dim: 4,
            blocks: 1,
        };
        Ensemble::new(
            (0..3)
                .map(|k| EncoderWeights::random(cams, config, 7 + k).unwrap())
                .collect(),
        )
        .unwrap()
    }

    #[test]
    fn the_held_out_frames_are_one_in_every_and_keep_their_images() {
        let set = walkers(3, 25);
        let held = held_out_frames(&set, 10);
        assert_eq!(held.frame_ids, vec![1, 11, 21]);
        assert_eq!(held.images.len(), 3);
        assert_eq!(held.images[1], set.images[11]);
        assert_eq!(held.scene.cameras.len(), 3);
        assert_eq!(held_out_frames(&set, 0).num_frames(), 0);
    }

    #[test]
    fn the_student_learns_its_teachers_cross_view_distances() {
        let (set, teacher) = (walkers(3, 40), teacher(3));
        // The members' own shape: the student starts as the teacher's first member.
        let opts = DistilOptions {
            epochs: 40,
            lr: 3e-3,
            width: Some(16),
            blocks: Some(1),
            holdout_every: 5,
            ..DistilOptions::default()
        };
        let frames = frame_batches(&teacher, &set).unwrap();
        let held: Vec<usize> = (0..frames.len()).filter(|&i| is_held_out(i, 5)).collect();
        // Before training: the first member, one of the three the teacher's distances average.
        let before = held_loss(
            &student(&teacher, &opts).unwrap(),
            &frames,
            &held,
            opts.loss,
        )
        .unwrap()
        .unwrap();
        let mut seen = 0;
        let out = distil(&teacher, &set, &opts, &mut |_, _, held| {
            assert!(held.is_some());
            seen += 1;
        })
        .unwrap();
        assert_eq!(seen, 40);
        assert_eq!(
            (out.weights.config.width, out.weights.blocks.len()),
            (16, 1)
        );
        let kept = out.held_out_loss[out.epoch - 1];
        assert!(
            kept < 0.3 * before,
            "held-out loss {kept} against {before} at the start"
        );
        // The kept epoch is the one with the lowest held-out loss.
        assert!(out.held_out_loss.iter().all(|&l| l >= kept));
        // The kept weights are the student that scores that loss.
        let again = TrainModel::from_weights(&out.weights, 0).unwrap();
        let l = held_loss(&again, &frames, &held, opts.loss)
            .unwrap()
            .unwrap();
        assert!(
            (l - kept).abs() <= 1e-4 * kept.max(1e-6) + 1e-7,
            "{l} vs {kept}"
        );
    }

    #[test]
    fn another_shape_starts_fresh_and_learns_too() {
        let (set, teacher) = (walkers(3, 30), teacher(3));
        let opts = DistilOptions {
            epochs: 30,
            lr: 3e-3,
            width: Some(24),
            blocks: Some(2),
            holdout_every: 5,
            loss: DistilLoss::Log,
            ..DistilOptions::default()
        };
        let out = distil(&teacher, &set, &opts, &mut |_, _, _| {}).unwrap();
        assert_eq!(
            (out.weights.config.width, out.weights.blocks.len()),
            (24, 2)
        );
        let first = out.held_out_loss[0];
        assert!(
            out.held_out_loss[out.epoch - 1] < 0.5 * first,
            "{:?}",
            out.held_out_loss
        );
    }

    #[test]
    fn bad_options_and_unusable_frames_are_refused() {
        let (set, teacher) = (walkers(3, 20), teacher(3));
        for opts in [
            DistilOptions {
                epochs: 0,
                ..DistilOptions::default()
            },
            DistilOptions {
                lr: f64::NAN,
                ..DistilOptions::default()
            },
            DistilOptions {
                frames_per_step: 0,
                ..DistilOptions::default()
            },
        ] {
            let err = distil(&teacher, &set, &opts, &mut |_, _, _| {}).unwrap_err();
            assert!(err.to_string().contains("must be positive"), "{err}");
        }
        // One camera per frame: no cross-view distance to learn.
        let mut lonely = set.clone();
        for frame in &mut lonely.images {
            for img in frame.iter_mut().skip(1) {
                img.boxes.clear();
            }
        }
        let err = distil(
            &teacher,
            &lonely,
            &DistilOptions::default(),
            &mut |_, _, _| {},
        )
        .unwrap_err();
        assert!(err.to_string().contains("two cameras"), "{err}");
        for (width, blocks) in [(Some(0), None), (Some(1 << 20), None), (None, Some(1000))] {
            let opts = DistilOptions {
                width,
                blocks,
                ..DistilOptions::default()
            };
            let err = distil(&teacher, &set, &opts, &mut |_, _, _| {}).unwrap_err();
            assert!(err.to_string().contains("width must be within"), "{err}");
        }
        assert!("cosine".parse::<DistilLoss>().is_err());
        assert_eq!("log".parse::<DistilLoss>().unwrap(), DistilLoss::Log);
    }
}

//! The evaluation driver: run an [`Encoder`] over a recording with ground-truth ids, associate
//! every frame, and turn every image pair into a [`PairRecord`] for the SPEC §5 metrics.
use crate::identities::IdentityStats;
use crate::metrics::{Metrics, PairRecord, compute_metrics};
use crate::parallel::{DEFAULT_WINDOW, map_ordered};
use crossview_core::Encoder;
use crossview_core::association::{
    AssociationConfig, FrameAssociation, Mode, associate_frame_with, embed_frame,
};
use crossview_core::identity::identity_matches;
use crossview_core::matching::Match;
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::{Error, Result};
use crossview_core::{Frame, SceneSpec};
use crossview_data::Recording;

/// The result of one evaluation setting (mode and threshold).
#[derive(Debug, Clone, PartialEq)]
pub struct EvalRun {
    /// Which matches were scored.
    pub mode: Mode,
    /// Threshold used: on `S` for [`Mode::Pairwise`], on the identity confidence otherwise.
    pub threshold: f32,
    /// Appearance weight used (only relevant when the data has appearance vectors).
    pub alpha: f32,
    /// SPEC §5 metrics over all image pairs.
    pub metrics: Metrics,
    /// One record per image pair (the `--dump-pairs` lines; they carry the identity matches
    /// too).
    pub records: Vec<PairRecord>,
    /// Whole-identity scores of the identities built under this setting.
    pub identities: IdentityStats,
}

/// The ground-truth ids of every box of a frame; an error naming the box when one is missing.
pub fn frame_ids(scene: &SceneSpec, frame: &Frame) -> Result<Vec<Option<Vec<u64>>>> {
    frame
        .views
        .iter()
        .enumerate()
        .map(|(c, view)| {
            view.as_ref()
                .map(|dets| {
                    dets.iter()
                        .enumerate()
                        .map(|(i, d)| {
                            d.id.ok_or_else(|| {
                                let cam = scene.cameras.get(c).map_or("?", |c| c.name.as_str());
                                Error::invalid(
                                    format!(
                                        "frame {} camera '{cam}' detections[{i}].id",
                                        frame.frame_id
                                    ),
                                    "missing: evaluation needs ground-truth ids on every box",
                                )
                            })
                        })
                        .collect::<Result<Vec<u64>>>()
                })
                .transpose()
        })
        .collect()
}

/// The image-pair records of one associated frame (`ids` from [`frame_ids`]), each with the
/// matches implied by the frame's identities beside the pairs' own.
pub fn pair_records(
    scene: &SceneSpec,
    ids: &[Option<Vec<u64>>],
    assoc: &FrameAssociation,
) -> Vec<PairRecord> {
    let empty = Vec::new();
    let name = |c: usize| {
        scene
            .cameras
            .get(c)
            .map_or_else(|| c.to_string(), |c| c.name.clone())
    };
    assoc
        .pairs
        .iter()
        .map(|p| {
            let ids_of = |c: usize| ids.get(c).and_then(Option::as_ref).unwrap_or(&empty);
            PairRecord {
                frame_id: assoc.frame_id,
                camera_a: name(p.cam_a),
                camera_b: name(p.cam_b),
                ids_a: ids_of(p.cam_a).clone(),
                ids_b: ids_of(p.cam_b).clone(),
                scores: p.matching.scores.iter().copied().collect(),
                matches: p.matching.matches.iter().map(Match::triple).collect(),
                identity_matches: Some(
                    identity_matches(&assoc.identities, p)
                        .iter()
                        .map(Match::triple)
                        .collect(),
                ),
            }
        })
        .collect()
}

/// Evaluates `encoder` on `recording` under several settings at once: each frame is
/// embedded once and associated once per setting `(mode, threshold)`, the other parameters
/// taken from `base`. The threshold is SPEC §3's on `S` for [`Mode::Pairwise`] and the
/// identity threshold for the other modes. Every box must carry a ground-truth id. Image
/// pairs are all camera pairs of a frame with boxes on both sides.
pub fn evaluate_settings(
    encoder: &mut dyn Encoder,
    recording: &Recording,
    base: &AssociationConfig,
    settings: &[(Mode, f32)],
) -> Result<Vec<EvalRun>> {
    evaluate_settings_on(&mut [encoder], recording, base, settings)
}

/// [`evaluate_settings`] with the frames dealt to one worker thread per encoder
/// ([`map_ordered`]); every encoder must be the same model (one ONNX Runtime session each).
/// The records are collected in frame order, so the runs are identical to one encoder's
/// whatever the number of workers; the settings' metrics are then computed on as many
/// threads. Panics when `encoders` is empty.
pub fn evaluate_settings_on(
    encoders: &mut [&mut dyn Encoder],
    recording: &Recording,
    base: &AssociationConfig,
    settings: &[(Mode, f32)],
) -> Result<Vec<EvalRun>> {
    evaluate_settings_with(encoders, recording, base, settings, None)
}

/// [`evaluate_settings_on`] with identities that remember the past frames: each
/// [`Mode::Identities`] setting its own [`Memory`], fed in frame order as the server feeds a
/// scene's (`None`: each frame alone). The pairwise rows stay SPEC §3's, frame by frame. With
/// memory the frames are embedded on the workers and associated in frame order.
pub fn evaluate_settings_with(
    encoders: &mut [&mut dyn Encoder],
    recording: &Recording,
    base: &AssociationConfig,
    settings: &[(Mode, f32)],
    memory: Option<&MemoryConfig>,
) -> Result<Vec<EvalRun>> {
    if settings.is_empty() {
        return Err(Error::invalid("settings", "no evaluation setting given"));
    }
    if let Some(&(_, t)) = settings.iter().find(|(_, t)| !t.is_finite()) {
        return Err(Error::invalid(
            "threshold",
            format!("must be finite, got {t}"),
        ));
    }
    let configs: Vec<AssociationConfig> = settings
        .iter()
        .map(|&(mode, t)| base.with_mode(mode, t))
        .collect();
    let scene = &recording.scene;
    let mut records: Vec<Vec<PairRecord>> = vec![Vec::new(); settings.len()];
    let mut stats = vec![IdentityStats::default(); settings.len()];
    let mut memories: Vec<Option<Memory>> = configs
        .iter()
        .map(|c| {
            memory
                .filter(|_| c.mode == Mode::Identities)
                .map(|m| Memory::new(m.clone()))
        })
        .collect();
    let remembers: Vec<bool> = memories.iter().map(Option::is_some).collect();
    // Per frame: its ids and embeddings, and the scores of the settings without memory (those
    // with memory need frame order: the sink scores them).
    let frame_work = |encoder: &mut &mut dyn Encoder, _: usize, frame: &Frame| {
        let ids = frame_ids(scene, frame)?;
        let embeddings = embed_frame(*encoder, scene, frame)?;
        let scored: Vec<_> = configs
            .iter()
            .zip(&remembers)
            .map(|(cfg, &later)| {
                (!later).then(|| score(scene, frame, &ids, embeddings.clone(), cfg, None))
            })
            .collect();
        Ok((ids, embeddings, scored))
    };
    map_ordered(
        &recording.frames,
        encoders,
        DEFAULT_WINDOW,
        frame_work,
        |i, (ids, embeddings, scored)| {
            let frame = &recording.frames[i];
            let scored = scored
                .into_iter()
                .zip(&configs)
                .zip(memories.iter_mut())
                .map(|((done, cfg), m)| {
                    done.unwrap_or_else(|| {
                        score(scene, frame, &ids, embeddings.clone(), cfg, m.as_mut())
                    })
                });
            for (k, (frame_records, frame_stats)) in scored.enumerate() {
                records[k].extend(frame_records);
                stats[k].merge(&frame_stats);
            }
            Ok(())
        },
    )?;
    // The settings' metrics are independent (each sorts all its scores for AP): computed on
    // as many threads as there are workers, one setting each at a time.
    let mut metrics = Vec::with_capacity(settings.len());
    let mut threads = vec![(); encoders.len()];
    map_ordered(
        &records,
        &mut threads,
        1,
        |_, _, r| Ok::<_, Error>(compute_metrics(r)),
        |_, m| {
            metrics.push(m);
            Ok(())
        },
    )?;
    Ok(settings
        .iter()
        .zip(records)
        .zip(stats)
        .zip(metrics)
        .map(|(((&(mode, threshold), records), identities), metrics)| {
            tracing::debug!(%mode, threshold, pairs = metrics.pairs, "evaluated");
            EvalRun {
                mode,
                threshold,
                alpha: base.alpha,
                metrics,
                records,
                identities,
            }
        })
        .collect())
}

/// One setting's image-pair records and identity scores of one frame.
fn score(
    scene: &SceneSpec,
    frame: &Frame,
    ids: &[Option<Vec<u64>>],
    embeddings: crossview_core::FrameEmbeddings,
    cfg: &AssociationConfig,
    memory: Option<&mut Memory>,
) -> (Vec<PairRecord>, IdentityStats) {
    let assoc = associate_frame_with(frame, embeddings, cfg, memory);
    let mut frame_stats = IdentityStats::default();
    frame_stats.add_frame(&assoc.identities, ids);
    (pair_records(scene, ids, &assoc), frame_stats)
}

/// Evaluates `encoder` on `recording` with one configuration: the metrics of `cfg.mode`'s
/// matches and one record per image pair.
pub fn evaluate(
    encoder: &mut dyn Encoder,
    recording: &Recording,
    cfg: &AssociationConfig,
) -> Result<(Metrics, Vec<PairRecord>)> {
    let setting = (cfg.mode, cfg.threshold_of(cfg.mode));
    let mut runs = evaluate_settings(encoder, recording, cfg, &[setting])?;
    let run = runs
        .pop()
        .ok_or_else(|| Error::invalid("settings", "no result"))?;
    Ok((run.metrics, run.records))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::Detection;

    use crossview_core::testing::{BottomCentre, cameras};

    fn recording() -> Recording {
        let scene = SceneSpec {
            name: "s".into(),
            cameras: cameras(3, 100, 100),
        };
        let d = |x: f32, id: u64| Detection {
            id: Some(id),
            ..Detection::new([x, 10.0, x + 10.0, 50.0])
        };
        let mut f0 = Frame::new(0, 3);
        f0.views[0] = Some(vec![d(10.0, 1), d(50.0, 2)]);
        f0.views[1] = Some(vec![d(51.0, 2), d(11.0, 1), d(85.0, 3)]);
        f0.views[2] = Some(vec![]);
        let mut f1 = Frame::new(1, 3);
        f1.views[0] = Some(vec![d(20.0, 1)]);
        f1.views[2] = Some(vec![d(21.0, 1)]);
        Recording {
            scene,
            frames: vec![f0, f1],
            fps: None,
        }
    }

    #[test]
    fn evaluates_every_pair_with_boxes_on_both_sides() {
        let rec = recording();
        let (m, records) =
            evaluate(&mut BottomCentre, &rec, &AssociationConfig::default()).unwrap();
        let pairs: Vec<_> = records
            .iter()
            .map(|r| (r.frame_id, r.camera_a.as_str(), r.camera_b.as_str()))
            .collect();
        assert_eq!(pairs, vec![(0, "c0", "c1"), (1, "c0", "c2")]);
        assert_eq!(records[0].scores.len(), 6);
        assert_eq!(m.pairs, 2);
        assert_eq!(m.frames, 2);
        // Frame 1 has one box per view: max-normalisation makes its only S = 1 - d/(d + 1e-6)
        // ~ 0, so the pair is dropped (SPEC §3, without the reference's keep-last quirk).
        assert_eq!((m.correct, m.kept), (2, 2));
        // Frame 0: 2 correct + 1 TN (id 3) over 3 persons; frame 1: 0 over 1.
        assert_eq!(m.acc, 0.75);
        assert_eq!(m.ipaa_100, 0.5);
        let both = evaluate_settings(
            &mut BottomCentre,
            &rec,
            &AssociationConfig::default(),
            &[(Mode::Pairwise, 0.4), (Mode::Identities, 0.4)],
        )
        .unwrap();
        assert_eq!(both[1].metrics.acc, 0.75);
        assert_eq!(both[0].records.len(), both[1].records.len());
        // The pairwise records carry the identity matches, scored the same way.
        let ids: Vec<PairRecord> = both[0]
            .records
            .iter()
            .map(|r| r.as_identities().unwrap())
            .collect();
        assert_eq!(compute_metrics(&ids), both[1].metrics);
        assert_eq!(both[1].identities.frames, 2);
    }

    #[test]
    fn several_encoders_give_the_same_runs_as_one() {
        let mut rec = recording();
        let frames = rec.frames.clone();
        rec.frames = (0..9u64)
            .map(|k| Frame {
                frame_id: k,
                ..frames[k as usize % 2].clone()
            })
            .collect();
        let settings = [(Mode::Pairwise, 0.4), (Mode::Identities, 0.3)];
        let cfg = AssociationConfig::default();
        let one = evaluate_settings(&mut BottomCentre, &rec, &cfg, &settings).unwrap();
        let (mut a, mut b, mut c) = (BottomCentre, BottomCentre, BottomCentre);
        let mut three: Vec<&mut dyn Encoder> = vec![&mut a, &mut b, &mut c];
        let runs = evaluate_settings_on(&mut three, &rec, &cfg, &settings).unwrap();
        assert_eq!(runs, one);
        let ids: Vec<u64> = runs[0].records.iter().map(|r| r.frame_id).collect();
        assert!(ids.windows(2).all(|w| w[0] <= w[1]), "{ids:?}");
        // The first frame in order with a missing id is the error, as with one encoder.
        rec.frames[4].views[0].as_mut().unwrap()[0].id = None;
        rec.frames[7].views[0].as_mut().unwrap()[0].id = None;
        let err = evaluate_settings_on(&mut three, &rec, &cfg, &settings)
            .unwrap_err()
            .to_string();
        assert!(err.contains("frame 4 "), "{err}");
    }

    #[test]
    fn missing_ids_are_a_clear_error() {
        let mut rec = recording();
        rec.frames[1].views[2].as_mut().unwrap()[0].id = None;
        let err = evaluate(&mut BottomCentre, &rec, &AssociationConfig::default())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("frame 1 camera 'c2' detections[0].id"),
            "{err}"
        );
    }
}

//! Whole-frame association: embed every box of a frame in one encoder call, match every pair of
//! reported views, and build global identities.
use ndarray::Array2;

use crate::Encoder;
use crate::distances::{all_pairs_distances, euclidean_distances};
use crate::identity::{Identity, IdentityConfig, build_identities, identity_matches};
pub use crate::matching::ViewPair;
use crate::matching::match_from_distances;
use crate::memory::Memory;
use crate::{Error, Result};
use crate::{Frame, FrameEmbeddings, SceneSpec};

/// Everything computed for one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameAssociation {
    pub frame_id: u64,
    /// The frame's embeddings (per view; `None` for views that did not report).
    pub embeddings: FrameEmbeddings,
    /// Every pair `cam_a < cam_b` where both views have at least one box.
    pub pairs: Vec<ViewPair>,
    /// Identities over all views (camera-exclusive, consistent across views).
    pub identities: Vec<Identity>,
}

/// Which matches a [`FrameAssociation`]'s `pairs` report.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// SPEC §3: each camera pair matched on its own, Hungarian pairs with `S ≥ threshold`.
    #[default]
    Pairwise,
    /// **[ours]** each camera pair on its own, Hungarian pairs whose calibrated
    /// `P(same | distance)` (`S` when the model has no calibration) reaches the calibrated
    /// threshold (`IdentityConfig::threshold`).
    Calibrated,
    /// **[ours]** the matches implied by the identities.
    Identities,
}

impl std::str::FromStr for Mode {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "pairwise" => Ok(Mode::Pairwise),
            "calibrated" => Ok(Mode::Calibrated),
            "identities" | "global" => Ok(Mode::Identities),
            other => Err(Error::invalid(
                "mode",
                format!("expected 'pairwise', 'calibrated' or 'identities', got '{other}'"),
            )),
        }
    }
}

impl std::fmt::Display for Mode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Mode::Pairwise => "pairwise",
            Mode::Calibrated => "calibrated",
            Mode::Identities => "identities",
        })
    }
}

/// Association parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct AssociationConfig {
    /// SPEC §3 threshold on `S`: the pairwise matches keep Hungarian pairs with
    /// `S ≥ threshold` (what the paper's metrics score).
    pub threshold: f32,
    /// Appearance weight in the distance fusion (used only when appearance is present).
    pub alpha: f32,
    /// Which matches the frame's `pairs` report.
    pub mode: Mode,
    /// How identities are built and scored (their own confidence and threshold).
    pub identity: IdentityConfig,
}

impl AssociationConfig {
    /// The threshold `mode`'s matches are kept at: SPEC §3's on `S` for [`Mode::Pairwise`],
    /// the calibrated pairwise threshold for [`Mode::Calibrated`], the identities' link
    /// threshold for [`Mode::Identities`].
    pub fn threshold_of(&self, mode: Mode) -> f32 {
        match mode {
            Mode::Pairwise => self.threshold,
            Mode::Calibrated => self.identity.threshold,
            Mode::Identities => self.identity.link_threshold,
        }
    }

    /// This configuration reporting `mode`'s matches, kept at `threshold` (see
    /// [`Self::threshold_of`]).
    pub fn with_mode(&self, mode: Mode, threshold: f32) -> AssociationConfig {
        let mut cfg = self.clone();
        cfg.mode = mode;
        match mode {
            Mode::Pairwise => cfg.threshold = threshold,
            Mode::Calibrated => cfg.identity.threshold = threshold,
            Mode::Identities => cfg.identity.link_threshold = threshold,
        }
        cfg
    }
}

impl Default for AssociationConfig {
    /// The WILDTRACK reference setting: threshold 0.4, alpha 0.1, pairwise, uncalibrated
    /// identities at the same threshold.
    fn default() -> Self {
        AssociationConfig {
            threshold: 0.4,
            alpha: 0.1,
            mode: Mode::Pairwise,
            identity: IdentityConfig::default(),
        }
    }
}

/// Embeds every box of `frame` with ONE encoder call (boxes normalised by their camera's
/// image size, SPEC §2) and keeps the result as it came, with each view's rows:
/// `Some([n_c, G])` for reported views (possibly with zero rows), `None` for views that did
/// not report.
///
/// Errors when the frame's camera count differs from the scene's, when a detection is
/// invalid (non-finite, negative or inverted box, see [`crate::Detection::validate`]),
/// or when the encoder fails or returns the wrong number of rows.
pub fn embed_frame(
    encoder: &mut dyn Encoder,
    scene: &SceneSpec,
    frame: &Frame,
) -> Result<FrameEmbeddings> {
    if frame.views.len() != scene.cameras.len() {
        return Err(Error::invalid(
            format!("frame {}", frame.frame_id),
            format!(
                "has {} views but scene '{}' has {} cameras",
                frame.views.len(),
                scene.name,
                scene.cameras.len()
            ),
        ));
    }
    let total = frame.num_boxes();
    let mut boxes = Vec::with_capacity(total);
    let mut cameras = Vec::with_capacity(total);
    for (c, view) in frame.views.iter().enumerate() {
        let Some(dets) = view else { continue };
        let cam = &scene.cameras[c];
        for (i, d) in dets.iter().enumerate() {
            // The field name is only needed for the error: built when the box is invalid.
            if d.validate("", None).is_err() {
                d.validate(
                    &format!(
                        "frame {} camera '{}' detections[{i}]",
                        frame.frame_id, cam.name
                    ),
                    None,
                )?;
            }
            boxes.push(d.normalized(cam));
            cameras.push(c as i64);
        }
    }
    let dim = encoder.dim();
    let all = if total == 0 {
        Array2::zeros((0, dim))
    } else {
        encoder.embed(&boxes, &cameras)?
    };
    // `FrameEmbeddings::new` rejects an encoder that returns the wrong number of rows.
    let rows: Vec<Option<usize>> = frame
        .views
        .iter()
        .map(|v| v.as_ref().map(Vec::len))
        .collect();
    FrameEmbeddings::new(all, &rows)
}

/// Appearance matrix of a view when every box has a vector and all have one length.
fn appearance_matrix(dets: &[crate::Detection]) -> Option<Array2<f32>> {
    let len = dets.first()?.appearance.as_ref()?.len();
    let mut data = Vec::with_capacity(dets.len() * len);
    for d in dets {
        let a = d.appearance.as_ref()?;
        if a.len() != len {
            return None;
        }
        data.extend_from_slice(a);
    }
    Array2::from_shape_vec((dets.len(), len), data).ok()
}

/// Associates one frame from its per-view embeddings (as returned by [`embed_frame`]):
/// SPEC §3 matching for every pair `cam_a < cam_b` with boxes on both sides (see
/// [`associate_pairs`]), then the identities (always). The pairs' matches are the ones
/// `cfg.mode` names; score matrices and assignments are the same in every mode.
pub fn associate_frame(
    frame: &Frame,
    embeddings: FrameEmbeddings,
    cfg: &AssociationConfig,
) -> FrameAssociation {
    associate_frame_with(frame, embeddings, cfg, None)
}

/// [`associate_frame`] with the scene's [`Memory`] (frames given in frame order): the pairs'
/// distances carry what the past said along each camera's tracks (see [`crate::memory`]).
pub fn associate_frame_with(
    frame: &Frame,
    embeddings: FrameEmbeddings,
    cfg: &AssociationConfig,
    memory: Option<&mut Memory>,
) -> FrameAssociation {
    let (sizes, mut pairs) = match_pairs(frame, &embeddings, cfg, &[], memory);
    let identities = build_identities(&sizes, &pairs, &cfg.identity);
    match cfg.mode {
        Mode::Pairwise => {}
        Mode::Calibrated => {
            for p in &mut pairs {
                p.matching.matches = cfg.identity.kept(&p.matching);
            }
        }
        Mode::Identities => {
            for p in &mut pairs {
                p.matching.matches = identity_matches(&identities, p);
            }
        }
    }
    FrameAssociation {
        frame_id: frame.frame_id,
        embeddings,
        pairs,
        identities,
    }
}

/// The identities of one frame and nothing else (what the service returns): the same as
/// `associate_frame(..).identities` without building the per-mode match lists.
pub fn frame_identities(
    frame: &Frame,
    embeddings: &FrameEmbeddings,
    cfg: &AssociationConfig,
) -> Vec<Identity> {
    frame_identities_fenced(frame, embeddings, cfg, &[])
}

/// [`frame_identities`] with the cameras `fenced[c]` left out of association: no pair with
/// them is matched, so each of their boxes comes back as an identity of its own and the
/// other cameras' identities are what they would be without them (a camera that no longer
/// fits the model, [`crate::fit`], would otherwise link people wrongly).
pub fn frame_identities_fenced(
    frame: &Frame,
    embeddings: &FrameEmbeddings,
    cfg: &AssociationConfig,
    fenced: &[bool],
) -> Vec<Identity> {
    frame_identities_with(frame, embeddings, cfg, fenced, None)
}

/// [`frame_identities_fenced`] with the scene's [`Memory`] (frames given in frame order; a
/// fenced camera's memory is dropped): what the service returns.
pub fn frame_identities_with(
    frame: &Frame,
    embeddings: &FrameEmbeddings,
    cfg: &AssociationConfig,
    fenced: &[bool],
    memory: Option<&mut Memory>,
) -> Vec<Identity> {
    let (sizes, pairs) = match_pairs(frame, embeddings, cfg, fenced, memory);
    build_identities(&sizes, &pairs, &cfg.identity)
}

/// SPEC §3 matching alone, without identities: every pair `cam_a < cam_b` with boxes on both
/// sides, matched on its own (appearance fusion when every box of both views carries an
/// appearance vector of one common length). This is all the reference pipeline computes;
/// [`associate_frame`] adds the identities.
///
/// A view whose embedding row count disagrees with its detections is treated as empty
/// (with a warning); [`embed_frame`] never produces that.
pub fn associate_pairs(
    frame: &Frame,
    embeddings: &FrameEmbeddings,
    cfg: &AssociationConfig,
) -> Vec<ViewPair> {
    match_pairs(frame, embeddings, cfg, &[], None).1
}

/// Per-view box counts (0 for unusable views) and the pairwise matchings of the views not
/// `fenced`, their distances blended with `memory`'s when given.
fn match_pairs(
    frame: &Frame,
    embeddings: &FrameEmbeddings,
    cfg: &AssociationConfig,
    fenced: &[bool],
    mut memory: Option<&mut Memory>,
) -> (Vec<usize>, Vec<ViewPair>) {
    let nv = embeddings.num_views().min(frame.views.len());
    let sizes: Vec<usize> = (0..nv)
        .map(|c| match (&frame.views[c], embeddings.view(c)) {
            (Some(d), Some(e)) if d.len() == e.nrows() => d.len(),
            (Some(d), Some(e)) => {
                tracing::warn!(
                    camera = c,
                    boxes = d.len(),
                    embeddings = e.nrows(),
                    "embedding rows differ from detections; view ignored"
                );
                0
            }
            _ => 0,
        })
        .collect();
    let apps: Vec<Option<Array2<f32>>> = (0..nv)
        .map(|c| {
            if sizes[c] > 0 {
                frame.views[c].as_deref().and_then(appearance_matrix)
            } else {
                None
            }
        })
        .collect();
    // Views with boxes, in camera order, and all their pairwise geometric distances.
    let cams: Vec<usize> = (0..nv)
        .filter(|&c| sizes[c] > 0 && !fenced.get(c).copied().unwrap_or(false))
        .collect();
    let rows: Vec<_> = cams.iter().filter_map(|&c| embeddings.rows(c)).collect();
    let mut dists = all_pairs_distances(embeddings.matrix(), &rows).into_iter();
    if let Some(m) = memory.as_deref_mut() {
        m.begin(
            frame.frame_id,
            &usable_views(frame, &sizes),
            embeddings,
            fenced,
        );
    }
    let mut pairs = Vec::with_capacity(dists.len());
    for (x, &a) in cams.iter().enumerate() {
        for &b in &cams[x + 1..] {
            let Some(mut dg) = dists.next() else { break };
            if let Some(m) = memory.as_deref_mut() {
                m.blend(a, b, &mut dg, &cfg.identity);
            }
            let da = match (&apps[a], &apps[b]) {
                (Some(p), Some(q)) if p.ncols() == q.ncols() => {
                    Some(euclidean_distances(p.view(), q.view()))
                }
                _ => None,
            };
            let matching = match_from_distances(dg, da.as_ref(), cfg.alpha, cfg.threshold);
            pairs.push(ViewPair {
                cam_a: a,
                cam_b: b,
                matching,
            });
        }
    }
    if let Some(m) = memory {
        m.end();
    }
    (sizes, pairs)
}

/// Each view's boxes (pixels) where the view is usable (`sizes[c]` boxes, possibly none);
/// `None` for views that did not report or cannot be used.
fn usable_views(frame: &Frame, sizes: &[usize]) -> Vec<Option<Vec<[f32; 4]>>> {
    sizes
        .iter()
        .zip(&frame.views)
        .map(|(&n, v)| {
            let v = v.as_ref()?;
            (v.len() == n).then(|| v.iter().map(|d| d.bbox).collect())
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CameraSpec, Detection};

    /// Embeds a box as its normalised centre (plus the camera index scaled to nothing):
    /// the same ground point in every camera gives the same embedding.
    struct CentreEncoder {
        calls: usize,
    }

    impl Encoder for CentreEncoder {
        fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
            self.calls += 1;
            assert_eq!(boxes.len(), cameras.len());
            let mut out = Array2::zeros((boxes.len(), 2));
            for (i, b) in boxes.iter().enumerate() {
                out[(i, 0)] = (b[0] + b[2]) / 2.0;
                out[(i, 1)] = (b[1] + b[3]) / 2.0;
            }
            Ok(out)
        }
        fn dim(&self) -> usize {
            2
        }
    }

    fn scene(n: usize) -> SceneSpec {
        SceneSpec {
            name: "test".into(),
            cameras: (0..n)
                .map(|i| CameraSpec {
                    offset: 0,
                    offset_ms: 0,
                    name: format!("cam{i}"),
                    width: 100,
                    height: 100,
                })
                .collect(),
        }
    }

    fn det(x: f32, y: f32) -> Detection {
        Detection::new([x, y, x + 10.0, y + 20.0])
    }

    #[test]
    fn one_encoder_call_and_all_pairs_with_boxes() {
        let sc = scene(4);
        let mut frame = Frame::new(7, 4);
        frame.views[0] = Some(vec![det(10.0, 10.0), det(60.0, 60.0)]);
        frame.views[1] = Some(vec![det(61.0, 60.0), det(11.0, 10.0), det(90.0, 0.0)]);
        frame.views[2] = Some(vec![]);
        frame.views[3] = Some(vec![det(10.0, 11.0)]);
        let mut enc = CentreEncoder { calls: 0 };
        let emb = embed_frame(&mut enc, &sc, &frame).unwrap();
        assert_eq!(enc.calls, 1);
        assert_eq!(emb.view(0).unwrap().nrows(), 2);
        assert_eq!(emb.view(2).unwrap().nrows(), 0);
        let fa = associate_frame(&frame, emb, &AssociationConfig::default());
        let cams: Vec<_> = fa.pairs.iter().map(|p| (p.cam_a, p.cam_b)).collect();
        assert_eq!(cams, vec![(0, 1), (0, 3), (1, 3)]);
        let m01: Vec<_> = fa.pairs[0]
            .matching
            .matches
            .iter()
            .map(|m| (m.a, m.b))
            .collect();
        assert_eq!(m01, vec![(0, 1), (1, 0)]);
        // Identities cover every box exactly once.
        let covered: usize = fa.identities.iter().map(|i| i.members.len()).sum();
        assert_eq!(covered, 6);
        assert!(
            fa.identities
                .iter()
                .any(|i| i.members == vec![(0, 0), (1, 1), (3, 0)])
        );
    }

    #[test]
    fn a_fenced_camera_links_nobody_and_the_others_are_as_without_it() {
        let sc = scene(3);
        let mut frame = Frame::new(7, 3);
        frame.views[0] = Some(vec![det(10.0, 10.0), det(60.0, 60.0)]);
        frame.views[1] = Some(vec![det(61.0, 60.0), det(11.0, 10.0)]);
        frame.views[2] = Some(vec![det(10.0, 11.0), det(60.0, 61.0)]);
        let emb = embed_frame(&mut CentreEncoder { calls: 0 }, &sc, &frame).unwrap();
        let cfg = AssociationConfig::default();
        let mut fenced = frame_identities_fenced(&frame, &emb, &cfg, &[false, true, false]);
        let mut members: Vec<Vec<(usize, usize)>> =
            fenced.iter_mut().map(|i| i.members.clone()).collect();
        members.sort();
        // Camera 1's boxes alone; cameras 0 and 2 linked as they are without camera 1.
        assert_eq!(
            members,
            vec![
                vec![(0, 0), (2, 0)],
                vec![(0, 1), (2, 1)],
                vec![(1, 0)],
                vec![(1, 1)]
            ]
        );
        let all = frame_identities(&frame, &emb, &cfg);
        assert!(all.iter().any(|i| i.members.len() == 3), "{all:?}");
    }

    #[test]
    fn identities_mode_reports_identity_matches() {
        let sc = scene(2);
        let mut frame = Frame::new(1, 2);
        frame.views[0] = Some(vec![det(10.0, 10.0)]);
        frame.views[1] = Some(vec![det(11.0, 10.0)]);
        let mut enc = CentreEncoder { calls: 0 };
        let emb = embed_frame(&mut enc, &sc, &frame).unwrap();
        let cfg = AssociationConfig {
            mode: Mode::Identities,
            threshold: 0.0,
            // A lone pair's S is ≈ 0 but positive: kept at a zero link threshold.
            identity: IdentityConfig {
                link_threshold: 0.0,
                ..IdentityConfig::new(None, 0.0)
            },
            ..Default::default()
        };
        let fa = associate_frame(&frame, emb, &cfg);
        assert_eq!(fa.pairs[0].matching.matches.len(), 1);
        assert_eq!(fa.identities.len(), 1);
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let sc = scene(2);
        let mut enc = CentreEncoder { calls: 0 };
        let frame = Frame::new(1, 3);
        assert!(embed_frame(&mut enc, &sc, &frame).is_err());
        let mut frame = Frame::new(1, 2);
        frame.views[0] = Some(vec![Detection::new([f32::NAN, 0.0, 1.0, 1.0])]);
        let err = embed_frame(&mut enc, &sc, &frame).unwrap_err().to_string();
        assert!(err.contains("cam0"), "{err}");
        assert!("bogus".parse::<Mode>().is_err());
        assert_eq!("global".parse::<Mode>().unwrap(), Mode::Identities);
        assert_eq!("calibrated".parse::<Mode>().unwrap(), Mode::Calibrated);
    }
}

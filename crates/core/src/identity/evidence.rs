//! The frame's pairwise evidence: every camera pair's Hungarian partners with their
//! confidence, each box pair's additive weight (the parent module's documentation), read
//! from the full score matrices.
use ndarray::Array2;

use super::{IdentityConfig, ViewPair};

/// No partner.
pub(super) const NONE: u32 = u32::MAX;

/// One camera pair's full matrix, as seen from camera `from` (`flip`: `from` is the pair's
/// second camera, so `(u, v)` reads entry `(v, u)`).
#[derive(Clone, Copy)]
struct PairView<'a> {
    scores: &'a Array2<f32>,
    scale: f32,
    flip: bool,
}

/// The frame's evidence, indexed by flattened box (boxes numbered camera by camera) and
/// camera: `u * cameras + c`.
pub(super) struct Evidence<'a> {
    pub(super) cameras: usize,
    pub(super) offsets: Vec<usize>,
    pub(super) cam_of: Vec<usize>,
    /// Hungarian partner of box `u` in camera `c`, or [`NONE`].
    pub(super) partner: Vec<u32>,
    /// Confidence of that pair: `max(S, P)` (`S` without a calibration).
    pub(super) conf: Vec<f32>,
    /// Weight of that pair: `conf − threshold + support · agreeing third cameras`.
    pub(super) weight: Vec<f32>,
    /// Full matrix of camera pair `cu * cameras + cv`, when it was given.
    mats: Vec<Option<PairView<'a>>>,
    cfg: &'a IdentityConfig,
}

impl<'a> Evidence<'a> {
    /// The frame's evidence: every consistent camera pair's Hungarian partners and
    /// confidences (the first of a repeated pair; inconsistent ones are ignored with a
    /// warning), then each Hungarian pair's weight.
    pub(super) fn collect(
        view_sizes: &[usize],
        offsets: Vec<usize>,
        pairs: &'a [ViewPair],
        cfg: &'a IdentityConfig,
    ) -> Self {
        let cameras = view_sizes.len();
        let cam_of: Vec<usize> = view_sizes
            .iter()
            .enumerate()
            .flat_map(|(c, &s)| std::iter::repeat_n(c, s))
            .collect();
        let n = cam_of.len();
        let mut ev = Evidence {
            cameras,
            offsets,
            cam_of,
            partner: vec![NONE; n * cameras],
            conf: vec![0f32; n * cameras],
            weight: vec![0f32; n * cameras],
            mats: vec![None; cameras * cameras],
            cfg,
        };
        for pair in pairs {
            ev.add_pair(view_sizes, pair);
        }
        ev.weigh();
        ev
    }

    fn add_pair(&mut self, view_sizes: &[usize], pair: &'a ViewPair) {
        let cameras = self.cameras;
        let (ca, cb) = (pair.cam_a, pair.cam_b);
        let m = &pair.matching;
        let fits = ca != cb
            && ca < cameras
            && cb < cameras
            && m.scores.dim() == (view_sizes[ca], view_sizes[cb])
            && m.assignment
                .iter()
                .all(|p| p.a < view_sizes[ca] && p.b < view_sizes[cb]);
        if !fits || self.mats[ca * cameras + cb].is_some() {
            tracing::warn!(
                cam_a = ca,
                cam_b = cb,
                "ignoring inconsistent or repeated camera pair"
            );
            return;
        }
        let view = |flip| PairView {
            scores: &m.scores,
            scale: m.distance_scale,
            flip,
        };
        self.mats[ca * cameras + cb] = Some(view(false));
        self.mats[cb * cameras + ca] = Some(view(true));
        for p in &m.assignment {
            let (u, v) = (self.offsets[ca] + p.a, self.offsets[cb] + p.b);
            let (ku, kv) = (u * cameras + cb, v * cameras + ca);
            if self.partner[ku] != NONE || self.partner[kv] != NONE {
                continue; // not one-to-one: keep the first
            }
            let c = self.cfg.link_confidence(p);
            self.partner[ku] = v as u32;
            self.partner[kv] = u as u32;
            self.conf[ku] = c;
            self.conf[kv] = c;
        }
    }

    /// Each Hungarian pair's weight: its confidence over the threshold, plus `support` for
    /// every third camera whose Hungarian partners of both boxes are one box.
    fn weigh(&mut self) {
        let cameras = self.cameras;
        for u in 0..self.cam_of.len() {
            for cv in 0..cameras {
                let k = u * cameras + cv;
                let v = self.partner[k];
                if v == NONE || (v as usize) < u {
                    continue;
                }
                let v = v as usize;
                let (pu, pv) = (
                    &self.partner[u * cameras..(u + 1) * cameras],
                    &self.partner[v * cameras..(v + 1) * cameras],
                );
                let agree = pu
                    .iter()
                    .zip(pv)
                    .filter(|&(&x, &y)| x != NONE && x == y)
                    .count();
                let w = self.conf[k] - self.cfg.link_threshold + self.cfg.support * agree as f32;
                self.weight[k] = w;
                self.weight[v * cameras + self.cam_of[u]] = w;
            }
        }
    }

    /// The additive weight between boxes `u` and `v` (0 within a camera).
    pub(super) fn pair_weight(&self, u: usize, v: usize) -> f32 {
        let (cu, cv) = (self.cam_of[u], self.cam_of[v]);
        if cu == cv {
            return 0.0;
        }
        let k = u * self.cameras + cv;
        if self.partner[k] == v as u32 {
            return self.weight[k];
        }
        // Not the camera pair's choice: no evidence for, and against it as far as its own
        // confidence is below the threshold.
        (self.entry_confidence(u, v) - self.cfg.link_threshold).min(0.0)
    }

    /// The weight below which a pair vetoes a merge: `−veto · t` (`−∞` without a veto).
    pub(super) fn veto_floor(&self) -> f32 {
        let f = -self.cfg.veto * self.cfg.link_threshold;
        if f.is_nan() { f32::NEG_INFINITY } else { f }
    }

    /// Whether boxes `u`, `v` of different cameras have evidence at all (their camera pair's
    /// matrix was given).
    pub(super) fn has_evidence(&self, u: usize, v: usize) -> bool {
        self.mats[self.cam_of[u] * self.cameras + self.cam_of[v]].is_some()
    }

    /// `S` and the calibrated `P` (from the raw distance; `None` without a calibration or a
    /// raw distance) of any entry of a camera pair's matrix; `None` without a matrix.
    fn entry(&self, u: usize, v: usize) -> Option<(f32, Option<f32>)> {
        let (cu, cv) = (self.cam_of[u], self.cam_of[v]);
        let m = self.mats[cu * self.cameras + cv]?;
        let (a, b) = (u - self.offsets[cu], v - self.offsets[cv]);
        let s = if m.flip {
            m.scores[(b, a)]
        } else {
            m.scores[(a, b)]
        };
        let p = match &self.cfg.calibration {
            Some(cal) if m.scale.is_finite() => Some(cal.probability((1.0 - s) * m.scale)),
            _ => None,
        };
        Some((s, p))
    }

    /// The confidence of any entry: its `P` (`S` without one); 0 when unknown or not finite.
    fn entry_confidence(&self, u: usize, v: usize) -> f32 {
        let c = self.entry(u, v).map_or(0.0, |(s, p)| p.unwrap_or(s));
        if c.is_finite() { c } else { 0.0 }
    }

    /// The confidence `max(S, P)` of boxes `u`, `v` as a link (the Hungarian pair's own, or
    /// read off the matrix for other entries); 0 when unknown or not finite.
    pub(super) fn link_confidence(&self, u: usize, v: usize) -> f32 {
        let k = u * self.cameras + self.cam_of[v];
        if self.partner[k] == v as u32 {
            return self.conf[k];
        }
        let c = self
            .entry(u, v)
            .map_or(0.0, |(s, p)| p.map_or(s, |p| p.max(s)));
        if c.is_finite() { c } else { 0.0 }
    }
}

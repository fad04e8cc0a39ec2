//! The frame's Hungarian evidence: every camera pair's partners and confidences, each pair's
//! additive weight, and an identity's confidence (the parent module's documentation).
use super::{IdentityConfig, ViewPair};

/// No partner.
pub(super) const NONE: u32 = u32::MAX;

/// The frame's Hungarian evidence, indexed by flattened box (boxes numbered camera by camera)
/// and camera: `u * cameras + c`.
pub(super) struct Evidence {
    pub(super) cameras: usize,
    pub(super) offsets: Vec<usize>,
    pub(super) cam_of: Vec<usize>,
    /// Hungarian partner of box `u` in camera `c`, or [`NONE`].
    pub(super) partner: Vec<u32>,
    /// Confidence of that pair.
    pub(super) conf: Vec<f32>,
    /// Weight of that pair (see the module documentation).
    pub(super) weight: Vec<f32>,
    threshold: f32,
    conflict: f32,
}

impl Evidence {
    /// Whether a camera other than box `u`'s has boxes in this frame.
    pub(super) fn others_have_boxes(&self, u: usize) -> bool {
        let cu = self.cam_of[u];
        (0..self.cameras).any(|c| c != cu && self.offsets[c + 1] > self.offsets[c])
    }

    fn kept(&self, u: usize, c: usize) -> bool {
        let k = u * self.cameras + c;
        self.partner[k] != NONE && self.conf[k] >= self.threshold
    }

    /// The additive weight between boxes `u` and `v`.
    pub(super) fn pair_weight(&self, u: usize, v: usize) -> f32 {
        let (cu, cv) = (self.cam_of[u], self.cam_of[v]);
        if cu == cv {
            return 0.0;
        }
        let k = u * self.cameras + cv;
        if self.partner[k] == v as u32 {
            self.weight[k]
        } else if self.kept(u, cv) || self.kept(v, cu) {
            -self.conflict
        } else {
            0.0
        }
    }
}

impl Evidence {
    /// The frame's evidence: every camera pair's Hungarian partners and confidences, then each
    /// pair's weight (its confidence margin and what the third cameras say).
    pub(super) fn collect(
        view_sizes: &[usize],
        offsets: Vec<usize>,
        pairs: &[ViewPair],
        cfg: &IdentityConfig,
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
            threshold: cfg.threshold,
            conflict: cfg.conflict_penalty,
        };
        ev.add_partners(view_sizes, pairs, cfg);
        ev.weigh(cfg);
        ev
    }

    /// Records the Hungarian pairs of every consistent camera pair (the first of a repeated
    /// pair; inconsistent ones are ignored with a warning), one partner per box and camera.
    fn add_partners(&mut self, view_sizes: &[usize], pairs: &[ViewPair], cfg: &IdentityConfig) {
        let cameras = self.cameras;
        let mut seen_pair = vec![false; cameras * cameras];
        for pair in pairs {
            let (ca, cb) = (pair.cam_a, pair.cam_b);
            let fits = ca != cb
                && ca < cameras
                && cb < cameras
                && pair
                    .matching
                    .assignment
                    .iter()
                    .all(|p| p.a < view_sizes[ca] && p.b < view_sizes[cb]);
            if !fits || seen_pair[ca * cameras + cb] {
                tracing::warn!(
                    cam_a = ca,
                    cam_b = cb,
                    "ignoring inconsistent or repeated camera pair"
                );
                continue;
            }
            seen_pair[ca * cameras + cb] = true;
            seen_pair[cb * cameras + ca] = true;
            for p in &pair.matching.assignment {
                let (u, v) = (self.offsets[ca] + p.a, self.offsets[cb] + p.b);
                let (ku, kv) = (u * cameras + cb, v * cameras + ca);
                if self.partner[ku] != NONE || self.partner[kv] != NONE {
                    continue; // not one-to-one: keep the first
                }
                let c = cfg.confidence(p);
                self.partner[ku] = v as u32;
                self.partner[kv] = u as u32;
                self.conf[ku] = c;
                self.conf[kv] = c;
            }
        }
    }

    /// Each Hungarian pair's weight: its confidence margin over the threshold, plus the
    /// support bonus for every third camera that matches both boxes to one box, minus the
    /// dissent penalty for every third camera that matches them to different boxes.
    fn weigh(&mut self, cfg: &IdentityConfig) {
        let cameras = self.cameras;
        for u in 0..self.cam_of.len() {
            let cu = self.cam_of[u];
            for cv in 0..cameras {
                let k = u * cameras + cv;
                let v = self.partner[k];
                if v == NONE || (v as usize) < u {
                    continue;
                }
                let v = v as usize;
                let mut w = self.conf[k] - cfg.threshold;
                let (pu, pv) = (
                    &self.partner[u * cameras..(u + 1) * cameras],
                    &self.partner[v * cameras..(v + 1) * cameras],
                );
                for c in 0..cameras {
                    if c == cu || c == cv || pu[c] == NONE || pv[c] == NONE {
                        continue;
                    }
                    w += if pu[c] == pv[c] {
                        cfg.support_bonus
                    } else {
                        -cfg.dissent_penalty
                    };
                }
                self.weight[k] = w;
                self.weight[v * cameras + cu] = w;
            }
        }
    }
}

/// An identity's confidence (see the module documentation).
pub(super) fn confidence(ev: &Evidence, members: &[usize]) -> f32 {
    let c = ev.cameras;
    // How likely the members are one person: the mean confidence of the Hungarian pairs
    // inside the identity (1 for a single box).
    let (mut sum, mut k) = (0f32, 0u32);
    for &u in members {
        for &v in members {
            let kk = u * c + ev.cam_of[v];
            if u < v && ev.cam_of[u] != ev.cam_of[v] && ev.partner[kk] == v as u32 {
                sum += ev.conf[kk];
                k += 1;
            }
        }
    }
    let together = match (members.len(), k) {
        (1, _) => 1.0,
        (_, 0) => 0.0,
        _ => sum / k as f32,
    };
    // How likely it is complete: for every other camera, the chance that the best Hungarian
    // partner of any member there is someone else.
    let mut complete = 1f32;
    let mut any_partner = false;
    for cam in 0..c {
        if members.iter().any(|&u| ev.cam_of[u] == cam) {
            continue;
        }
        let best = members
            .iter()
            .filter(|&&u| ev.partner[u * c + cam] != NONE)
            .map(|&u| ev.conf[u * c + cam].clamp(0.0, 1.0))
            .reduce(f32::max);
        if let Some(best) = best {
            any_partner = true;
            complete *= 1.0 - best;
        }
    }
    if let [u] = members
        && !any_partner
        && ev.others_have_boxes(*u)
    {
        // No camera pair assigned this box although other cameras have boxes (its view has
        // more boxes than theirs): a coin toss.
        return 0.5;
    }
    together * complete
}

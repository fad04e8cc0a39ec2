//! **[ours]** Identities with memory: what the past frames said about two people, carried
//! along each camera's own tracks into the identity step.
//!
//! Each frame is otherwise associated alone, yet the same two people seen by the same two
//! cameras a moment ago were compared with evidence that still holds, and most single-frame
//! mistakes are transient (a box cut by an occluder, a detector's jitter). Two parts:
//!
//! 1. **Per-camera continuity** ([`links`]): each camera's boxes are linked to its boxes of the
//!    last frame it reported, by one assignment on where each old box and its embedding are
//!    expected now (their own smoothed motion); only confident links are kept, and a box
//!    without one starts fresh.
//! 2. **Evidence that accumulates**: for every camera pair, the raw geometric distance of two
//!    boxes becomes the exponentially weighted mean of the distances of the two tracks they
//!    continue — `λ·m + (1 − λ)·d` once the history is long ([`MemoryConfig::carry`] = λ),
//!    the plain mean while it is short — and that mean is remembered in turn. Strong present
//!    evidence is never overridden: a pair whose own `P(same | d)` reaches
//!    [`MemoryConfig::hold`] is taken as it is now and its memory starts over from it.
//!    Everything after the distances — normalisation, Hungarian, `S`, `P`, the identities —
//!    is the per-frame step unchanged, so a pair the present separates clearly is separated
//!    as soon as its mean says so (the memory of two different people is of two people).
//!
//! Bounded and never wrongly applied: the memory holds one distance per pair of boxes of the
//! cameras' last frames (what one frame holds); it is dropped whole when frame ids go
//! backwards or repeat (a restart, out-of-order frames), when they jump by more than
//! [`MemoryConfig::max_gap`] frames (in the scene's own id step), when the camera count
//! changes, and on [`Memory::clear`] (a model swap, a clock-offset change); a camera's part is
//! dropped when it is fenced, silent for longer than `max_gap` frames, or on
//! [`Memory::forget_camera`].
use ndarray::Array2;

use crate::distances::{NORM_EPS, finite_max_of};
use crate::identity::IdentityConfig;

pub(crate) mod links;

use links::CameraTracks;

/// How much the past counts, and how boxes are linked within a camera. Every default was
/// chosen on the WILDTRACK training frames under two models and on the simulator's `square4`
/// scenes (BENCHMARKS.md, "Identities with memory"); the validation frames only report.
#[derive(Debug, Clone, PartialEq)]
pub struct MemoryConfig {
    /// λ: the past's share of a pair's distance once the pair has a history (0 = every frame
    /// alone).
    pub carry: f32,
    /// Present evidence this strong — the pair's calibrated `P(same | d)` (`S` without a
    /// calibration) at least this — is taken as it is, and the pair's memory starts over from
    /// it.
    pub hold: f32,
    /// Weight of the embedding distance (in the camera's spacings) against `1 − IoU` in a
    /// within-camera link's cost.
    pub link_weight: f32,
    /// Largest embedding distance of a within-camera link, in the camera's spacings.
    pub link_gate: f32,
    /// A within-camera link is dropped when another entry of its row or column costs less by
    /// more than this (the assignment forced it).
    pub link_margin: f32,
    /// Most frames (in the scene's frame-id step) between two looks at a camera before its
    /// memory is dropped (the tracker's `max_age`).
    pub max_gap: u64,
    /// How fast a box's motion, and its embedding's, follow what was observed (the tracker's
    /// box velocity weight).
    pub velocity_weight: f32,
}

impl Default for MemoryConfig {
    fn default() -> Self {
        MemoryConfig {
            carry: 0.75,
            hold: 0.9,
            link_weight: 2.0,
            link_gate: 2.0,
            link_margin: 1.0,
            max_gap: 5,
            velocity_weight: 0.7,
        }
    }
}

impl MemoryConfig {
    /// The default memory with the past's share `carry` (what `--memory` sets); `None` for 0
    /// (each frame alone). An error outside `[0, 1)`: at 1 the present would never count.
    pub fn with_carry(carry: f32) -> crate::Result<Option<Self>> {
        if !(0.0..1.0).contains(&carry) {
            return Err(crate::Error::invalid(
                "memory",
                format!("the past's share must be in [0, 1) (0: each frame alone), got {carry}"),
            ));
        }
        Ok((carry > 0.0).then(|| MemoryConfig {
            carry,
            ..MemoryConfig::default()
        }))
    }
}

/// The memory of one scene (see the module documentation): feed it every frame in frame
/// order through [`crate::association::frame_identities_with`].
#[derive(Debug, Clone)]
pub struct Memory {
    cfg: MemoryConfig,
    cameras: Vec<CameraTracks>,
    /// What pair `a < b` remembers (index `a * cameras + b`): rows the boxes of `a`'s last
    /// look, columns `b`'s.
    pairs: Vec<Option<PairMemory>>,
    /// Which pairs this frame has written.
    written: Vec<bool>,
    last_frame: Option<u64>,
    /// The smallest positive step seen between frame ids (WILDTRACK's ids go by 5).
    step: Option<u64>,
}

impl Memory {
    /// An empty memory.
    pub fn new(cfg: MemoryConfig) -> Self {
        Memory {
            cfg,
            cameras: Vec::new(),
            pairs: Vec::new(),
            written: Vec::new(),
            last_frame: None,
            step: None,
        }
    }

    /// Forgets everything (a model swap, a clock-offset change).
    pub fn clear(&mut self) {
        self.cameras.clear();
        self.pairs.clear();
        self.written.clear();
        self.last_frame = None;
        self.step = None;
    }

    /// Forgets camera `c`'s tracks and every pair with it (a fenced or re-aligned camera).
    pub fn forget_camera(&mut self, c: usize) {
        let n = self.cameras.len();
        if c >= n {
            return;
        }
        self.cameras[c] = CameraTracks::default();
        for o in 0..n {
            let k = c.min(o) * n + c.max(o);
            self.pairs[k] = None;
        }
    }

    /// Remembered pair distances held now (the memory's size).
    pub fn remembered(&self) -> usize {
        self.pairs.iter().flatten().map(|p| p.mean.len()).sum()
    }

    /// For each camera, each box of the last frame: the index of the box of the camera's
    /// previous look that it continues, if any (empty for cameras that did not report).
    pub fn links(&self) -> Vec<Vec<Option<usize>>> {
        self.cameras.iter().map(|c| c.links().to_vec()).collect()
    }

    /// Starts frame `frame_id`: drops what no longer applies (see the module documentation),
    /// then links each reported camera's boxes (`views[c]`, `None` for cameras that did not
    /// report) to its last look; cameras `fenced[c]` are forgotten and not linked.
    pub(crate) fn begin(
        &mut self,
        frame_id: u64,
        views: &[Option<Vec<[f32; 4]>>],
        embeddings: &crate::FrameEmbeddings,
        fenced: &[bool],
    ) {
        self.age(frame_id, views.len());
        let step = self.step.unwrap_or(1);
        for (c, view) in views.iter().enumerate() {
            if fenced.get(c).copied().unwrap_or(false) {
                self.forget_camera(c);
                continue;
            }
            let emb = embeddings.view(c);
            self.cameras[c].look(frame_id, step, view.as_deref(), emb, &self.cfg);
        }
        self.written.iter_mut().for_each(|w| *w = false);
    }

    /// Drops everything on a restart, out-of-order id, long gap or new camera count; a
    /// camera's part when it has been silent too long. Learns the id step.
    fn age(&mut self, frame_id: u64, cameras: usize) {
        let fresh = match self.last_frame {
            None => true,
            Some(last) if frame_id <= last => true,
            Some(last) => {
                let d = frame_id - last;
                let step = self.step.map_or(d, |s| s.min(d));
                let gap = d / step.max(1);
                if gap <= self.cfg.max_gap {
                    self.step = Some(step);
                }
                gap > self.cfg.max_gap
            }
        };
        if fresh || self.cameras.len() != cameras {
            let step = if fresh { None } else { self.step };
            self.clear();
            self.step = step;
            self.cameras = vec![CameraTracks::default(); cameras];
            self.pairs = vec![None; cameras * cameras];
            self.written = vec![false; cameras * cameras];
        }
        self.last_frame = Some(frame_id);
        let (step, max_gap) = (self.step.unwrap_or(1), self.cfg.max_gap);
        for c in 0..cameras {
            if self.cameras[c].stale(frame_id, step, max_gap) {
                self.forget_camera(c);
            }
        }
    }

    /// Blends the present raw distances `d` of camera pair `a < b` (this frame's boxes) with
    /// what is remembered of the boxes they continue, and remembers the result.
    pub(crate) fn blend(&mut self, a: usize, b: usize, d: &mut Array2<f32>, id: &IdentityConfig) {
        let n = self.cameras.len();
        if a >= b || b >= n {
            return;
        }
        let k = a * n + b;
        let (la, lb) = (self.cameras[a].links(), self.cameras[b].links());
        let (rows, cols) = d.dim();
        if (rows, cols) != (la.len(), lb.len()) {
            self.pairs[k] = None;
            return;
        }
        if !d.is_standard_layout() {
            *d = d.as_standard_layout().into_owned();
        }
        let values = d.as_slice_mut().expect("standard layout");
        let mut weight = vec![1.0f32; values.len()];
        // A share outside [0, 1) (a hand-built configuration) remembers nothing.
        let old = self.pairs[k]
            .as_ref()
            .filter(|_| (0.0..1.0).contains(&self.cfg.carry));
        if let Some(old) = old {
            // Present evidence that holds: `P(same | d) ≥ hold`, i.e. `d` within its reach
            // (`S ≥ hold` without a calibration, `S` normalised as §3 normalises it).
            let reach = match &id.calibration {
                Some(cal) => cal.reach(self.cfg.hold),
                None => (1.0 - self.cfg.hold) * (finite_max_of(values) + NORM_EPS),
            };
            let carry = self.cfg.carry;
            let old_cols: Vec<usize> = lb
                .iter()
                .map(|l| l.filter(|&j| j < old.cols).unwrap_or(usize::MAX))
                .collect();
            let rows_of = values
                .chunks_exact_mut(cols)
                .zip(weight.chunks_exact_mut(cols));
            for ((row, w_row), l) in rows_of.zip(la) {
                let Some(base) = l.filter(|&p| p < old.rows()).map(|p| p * old.cols) else {
                    continue;
                };
                let (om, ow) = (
                    &old.mean[base..base + old.cols],
                    &old.weight[base..base + old.cols],
                );
                for ((v, wv), &pj) in row.iter_mut().zip(w_row.iter_mut()).zip(&old_cols) {
                    let (Some(&m), Some(&w)) = (om.get(pj), ow.get(pj)) else {
                        continue;
                    };
                    if !(m.is_finite() && v.is_finite()) || *v <= reach {
                        continue;
                    }
                    // The exponentially weighted mean of the pair's distances, its weights
                    // normalised: λ·m + (1 − λ)·d once the history is long, their plain mean
                    // at first (a short history is not trusted more than it deserves).
                    let past = carry * w;
                    *v = (past * m + *v) / (past + 1.0);
                    *wv = past + 1.0;
                }
            }
        }
        let mean = values.to_vec();
        self.pairs[k] = Some(PairMemory { cols, mean, weight });
        self.written[k] = true;
    }

    /// Ends the frame: the pairs it did not write follow their cameras' links (or go).
    pub(crate) fn end(&mut self) {
        let n = self.cameras.len();
        for a in 0..n {
            for b in a + 1..n {
                let k = a * n + b;
                if self.written[k] {
                    continue;
                }
                let Some(old) = self.pairs[k].take() else {
                    continue;
                };
                let ra = self.cameras[a].rows_from(old.rows());
                let rb = self.cameras[b].rows_from(old.cols);
                if let (Some(ra), Some(rb)) = (ra, rb)
                    && !ra.is_empty()
                    && !rb.is_empty()
                {
                    self.pairs[k] = Some(old.moved(&ra, &rb));
                }
            }
        }
    }
}

/// What one camera pair remembers: for each pair of boxes of the two cameras' last looks (row
/// major, `cols` per row), the weighted mean of its distances and the weight behind it (NaN
/// and 0 where nothing is remembered).
#[derive(Debug, Clone)]
struct PairMemory {
    cols: usize,
    mean: Vec<f32>,
    weight: Vec<f32>,
}

impl PairMemory {
    fn rows(&self) -> usize {
        self.mean.len().checked_div(self.cols).unwrap_or(0)
    }

    /// The memory re-indexed: row `i` is old row `rows[i]`, column `j` old column `cols[j]`.
    fn moved(&self, rows: &[Option<usize>], cols: &[Option<usize>]) -> PairMemory {
        let mut mean = Vec::with_capacity(rows.len() * cols.len());
        let mut weight = Vec::with_capacity(rows.len() * cols.len());
        for r in rows {
            for c in cols {
                let at = r.zip(*c).map(|(r, c)| r * self.cols + c);
                mean.push(at.map_or(f32::NAN, |k| self.mean[k]));
                weight.push(at.map_or(0.0, |k| self.weight[k]));
            }
        }
        PairMemory {
            cols: cols.len(),
            mean,
            weight,
        }
    }
}

#[cfg(test)]
mod tests;

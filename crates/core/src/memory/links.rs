//! Per-camera continuity: which box of a camera's last look each of its boxes now continues.
//!
//! One assignment per camera between its boxes now and its boxes of the last look, on a cost
//! of two cues: `1 − IoU` with where each old box is expected now (its own smoothed motion),
//! plus [`MemoryConfig::link_weight`] times the distance between the embeddings, each old one
//! moved on by its own smoothed velocity, in units of the camera's spacing (the median
//! distance from a box now to its nearest neighbour now: how far apart people are in this
//! view). A link is kept only when it is confident: its embedding distance within
//! [`MemoryConfig::link_gate`] spacings, and no other entry of its row or column cheaper by
//! more than [`MemoryConfig::link_margin`] (the assignment did not force it).
use ndarray::{Array2, ArrayView2};

use super::MemoryConfig;
use crate::distances::{dot_t, row_sq_norms};
use crate::lsa;
use crate::motion::{MovingBox, iou};

/// One camera's boxes of its last look and how they continue the look before.
#[derive(Debug, Clone, Default)]
pub(crate) struct CameraTracks {
    /// The last look's boxes, with their motion.
    boxes: Vec<MovingBox>,
    /// Their embeddings (rows) and the embeddings' change per frame (smoothed).
    emb: Option<(Array2<f32>, Array2<f32>)>,
    /// For each box of the last look: the index of the box of the look before it continues.
    links: Vec<Option<usize>>,
    /// How many boxes the look before had.
    before: usize,
    /// Frame id of the last look.
    seen_at: Option<u64>,
    /// Whether the last look is this frame's.
    fresh: bool,
}

impl CameraTracks {
    /// This frame's look: `view` (pixels; `None` when the camera did not report) with its
    /// embeddings `emb`, linked to the last look (see the module documentation).
    pub(crate) fn look(
        &mut self,
        frame_id: u64,
        step: u64,
        view: Option<&[[f32; 4]]>,
        emb: Option<ArrayView2<f32>>,
        cfg: &MemoryConfig,
    ) {
        self.fresh = false;
        let Some(view) = view else { return };
        let emb = emb.filter(|e| e.nrows() == view.len());
        let frames = self
            .seen_at
            .map_or(1, |s| (frame_id.saturating_sub(s) / step.max(1)).max(1));
        let links = match emb {
            Some(e) => self.link(view, e, frames, cfg),
            None => vec![None; view.len()],
        };
        self.advance(view, emb, links, frames, cfg.velocity_weight);
        self.seen_at = Some(frame_id);
        self.fresh = true;
    }

    /// The confident links of `view` (embeddings `emb`) to the last look, `frames` frames ago.
    fn link(
        &mut self,
        view: &[[f32; 4]],
        emb: ArrayView2<f32>,
        frames: u64,
        cfg: &MemoryConfig,
    ) -> Vec<Option<usize>> {
        let mut links = vec![None; view.len()];
        let Some((old, vel)) = &self.emb else {
            return links;
        };
        if view.is_empty()
            || self.boxes.is_empty()
            || old.ncols() != emb.ncols()
            || old.nrows() != self.boxes.len()
        {
            return links;
        }
        let unseen = u32::try_from(frames - 1).unwrap_or(u32::MAX);
        let predicted: Vec<[f32; 4]> = self
            .boxes
            .iter_mut()
            .map(|b| {
                b.unseen = unseen;
                b.predicted()
            })
            .collect();
        let d = expected_distances(emb, old.view(), vel.view(), frames);
        let m = predicted.len();
        let mut cost = Vec::with_capacity(d.len());
        for (row, b) in d.chunks_exact(m).zip(view) {
            let costs = row.iter().zip(&predicted);
            cost.extend(costs.map(|(&d, p)| 1.0 - iou(b, p) + cfg.link_weight * d));
        }
        let cost = Array2::from_shape_vec((view.len(), m), cost).expect("sized above");
        for (i, j) in lsa::assign(cost.view()) {
            if d[i * m + j] <= cfg.link_gate && unforced(&cost, i, j, cfg.link_margin) {
                links[i] = Some(j);
            }
        }
        links
    }

    /// Makes `view` the last look: linked boxes carry their motion on, the others start fresh.
    fn advance(
        &mut self,
        view: &[[f32; 4]],
        emb: Option<ArrayView2<f32>>,
        links: Vec<Option<usize>>,
        frames: u64,
        weight: f32,
    ) {
        let boxes = view
            .iter()
            .zip(&links)
            .map(|(&b, l)| match l {
                Some(j) => {
                    let mut m = self.boxes[*j].clone();
                    m.observe(b, weight);
                    m
                }
                None => MovingBox::new(b),
            })
            .collect();
        self.emb = emb.map(|e| {
            let mut vel = Array2::zeros(e.dim());
            if let Some((old, old_vel)) = &self.emb {
                let per = 1.0 / frames as f32;
                for (i, l) in links.iter().enumerate() {
                    let Some(j) = *l else { continue };
                    ndarray::Zip::from(vel.row_mut(i))
                        .and(e.row(i))
                        .and(old.row(j))
                        .and(old_vel.row(j))
                        .for_each(|v, &now, &then, &was| {
                            *v = was + weight * ((now - then) * per - was);
                        });
                }
            }
            (e.to_owned(), vel)
        });
        self.before = self.boxes.len();
        self.boxes = boxes;
        self.links = links;
    }

    /// This frame's links (empty when the camera did not report this frame).
    pub(crate) fn links(&self) -> &[Option<usize>] {
        if self.fresh { &self.links } else { &[] }
    }

    /// For each box of the last look, the row it had in a matrix of `len` rows written
    /// before this frame; `None` when such a matrix does not fit this camera.
    pub(crate) fn rows_from(&self, len: usize) -> Option<Vec<Option<usize>>> {
        if self.fresh {
            (len == self.before).then(|| self.links.clone())
        } else {
            (len == self.boxes.len()).then(|| (0..len).map(Some).collect())
        }
    }

    /// Whether the camera has been silent for more than `max_gap` frames.
    pub(crate) fn stale(&self, frame_id: u64, step: u64, max_gap: u64) -> bool {
        self.seen_at
            .is_some_and(|s| frame_id.saturating_sub(s) / step.max(1) > max_gap)
    }
}

/// The distances (row major, `[now, old]`) from the embeddings `now` to where the `old` ones
/// are expected `frames` frames later (moved by their velocities `vel`), in units of the
/// camera's spacing: one matrix product, against the boxes now too (the spacing), with
/// square roots taken only where a distance is used.
fn expected_distances(
    now: ArrayView2<f32>,
    old: ArrayView2<f32>,
    vel: ArrayView2<f32>,
    frames: u64,
) -> Vec<f32> {
    let mut both = ndarray::concatenate![ndarray::Axis(0), now, old];
    both.slice_mut(ndarray::s![now.nrows().., ..])
        .scaled_add(frames as f32, &vel);
    let gram = dot_t(now, both.view());
    let norms = row_sq_norms(both.view());
    let (norms, gram) = (
        norms.as_slice().expect("freshly collected"),
        gram.as_slice().expect("freshly made"),
    );
    let (n, width) = (now.nrows(), both.nrows());
    let mut nearest = Vec::with_capacity(n);
    let mut d = Vec::with_capacity(n * (width - n));
    for (i, row) in gram.chunks_exact(width).enumerate() {
        let sq = |(&g, &nj): (&f32, &f32)| (norms[i] + nj - 2.0 * g).max(0.0);
        let others = row[..i].iter().zip(&norms[..i]);
        let others = others.chain(row[i + 1..n].iter().zip(&norms[i + 1..n]));
        nearest.push(others.map(sq).fold(f32::INFINITY, f32::min));
        d.extend(row[n..].iter().zip(&norms[n..]).map(|x| sq(x).sqrt()));
    }
    let scale = 1.0 / spacing(nearest);
    d.iter_mut().for_each(|v| *v *= scale);
    d
}

/// The median over the boxes of the distance to their nearest other box, from each box's
/// squared distance to its nearest (the typical spacing of people in the view; 1 with fewer
/// than two boxes, never below 1e-6). The square root is taken of the median only (it keeps
/// the order).
fn spacing(mut nearest: Vec<f32>) -> f32 {
    nearest.retain(|v| v.is_finite());
    if nearest.is_empty() {
        return 1.0;
    }
    let mid = nearest.len() / 2;
    nearest.select_nth_unstable_by(mid, f32::total_cmp);
    nearest[mid].sqrt().max(1e-6)
}

/// Whether `(i, j)` was not forced by the assignment: no other entry of its row or column
/// costs less by more than `margin`.
fn unforced(cost: &Array2<f32>, i: usize, j: usize, margin: f32) -> bool {
    let floor = cost[(i, j)] - margin;
    let fine = |x: &f32| x.partial_cmp(&floor) != Some(std::cmp::Ordering::Less);
    cost.row(i).iter().all(fine) && cost.column(j).iter().all(fine)
}

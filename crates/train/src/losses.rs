//! The three self-supervised losses of SPEC §4, batched over many triplets per step:
//! the synchronization triplet loss on Hungarian-matched boxes, the per-camera re-projection
//! L1 loss, and the edge triplet loss on pseudo-persons between matched pairs.
use candle_core::Tensor;
use ndarray::{ArrayView2, s};
use rand::Rng;
use rand::seq::index::sample;

use crate::data::{Image, TrainingSet};
use crate::hinge::HingeSet;
use crate::model::{TrainModel, ce};
use crate::pseudo::PseudoLabels;
use crate::sampler::Triplet;
use crate::transport::soft_assignment;
use crossview_core::distances::{euclidean_distances, normalized_distance};
use crossview_core::matching::hungarian;
use crossview_core::{Error, Result};

/// Knobs of the loss computation that trade fidelity for speed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LossOptions {
    /// Edge pairs per matching: at most this many of the k(k-1)/2 unique unordered edges,
    /// drawn at random; 0 = all of them.
    pub max_edges: usize,
    /// Appearance weight when both images carry appearance vectors (SPEC §3).
    pub alpha: f32,
    /// **[ours]** Fraction of each image pair's Hungarian pairs that enter the image distance
    /// `H` and the edges: the most confident ones (smallest detached normalised distance).
    /// 1.0 = SPEC §4 (all pairs). Lower values ignore forced matches between boxes that have
    /// no counterpart (false detections, people seen by one camera only).
    pub pair_fraction: f32,
    /// **[ours]** Temperature of the synchronization loss's soft assignment
    /// ([`crate::transport`]); `None` = the Hungarian pairs (SPEC §4).
    pub temperature: Option<f32>,
}

impl Default for LossOptions {
    fn default() -> Self {
        LossOptions {
            max_edges: 0,
            alpha: 0.1,
            pair_fraction: 1.0,
            temperature: None,
        }
    }
}

/// Loss values of one step (averaged over its triplets).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct StepStats {
    /// Total loss.
    pub total: f32,
    /// Synchronization triplet loss.
    pub syn: f32,
    /// Re-projection loss.
    pub pro: f32,
    /// Edge triplet loss.
    pub edge: f32,
    /// **[ours]** Pseudo-identity loss (self-training stage; 0 without labels).
    pub id: f32,
    /// Triplets that contributed (non-empty images).
    pub triplets: usize,
}

/// The pseudo-person between boxes `u` and `v` (SPEC §4): bottom-centre at the midpoint of
/// their bottom-centres, width and height the means: `[gx - w/2, gy - h, gx + w/2, gy]`.
pub(crate) fn pseudo_box(u: [f32; 4], v: [f32; 4]) -> [f32; 4] {
    let gx = ((u[0] + u[2]) * 0.5 + (v[0] + v[2]) * 0.5) * 0.5;
    let gy = (u[3] + v[3]) * 0.5;
    let w = ((u[2] - u[0]) + (v[2] - v[0])) * 0.5;
    let h = ((u[3] - u[1]) + (v[3] - v[1])) * 0.5;
    [gx - w * 0.5, gy - h, gx + w * 0.5, gy]
}

/// The unique unordered edges `(s, t)`, `s < t`, over `k` matched pairs; at most `max`
/// of them drawn without replacement when `max > 0`.
pub(crate) fn edge_indices<R: Rng>(k: usize, max: usize, rng: &mut R) -> Vec<(usize, usize)> {
    let all: Vec<(usize, usize)> = (0..k)
        .flat_map(|s| (s + 1..k).map(move |t| (s, t)))
        .collect();
    if max == 0 || all.len() <= max {
        return all;
    }
    let mut picked: Vec<usize> = sample(rng, all.len(), max).into_vec();
    picked.sort_unstable();
    picked.into_iter().map(|i| all[i]).collect()
}

/// Pseudo-boxes of matching edges in two images: for each edge `(s, t)` of the matched pairs
/// `(a_t, b_t)`, the pseudo-person of `a_s, a_t` in the first image and of `b_s, b_t` in the
/// second.
pub(crate) fn edge_boxes(
    boxes_a: &[[f32; 4]],
    boxes_b: &[[f32; 4]],
    pairs: &[(usize, usize)],
    edges: &[(usize, usize)],
) -> Vec<([f32; 4], [f32; 4])> {
    edges
        .iter()
        .map(|&(s, t)| {
            let (a_s, b_s) = pairs[s];
            let (a_t, b_t) = pairs[t];
            (
                pseudo_box(boxes_a[a_s], boxes_a[a_t]),
                pseudo_box(boxes_b[b_s], boxes_b[b_t]),
            )
        })
        .collect()
}

/// The detached, max-normalised distance between two images' boxes (SPEC §3), fusing
/// appearance when both images carry it: what the Hungarian pairs (and the soft assignment)
/// of the synchronization loss minimise.
fn image_costs(
    emb_a: ArrayView2<f32>,
    emb_b: ArrayView2<f32>,
    img_a: &Image,
    img_b: &Image,
    alpha: f32,
) -> ndarray::Array2<f32> {
    let dg = euclidean_distances(emb_a, emb_b);
    let da = match (&img_a.appearance, &img_b.appearance) {
        (Some(a), Some(b)) => {
            let to_arr = |v: &Vec<Vec<f32>>| {
                let d = v[0].len();
                ndarray::Array2::from_shape_vec((v.len(), d), v.concat()).ok()
            };
            match (to_arr(a), to_arr(b)) {
                (Some(a), Some(b)) if a.ncols() == b.ncols() => {
                    Some(euclidean_distances(a.view(), b.view()))
                }
                _ => None,
            }
        }
        _ => None,
    };
    normalized_distance(&dg, da.as_ref(), alpha)
}

/// `Σ_i w_i Σ_c |pred_ic - target_ic|`: the re-projection L1 with per-box weights
/// (`1/n` for the boxes of the anchor and positive images, 0 for the negatives).
pub(crate) fn reprojection_loss(
    pred: &Tensor,
    target: &[[f32; 4]],
    weights: &[f32],
) -> Result<Tensor> {
    let dev = pred.device();
    let n = target.len();
    let run = || -> candle_core::Result<Tensor> {
        let tgt = Tensor::from_slice(target.as_flattened(), (n, 4), dev)?;
        let w = Tensor::from_slice(weights, n, dev)?;
        let l1 = (pred - tgt)?.abs()?.sum(1)?;
        (l1 * w)?.sum_all()
    };
    run().map_err(ce)
}

/// `((anchor row, positive row), (anchor row, negative row))` of one pseudo-identity triplet.
type IdTriplet = ((u32, u32), (u32, u32));

/// **[ours]** The pseudo-identity triplets of one anchor/positive image pair (same frame):
/// for each anchor box with a label that the positive image also has, the positive is that
/// box and the negative the positive image's other box nearest to the anchor (hardest, on
/// the detached embeddings). Row indices are offset by `oa` / `ob`.
fn identity_triplets(
    host: &ndarray::Array2<f32>,
    (oa, na): (usize, usize),
    (ob, nb): (usize, usize),
    label_a: impl Fn(usize) -> Option<u32>,
    label_b: impl Fn(usize) -> Option<u32>,
    out: &mut Vec<IdTriplet>,
) {
    if nb < 2 {
        return;
    }
    for a in 0..na {
        let Some(l) = label_a(a) else { continue };
        let Some(b) = (0..nb).find(|&b| label_b(b) == Some(l)) else {
            continue;
        };
        let ra = host.row(oa + a);
        let dist = |k: usize| {
            let d = &ra - &host.row(ob + k);
            d.dot(&d)
        };
        let neg = (0..nb)
            .filter(|&k| k != b)
            .min_by(|&x, &y| dist(x).total_cmp(&dist(y)))
            .expect("nb >= 2");
        let (ra, rb, rn) = ((oa + a) as u32, (ob + b) as u32, (ob + neg) as u32);
        out.push(((ra, rb), (ra, rn)));
    }
}

/// The boxes of one step's images in one batch: every box of every kept triplet's images,
/// their cameras, their re-projection weights and each triplet's (anchor, positive,
/// negative) start rows.
struct StepBatch {
    boxes: Vec<[f32; 4]>,
    cams: Vec<u32>,
    pro_w: Vec<f32>,
    offsets: Vec<[usize; 3]>,
}

impl StepBatch {
    fn new(set: &TrainingSet, kept: &[&Triplet]) -> Self {
        let mut b = StepBatch {
            boxes: Vec::new(),
            cams: Vec::new(),
            pro_w: Vec::new(),
            offsets: Vec::with_capacity(kept.len()),
        };
        for tr in kept {
            let mut o = [0usize; 3];
            for (k, r) in [tr.anchor, tr.positive, tr.negative]
                .into_iter()
                .enumerate()
            {
                o[k] = b.boxes.len();
                let boxes = &set.images[r.frame][r.camera].boxes;
                let w = if k < 2 { 1.0 / boxes.len() as f32 } else { 0.0 };
                b.boxes.extend_from_slice(boxes);
                b.cams
                    .extend(std::iter::repeat_n(r.camera as u32, boxes.len()));
                b.pro_w.extend(std::iter::repeat_n(w, boxes.len()));
            }
            b.offsets.push(o);
        }
        b
    }
}

/// What the Hungarian matches of one step select: the synchronization and edge hinge terms,
/// the edge boxes (embedded separately) and the pseudo-identity triplets.
struct Selected {
    syn: HingeSet,
    edge: HingeSet,
    edge_boxes: Vec<[f32; 4]>,
    edge_cams: Vec<u32>,
    id_triplets: Vec<IdTriplet>,
}

/// Runs the Hungarian matches on the detached embeddings `host` and gathers the pairs,
/// edges and pseudo-identity triplets of every kept triplet.
fn select_pairs<R: Rng>(
    set: &TrainingSet,
    kept: &[&Triplet],
    batch: &StepBatch,
    host: &ndarray::Array2<f32>,
    opts: &LossOptions,
    pseudo: Option<&PseudoLabels>,
    rng: &mut R,
) -> Selected {
    let img = |r: crate::sampler::ImageRef| &set.images[r.frame][r.camera];
    let t = kept.len();
    let mut sel = Selected {
        syn: HingeSet::new(t),
        edge: HingeSet::new(t),
        edge_boxes: Vec::new(),
        edge_cams: Vec::new(),
        id_triplets: Vec::new(),
    };
    for (ti, (tr, o)) in kept.iter().zip(&batch.offsets).enumerate() {
        let (ia, ip, ineg) = (img(tr.anchor), img(tr.positive), img(tr.negative));
        if let Some(pl) = pseudo {
            let (a, p) = (tr.anchor, tr.positive);
            identity_triplets(
                host,
                (o[0], ia.boxes.len()),
                (o[1], ip.boxes.len()),
                |k| pl.get(a.frame, a.camera, k),
                |k| pl.get(p.frame, p.camera, k),
                &mut sel.id_triplets,
            );
        }
        let view = |start: usize, n: usize| host.slice(s![start..start + n, ..]);
        let va = view(o[0], ia.boxes.len());
        let mut sides: Vec<Vec<(u32, u32, f32)>> = Vec::with_capacity(2);
        let mut edge_sides: Vec<Vec<(u32, u32)>> = Vec::with_capacity(2);
        for (other, start, r) in [(ip, o[1], tr.positive), (ineg, o[2], tr.negative)] {
            let cost = image_costs(va, view(start, other.boxes.len()), ia, other, opts.alpha);
            let pairs = hungarian(cost.view());
            let weighted = match opts.temperature {
                Some(eps) => soft_assignment(cost.view(), eps),
                None => pairs.iter().map(|&(a, b)| (a, b, 1.0)).collect(),
            };
            sides.push(
                weighted
                    .into_iter()
                    .map(|(a, b, w)| ((o[0] + a) as u32, (start + b) as u32, w))
                    .collect(),
            );
            let edges = edge_indices(pairs.len(), opts.max_edges, rng);
            let mut list = Vec::with_capacity(edges.len());
            for (l, r_box) in edge_boxes(&ia.boxes, &other.boxes, &pairs, &edges) {
                let li = sel.edge_boxes.len() as u32;
                sel.edge_boxes.push(l);
                sel.edge_cams.push(tr.anchor.camera as u32);
                sel.edge_boxes.push(r_box);
                sel.edge_cams.push(r.camera as u32);
                list.push((li, li + 1));
            }
            edge_sides.push(list);
        }
        sel.syn.add_weighted(ti, &sides[0], &sides[1]);
        sel.edge.add(ti, &edge_sides[0], &edge_sides[1]);
    }
    sel
}

/// Computes the total loss of one step over `triplets` (skipping those with an empty image).
/// With `pseudo` labels (the self-training stage) the pseudo-identity triplet loss is added.
/// Returns `None` when every triplet was skipped.
pub(crate) fn step_loss<R: Rng>(
    model: &TrainModel,
    set: &TrainingSet,
    triplets: &[Triplet],
    opts: &LossOptions,
    pseudo: Option<&PseudoLabels>,
    rng: &mut R,
) -> Result<Option<(Tensor, StepStats)>> {
    let img = |r: crate::sampler::ImageRef| &set.images[r.frame][r.camera];
    let kept: Vec<&Triplet> = triplets
        .iter()
        .filter(|t| {
            !img(t.anchor).boxes.is_empty()
                && !img(t.positive).boxes.is_empty()
                && !img(t.negative).boxes.is_empty()
        })
        .collect();
    let t = kept.len();
    if t == 0 {
        return Ok(None);
    }
    // 1. All real boxes of all images in one batch.
    let batch = StepBatch::new(set, &kept);
    let emb = model.forward(&batch.boxes, &batch.cams)?.embedding;
    let host = emb
        .flatten_all()
        .and_then(|x| x.to_vec1::<f32>())
        .map_err(ce)?;
    let host = ndarray::Array2::from_shape_vec((batch.boxes.len(), model.config.width), host)
        .map_err(|e| Error::Training(format!("embedding shape: {e}")))?;
    // 2. Hungarian on detached distances; gather pairs and edges.
    let sel = select_pairs(set, &kept, &batch, &host, opts, pseudo, rng);
    // 3. Losses.
    let zero = || Tensor::zeros((), candle_core::DType::F32, &model.device).map_err(ce);
    let l_syn = sel.syn.loss(&emb, t)?;
    let pred = model.decode(&emb, &batch.cams)?;
    let l_pro = (reprojection_loss(&pred, &batch.boxes, &batch.pro_w)? / t as f64).map_err(ce)?;
    let l_edge = if sel.edge.is_empty() {
        zero()?
    } else {
        let e = model.forward(&sel.edge_boxes, &sel.edge_cams)?.embedding;
        sel.edge.loss(&e, t)?
    };
    let l_id = if sel.id_triplets.is_empty() {
        zero()?
    } else {
        let mut id = HingeSet::new(sel.id_triplets.len());
        for (k, (pos, neg)) in sel.id_triplets.iter().enumerate() {
            id.add(k, &[*pos], &[*neg]);
        }
        id.loss(&emb, sel.id_triplets.len())?
    };
    let total = (&l_syn + &l_pro)
        .and_then(|x| x + &l_edge)
        .and_then(|x| x + &l_id)
        .map_err(ce)?;
    let scalar = |x: &Tensor| x.to_scalar::<f32>().map_err(ce);
    let stats = StepStats {
        total: scalar(&total)?,
        syn: scalar(&l_syn)?,
        pro: scalar(&l_pro)?,
        edge: scalar(&l_edge)?,
        id: scalar(&l_id)?,
        triplets: t,
    };
    Ok(Some((total, stats)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use ndarray::array;
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() < 1e-5
    }

    #[test]
    fn pseudo_box_is_midpoint_of_bottom_centres_with_mean_size() {
        // u: bottom-centre (1, 4), 2 x 4; v: bottom-centre (5, 4), 2 x 2.
        let p = pseudo_box([0.0, 0.0, 2.0, 4.0], [4.0, 2.0, 6.0, 4.0]);
        assert_eq!(p, [2.0, 1.0, 4.0, 4.0]);
        // The pseudo-person of a box with itself is the box.
        let b = [0.1, 0.2, 0.3, 0.7];
        let q = pseudo_box(b, b);
        assert!(q.iter().zip(b).all(|(x, y)| close(*x, y)));
        // Symmetric in its arguments.
        assert_eq!(
            pseudo_box([0.0, 0.0, 2.0, 4.0], [4.0, 2.0, 6.0, 4.0]),
            pseudo_box([4.0, 2.0, 6.0, 4.0], [0.0, 0.0, 2.0, 4.0])
        );
    }

    #[test]
    fn edges_are_unique_unordered_and_sampled_without_replacement() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        assert_eq!(edge_indices(3, 0, &mut rng), vec![(0, 1), (0, 2), (1, 2)]);
        assert!(edge_indices(1, 0, &mut rng).is_empty());
        assert!(edge_indices(0, 5, &mut rng).is_empty());
        let e = edge_indices(10, 7, &mut rng);
        assert_eq!(e.len(), 7);
        let mut d = e.clone();
        d.dedup();
        assert_eq!(d.len(), 7);
        assert!(e.iter().all(|&(s, t)| s < t && t < 10));
        assert_eq!(edge_indices(4, 100, &mut rng).len(), 6);
    }

    #[test]
    fn edge_boxes_follow_the_matched_pairs() {
        let a = [
            [0.0, 0.0, 2.0, 4.0],
            [4.0, 2.0, 6.0, 4.0],
            [9.0, 9.0, 10.0, 10.0],
        ];
        let b = [
            [100.0, 0.0, 102.0, 4.0],
            [50.0, 50.0, 51.0, 51.0],
            [104.0, 2.0, 106.0, 4.0],
        ];
        // a0 <-> b0, a1 <-> b2; a2 unmatched.
        let pairs = [(0, 0), (1, 2)];
        let e = edge_boxes(&a, &b, &pairs, &[(0, 1)]);
        assert_eq!(e, vec![([2.0, 1.0, 4.0, 4.0], [102.0, 1.0, 104.0, 4.0])]);
    }

    fn match_images(
        emb_a: ArrayView2<f32>,
        emb_b: ArrayView2<f32>,
        img_a: &Image,
        img_b: &Image,
        alpha: f32,
    ) -> Vec<(usize, usize)> {
        hungarian(image_costs(emb_a, emb_b, img_a, img_b, alpha).view())
    }

    #[test]
    fn hungarian_gather_pairs_boxes_by_nearest_embedding_globally() {
        // Greedy would pair a0-b0 (distance 0.1) and leave a1-b1 (distance 5); the optimal
        // assignment is a0-b1, a1-b0 (1 + 1).
        let ea = array![[0.0f32, 0.0], [2.0, 0.0]];
        let eb = array![[0.1f32, 0.0], [-1.0, 0.0]];
        let img = Image {
            boxes: vec![[0.0; 4]; 2],
            appearance: None,
        };
        let p = match_images(ea.view(), eb.view(), &img, &img, 0.1);
        assert_eq!(p, vec![(0, 1), (1, 0)]);
        // Rectangular: min(n, m) pairs.
        let eb3 = array![[5.0f32, 5.0], [0.0, 0.1], [2.0, 0.1]];
        let img3 = Image {
            boxes: vec![[0.0; 4]; 3],
            appearance: None,
        };
        assert_eq!(
            match_images(ea.view(), eb3.view(), &img, &img3, 0.1),
            vec![(0, 1), (1, 2)]
        );
    }

    #[test]
    fn hinge_uses_mean_raw_distances_of_the_gathered_pairs() {
        let dev = Device::Cpu;
        // rows: 0 anchor (0,0); 1 anchor (0,1); 2 pos (3,4); 3 pos (0,1); 4 neg (0,0); 5 neg (0,2)
        let emb = Tensor::from_slice(
            &[
                0.0f32, 0.0, 0.0, 1.0, 3.0, 4.0, 0.0, 1.0, 0.0, 0.0, 0.0, 2.0,
            ],
            (6, 2),
            &dev,
        )
        .unwrap();
        let mut h = HingeSet::new(2);
        // triplet 0: pos pairs (0,2)=5, (1,3)=0 -> mean 2.5; neg (0,4)=0, (1,5)=1 -> 0.5
        h.add(0, &[(0, 2), (1, 3)], &[(0, 4), (1, 5)]);
        // triplet 1 has no negative side: ignored.
        h.add(1, &[(0, 3)], &[]);
        let l = h.loss(&emb, 2).unwrap().to_scalar::<f32>().unwrap();
        // relu(2.5 - 0.5 + 1) / 2 = 1.5
        assert!(close(l, 1.5), "{l}");
        // A triplet well separated contributes 0.
        let mut h2 = HingeSet::new(1);
        h2.add(0, &[(1, 3)], &[(0, 2)]); // 0 - 5 + 1 < 0
        assert!(close(
            h2.loss(&emb, 1).unwrap().to_scalar::<f32>().unwrap(),
            0.0
        ));
        assert!(close(
            HingeSet::new(3)
                .loss(&emb, 3)
                .unwrap()
                .to_scalar::<f32>()
                .unwrap(),
            0.0
        ));
    }

    #[test]
    fn hinge_gradient_pulls_positives_together() {
        let dev = Device::Cpu;
        let v =
            candle_core::Var::from_slice(&[0.0f32, 0.0, 3.0, 4.0, 1.0, 0.0], (3, 2), &dev).unwrap();
        let mut h = HingeSet::new(1);
        h.add(0, &[(0, 1)], &[(0, 2)]);
        let l = h.loss(v.as_tensor(), 1).unwrap();
        assert!(close(l.to_scalar::<f32>().unwrap(), 5.0)); // 5 - 1 + 1
        let g = l.backward().unwrap();
        let g = g.get(v.as_tensor()).unwrap().to_vec2::<f32>().unwrap();
        // d/d row1 of ||r1 - r0|| = (r1 - r0)/5 = (0.6, 0.8)
        assert!(close(g[1][0], 0.6) && close(g[1][1], 0.8), "{g:?}");
        // d/d row2 of -||r2 - r0|| = -(1, 0)
        assert!(close(g[2][0], -1.0) && close(g[2][1], 0.0), "{g:?}");
    }

    #[test]
    fn reprojection_is_weighted_l1_summed_over_coordinates() {
        let dev = Device::Cpu;
        let pred =
            Tensor::from_slice(&[0.0f32, 0.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5], (2, 4), &dev).unwrap();
        let target = [[0.1, 0.0, 1.0, 0.8], [0.0, 0.0, 0.0, 0.0]];
        // |.|: 0.1 + 0 + 0 + 0.2 = 0.3 (weight 0.5); 2.0 (weight 0.25)
        let l = reprojection_loss(&pred, &target, &[0.5, 0.25]).unwrap();
        assert!(close(l.to_scalar::<f32>().unwrap(), 0.15 + 0.5));
    }
}

//! **[ours]** Global identities: the pairwise matches of all camera pairs of a frame turned
//! into clusters with at most one box per camera, each with a confidence.
//!
//! # Scheme: constrained average-linkage agglomeration
//!
//! Pairwise Hungarian matching decides each camera pair in isolation, so its results can be
//! mutually inconsistent (A1↔B1, B1↔C1 but A1↔C2) and a near-tie in one pair cannot be
//! resolved with evidence from the other cameras. Here every box of the frame starts as its
//! own cluster and the two clusters with the highest *average linkage* — the mean confidence
//! `S` over all cross-camera box pairs between them, taken from the S matrices of all camera
//! pairs — are merged, repeatedly, subject to two rules:
//! - **exclusivity**: a cluster holds at most one box per camera (clusters sharing a camera
//!   never merge), the global counterpart of the one-to-one Hungarian constraint;
//! - **threshold**: merging stops when the best remaining linkage is below the threshold,
//!   the global counterpart of dropping pairs with `S < threshold`.
//!
//! Because the linkage of a candidate box to a cluster averages its scores to *every* member,
//! a box that one camera pair mismatched is pulled to the cluster that the other cameras
//! agree on (transitivity repair). With two cameras the scheme reduces to greedy
//! best-first one-to-one matching above the threshold.
//!
//! A pair of clusters is a candidate only when some member pair scores `S >= threshold`
//! (an average cannot reach the threshold otherwise), so with a sensible threshold each
//! cluster has a handful of candidates and no `N × N` state is kept. Candidates wait in a
//! max-heap at their current linkage; a merge recomputes only the merged cluster's links
//! (the two old links added up, or one old link plus the raw member scores it lacked) and
//! pushes them, and outdated heap entries are skipped when popped. A WILDTRACK-sized frame
//! (7 × 35 boxes) takes about a tenth of a millisecond on one core (BENCHMARKS.md).
//!
//! # Confidence
//! A cluster of two or more boxes: the mean `S` over all its member pairs (its internal
//! average linkage). A singleton: `1 − max S` to any box of another camera (how clearly it
//! matches nobody), or 1 when no other camera has boxes. Both lie in [0, 1] (clamped).
use std::collections::BinaryHeap;

use crate::core::association::ViewPair;
use crate::core::matching::{Match, PairMatching};

/// A person seen by one or more cameras in one frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Identity {
    /// Identity number within the frame (0-based, dense).
    pub id: usize,
    /// Confidence in [0, 1].
    pub confidence: f32,
    /// Members as `(camera index, index into that camera's detections)`, sorted by camera.
    pub members: Vec<(usize, usize)>,
}

/// The original scores of a frame, looked up by flattened box index (boxes numbered camera
/// by camera).
struct Scores<'a> {
    pairs: &'a [ViewPair],
    /// First flattened index of each camera.
    offsets: Vec<usize>,
    cam_of: Vec<usize>,
    cameras: usize,
    /// `table[a * cameras + b]`: the pair scoring cameras `a` and `b`, and whether it is
    /// stored as `(b, a)`.
    table: Vec<Option<(usize, bool)>>,
}

impl Scores<'_> {
    /// The highest finite score of box `i` to any box of another camera (read only for the
    /// boxes left alone, so it is not precomputed for all).
    fn best(&self, i: usize) -> Option<f32> {
        let a = self.cam_of[i];
        let x = i - self.offsets[a];
        (0..self.cameras)
            .filter_map(|b| self.table[a * self.cameras + b])
            .flat_map(|(p, swapped)| {
                let s = &self.pairs[p].matching.scores;
                if swapped { s.column(x) } else { s.row(x) }
            })
            .copied()
            .filter(|v| v.is_finite())
            .reduce(f32::max)
    }

    /// The finite score between boxes `i` and `j` (different cameras), if any.
    fn get(&self, i: usize, j: usize) -> Option<f32> {
        let (a, b) = (self.cam_of[i], self.cam_of[j]);
        let (p, swapped) = self.table[a * self.cameras + b]?;
        let (x, y) = (i - self.offsets[a], j - self.offsets[b]);
        let s = &self.pairs[p].matching.scores;
        let v = if swapped { s[(y, x)] } else { s[(x, y)] };
        v.is_finite().then_some(v)
    }
}

/// Scores between two live clusters: their sum over scored member pairs and the count.
#[derive(Debug, Clone, Copy)]
struct Link {
    to: usize,
    sum: f32,
    count: u32,
}

impl Link {
    fn linkage(&self) -> f32 {
        self.sum / self.count as f32
    }
}

/// A possible merge of clusters `lo < hi` at average linkage `linkage`, packed into one
/// integer whose order is the merge order: highest linkage first, ties to the lowest
/// `(lo, hi)` (a strict total order, so the result never depends on the order candidates
/// were seen in). Packing keeps the heap's comparisons and moves cheap.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Candidate(u128);

/// Box indices must fit in this many bits of a [`Candidate`] (a frame of 2^48 boxes could
/// not be held in memory anyway).
const INDEX_BITS: u32 = 48;
const INDEX_MASK: u128 = (1 << INDEX_BITS) - 1;

impl Candidate {
    fn new(linkage: f32, a: usize, b: usize) -> Self {
        // f32 bits mapped to an unsigned key with the same order as `f32::total_cmp`.
        let bits = linkage.to_bits();
        let key = if bits >> 31 == 1 {
            !bits
        } else {
            bits | 1 << 31
        };
        let (lo, hi) = (a.min(b) as u128, a.max(b) as u128);
        Candidate(
            (key as u128) << (2 * INDEX_BITS)
                | (!lo & INDEX_MASK) << INDEX_BITS
                | (!hi & INDEX_MASK),
        )
    }

    fn linkage(self) -> f32 {
        let key = (self.0 >> (2 * INDEX_BITS)) as u32;
        f32::from_bits(if key >> 31 == 1 {
            key & !(1 << 31)
        } else {
            !key
        })
    }

    fn lo(self) -> usize {
        (!(self.0 >> INDEX_BITS) & INDEX_MASK) as usize
    }

    fn hi(self) -> usize {
        (!self.0 & INDEX_MASK) as usize
    }
}

/// End of a member list.
const END: usize = usize::MAX;

/// Working state of the agglomeration over the frame's boxes (a cluster is named by its
/// smallest box index).
struct Agglomeration<'a> {
    scores: Scores<'a>,
    threshold: f32,
    /// Camera bitset of each cluster (`words` u64 per cluster).
    cams: Vec<u64>,
    words: usize,
    alive: Vec<bool>,
    /// Members as linked lists: `next[i]` follows box `i` in its cluster ([`END`] ends it),
    /// `last[r]` is the last member of cluster `r` (so a merge is O(1)).
    next: Vec<usize>,
    last: Vec<usize>,
    /// Merge partners of each live cluster, sorted by `to`: live clusters on other cameras
    /// with at least one member pair scoring `S >= threshold` (an average can reach the
    /// threshold only then), so a merge touches a handful of clusters instead of all.
    links: Vec<Vec<Link>>,
    /// Every candidate pair at its current linkage, plus stale entries (a dead cluster or an
    /// outdated linkage) that are skipped when popped.
    heap: BinaryHeap<Candidate>,
}

impl Agglomeration<'_> {
    fn disjoint(&self, r: usize, s: usize) -> bool {
        let w = self.words;
        let (a, b) = (
            &self.cams[r * w..(r + 1) * w],
            &self.cams[s * w..(s + 1) * w],
        );
        a.iter().zip(b).all(|(x, y)| x & y == 0)
    }

    /// The current linkage of live clusters `lo < hi`, when they are merge partners.
    fn linkage(&self, lo: usize, hi: usize) -> Option<f32> {
        if !(self.alive[lo] && self.alive[hi]) {
            return None;
        }
        let links = &self.links[lo];
        let k = links.binary_search_by_key(&hi, |l| l.to).ok()?;
        Some(links[k].linkage())
    }

    /// The members of cluster `r`.
    fn members(&self, r: usize) -> impl Iterator<Item = usize> + '_ {
        std::iter::successors(Some(r), |&i| Some(self.next[i]).filter(|&j| j != END))
    }

    /// Sum and count of the scores between the members of clusters `x` and `k`.
    fn raw(&self, x: usize, k: usize) -> (f32, u32) {
        let (mut sum, mut count) = (0f32, 0u32);
        for i in self.members(x) {
            for j in self.members(k) {
                if let Some(v) = self.scores.get(i, j) {
                    sum += v;
                    count += 1;
                }
            }
        }
        (sum, count)
    }

    /// Merges cluster `s` into cluster `r`: the merged cluster's partners are the union of
    /// both partner lists (minus those sharing a camera with it), each at the linkage of the
    /// merged member set, and every partner's own list is updated to match.
    fn merge(&mut self, r: usize, s: usize) {
        let w = self.words;
        for i in 0..w {
            self.cams[r * w + i] |= self.cams[s * w + i];
        }
        let old_r = std::mem::take(&mut self.links[r]);
        let old_s = std::mem::take(&mut self.links[s]);
        let mut merged = Vec::with_capacity(old_r.len() + old_s.len());
        let (mut x, mut y) = (0, 0);
        loop {
            let (k, sum, count) = match (old_r.get(x), old_s.get(y)) {
                (None, None) => break,
                (Some(a), Some(b)) if a.to == b.to => {
                    (x, y) = (x + 1, y + 1);
                    (a.to, a.sum + b.sum, a.count + b.count)
                }
                (Some(a), b) if b.is_none_or(|b| a.to < b.to) => {
                    x += 1;
                    if a.to == s || !self.disjoint(r, a.to) {
                        (a.to, 0.0, 0)
                    } else {
                        let (sum, count) = self.raw(s, a.to);
                        (a.to, a.sum + sum, a.count + count)
                    }
                }
                (_, Some(b)) => {
                    y += 1;
                    if b.to == r || !self.disjoint(r, b.to) {
                        (b.to, 0.0, 0)
                    } else {
                        let (sum, count) = self.raw(r, b.to);
                        (b.to, b.sum + sum, b.count + count)
                    }
                }
                (Some(_), None) => unreachable!("covered by the arm above"),
            };
            if k == r || k == s {
                continue;
            }
            // `k` drops `s`; it keeps `r`, at the new linkage, only while it may still merge.
            let keep = count > 0 && self.disjoint(r, k);
            let theirs = &mut self.links[k];
            if let Ok(pos) = theirs.binary_search_by_key(&s, |l| l.to) {
                theirs.remove(pos);
            }
            let link = Link { to: r, sum, count };
            match (theirs.binary_search_by_key(&r, |l| l.to), keep) {
                (Ok(pos), true) => theirs[pos] = link,
                (Ok(pos), false) => {
                    theirs.remove(pos);
                }
                (Err(pos), true) => theirs.insert(pos, link),
                (Err(_), false) => {}
            }
            if keep {
                let l = link.linkage();
                if l >= self.threshold {
                    self.heap.push(Candidate::new(l, r, k));
                }
                merged.push(Link { to: k, sum, count });
            }
        }
        self.links[r] = merged;
        self.next[self.last[r]] = s;
        self.last[r] = self.last[s];
        self.alive[s] = false;
    }
}

/// Builds the global identities of one frame.
///
/// `view_sizes[c]` is the number of boxes of camera `c` (0 for cameras without boxes or
/// that did not report); `pairs` holds the S matrices of camera pairs (`cam_a != cam_b`,
/// scores of shape `[view_sizes[cam_a], view_sizes[cam_b]]`; pairs with another shape, and
/// repeats of a camera pair, are ignored with a warning). Box pairs without a score never
/// link directly. Every box ends in exactly one identity. See the module documentation for
/// the scheme and the confidence.
pub fn build_identities(view_sizes: &[usize], pairs: &[ViewPair], threshold: f32) -> Vec<Identity> {
    let mut offsets = Vec::with_capacity(view_sizes.len() + 1);
    let mut total = 0usize;
    for &s in view_sizes {
        offsets.push(total);
        total += s;
    }
    offsets.push(total);
    let n = total;
    if n == 0 {
        return Vec::new();
    }
    let cameras = view_sizes.len();
    let cam_of: Vec<usize> = view_sizes
        .iter()
        .enumerate()
        .flat_map(|(c, &s)| std::iter::repeat_n(c, s))
        .collect();
    let words = cameras.div_ceil(64).max(1);
    let mut cams = vec![0u64; n * words];
    for (i, &c) in cam_of.iter().enumerate() {
        cams[i * words + c / 64] |= 1u64 << (c % 64);
    }
    let mut table = vec![None; cameras * cameras];
    let mut candidates = Vec::new();
    for (p, pair) in pairs.iter().enumerate() {
        let (ca, cb) = (pair.cam_a, pair.cam_b);
        let s = &pair.matching.scores;
        if ca == cb
            || ca >= cameras
            || cb >= cameras
            || s.dim() != (view_sizes[ca], view_sizes[cb])
            || table[ca * cameras + cb].is_some()
        {
            tracing::warn!(
                cam_a = ca,
                cam_b = cb,
                "ignoring inconsistent or repeated camera pair"
            );
            continue;
        }
        table[ca * cameras + cb] = Some((p, false));
        table[cb * cameras + ca] = Some((p, true));
        let cols = s.ncols();
        if cols == 0 {
            continue;
        }
        let s = s.as_standard_layout();
        let data = s.as_slice().expect("standard layout is contiguous");
        for (a, row) in data.chunks_exact(cols).enumerate() {
            let i = offsets[ca] + a;
            // A branch-free bit mask per 16 scores (vector code), then only the set bits.
            // NaN fails the comparison; infinities are no evidence either.
            let mut push = |b: usize| {
                let v = row[b];
                if v.is_finite() {
                    candidates.push(Candidate::new(v, i, offsets[cb] + b));
                }
            };
            let mut chunks = row.chunks_exact(16);
            for (c, chunk) in (&mut chunks).enumerate() {
                let mut mask = 0u32;
                for (k, &v) in chunk.iter().enumerate() {
                    mask |= u32::from(v >= threshold) << k;
                }
                while mask != 0 {
                    push(c * 16 + mask.trailing_zeros() as usize);
                    mask &= mask - 1;
                }
            }
            let done = cols - chunks.remainder().len();
            for (k, &v) in chunks.remainder().iter().enumerate() {
                if v >= threshold {
                    push(done + k);
                }
            }
        }
    }
    // Every box's links, allocated once at their final size.
    let mut degree = vec![0usize; n];
    for c in &candidates {
        degree[c.lo()] += 1;
        degree[c.hi()] += 1;
    }
    let mut links: Vec<Vec<Link>> = degree.into_iter().map(Vec::with_capacity).collect();
    for c in &candidates {
        let (lo, hi, v) = (c.lo(), c.hi(), c.linkage());
        links[lo].push(Link {
            to: hi,
            sum: v,
            count: 1,
        });
        links[hi].push(Link {
            to: lo,
            sum: v,
            count: 1,
        });
    }
    for l in &mut links {
        l.sort_unstable_by_key(|l| l.to);
    }
    let mut ag = Agglomeration {
        scores: Scores {
            pairs,
            offsets,
            cam_of,
            cameras,
            table,
        },
        threshold,
        cams,
        words,
        alive: vec![true; n],
        next: vec![END; n],
        last: (0..n).collect(),
        links,
        heap: BinaryHeap::from(candidates),
    };
    while let Some(c) = ag.heap.pop() {
        let (lo, hi) = (c.lo(), c.hi());
        if ag.linkage(lo, hi) == Some(c.linkage()) {
            ag.merge(lo, hi);
        }
    }
    // Identities, ordered by their first member (camera, index).
    let mut clusters: Vec<Vec<usize>> = (0..n)
        .filter(|&r| ag.alive[r])
        .map(|r| {
            let mut m: Vec<usize> = ag.members(r).collect();
            m.sort_unstable();
            m
        })
        .collect();
    clusters.sort_unstable_by_key(|m| m[0]);
    let scores = &ag.scores;
    clusters
        .into_iter()
        .enumerate()
        .map(|(id, m)| {
            let confidence = if m.len() == 1 {
                scores.best(m[0]).map_or(1.0, |s| 1.0 - s)
            } else {
                let (mut acc, mut k) = (0f32, 0u32);
                for (x, &i) in m.iter().enumerate() {
                    for &j in &m[x + 1..] {
                        if let Some(v) = scores.get(i, j) {
                            acc += v;
                            k += 1;
                        }
                    }
                }
                if k > 0 { acc / k as f32 } else { 0.0 }
            };
            Identity {
                id,
                confidence: confidence.clamp(0.0, 1.0),
                members: m
                    .iter()
                    .map(|&i| (scores.cam_of[i], i - scores.offsets[scores.cam_of[i]]))
                    .collect(),
            }
        })
        .collect()
}

/// Pairwise matches implied by identities: for every camera pair of `pairs`, the boxes that
/// share an identity, scored with that pair's `S`. Returns `pairs` with their matches
/// replaced (scores unchanged, matches sorted by `a`), so evaluation can score the global
/// mode exactly like the pairwise one.
pub fn pairs_from_identities(identities: &[Identity], pairs: &[ViewPair]) -> Vec<ViewPair> {
    pairs
        .iter()
        .map(|p| {
            let s = &p.matching.scores;
            let mut matches: Vec<Match> = identities
                .iter()
                .filter_map(|ident| {
                    let a = ident.members.iter().find(|m| m.0 == p.cam_a)?.1;
                    let b = ident.members.iter().find(|m| m.0 == p.cam_b)?.1;
                    let score = *s.get((a, b))?;
                    Some(Match { a, b, score })
                })
                .collect();
            matches.sort_unstable_by_key(|m| m.a);
            ViewPair {
                cam_a: p.cam_a,
                cam_b: p.cam_b,
                matching: PairMatching {
                    scores: s.clone(),
                    matches,
                },
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::matching::hungarian;
    use ndarray::{Array2, array};
    use proptest::prelude::*;

    fn pair(cam_a: usize, cam_b: usize, scores: Array2<f32>, threshold: f32) -> ViewPair {
        let matches = hungarian(scores.mapv(|v| 1.0 - v).view())
            .into_iter()
            .filter(|&(a, b)| scores[(a, b)] >= threshold)
            .map(|(a, b)| Match {
                a,
                b,
                score: scores[(a, b)],
            })
            .collect();
        ViewPair {
            cam_a,
            cam_b,
            matching: PairMatching { scores, matches },
        }
    }

    fn members(ids: &[Identity]) -> Vec<Vec<(usize, usize)>> {
        ids.iter().map(|i| i.members.clone()).collect()
    }

    #[test]
    fn consistent_triangle_forms_two_identities() {
        let s = array![[0.9f32, 0.1], [0.1, 0.8]];
        let pairs = vec![
            pair(0, 1, s.clone(), 0.4),
            pair(0, 2, s.clone(), 0.4),
            pair(1, 2, s, 0.4),
        ];
        let ids = build_identities(&[2, 2, 2], &pairs, 0.4);
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(0, 1), (1, 1), (2, 1)]]
        );
        assert!((ids[0].confidence - 0.9).abs() < 1e-6);
        assert!((ids[1].confidence - 0.8).abs() < 1e-6);
        assert_eq!(ids[1].id, 1);
        // Derived pairs equal the pairwise matches here.
        let derived = pairs_from_identities(&ids, &pairs);
        for (d, p) in derived.iter().zip(&pairs) {
            assert_eq!(d.matching.matches, p.matching.matches);
        }
    }

    #[test]
    fn transitivity_repairs_a_pairwise_mistake() {
        // Cameras A(0), B(1), C(2); persons p, q with A0,B0,C0 = p and A1,B1,C1 = q.
        // A–B is ambiguous and the Hungarian there swaps the persons.
        let ab = array![[0.60f32, 0.62], [0.62, 0.60]];
        let ac = array![[0.95f32, 0.10], [0.10, 0.95]];
        let bc = array![[0.95f32, 0.10], [0.10, 0.95]];
        let pairs = vec![
            pair(0, 1, ab, 0.4),
            pair(0, 2, ac, 0.4),
            pair(1, 2, bc, 0.4),
        ];
        let wrong: Vec<_> = pairs[0]
            .matching
            .matches
            .iter()
            .map(|m| (m.a, m.b))
            .collect();
        assert_eq!(
            wrong,
            vec![(0, 1), (1, 0)],
            "pairwise A–B is wrong by design"
        );
        let ids = build_identities(&[2, 2, 2], &pairs, 0.4);
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(0, 1), (1, 1), (2, 1)]]
        );
        let derived = pairs_from_identities(&ids, &pairs);
        let fixed: Vec<_> = derived[0]
            .matching
            .matches
            .iter()
            .map(|m| (m.a, m.b))
            .collect();
        assert_eq!(fixed, vec![(0, 0), (1, 1)]);
        assert!((derived[0].matching.matches[0].score - 0.60).abs() < 1e-6);
    }

    #[test]
    fn exclusivity_keeps_one_box_per_camera() {
        // Camera 1 has two boxes that both look like box 0 of camera 0 and like each other's
        // counterpart in camera 2: only one of them may join.
        let s01 = array![[0.9f32, 0.85]];
        let s02 = array![[0.9f32]];
        let s12 = array![[0.9f32], [0.88]];
        let pairs = vec![
            pair(0, 1, s01, 0.4),
            pair(0, 2, s02, 0.4),
            pair(1, 2, s12, 0.4),
        ];
        let ids = build_identities(&[1, 2, 1], &pairs, 0.4);
        for ident in &ids {
            let mut cams: Vec<usize> = ident.members.iter().map(|m| m.0).collect();
            cams.dedup();
            assert_eq!(cams.len(), ident.members.len(), "{ids:?}");
        }
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(1, 1)]]
        );
        // The loser is a singleton whose confidence reflects its strong rival evidence.
        assert!((ids[1].confidence - (1.0 - 0.88)).abs() < 1e-6);
    }

    #[test]
    fn threshold_stops_merging_and_handles_empty_views() {
        let s = array![[0.3f32]];
        let pairs = vec![pair(0, 2, s, 0.4)];
        let ids = build_identities(&[1, 0, 1], &pairs, 0.4);
        assert_eq!(members(&ids), vec![vec![(0, 0)], vec![(2, 0)]]);
        assert!((ids[0].confidence - 0.7).abs() < 1e-6);
        assert!(build_identities(&[0, 0], &[], 0.4).is_empty());
        // A lone camera: every box is a confident singleton.
        let ids = build_identities(&[3], &[], 0.4);
        assert_eq!(ids.len(), 3);
        assert!(ids.iter().all(|i| i.confidence == 1.0));
    }

    #[test]
    fn many_cameras_beyond_one_bitset_word() {
        // 70 cameras with one box each, all mutually similar: one identity of 70 members.
        let c = 70;
        let mut pairs = Vec::new();
        for a in 0..c {
            for b in a + 1..c {
                pairs.push(pair(a, b, array![[0.9f32]], 0.4));
            }
        }
        let ids = build_identities(&vec![1; c], &pairs, 0.4);
        assert_eq!(ids.len(), 1);
        assert_eq!(ids[0].members.len(), c);
    }

    /// Straightforward O(N³) agglomeration with the same rules and tie-breaks (clusters named
    /// by their smallest node), to check the cached implementation against.
    fn naive(sizes: &[usize], pairs: &[ViewPair], threshold: f32) -> Vec<Vec<(usize, usize)>> {
        let nodes: Vec<(usize, usize)> = sizes
            .iter()
            .enumerate()
            .flat_map(|(c, &k)| (0..k).map(move |i| (c, i)))
            .collect();
        let score = |x: (usize, usize), y: (usize, usize)| -> Option<f32> {
            pairs.iter().find_map(|p| {
                if (p.cam_a, p.cam_b) == (x.0, y.0) {
                    Some(p.matching.scores[(x.1, y.1)])
                } else if (p.cam_a, p.cam_b) == (y.0, x.0) {
                    Some(p.matching.scores[(y.1, x.1)])
                } else {
                    None
                }
            })
        };
        let mut clusters: Vec<Vec<usize>> = (0..nodes.len()).map(|i| vec![i]).collect();
        loop {
            let mut pick: Option<(f32, usize, usize)> = None;
            for a in 0..clusters.len() {
                for b in a + 1..clusters.len() {
                    let (ca, cb) = (&clusters[a], &clusters[b]);
                    if ca
                        .iter()
                        .any(|&i| cb.iter().any(|&j| nodes[i].0 == nodes[j].0))
                    {
                        continue;
                    }
                    let (mut sum, mut cnt) = (0f32, 0u32);
                    for &i in ca {
                        for &j in cb {
                            if let Some(v) = score(nodes[i], nodes[j]) {
                                sum += v;
                                cnt += 1;
                            }
                        }
                    }
                    if cnt == 0 {
                        continue;
                    }
                    let l = sum / cnt as f32;
                    if l < threshold {
                        continue;
                    }
                    let (ra, rb) = (ca[0].min(cb[0]), ca[0].max(cb[0]));
                    let better = match pick {
                        None => true,
                        Some((pl, pa, pb)) => {
                            let (qa, qb) = (clusters[pa][0], clusters[pb][0]);
                            l > pl || (l == pl && (ra, rb) < (qa.min(qb), qa.max(qb)))
                        }
                    };
                    if better {
                        pick = Some((l, a, b));
                    }
                }
            }
            let Some((_, a, b)) = pick else { break };
            let moved = clusters.remove(b);
            clusters[a].extend(moved);
            clusters[a].sort_unstable();
        }
        clusters.sort_unstable_by_key(|c| c[0]);
        clusters
            .into_iter()
            .map(|c| c.into_iter().map(|i| nodes[i]).collect())
            .collect()
    }

    /// Scores on a 1/64 grid: every partial sum is exact in f32, so both implementations
    /// see identical linkages (and identical ties).
    fn check_against_naive(sizes: &[usize], raw: &[u8], t: u8) -> Result<(), TestCaseError> {
        let mut k = 0;
        let mut pairs = Vec::new();
        for a in 0..sizes.len() {
            for b in a + 1..sizes.len() {
                if sizes[a] == 0 || sizes[b] == 0 {
                    continue;
                }
                let s = Array2::from_shape_fn((sizes[a], sizes[b]), |_| {
                    k += 1;
                    raw[k % raw.len()] as f32 / 64.0
                });
                pairs.push(pair(a, b, s, 0.0));
            }
        }
        let threshold = t as f32 / 64.0;
        let got = members(&build_identities(sizes, &pairs, threshold));
        prop_assert_eq!(got, naive(sizes, &pairs, threshold));
        Ok(())
    }

    proptest! {
        #[test]
        fn sparse_agglomeration_equals_naive(
            sizes in proptest::collection::vec(0usize..7, 2..6),
            raw in proptest::collection::vec(0u8..=64, 400),
            t in 0u8..=64,
        ) {
            check_against_naive(&sizes, &raw, t)?;
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(32))]
        /// Views wider than the 16-score scan blocks.
        #[test]
        fn wide_views_equal_naive(
            sizes in proptest::collection::vec(0usize..40, 2..4),
            raw in proptest::collection::vec(0u8..=64, 997),
            t in 16u8..=64,
        ) {
            check_against_naive(&sizes, &raw, t)?;
        }
    }
}

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
//! cluster has a handful of candidates. Per-cluster best/second-best caches are refreshed
//! only for the neighbours of a merge. A WILDTRACK frame (7 × 35 boxes) takes about half a
//! millisecond on a loaded 2-vCPU machine (BENCHMARKS.md).
//!
//! # Confidence
//! A cluster of two or more boxes: the mean `S` over all its member pairs (its internal
//! average linkage). A singleton: `1 − max S` to any box of another camera (how clearly it
//! matches nobody), or 1 when no other camera has boxes. Both lie in [0, 1] (clamped).
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

/// A merge candidate of a cluster: `(linkage, partner)`.
type Cand = Option<(f32, usize)>;

/// `a` ranks above `b`: higher linkage, ties to the lower partner index (a strict total
/// order, so the result never depends on the order candidates were seen in).
fn ranks_above(a: (f32, usize), b: Cand) -> bool {
    match b {
        None => true,
        Some((l, p)) => a.0 > l || (a.0 == l && a.1 < p),
    }
}

/// Best and second-best merge partners of a cluster. `second` is exact only while
/// `second_known`; it is needed only when the best partner disappears.
#[derive(Debug, Clone, Copy, Default)]
struct Top2 {
    best: Cand,
    second: Cand,
    second_known: bool,
}

impl Top2 {
    fn offer(&mut self, c: (f32, usize)) {
        if ranks_above(c, self.best) {
            self.second = self.best;
            self.best = Some(c);
        } else if ranks_above(c, self.second) {
            self.second = Some(c);
        }
    }
}

/// Working state of the agglomeration over `n` boxes (flattened node indices; a cluster is
/// named by one of its nodes).
struct Agglomeration {
    n: usize,
    /// Sum of S over member pairs between clusters (row-major `n × n`).
    sum: Vec<f32>,
    /// Number of scored member pairs between clusters.
    count: Vec<u32>,
    /// Camera bitset of each cluster (`words` u64 per cluster).
    cams: Vec<u64>,
    words: usize,
    /// Clusters still alive, ascending.
    alive: Vec<usize>,
    /// Candidate partners of each live cluster, ascending: clusters with at least one member
    /// pair scoring `S >= threshold` (an average can reach the threshold only then), so
    /// searches touch a handful of clusters instead of all of them.
    adj: Vec<Vec<usize>>,
    members: Vec<Vec<usize>>,
    top: Vec<Top2>,
    threshold: f32,
}

impl Agglomeration {
    fn disjoint(&self, r: usize, s: usize) -> bool {
        if self.words == 1 {
            return self.cams[r] & self.cams[s] == 0;
        }
        let (a, b) = (
            &self.cams[r * self.words..(r + 1) * self.words],
            &self.cams[s * self.words..(s + 1) * self.words],
        );
        a.iter().zip(b).all(|(x, y)| x & y == 0)
    }

    /// Average linkage between live clusters `r != s` when they may merge (disjoint cameras,
    /// at least one scored pair, linkage at or above the threshold).
    fn linkage(&self, r: usize, s: usize) -> Option<f32> {
        let k = r * self.n + s;
        let c = self.count[k];
        if c == 0 || !self.disjoint(r, s) {
            return None;
        }
        let l = self.sum[k] / c as f32;
        (l >= self.threshold).then_some(l)
    }

    fn rescan(&mut self, r: usize) {
        let mut t = Top2 {
            second_known: true,
            ..Top2::default()
        };
        for &s in &self.adj[r] {
            if let Some(l) = self.linkage(r, s) {
                t.offer((l, s));
            }
        }
        self.top[r] = t;
    }

    /// Merges cluster `s` into cluster `r` and refreshes the partner caches: only the
    /// linkages to `r` and `s` changed (both replaced by the merged cluster, named `r`).
    fn merge(&mut self, r: usize, s: usize) {
        let n = self.n;
        for &k in &self.alive {
            let (rk, sk) = (r * n + k, s * n + k);
            self.sum[rk] += self.sum[sk];
            self.count[rk] += self.count[sk];
            self.sum[k * n + r] = self.sum[rk];
            self.count[k * n + r] = self.count[rk];
        }
        for w in 0..self.words {
            self.cams[r * self.words + w] |= self.cams[s * self.words + w];
        }
        let moved = std::mem::take(&mut self.members[s]);
        self.members[r].extend(moved);
        if let Ok(pos) = self.alive.binary_search(&s) {
            self.alive.remove(pos);
        }
        self.top[s] = Top2::default();
        // Candidate lists: `s` becomes `r` everywhere; `r` gets the union.
        let adj_s = std::mem::take(&mut self.adj[s]);
        for &k in &adj_s {
            if k == r {
                continue;
            }
            let a = &mut self.adj[k];
            if let Ok(pos) = a.binary_search(&s) {
                a.remove(pos);
            }
            if let Err(pos) = a.binary_search(&r) {
                a.insert(pos, r);
            }
        }
        let mut adj_r = std::mem::take(&mut self.adj[r]);
        adj_r.extend(adj_s);
        adj_r.sort_unstable();
        adj_r.dedup();
        adj_r.retain(|&k| k != r && k != s);
        self.adj[r] = adj_r;
        self.rescan(r);
        let gone = |c: Cand| matches!(c, Some((_, p)) if p == r || p == s);
        // Only neighbours of `r` or `s` can have had them as candidates.
        for idx in 0..self.adj[r].len() {
            let k = self.adj[r][idx];
            let new = self.linkage(k, r).map(|l| (l, r));
            let mut t = self.top[k];
            if gone(t.best) {
                if !t.second_known || gone(t.second) {
                    self.rescan(k);
                    continue;
                }
                // The old second now leads the unchanged candidates.
                match new {
                    Some(c) if ranks_above(c, t.second) => t.best = Some(c),
                    _ => {
                        t.best = t.second;
                        // Candidates below the old second may outrank `new`: unknown.
                        t.second_known = false;
                    }
                }
            } else if gone(t.second) {
                match new {
                    Some(c) if ranks_above(c, t.best) => {
                        t.second = t.best;
                        t.best = Some(c);
                        t.second_known = true;
                    }
                    _ => t.second_known = false,
                }
            } else if let Some(c) = new {
                if ranks_above(c, t.best) {
                    t.second = t.best;
                    t.best = Some(c);
                    t.second_known = true;
                } else if t.second_known && ranks_above(c, t.second) {
                    t.second = Some(c);
                }
            }
            self.top[k] = t;
        }
    }
}

/// Builds the global identities of one frame.
///
/// `view_sizes[c]` is the number of boxes of camera `c` (0 for cameras without boxes or
/// that did not report); `pairs` holds the S matrices of camera pairs (`cam_a != cam_b`,
/// scores of shape `[view_sizes[cam_a], view_sizes[cam_b]]`; pairs with another shape are
/// ignored). Box pairs without a score never link directly. Every box ends in exactly one
/// identity. See the module documentation for the scheme and the confidence.
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
    let cam_of: Vec<usize> = view_sizes
        .iter()
        .enumerate()
        .flat_map(|(c, &s)| std::iter::repeat_n(c, s))
        .collect();
    let words = view_sizes.len().div_ceil(64).max(1);
    let mut cams = vec![0u64; n * words];
    for (i, &c) in cam_of.iter().enumerate() {
        cams[i * words + c / 64] |= 1u64 << (c % 64);
    }
    let mut sum = vec![0f32; n * n];
    let mut count = vec![0u32; n * n];
    // Highest S of each box to any box of another camera (for singleton confidence).
    let mut max_s = vec![f32::NEG_INFINITY; n];
    let mut adj: Vec<Vec<usize>> = vec![Vec::new(); n];
    for p in pairs {
        let (ca, cb) = (p.cam_a, p.cam_b);
        let s = &p.matching.scores;
        if ca == cb
            || ca >= view_sizes.len()
            || cb >= view_sizes.len()
            || s.dim() != (view_sizes[ca], view_sizes[cb])
        {
            tracing::warn!(cam_a = ca, cam_b = cb, "ignoring inconsistent camera pair");
            continue;
        }
        for ((a, b), &v) in s.indexed_iter() {
            if !v.is_finite() {
                continue;
            }
            let (i, j) = (offsets[ca] + a, offsets[cb] + b);
            sum[i * n + j] += v;
            count[i * n + j] += 1;
            sum[j * n + i] += v;
            count[j * n + i] += 1;
            max_s[i] = max_s[i].max(v);
            max_s[j] = max_s[j].max(v);
            if v >= threshold {
                adj[i].push(j);
                adj[j].push(i);
            }
        }
    }
    for a in &mut adj {
        a.sort_unstable();
        a.dedup();
    }
    let mut ag = Agglomeration {
        n,
        sum,
        count,
        cams,
        words,
        alive: (0..n).collect(),
        adj,
        members: (0..n).map(|i| vec![i]).collect(),
        top: vec![Top2::default(); n],
        threshold,
    };
    for r in 0..n {
        ag.rescan(r);
    }
    loop {
        // The globally best pair: highest linkage, ties to the lowest (lo, hi) node pair.
        let mut pick: Option<(f32, usize, usize)> = None;
        for &r in &ag.alive {
            if let Some((l, s)) = ag.top[r].best {
                let (lo, hi) = (r.min(s), r.max(s));
                let better = match pick {
                    None => true,
                    Some((pl, pr, ps)) => l > pl || (l == pl && (lo, hi) < (pr, ps)),
                };
                if better {
                    pick = Some((l, lo, hi));
                }
            }
        }
        match pick {
            Some((_, r, s)) => ag.merge(r, s),
            None => break,
        }
    }
    let alive = std::mem::take(&mut ag.alive);
    // Identities, ordered by their first member (camera, index).
    let mut clusters: Vec<Vec<usize>> = alive
        .into_iter()
        .map(|r| {
            let mut m = std::mem::take(&mut ag.members[r]);
            m.sort_unstable();
            m
        })
        .collect();
    clusters.sort_unstable_by_key(|m| m[0]);
    // The original (unmerged) scores between two boxes.
    let pair_score = |i: usize, j: usize| -> Option<f32> {
        let (a, b) = (cam_of[i], cam_of[j]);
        pairs
            .iter()
            .find_map(|p| {
                if (p.cam_a, p.cam_b) == (a, b) {
                    p.matching
                        .scores
                        .get((i - offsets[a], j - offsets[b]))
                        .copied()
                } else if (p.cam_a, p.cam_b) == (b, a) {
                    p.matching
                        .scores
                        .get((j - offsets[b], i - offsets[a]))
                        .copied()
                } else {
                    None
                }
            })
            .filter(|v| v.is_finite())
    };
    clusters
        .into_iter()
        .enumerate()
        .map(|(id, m)| {
            let confidence = if m.len() == 1 {
                let s = max_s[m[0]];
                if s.is_finite() { 1.0 - s } else { 1.0 }
            } else {
                let (mut acc, mut k) = (0f32, 0u32);
                for (x, &i) in m.iter().enumerate() {
                    for &j in &m[x + 1..] {
                        if let Some(v) = pair_score(i, j) {
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
                    .map(|&i| (cam_of[i], i - offsets[cam_of[i]]))
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

    proptest::proptest! {
        #[test]
        fn cached_agglomeration_equals_naive(
            sizes in proptest::collection::vec(0usize..7, 2..6),
            raw in proptest::collection::vec(0u8..=64, 400),
            t in 0u8..=64,
        ) {
            // Scores on a 1/64 grid: every partial sum is exact in f32, so both
            // implementations see identical linkages (and identical ties).
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
            let got = members(&build_identities(&sizes, &pairs, threshold));
            proptest::prop_assert_eq!(got, naive(&sizes, &pairs, threshold));
        }
    }
}

//! Greedy additive clustering of the evidence: the two clusters with the largest total weight
//! between them merge while it is positive, their cameras are disjoint and no pair of their
//! boxes is vetoed ([`VETO`]; the parent module's documentation), with a max-heap of versioned
//! candidates.
use std::collections::BinaryHeap;

use super::evidence::{Evidence, NONE};

/// A merge candidate: clusters `lo < hi` at total weight `w`, valid while both clusters still
/// have the (16-bit, wrapping) versions they had when it was pushed. Packed into one integer
/// whose order is the merge order — weight first, then the lowest `(lo, hi)` — so the heap's
/// comparisons and moves are cheap: `key(32) | !lo(32) | !hi(32) | version lo(16) | version hi(16)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
struct Candidate(u128);

impl Candidate {
    fn new(w: f32, lo: usize, hi: usize, versions: (u32, u32)) -> Self {
        let (lo, hi) = (!(lo as u32) as u128, !(hi as u32) as u128);
        Candidate(
            (order_key(w) as u128) << 96
                | lo << 64
                | hi << 32
                | ((versions.0 & 0xffff) as u128) << 16
                | (versions.1 & 0xffff) as u128,
        )
    }

    fn lo(self) -> usize {
        !((self.0 >> 64) as u32) as usize
    }

    fn hi(self) -> usize {
        !((self.0 >> 32) as u32) as usize
    }

    fn versions(self) -> (u32, u32) {
        (((self.0 >> 16) & 0xffff) as u32, (self.0 & 0xffff) as u32)
    }
}

/// `f32` bits mapped to an unsigned key with the same order as `f32::total_cmp`.
fn order_key(w: f32) -> u32 {
    let bits = w.to_bits();
    if bits >> 31 == 1 {
        !bits
    } else {
        bits | 1 << 31
    }
}

/// The veto, as a share of the link threshold `t`: two clusters never merge while one pair of
/// their boxes weighs below `−VETO · t` (complete linkage against a clear contradiction, which
/// a sum over many weak links would otherwise outvote). Chosen from {0, ¼, ½, none} on the
/// WILDTRACK training frames under six models (BENCHMARKS.md, "Identities").
pub(super) const VETO: f32 = 0.5;

/// End of a member list.
const END: usize = usize::MAX;

/// Working state of the clustering (a cluster is named by its smallest box index).
pub(super) struct Clustering<'a> {
    ev: &'a Evidence<'a>,
    /// Camera bitset of each cluster (`words` u64 per cluster).
    cams: Vec<u64>,
    words: usize,
    root: Vec<usize>,
    version: Vec<u32>,
    /// Members as linked lists: `next[i]` follows box `i` ([`END`] ends it), `last[r]` is the
    /// last member of cluster `r`.
    next: Vec<usize>,
    last: Vec<usize>,
    heap: BinaryHeap<Candidate>,
    /// Scratch list of the clusters already offered to a merged cluster.
    seen: Vec<usize>,
}

impl<'a> Clustering<'a> {
    /// Every box its own cluster, the heap seeded with every Hungarian pair's candidate.
    pub(super) fn new(ev: &'a Evidence<'a>) -> Self {
        let (n, cameras) = (ev.cam_of.len(), ev.cameras);
        let words = cameras.div_ceil(64).max(1);
        let mut cams = vec![0u64; n * words];
        for (i, &c) in ev.cam_of.iter().enumerate() {
            cams[i * words + c / 64] |= 1u64 << (c % 64);
        }
        let mut cl = Clustering {
            ev,
            cams,
            words,
            root: (0..n).collect(),
            version: vec![0; n],
            next: vec![END; n],
            last: (0..n).collect(),
            heap: BinaryHeap::new(),
            seen: Vec::with_capacity(2 * cameras),
        };
        let mut initial = Vec::with_capacity(n * cameras / 2);
        for u in 0..n {
            for c in 0..cameras {
                let v = ev.partner[u * cameras + c];
                if v != NONE && u < v as usize {
                    initial.extend(cl.candidate(u, v as usize));
                }
            }
        }
        cl.heap = BinaryHeap::from(initial);
        cl
    }

    /// Greedy merging: the best positive candidate first, skipping stale ones (a cluster that
    /// changed since the candidate was made), until no merge gains anything.
    pub(super) fn run(&mut self) {
        while let Some(c) = self.heap.pop() {
            let (lo, hi) = (c.lo(), c.hi());
            let now = (self.version[lo] & 0xffff, self.version[hi] & 0xffff);
            // (The disjointness check only matters if a version wrapped, with over 65,535
            // cameras: a stale entry must never merge two boxes of one camera.)
            if self.root[lo] == lo
                && self.root[hi] == hi
                && now == c.versions()
                && self.disjoint(lo, hi)
            {
                self.merge(lo, hi);
            }
        }
    }

    /// The final clusters (boxes in the frame's numbering), each sorted, ordered by their
    /// first box.
    pub(super) fn clusters(&self) -> Vec<Vec<usize>> {
        let mut clusters: Vec<Vec<usize>> = (0..self.ev.cam_of.len())
            .filter(|&r| self.root[r] == r)
            .map(|r| {
                let mut m: Vec<usize> = self.members(r).collect();
                m.sort_unstable();
                m
            })
            .collect();
        clusters.sort_unstable_by_key(|m| m[0]);
        clusters
    }
}

impl Clustering<'_> {
    fn disjoint(&self, r: usize, s: usize) -> bool {
        let w = self.words;
        self.cams[r * w..(r + 1) * w]
            .iter()
            .zip(&self.cams[s * w..(s + 1) * w])
            .all(|(x, y)| x & y == 0)
    }

    fn members(&self, r: usize) -> impl Iterator<Item = usize> + '_ {
        std::iter::successors(Some(r), |&i| Some(self.next[i]).filter(|&j| j != END))
    }

    /// Total weight between clusters `r` and `s`, or `None` when one pair of their boxes
    /// (with evidence) weighs below the veto `−veto · t` ([`IdentityConfig::veto`]).
    fn weight(&self, r: usize, s: usize) -> Option<f32> {
        let floor = self.ev.veto_floor();
        let mut w = 0f32;
        for u in self.members(r) {
            for v in self.members(s) {
                let x = self.ev.pair_weight(u, v);
                if x < floor && self.ev.has_evidence(u, v) {
                    return None;
                }
                w += x;
            }
        }
        Some(w)
    }

    /// The candidate for merging `r` and `s`, when they may merge.
    fn candidate(&self, r: usize, s: usize) -> Option<Candidate> {
        if !self.disjoint(r, s) {
            return None;
        }
        let w = self.weight(r, s)?;
        let (lo, hi) = (r.min(s), r.max(s));
        (w > 0.0).then(|| Candidate::new(w, lo, hi, (self.version[lo], self.version[hi])))
    }

    fn merge(&mut self, r: usize, s: usize) {
        let w = self.words;
        for i in 0..w {
            self.cams[r * w + i] |= self.cams[s * w + i];
        }
        let mut i = s;
        while i != END {
            self.root[i] = r;
            i = self.next[i];
        }
        self.next[self.last[r]] = s;
        self.last[r] = self.last[s];
        self.version[r] += 1;
        self.version[s] += 1;
        // Fresh candidates for every cluster a member of the merged one has a partner in.
        let c = self.ev.cameras;
        let mut seen = std::mem::take(&mut self.seen);
        seen.clear();
        let mut u = r;
        while u != END {
            for &p in &self.ev.partner[u * c..(u + 1) * c] {
                if p == NONE {
                    continue;
                }
                let k = self.root[p as usize];
                if k != r && !seen.contains(&k) {
                    seen.push(k);
                    if let Some(cand) = self.candidate(r, k) {
                        self.heap.push(cand);
                    }
                }
            }
            u = self.next[u];
        }
        self.seen = seen;
    }
}

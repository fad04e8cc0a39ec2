//! The plain baseline (BENCHMARKS.md's baseline row, kept as the tests' oracle and as a
//! fallback): union-find over the kept Hungarian matches of SPEC §3's `S` (`S ≥ threshold`),
//! strongest first, where a match's strength is its `S` plus `support` for every third camera
//! whose kept partners of both boxes are one box; a merge that would put two boxes of one
//! camera together is skipped. Two parameters, no calibration.
use super::ViewPair;
use super::evidence::NONE;

/// The baseline's clusters (boxes numbered camera by camera from `offsets`), each sorted,
/// ordered by their first box. Inconsistent camera pairs are ignored.
pub(super) fn clusters(
    view_sizes: &[usize],
    offsets: &[usize],
    pairs: &[ViewPair],
    threshold: f32,
    support: f32,
) -> Vec<Vec<usize>> {
    let cameras = view_sizes.len();
    let n = offsets[cameras];
    let cam_of: Vec<usize> = view_sizes
        .iter()
        .enumerate()
        .flat_map(|(c, &s)| std::iter::repeat_n(c, s))
        .collect();
    // Kept partners: box u's kept match in camera c, with its S.
    let mut partner = vec![NONE; n * cameras];
    let mut kept: Vec<(f32, usize, usize)> = Vec::new();
    for pair in pairs {
        let (ca, cb) = (pair.cam_a, pair.cam_b);
        if ca == cb || ca >= cameras || cb >= cameras {
            continue;
        }
        for p in &pair.matching.assignment {
            let keep = p.score >= threshold; // NaN: not kept
            if p.a >= view_sizes[ca] || p.b >= view_sizes[cb] || !keep {
                continue;
            }
            let (u, v) = (offsets[ca] + p.a, offsets[cb] + p.b);
            if partner[u * cameras + cb] != NONE || partner[v * cameras + ca] != NONE {
                continue;
            }
            partner[u * cameras + cb] = v as u32;
            partner[v * cameras + ca] = u as u32;
            kept.push((p.score, u.min(v), u.max(v)));
        }
    }
    for e in &mut kept {
        let (pu, pv) = (
            &partner[e.1 * cameras..(e.1 + 1) * cameras],
            &partner[e.2 * cameras..(e.2 + 1) * cameras],
        );
        let agree = pu
            .iter()
            .zip(pv)
            .filter(|&(&x, &y)| x != NONE && x == y)
            .count();
        e.0 += support * agree as f32;
    }
    kept.sort_unstable_by(|x, y| y.0.total_cmp(&x.0).then((x.1, x.2).cmp(&(y.1, y.2))));
    let mut sets = Sets::new(n, &cam_of, cameras);
    for &(_, u, v) in &kept {
        sets.union_disjoint(u, v);
    }
    sets.clusters()
}

/// Disjoint sets with each set's cameras (a bitset of `words` u64 per root).
struct Sets {
    root: Vec<usize>,
    cams: Vec<u64>,
    words: usize,
}

impl Sets {
    fn new(n: usize, cam_of: &[usize], cameras: usize) -> Self {
        let words = cameras.div_ceil(64).max(1);
        let mut cams = vec![0u64; n * words];
        for (u, &c) in cam_of.iter().enumerate() {
            cams[u * words + c / 64] |= 1 << (c % 64);
        }
        Sets {
            root: (0..n).collect(),
            cams,
            words,
        }
    }

    fn find(&mut self, mut x: usize) -> usize {
        while self.root[x] != x {
            self.root[x] = self.root[self.root[x]];
            x = self.root[x];
        }
        x
    }

    /// Joins the sets of `u` and `v` when their cameras are disjoint (the smaller root
    /// stays the root).
    fn union_disjoint(&mut self, u: usize, v: usize) {
        let (r, s) = (self.find(u), self.find(v));
        let w = self.words;
        let clash = (0..w).any(|i| self.cams[r * w + i] & self.cams[s * w + i] != 0);
        if r == s || clash {
            return;
        }
        let (r, s) = (r.min(s), r.max(s));
        for i in 0..w {
            self.cams[r * w + i] |= self.cams[s * w + i];
        }
        self.root[s] = r;
    }

    fn clusters(mut self) -> Vec<Vec<usize>> {
        let n = self.root.len();
        let mut by_root: Vec<Vec<usize>> = vec![Vec::new(); n];
        for u in 0..n {
            let r = self.find(u);
            by_root[r].push(u);
        }
        by_root.into_iter().filter(|c| !c.is_empty()).collect()
    }
}

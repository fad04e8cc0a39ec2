//! The identity step's guarantees.
use super::*;
use crate::matching::{hungarian, kept_matches};
use ndarray::{Array2, array};
use proptest::prelude::*;

/// A camera pair matched on `scores` (as `S`; distance = 1 − S, so a calibration is not
/// needed), with its SPEC §3 matches at `threshold`.
fn pair(cam_a: usize, cam_b: usize, scores: Array2<f32>, threshold: f32) -> ViewPair {
    let assignment: Vec<Assigned> = hungarian(scores.mapv(|v| 1.0 - v).view())
        .into_iter()
        .map(|(a, b)| Assigned {
            a,
            b,
            score: scores[(a, b)],
            distance: 1.0 - scores[(a, b)],
        })
        .collect();
    let matches = kept_matches(&assignment, threshold);
    ViewPair {
        cam_a,
        cam_b,
        matching: PairMatching {
            scores,
            assignment,
            matches,
            distance_scale: 1.0,
        },
    }
}

/// Pairwise matches implied by identities: for every camera pair of `pairs`, the boxes that
/// share an identity, scored with that pair's `S`. Returns `pairs` with their matches
/// replaced (scores and assignment unchanged, matches sorted by `a`), so evaluation can score
/// identities exactly like pairwise matching.
fn pairs_from_identities(identities: &[Identity], pairs: &[ViewPair]) -> Vec<ViewPair> {
    pairs
        .iter()
        .map(|p| ViewPair {
            cam_a: p.cam_a,
            cam_b: p.cam_b,
            matching: PairMatching {
                scores: p.matching.scores.clone(),
                assignment: p.matching.assignment.clone(),
                matches: identity_matches(identities, p),
                distance_scale: p.matching.distance_scale,
            },
        })
        .collect()
}

fn members(ids: &[Identity]) -> Vec<Vec<(usize, usize)>> {
    ids.iter().map(|i| i.members.clone()).collect()
}

fn cfg(t: f32) -> IdentityConfig {
    IdentityConfig {
        link_threshold: t,
        ..IdentityConfig::new(None, t)
    }
}

/// Camera pairs from grid scores (multiples of 1/64, so with the dyadic parameters of
/// [`grid_cfg`] every partial sum is exact and both implementations see equal ties).
fn grid_pairs(sizes: &[usize], raw: &[u8]) -> Vec<ViewPair> {
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
    pairs
}

fn grid_cfg(t: u8) -> IdentityConfig {
    IdentityConfig {
        link_threshold: t as f32 / 64.0,
        support: 0.125,
        ..IdentityConfig::new(None, t as f32 / 64.0)
    }
}

/// Every box once, camera-exclusive, deterministic: the heap implementation equals a naive one.
mod clusters {
    use super::*;

    /// Straightforward O(N⁴) clustering with the same weights, veto and tie-breaks (clusters
    /// named by their smallest box), to check the heap-based implementation against.
    /// Uncalibrated.
    fn naive(
        sizes: &[usize],
        pairs: &[ViewPair],
        cfg: &IdentityConfig,
    ) -> Vec<Vec<(usize, usize)>> {
        let nodes: Vec<(usize, usize)> = sizes
            .iter()
            .enumerate()
            .flat_map(|(c, &k)| (0..k).map(move |i| (c, i)))
            .collect();
        let pair_of = |x: (usize, usize), cam: usize| {
            pairs
                .iter()
                .find(|p| (p.cam_a, p.cam_b) == (x.0, cam) || (p.cam_a, p.cam_b) == (cam, x.0))
        };
        let partner = |x: (usize, usize), cam: usize| -> Option<usize> {
            let p = pair_of(x, cam)?;
            let asg = &p.matching.assignment;
            if p.cam_a == x.0 {
                asg.iter().find(|m| m.a == x.1).map(|m| m.b)
            } else {
                asg.iter().find(|m| m.b == x.1).map(|m| m.a)
            }
        };
        let pw = |x: (usize, usize), y: (usize, usize)| -> f32 {
            let Some(p) = pair_of(x, y.0).filter(|_| x.0 != y.0) else {
                return 0.0;
            };
            let (a, b) = if p.cam_a == x.0 {
                (x.1, y.1)
            } else {
                (y.1, x.1)
            };
            let s = p.matching.scores[(a, b)];
            if partner(x, y.0) == Some(y.1) {
                let agree = (0..sizes.len())
                    .filter(|&c| c != x.0 && c != y.0)
                    .filter(|&c| partner(x, c).is_some() && partner(x, c) == partner(y, c))
                    .count();
                s - cfg.link_threshold + cfg.support * agree as f32
            } else {
                (s - cfg.link_threshold).min(0.0)
            }
        };
        let mut clusters: Vec<Vec<usize>> = (0..nodes.len()).map(|i| vec![i]).collect();
        loop {
            let mut pick: Option<(f32, usize, usize, (usize, usize))> = None;
            for a in 0..clusters.len() {
                for b in a + 1..clusters.len() {
                    let (ca, cb) = (&clusters[a], &clusters[b]);
                    let clash = ca
                        .iter()
                        .any(|&i| cb.iter().any(|&j| nodes[i].0 == nodes[j].0));
                    if clash {
                        continue;
                    }
                    let ws: Vec<f32> = ca
                        .iter()
                        .flat_map(|&i| cb.iter().map(move |&j| (i, j)))
                        .map(|(i, j)| pw(nodes[i], nodes[j]))
                        .collect();
                    // The veto: no pair below −veto · t.
                    let w: f32 = ws.iter().sum();
                    if w <= 0.0 || ws.iter().any(|&x| x < -cfg.veto * cfg.link_threshold) {
                        continue;
                    }
                    let names = (ca[0].min(cb[0]), ca[0].max(cb[0]));
                    if pick.is_none_or(|(pw, _, _, pn)| w > pw || (w == pw && names < pn)) {
                        pick = Some((w, a, b, names));
                    }
                }
            }
            let Some((_, a, b, _)) = pick else { break };
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

    proptest! {
        #[test]
        fn heap_clustering_equals_naive(
            sizes in proptest::collection::vec(0usize..6, 2..6),
            raw in proptest::collection::vec(0u8..=64, 400),
            t in 0u8..=64,
        ) {
            let pairs = grid_pairs(&sizes, &raw);
            let c = grid_cfg(t);
            let got = build_identities(&sizes, &pairs, &c);
            prop_assert_eq!(members(&got), naive(&sizes, &pairs, &c));
            // Camera-exclusive, every box once, deterministic.
            let mut all: Vec<(usize, usize)> = Vec::new();
            for ident in &got {
                let mut cams: Vec<usize> = ident.members.iter().map(|m| m.0).collect();
                cams.dedup();
                prop_assert_eq!(cams.len(), ident.members.len());
                prop_assert!((0.0..=1.0).contains(&ident.confidence));
                all.extend(&ident.members);
            }
            all.sort_unstable();
            prop_assert_eq!(all.len(), sizes.iter().sum::<usize>());
            all.dedup();
            prop_assert_eq!(all.len(), sizes.iter().sum::<usize>());
            prop_assert_eq!(build_identities(&sizes, &pairs, &c), got);
        }
    }
}

/// At most one box per camera in an identity, whatever the number of cameras.
mod exclusivity {
    use super::*;

    #[test]
    fn exclusivity_keeps_one_box_per_camera() {
        let s01 = array![[0.9f32, 0.85]];
        let s02 = array![[0.9f32]];
        let s12 = array![[0.9f32], [0.88]];
        let pairs = vec![
            pair(0, 1, s01, 0.4),
            pair(0, 2, s02, 0.4),
            pair(1, 2, s12, 0.4),
        ];
        let ids = build_identities(&[1, 2, 1], &pairs, &cfg(0.4));
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(1, 1)]]
        );
        // B1 has no Hungarian partner (nothing missing) but spans one camera of three.
        assert!((ids[1].confidence - (1.0f32 / 3.0).cbrt()).abs() < 1e-6);
        // The full identity: mean pair confidence 0.9, nothing missing, every camera.
        assert!((ids[0].confidence - 0.9f32.cbrt()).abs() < 1e-6);
    }

    #[test]
    fn many_cameras_beyond_one_bitset_word() {
        let c = 70;
        let mut pairs = Vec::new();
        for a in 0..c {
            for b in a + 1..c {
                pairs.push(pair(a, b, array![[0.9f32]], 0.4));
            }
        }
        let ids = build_identities(&vec![1; c], &pairs, &cfg(0.4));
        assert_eq!(ids.len(), 1);
        assert_eq!(ids[0].members.len(), c);
    }
}

/// With two cameras the identities are the Hungarian pairs above the link threshold.
mod two_cameras {
    use super::*;

    proptest! {
        #[test]
        fn two_cameras_equal_pairwise(
            n in 0usize..8, m in 0usize..8,
            raw in proptest::collection::vec(0u8..=64, 64),
            t in 0u8..=64,
        ) {
            let pairs = grid_pairs(&[n, m], &raw);
            let c = grid_cfg(t);
            let ids = build_identities(&[n, m], &pairs, &c);
            for (p, d) in pairs.iter().zip(pairs_from_identities(&ids, &pairs)) {
                // The Hungarian pairs whose confidence exceeds the link threshold.
                let kept: Vec<_> = p.matching.assignment.iter()
                    .filter(|x| x.score > c.link_threshold)
                    .map(|x| (x.a, x.b)).collect();
                let got: Vec<_> = d.matching.matches.iter().map(|x| (x.a, x.b)).collect();
                prop_assert_eq!(got, kept);
            }
        }
    }

    #[test]
    fn threshold_empty_views_and_lone_cameras() {
        let pairs = vec![pair(0, 2, array![[0.3f32]], 0.4)];
        let ids = build_identities(&[1, 0, 1], &pairs, &cfg(0.4));
        assert_eq!(members(&ids), vec![vec![(0, 0)], vec![(2, 0)]]);
        // Alone: its partner in camera 2 (0.3) may be it, and it spans one camera of two.
        assert!((ids[0].confidence - (0.7f32 * 0.5).cbrt()).abs() < 1e-6);
        assert!(build_identities(&[0, 0], &[], &cfg(0.4)).is_empty());
        let ids = build_identities(&[3], &[], &cfg(0.4));
        assert_eq!(ids.len(), 3);
        assert!(ids.iter().all(|i| i.confidence == 1.0));
    }
}

/// Consistent matches are kept as they are (the baseline agrees); a swapped camera pair is repaired.
mod repair {
    use super::*;

    #[test]
    fn consistent_triangle_forms_two_identities() {
        let s = array![[0.9f32, 0.1], [0.1, 0.8]];
        let pairs = vec![
            pair(0, 1, s.clone(), 0.4),
            pair(0, 2, s.clone(), 0.4),
            pair(1, 2, s, 0.4),
        ];
        let ids = build_identities(&[2, 2, 2], &pairs, &cfg(0.4));
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(0, 1), (1, 1), (2, 1)]]
        );
        // Cohesion 0.9 / 0.8, nothing missing, every camera: the cube roots.
        assert!((ids[0].confidence - 0.9f32.cbrt()).abs() < 1e-6);
        assert!((ids[1].confidence - 0.8f32.cbrt()).abs() < 1e-6);
        assert_eq!(ids[1].id, 1);
        let derived = pairs_from_identities(&ids, &pairs);
        for (d, p) in derived.iter().zip(&pairs) {
            assert_eq!(d.matching.matches, p.matching.matches);
        }
    }

    #[test]
    fn a_clear_contradiction_vetoes_a_merge_the_sum_would_carry() {
        // A0–B0 and A0–C0 and B0–C1 are strong Hungarian pairs, but B0–C0 and A0–C1 are
        // clearly different (score 0): at t = 0.4 adding either C box to {A0, B0} sums to
        // 0.5 − 0.4 > 0, yet one of its pairs weighs −0.4 < −t/2, so C stays apart.
        let pairs = vec![
            pair(0, 1, array![[0.9f32]], 0.4),
            pair(0, 2, array![[0.9f32, 0.0]], 0.4),
            pair(1, 2, array![[0.0f32, 0.9]], 0.4),
        ];
        let ids = build_identities(&[1, 1, 2], &pairs, &cfg(0.4));
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0)], vec![(2, 0)], vec![(2, 1)]]
        );
    }

    #[test]
    fn third_views_repair_a_pairwise_mistake() {
        // Persons p = A0,B0,C0 and q = A1,B1,C1; the Hungarian of A–B swaps them.
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
        let ids = build_identities(&[2, 2, 2], &pairs, &cfg(0.4));
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
    }

    /// Persons with a position; camera `c` sees each person with probability ~0.8 and
    /// scores boxes by closeness: a consistent scene (every pair's Hungarian is right).
    fn consistent_scene(
        cams: usize,
        people: &[u8],
        seen: &[bool],
    ) -> (Vec<usize>, Vec<ViewPair>, Vec<Vec<usize>>) {
        // views[c] = person index of each box of camera c.
        let views: Vec<Vec<usize>> = (0..cams)
            .map(|c| {
                (0..people.len())
                    .filter(|&p| seen[(c * people.len() + p) % seen.len()])
                    .collect()
            })
            .collect();
        let sizes: Vec<usize> = views.iter().map(Vec::len).collect();
        let mut pairs = Vec::new();
        for a in 0..cams {
            for b in a + 1..cams {
                if sizes[a] == 0 || sizes[b] == 0 {
                    continue;
                }
                let s = Array2::from_shape_fn((sizes[a], sizes[b]), |(i, j)| {
                    let (p, q) = (views[a][i], views[b][j]);
                    if p == q {
                        0.9
                    } else {
                        // At most 0.07: a wrong Hungarian pair (a box whose person the
                        // other camera does not see) that two third cameras agree with
                        // weighs 0.07 − 0.4 + 2 × 0.125 < 0, so it stays apart.
                        let d = (people[p] as f32 - people[q] as f32).abs() / 255.0;
                        (0.07 * d).min(0.07)
                    }
                });
                pairs.push(pair(a, b, s, 0.0));
            }
        }
        (sizes, pairs, views)
    }

    proptest! {
        #[test]
        fn consistent_matches_unchanged_and_one_swap_repaired(
            people in proptest::collection::vec(0u8..=255, 2..7),
            seen in proptest::collection::vec(proptest::bool::weighted(0.8), 1..40),
            swap in 0usize..100,
        ) {
            let cams = 4;
            let (sizes, mut pairs, views) = consistent_scene(cams, &people, &seen);
            let c = IdentityConfig::new(None, 0.5);
            // Truth: one identity per person seen by any camera.
            let mut truth: Vec<Vec<(usize, usize)>> = (0..people.len())
                .map(|p| (0..cams).filter_map(|cam| views[cam].iter().position(|&q| q == p).map(|i| (cam, i))).collect::<Vec<_>>())
                .filter(|m: &Vec<_>| !m.is_empty())
                .collect();
            truth.sort();
            let mut got = members(&build_identities(&sizes, &pairs, &c));
            got.sort();
            prop_assert_eq!(&got, &truth);
            // The baseline (the oracle) agrees on transitively consistent matches.
            let uf = IdentityConfig::with_method(None, 0.5, IdentityMethod::UnionFind);
            let mut oracle = members(&build_identities(&sizes, &pairs, &uf));
            oracle.sort();
            prop_assert_eq!(&oracle, &truth);
            // Corrupt one pair: swap the partners of two of its matches (both stay kept).
            if pairs.is_empty() { return Ok(()); }
            let k = swap % pairs.len();
            let asg = &mut pairs[k].matching.assignment;
            if asg.len() < 2 { return Ok(()); }
            let (x, y) = (swap % asg.len(), (swap / 7 + 1 + swap % asg.len()) % asg.len());
            if x == y { return Ok(()); }
            let (bx, by) = (asg[x].b, asg[y].b);
            asg[x].b = by;
            asg[y].b = bx;
            let (pa, pb) = (pairs[k].cam_a, pairs[k].cam_b);
            // Repairable when both swapped persons are seen by the two other cameras.
            let persons = [views[pa][pairs[k].matching.assignment[x].a], views[pa][pairs[k].matching.assignment[y].a]];
            let others: Vec<usize> = (0..cams).filter(|&q| q != pa && q != pb).collect();
            let witnessed = persons.iter().all(|p| others.iter().all(|&q| views[q].contains(p)));
            if witnessed {
                let mut got = members(&build_identities(&sizes, &pairs, &c));
                got.sort();
                prop_assert_eq!(got, truth);
            }
        }
    }
}

/// A lone correct match (S ≈ 0) is kept through the calibrated P.
mod lone_match {
    use super::*;

    #[test]
    fn calibrated_confidence_keeps_a_lone_match() {
        // One person per view: S = 1 − d/(d + 1e-6) ≈ 0 drops it; the calibrated
        // probability of its small distance keeps it.
        let mut p = pair(0, 1, array![[1e-6f32]], 0.5);
        p.matching.assignment[0].distance = 0.3;
        assert!(p.matching.matches.is_empty());
        let cal = Calibration {
            distances: vec![0.5, 2.0],
            probabilities: vec![0.95, 0.05],
            false_share: 0.5,
            samples: [100, 100],
        };
        let c = IdentityConfig::new(Some(Arc::new(cal)), 0.5);
        assert_eq!(c.kept(&p.matching).len(), 1);
        let ids = build_identities(&[1, 1], &[p], &c);
        assert_eq!(members(&ids), vec![vec![(0, 0), (1, 0)]]);
        assert!((ids[0].confidence - 0.95f32.cbrt()).abs() < 1e-6);
    }

    #[test]
    fn the_baseline_loses_a_lone_match_the_clustering_keeps() {
        // One box per camera: S ≈ 0 (max-normalised), the calibrated P of its distance is high.
        let mut p = pair(0, 1, array![[1e-6f32]], 0.5);
        p.matching.assignment[0].distance = 0.3;
        let cal = Calibration {
            distances: vec![0.5, 2.0],
            probabilities: vec![0.95, 0.05],
            false_share: 0.5,
            samples: [100, 100],
        };
        let cal = Some(Arc::new(cal));
        let uf = IdentityConfig::with_method(cal.clone(), 0.5, IdentityMethod::UnionFind);
        let pairs = [p];
        assert_eq!(members(&build_identities(&[1, 1], &pairs, &uf)).len(), 2);
        let cl = IdentityConfig::new(cal, 0.5);
        assert_eq!(
            members(&build_identities(&[1, 1], &pairs, &cl)),
            vec![vec![(0, 0), (1, 0)]]
        );
    }
}

/// The confidence ranks: complete and strong above weak above lone.
mod confidence {
    use super::*;

    #[test]
    fn confidence_ranks_complete_weak_and_lone_identities() {
        // p: three cameras, every link 0.9. q: the same cameras, its camera-2 links only 0.45
        // (kept by the two agreeing third cameras).
        let s01 = array![[0.9f32, 0.1], [0.1, 0.9]];
        let s2 = array![[0.9f32, 0.1], [0.1, 0.45]];
        let pairs = vec![
            pair(0, 1, s01, 0.4),
            pair(0, 2, s2.clone(), 0.4),
            pair(1, 2, s2, 0.4),
        ];
        let ids = build_identities(&[2, 2, 2], &pairs, &cfg(0.4));
        assert_eq!(
            members(&ids),
            vec![vec![(0, 0), (1, 0), (2, 0)], vec![(0, 1), (1, 1), (2, 1)]]
        );
        assert!(ids[0].confidence > ids[1].confidence, "{ids:?}");
        // A box that matches nobody well among three cameras with boxes: below both.
        let lone = vec![
            pair(0, 1, array![[0.9f32]], 0.4),
            pair(0, 2, array![[0.2f32]], 0.4),
            pair(1, 2, array![[0.2f32]], 0.4),
        ];
        let l = build_identities(&[1, 1, 1], &lone, &cfg(0.4));
        assert_eq!(members(&l), vec![vec![(0, 0), (1, 0)], vec![(2, 0)]]);
        assert!(l[1].confidence < ids[1].confidence, "{l:?}");
        // The pair misses camera 2, whose box may be its person (0.2): below the complete p.
        assert!(l[0].confidence < ids[0].confidence, "{l:?}");
    }
}

/// Bad input is ignored or read as no evidence, never a panic.
mod bad_input {
    use super::*;

    #[test]
    fn bad_pairs_are_ignored_not_a_panic() {
        let good = pair(0, 1, array![[0.9f32]], 0.4);
        let mut wrong_shape = pair(0, 1, array![[0.9f32, 0.1]], 0.4);
        wrong_shape.matching.assignment[0].b = 7;
        let same_cam = pair(1, 1, array![[0.9f32]], 0.4);
        let far = pair(0, 9, array![[0.9f32]], 0.4);
        let mut nan = pair(0, 1, array![[0.9f32]], 0.4);
        nan.matching.assignment[0].score = f32::NAN;
        let ids = build_identities(&[1, 1], &[wrong_shape, same_cam, far, good, nan], &cfg(0.4));
        assert_eq!(members(&ids), vec![vec![(0, 0), (1, 0)]]);
    }

    #[test]
    fn non_finite_scores_and_distances_are_no_evidence_not_a_panic() {
        let mut p = pair(0, 1, array![[0.9f32, 0.2], [0.2, 0.9]], 0.4);
        p.matching.scores[(0, 1)] = f32::NAN;
        p.matching.assignment[1].distance = f32::NAN;
        p.matching.distance_scale = f32::INFINITY;
        let cal = Calibration {
            distances: vec![0.5, 2.0],
            probabilities: vec![0.95, 0.05],
            false_share: 0.5,
            samples: [100, 100],
        };
        for c in [cfg(0.4), IdentityConfig::new(Some(Arc::new(cal)), 0.4)] {
            let ids = build_identities(&[2, 2], std::slice::from_ref(&p), &c);
            let boxes: usize = ids.iter().map(|i| i.members.len()).sum();
            assert_eq!(boxes, 4);
            assert!(
                ids.iter().all(|i| (0.0..=1.0).contains(&i.confidence)),
                "{ids:?}"
            );
        }
    }
}

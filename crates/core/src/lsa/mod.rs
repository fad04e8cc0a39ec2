//! Linear sum assignment: the minimum-cost one-to-one assignment of a cost matrix's rows and
//! columns. Square problems go to LAPJV ([`jv`]), rectangular ones to shortest augmenting
//! paths from a row reduction ([`sap`], SciPy's algorithm); both were measured against
//! each other and against `pathfinding::kuhn_munkres` on the matcher's real cost matrices
//! (BENCHMARKS.md).
//!
//! Ours rather than a crate's because it is the hot loop of every frame (21 solves for 7
//! cameras): the solver keeps its buffers between calls ([`Solver`], one per thread behind
//! [`assign`]), works on the `f32` cost matrix the matcher already has, and gives every
//! input, NaN and infinities included, a valid answer instead of an error. `pathfinding`
//! stays the oracle its tests compare against.
use std::cell::RefCell;

use ndarray::ArrayView2;

mod jv;
mod sap;

/// Marks "no row / no column" in the solvers' index arrays.
const NONE: usize = usize::MAX;

/// A reusable assignment solver: the buffers of one solve are kept for the next, so a
/// steady stream of similar-sized problems allocates nothing after the first.
#[derive(Debug, Default)]
pub(crate) struct Solver {
    /// The cost matrix as solved: `rows ≤ cols`, row-major, `f64`, every entry finite.
    cost: Vec<f64>,
    square: jv::Jv,
    rectangular: sap::Sap,
}

impl Solver {
    /// A solver with no buffers yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Minimum-cost one-to-one assignment of `cost` (`n × m`): `min(n, m)` pairs
    /// `(row, col)` written to `out` (cleared first), sorted by row. An empty side gives no
    /// pairs.
    ///
    /// Non-finite entries never hang, panic or poison the duals: NaN and `+inf` cost more
    /// than every finite entry, and `-inf` less (each is replaced by a finite value beyond
    /// the finite range before solving), so a matrix with a few bad entries is solved as if
    /// they were the worst (or best) choices.
    pub(crate) fn solve(&mut self, cost: ArrayView2<f32>, out: &mut Vec<(usize, usize)>) {
        out.clear();
        let (n, m) = cost.dim();
        if n == 0 || m == 0 {
            return;
        }
        let transpose = n > m;
        let (rows, cols) = if transpose { (m, n) } else { (n, m) };
        self.load(cost, transpose);
        let col_of: &[usize] = if rows == 1 {
            // One row: its cheapest column (the first of equals).
            let best = self
                .cost
                .iter()
                .enumerate()
                .fold(
                    (0, f64::INFINITY),
                    |b, (j, &c)| if c < b.1 { (j, c) } else { b },
                )
                .0;
            self.square.x.clear();
            self.square.x.push(best);
            &self.square.x
        } else if rows < cols || self.rectangular.start(&self.cost, rows, cols) * 4 <= rows {
            // Rectangular, or square with a clear best column for most rows (the row
            // reduction did most of the work): shortest augmenting paths for the rest.
            if rows < cols {
                self.rectangular.start(&self.cost, rows, cols);
            }
            self.rectangular.finish(&self.cost, rows, cols);
            &self.rectangular.col4row
        } else {
            // Square with many conflicts: LAPJV's reductions settle them faster.
            self.square.solve(&self.cost, rows);
            &self.square.x
        };
        if transpose {
            // Row `r` of the solved matrix is column `r` of the caller's.
            out.extend((0..rows).map(|r| (col_of[r], r)));
            out.sort_unstable();
        } else {
            out.extend((0..rows).map(|r| (r, col_of[r])));
        }
    }

    /// Copies `cost` (transposed when asked) into `self.cost` as finite `f64`s: NaN and
    /// `+inf` become one value above the finite range, `-inf` one below it.
    fn load(&mut self, cost: ArrayView2<f32>, transpose: bool) {
        let cost = cost.as_standard_layout();
        let flat = cost.as_slice().expect("standard layout is contiguous");
        let (n, m) = cost.dim();
        // One branch-free pass (vector code) for the common, all-finite case.
        let all_finite = flat.iter().fold(true, |ok, v| ok & v.is_finite());
        let (worse, better) = if all_finite {
            (0.0, 0.0)
        } else {
            let (lo, hi) = flat
                .iter()
                .filter(|v| v.is_finite())
                .fold(None, |r: Option<(f32, f32)>, &v| match r {
                    None => Some((v, v)),
                    Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
                })
                .map_or((0.0, 0.0), |(lo, hi)| (lo as f64, hi as f64));
            let span = hi - lo + 1.0;
            (hi + span, lo - span)
        };
        let sanitize = |v: f32| {
            if all_finite || v.is_finite() {
                v as f64
            } else if v == f32::NEG_INFINITY {
                better
            } else {
                worse
            }
        };
        self.cost.clear();
        if transpose {
            self.cost.resize(n * m, 0.0);
            for (r, row) in flat.chunks_exact(m).enumerate() {
                for (c, &v) in row.iter().enumerate() {
                    self.cost[c * n + r] = sanitize(v);
                }
            }
        } else if all_finite {
            self.cost.extend(flat.iter().map(|&v| v as f64));
        } else {
            self.cost.extend(flat.iter().map(|&v| sanitize(v)));
        }
    }
}

thread_local! {
    static SOLVER: RefCell<Solver> = RefCell::new(Solver::new());
}

/// [`Solver::solve`] on this thread's solver: the minimum-cost assignment of `cost` as
/// `min(n, m)` pairs `(row, col)` sorted by row.
pub fn assign(cost: ArrayView2<f32>) -> Vec<(usize, usize)> {
    let mut out = Vec::with_capacity(cost.nrows().min(cost.ncols()));
    SOLVER.with(|s| s.borrow_mut().solve(cost, &mut out));
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::is_valid_assignment;
    use ndarray::{Array2, array};
    use pathfinding::kuhn_munkres::{Weights, kuhn_munkres_min};
    use proptest::prelude::*;

    /// Integer weights for the `pathfinding` oracle (costs ≥ 0 scaled by 2^20).
    struct Oracle(Vec<Vec<i64>>);

    impl Weights<i64> for Oracle {
        fn rows(&self) -> usize {
            self.0.len()
        }
        fn columns(&self) -> usize {
            self.0[0].len()
        }
        fn at(&self, r: usize, c: usize) -> i64 {
            self.0[r][c]
        }
        fn neg(&self) -> Self {
            Oracle(
                self.0
                    .iter()
                    .map(|r| r.iter().map(|v| -v).collect())
                    .collect(),
            )
        }
    }

    /// Integer costs, so that the optimum is exact for both solvers.
    fn int_matrix(max: usize, levels: i32) -> impl Strategy<Value = Array2<f32>> {
        (1..=max, 1..=max).prop_flat_map(move |(n, m)| {
            proptest::collection::vec(0..levels, n * m).prop_map(move |v| {
                Array2::from_shape_vec((n, m), v.into_iter().map(|x| x as f32).collect()).unwrap()
            })
        })
    }

    fn oracle_min(cost: &Array2<f32>) -> i64 {
        let (n, m) = cost.dim();
        let t = n > m;
        let (rows, cols) = if t { (m, n) } else { (n, m) };
        let w = Oracle(
            (0..rows)
                .map(|r| {
                    (0..cols)
                        .map(|c| {
                            let v = if t { cost[(c, r)] } else { cost[(r, c)] };
                            v as i64
                        })
                        .collect()
                })
                .collect(),
        );
        kuhn_munkres_min(&w).0
    }

    fn total(cost: &Array2<f32>, pairs: &[(usize, usize)]) -> i64 {
        pairs.iter().map(|&(r, c)| cost[(r, c)] as i64).sum()
    }

    #[test]
    fn known_cases() {
        let c = array![[4.0f32, 1.0, 3.0], [2.0, 0.0, 5.0], [3.0, 2.0, 2.0]];
        assert_eq!(assign(c.view()), vec![(0, 1), (1, 0), (2, 2)]);
        let c = array![[1.0f32, 9.0], [9.0, 1.0], [0.0, 0.5]];
        assert_eq!(assign(c.view()), vec![(1, 1), (2, 0)]);
        // A constant matrix is solved by the identity (SciPy's tie rule).
        let c = Array2::<f32>::ones((3, 4));
        assert_eq!(assign(c.view()), vec![(0, 0), (1, 1), (2, 2)]);
        assert!(assign(Array2::<f32>::zeros((0, 3)).view()).is_empty());
        assert!(assign(Array2::<f32>::zeros((2, 0)).view()).is_empty());
    }

    #[test]
    fn non_finite_entries_are_worst_or_best() {
        let c = array![
            [f32::NAN, 0.5, 0.25],
            [0.2, f32::NEG_INFINITY, 0.3],
            [0.3, 0.4, f32::INFINITY]
        ];
        assert_eq!(assign(c.view()), vec![(0, 2), (1, 1), (2, 0)]);
        let nan = Array2::from_elem((4, 2), f32::NAN);
        assert!(is_valid_assignment(&assign(nan.view()), 4, 2));
        let huge = array![[f32::MAX, -f32::MAX], [0.0, f32::MAX]];
        assert_eq!(assign(huge.view()), vec![(0, 1), (1, 0)]);
        let mixed = array![[f32::INFINITY, f32::MAX], [f32::NEG_INFINITY, -f32::MAX]];
        assert!(is_valid_assignment(&assign(mixed.view()), 2, 2));
    }

    #[test]
    fn a_reused_solver_forgets_the_previous_problem() {
        let mut s = Solver::new();
        let mut out = Vec::new();
        let big = Array2::from_shape_fn((9, 7), |(r, c)| ((r * 7 + c * 3) % 11) as f32);
        s.solve(big.view(), &mut out);
        assert!(is_valid_assignment(&out, 9, 7));
        let small = array![[0.0f32, 1.0], [1.0, 0.0]];
        s.solve(small.view(), &mut out);
        assert_eq!(out, vec![(0, 0), (1, 1)]);
    }

    proptest! {
        #[test]
        fn optimal_like_the_oracle(cost in int_matrix(9, 20)) {
            let (n, m) = cost.dim();
            let pairs = assign(cost.view());
            prop_assert!(is_valid_assignment(&pairs, n, m));
            prop_assert_eq!(total(&cost, &pairs), oracle_min(&cost));
        }

        #[test]
        fn optimal_like_the_oracle_with_many_ties(cost in int_matrix(40, 3)) {
            let (n, m) = cost.dim();
            let pairs = assign(cost.view());
            prop_assert!(is_valid_assignment(&pairs, n, m));
            prop_assert_eq!(total(&cost, &pairs), oracle_min(&cost));
        }

        #[test]
        fn optimal_on_wide_integer_ranges(cost in int_matrix(40, 1 << 20)) {
            prop_assert_eq!(total(&cost, &assign(cost.view())), oracle_min(&cost));
        }

        #[test]
        fn both_algorithms_are_optimal_on_square_problems(
            cost in (2usize..=12).prop_flat_map(|n| {
                proptest::collection::vec(0..6i32, n * n).prop_map(move |v| {
                    Array2::from_shape_vec((n, n), v.into_iter().map(|x| x as f32).collect())
                        .unwrap()
                })
            })
        ) {
            let n = cost.nrows();
            let flat: Vec<f64> = cost.iter().map(|&v| v as f64).collect();
            let best = oracle_min(&cost);
            let mut square = jv::Jv::default();
            square.solve(&flat, n);
            let pairs: Vec<_> = square.x.iter().copied().enumerate().collect();
            prop_assert!(is_valid_assignment(&pairs, n, n));
            prop_assert_eq!(total(&cost, &pairs), best);
            let mut rect = sap::Sap::default();
            rect.start(&flat, n, n);
            rect.finish(&flat, n, n);
            let pairs: Vec<_> = rect.col4row.iter().copied().enumerate().collect();
            prop_assert!(is_valid_assignment(&pairs, n, n));
            prop_assert_eq!(total(&cost, &pairs), best);
        }

        #[test]
        fn any_floats_give_a_valid_assignment(
            v in proptest::collection::vec(
                prop_oneof![
                    4 => -1e30f32..1e30,
                    1 => Just(f32::NAN),
                    1 => Just(f32::INFINITY),
                    1 => Just(f32::NEG_INFINITY),
                ],
                1..64,
            ),
            cols in 1usize..9,
        ) {
            let rows = v.len().div_ceil(cols);
            let mut v = v;
            v.resize(rows * cols, 0.0);
            let cost = Array2::from_shape_vec((rows, cols), v).unwrap();
            prop_assert!(is_valid_assignment(&assign(cost.view()), rows, cols));
        }
    }
}

//! Square assignment by LAPJV (Jonker & Volgenant, "A shortest augmenting path algorithm
//! for dense and sparse linear assignment problems", Computing 38, 1987), in the dense form of
//! Tomas Kazmar's `lapjv.cpp` (github gatagat/lap): column reduction with reduction transfer,
//! two rounds of augmenting row reduction, then a shortest augmenting path (Dijkstra on
//! reduced costs) for each row still free.
use super::NONE;

/// LAPJV's buffers, kept between solves.
#[derive(Debug, Default)]
pub(super) struct Jv {
    /// Column dual variables.
    v: Vec<f64>,
    /// Column assigned to each row, row assigned to each column.
    pub(super) x: Vec<usize>,
    y: Vec<usize>,
    /// Rows without a column, worked through by each phase.
    free: Vec<usize>,
    /// Scratch of the column reduction (rows that took exactly one column).
    unique: Vec<bool>,
    /// Scratch of the path search: tentative distances, predecessor rows and the columns
    /// ordered as settled | scanning | to do.
    d: Vec<f64>,
    pred: Vec<usize>,
    cols: Vec<usize>,
}

impl Jv {
    /// Solves the `size × size` problem `cost` (row-major, finite, `size ≥ 2`); the column
    /// of row `i` is then `self.x[i]`.
    pub(super) fn solve(&mut self, cost: &[f64], size: usize) {
        debug_assert!(size >= 2 && cost.len() == size * size);
        self.resize(size);
        let mut free = self.column_reduction(cost, size);
        for _ in 0..2 {
            if free == 0 {
                break;
            }
            free = self.augmenting_row_reduction(cost, size, free);
        }
        for k in 0..free {
            self.augment(cost, size, self.free[k]);
        }
    }

    fn resize(&mut self, size: usize) {
        for v in [&mut self.x, &mut self.y, &mut self.pred, &mut self.cols] {
            v.clear();
            v.resize(size, NONE);
        }
        self.v.resize(size, 0.0);
        self.d.resize(size, 0.0);
        self.free.resize(size, NONE);
        self.unique.clear();
        self.unique.resize(size, true);
    }

    /// Column reduction and reduction transfer: each column's dual is its smallest cost and
    /// goes to the row holding it (the last such column for a row that holds several); a row
    /// holding exactly one column passes its slack to that column's dual. Returns how many
    /// rows are left free (listed in `self.free`).
    fn column_reduction(&mut self, cost: &[f64], size: usize) -> usize {
        self.v.fill(f64::INFINITY);
        for i in 0..size {
            let row = &cost[i * size..(i + 1) * size];
            for (j, &c) in row.iter().enumerate() {
                if c < self.v[j] {
                    self.v[j] = c;
                    self.y[j] = i;
                }
            }
        }
        for j in (0..size).rev() {
            let i = self.y[j];
            if self.x[i] == NONE {
                self.x[i] = j;
            } else {
                self.unique[i] = false;
                self.y[j] = NONE;
            }
        }
        let mut free = 0;
        for i in 0..size {
            if self.x[i] == NONE {
                self.free[free] = i;
                free += 1;
            } else if self.unique[i] {
                let j = self.x[i];
                let min = cost[i * size..(i + 1) * size]
                    .iter()
                    .zip(&self.v)
                    .enumerate()
                    .filter(|&(j2, _)| j2 != j)
                    .map(|(_, (&c, &v))| c - v)
                    .fold(f64::INFINITY, f64::min);
                self.v[j] -= min;
            }
        }
        free
    }

    /// Augmenting row reduction: each free row takes its cheapest column (in reduced cost),
    /// lowering that column's dual to the row's second-best, and the row it displaces is
    /// free again. Bounded as in LAPJV (at most `size` passes over the free rows). Returns
    /// how many rows are still free.
    fn augmenting_row_reduction(&mut self, cost: &[f64], size: usize, free_count: usize) -> usize {
        let mut current = 0;
        let mut new_free = 0;
        let mut passes = 0usize;
        while current < free_count {
            passes += 1;
            let free_i = self.free[current];
            current += 1;
            let row = &cost[free_i * size..(free_i + 1) * size];
            let (mut j1, mut v1) = (0, row[0] - self.v[0]);
            let (mut j2, mut v2) = (NONE, f64::INFINITY);
            for (j, (&cj, &vj)) in row.iter().zip(&self.v).enumerate().skip(1) {
                let c = cj - vj;
                if c < v2 {
                    if c >= v1 {
                        (j2, v2) = (j, c);
                    } else {
                        (j2, v2) = (j1, v1);
                        (j1, v1) = (j, c);
                    }
                }
            }
            let mut i0 = self.y[j1];
            let v1_new = self.v[j1] - (v2 - v1);
            let lowers = v1_new < self.v[j1];
            if passes < current * size {
                if lowers {
                    self.v[j1] = v1_new;
                } else if i0 != NONE && j2 != NONE {
                    j1 = j2;
                    i0 = self.y[j2];
                }
                if i0 != NONE {
                    if lowers {
                        current -= 1;
                        self.free[current] = i0;
                    } else {
                        self.free[new_free] = i0;
                        new_free += 1;
                    }
                }
            } else if i0 != NONE {
                self.free[new_free] = i0;
                new_free += 1;
            }
            self.x[free_i] = j1;
            self.y[j1] = free_i;
        }
        new_free
    }

    /// Shortest augmenting path from the free row `start` (Dijkstra on reduced costs, the
    /// columns at the current minimum distance scanned together), then the column duals of
    /// the settled columns are updated and the assignment flipped along the path.
    fn augment(&mut self, cost: &[f64], size: usize, start: usize) {
        for j in 0..size {
            self.cols[j] = j;
            self.pred[j] = start;
            self.d[j] = cost[start * size + j] - self.v[j];
        }
        let (mut lo, mut hi) = (0, 0);
        // Columns cols[..ready] are settled; `level` is the distance of those being scanned.
        let mut ready = 0;
        let mut level = 0.0;
        let sink = 'search: loop {
            if lo == hi {
                // Move the columns at the new minimum distance to the scan list.
                ready = lo;
                hi = lo + 1;
                let mut mind = self.d[self.cols[lo]];
                // (The columns moved forward below were already looked at: the range is
                // fixed at the start, as in LAPJV.)
                let first = hi;
                for k in first..size {
                    let j = self.cols[k];
                    if self.d[j] <= mind {
                        if self.d[j] < mind {
                            hi = lo;
                            mind = self.d[j];
                        }
                        self.cols[k] = self.cols[hi];
                        self.cols[hi] = j;
                        hi += 1;
                    }
                }
                level = mind;
                if let Some(&j) = self.cols[lo..hi].iter().rev().find(|&&j| self.y[j] == NONE) {
                    break 'search j;
                }
            }
            // Scan the rows assigned to the columns at the minimum distance.
            while lo != hi {
                let j = self.cols[lo];
                lo += 1;
                let i = self.y[j];
                let mind = self.d[j];
                let row = &cost[i * size..(i + 1) * size];
                let h = row[j] - self.v[j] - mind;
                let first = hi;
                for k in first..size {
                    let j = self.cols[k];
                    let reduced = row[j] - self.v[j] - h;
                    if reduced < self.d[j] {
                        self.d[j] = reduced;
                        self.pred[j] = i;
                        if reduced == mind {
                            if self.y[j] == NONE {
                                break 'search j;
                            }
                            self.cols[k] = self.cols[hi];
                            self.cols[hi] = j;
                            hi += 1;
                        }
                    }
                }
            }
        };
        for k in 0..ready {
            let j = self.cols[k];
            self.v[j] += self.d[j] - level;
        }
        let mut j = sink;
        for _ in 0..size {
            let i = self.pred[j];
            self.y[j] = i;
            std::mem::swap(&mut self.x[i], &mut j);
            if i == start {
                return;
            }
        }
        debug_assert!(false, "augmenting path longer than the matrix");
    }
}

//! Rectangular assignment (fewer rows than columns) by shortest augmenting paths, as Crouse
//! describes it ("On implementing 2D rectangular assignment algorithms", IEEE TAES 2016) and
//! SciPy's `linear_sum_assignment` implements it (`rectangular_lsap.cpp`), started from a row
//! reduction. Used instead of padding the problem square for LAPJV: padding rows of equal
//! cost are all ties, the worst case of LAPJV's reductions.
use super::NONE;

/// The buffers of the shortest-augmenting-path solver, kept between solves.
#[derive(Debug, Default)]
pub(super) struct Sap {
    /// Row and column dual variables.
    u: Vec<f64>,
    v: Vec<f64>,
    /// Length of the shortest alternating path found so far to each column.
    shortest: Vec<f64>,
    /// Row preceding each column on its shortest path.
    path: Vec<usize>,
    /// Column assigned to each row, row assigned to each column.
    pub(super) col4row: Vec<usize>,
    row4col: Vec<usize>,
    /// Rows reached by the current search.
    seen_rows: Vec<bool>,
    /// Columns settled by the current search: `+inf`, open ones 0 (added to a distance, it
    /// takes a settled column out of the minimum without a branch).
    settled: Vec<f64>,
}

impl Sap {
    /// The row reduction of the `rows × cols` problem `cost` (row-major, finite,
    /// `1 ≤ rows ≤ cols`): returns how many rows it left free. After [`Sap::finish`] the
    /// column of row `i` is `self.col4row[i]`.
    pub(super) fn start(&mut self, cost: &[f64], rows: usize, cols: usize) -> usize {
        debug_assert!(rows >= 1 && rows <= cols && cost.len() == rows * cols);
        self.reset(rows, cols);
        self.row_reduction(cost, rows, cols);
        self.col4row.iter().filter(|&&j| j == NONE).count()
    }

    /// Shortest augmenting paths for the rows [`Sap::start`] left free.
    pub(super) fn finish(&mut self, cost: &[f64], rows: usize, cols: usize) {
        for cur in 0..rows {
            if self.col4row[cur] != NONE {
                continue;
            }
            let (sink, min_val) = self.shortest_path(cost, cur, rows, cols);
            // Dual update (Crouse's step 3).
            self.u[cur] += min_val;
            for i in 0..rows {
                if self.seen_rows[i] && i != cur {
                    self.u[i] += min_val - self.shortest[self.col4row[i]];
                }
            }
            for j in 0..cols {
                if self.settled[j] != 0.0 {
                    self.v[j] -= min_val - self.shortest[j];
                }
            }
            // Augment along the path ending at `sink`.
            // (A path visits each row at most once: bounded even if rounding ever broke it.)
            let mut j = sink;
            for _ in 0..rows {
                let i = self.path[j];
                self.row4col[j] = i;
                std::mem::swap(&mut self.col4row[i], &mut j);
                if i == cur {
                    break;
                }
            }
        }
    }

    fn reset(&mut self, rows: usize, cols: usize) {
        let fill = |v: &mut Vec<usize>, len| {
            v.clear();
            v.resize(len, NONE);
        };
        fill(&mut self.col4row, rows);
        fill(&mut self.row4col, cols);
        fill(&mut self.path, cols);
        for (x, len) in [(&mut self.u, rows), (&mut self.v, cols)] {
            x.clear();
            x.resize(len, 0.0);
        }
        self.shortest.resize(cols, f64::INFINITY);
        self.seen_rows.resize(rows, false);
        self.settled.resize(cols, 0.0);
    }

    /// Starting point: every row's dual is its smallest cost (all reduced costs ≥ 0, column
    /// duals 0, as the rectangular problem needs for its free columns), and a row whose
    /// cheapest column no earlier row took gets it at zero reduced cost. On cost matrices with
    /// a clear best match per row, most rows end here and only the conflicts are searched.
    fn row_reduction(&mut self, cost: &[f64], rows: usize, cols: usize) {
        for i in 0..rows {
            let row = &cost[i * cols..(i + 1) * cols];
            let (mut best, mut min) = (0, row[0]);
            for (j, &c) in row.iter().enumerate().skip(1) {
                if c < min {
                    (best, min) = (j, c);
                }
            }
            self.u[i] = min;
            if self.row4col[best] == NONE {
                self.row4col[best] = i;
                self.col4row[i] = best;
            }
        }
    }

    /// Dijkstra-like search from the free row `start` for the shortest augmenting path in
    /// the reduced costs: returns its free end column and its length.
    ///
    /// Every step relaxes all columns through one row and takes the nearest unsettled one.
    /// Settled columns carry `+inf` in `self.settled` (open ones 0) instead of leaving a list
    /// of remaining columns, so both loops run over plain slices without branches and
    /// compile to vector code; among equally near columns the first free one is taken (it
    /// ends the search), else the first.
    fn shortest_path(
        &mut self,
        cost: &[f64],
        start: usize,
        rows: usize,
        cols: usize,
    ) -> (usize, f64) {
        self.seen_rows[..rows].fill(false);
        let settled = &mut self.settled[..cols];
        let shortest = &mut self.shortest[..cols];
        let path = &mut self.path[..cols];
        let v = &self.v[..cols];
        let row4col = &self.row4col[..cols];
        settled.fill(0.0);
        shortest.fill(f64::INFINITY);
        let mut min_val = 0.0;
        let mut i = start;
        loop {
            self.seen_rows[i] = true;
            let row = &cost[i * cols..(i + 1) * cols];
            let ui = self.u[i];
            for j in 0..cols {
                let r = min_val + row[j] - ui - v[j];
                let closer = r < shortest[j] && settled[j] == 0.0;
                shortest[j] = if closer { r } else { shortest[j] };
                path[j] = if closer { i } else { path[j] };
            }
            let mut lanes = [f64::INFINITY; 4];
            let mut chunks = shortest.chunks_exact(4).zip(settled.chunks_exact(4));
            for (sp, st) in &mut chunks {
                for k in 0..4 {
                    lanes[k] = lanes[k].min(sp[k] + st[k]);
                }
            }
            let tail = cols - cols % 4;
            for j in tail..cols {
                lanes[0] = lanes[0].min(shortest[j] + settled[j]);
            }
            let lowest = lanes.into_iter().fold(f64::INFINITY, f64::min);
            let mut chosen = NONE;
            if lowest.is_finite() {
                for j in 0..cols {
                    if shortest[j] + settled[j] == lowest {
                        if row4col[j] == NONE {
                            chosen = j;
                            break;
                        }
                        if chosen == NONE {
                            chosen = j;
                        }
                    }
                }
                min_val = lowest;
            }
            if chosen == NONE {
                // Only if rounding ever made every distance non-finite: the first open column,
                // reached from this row, which keeps the path (and the result) valid.
                chosen = settled.iter().position(|&s| s == 0.0).unwrap_or(0);
                path[chosen] = i;
            }
            settled[chosen] = f64::INFINITY;
            match row4col[chosen] {
                NONE => return (chosen, min_val),
                next => i = next,
            }
        }
    }
}

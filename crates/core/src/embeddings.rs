//! The embeddings of one frame, kept the way the encoder returned them.
use std::ops::Range;

use ndarray::{Array2, ArrayView2, s};

use crate::{Error, Result};

/// The geometric embeddings of one frame: one row per box, the views' rows back to back in
/// camera order in ONE contiguous `[N, G]` matrix (the encoder's output, not copied), with
/// each view's row range.
///
/// Keeping the rows together lets the matcher multiply whole groups of views in a few large
/// matrix products ([`crate::distances::all_pairs_distances`]) instead of copying them.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameEmbeddings {
    /// `[N, G]`, standard (row-major) layout.
    matrix: Array2<f32>,
    /// Row range of each view; `None` for views that did not report.
    views: Vec<Option<Range<usize>>>,
}

impl FrameEmbeddings {
    /// `matrix` holds `rows[c]` rows for each view `c` in camera order (`None`: the view did
    /// not report, no rows). Errors when the counts do not add up to the matrix's rows.
    pub fn new(matrix: Array2<f32>, rows: &[Option<usize>]) -> Result<Self> {
        let total: usize = rows.iter().flatten().sum();
        if total != matrix.nrows() {
            return Err(Error::Encoder(format!(
                "{} embedding rows for {total} boxes",
                matrix.nrows()
            )));
        }
        let matrix = if matrix.is_standard_layout() {
            matrix
        } else {
            matrix.as_standard_layout().into_owned()
        };
        let mut start = 0;
        let views = rows
            .iter()
            .map(|r| {
                r.map(|n| {
                    start += n;
                    start - n..start
                })
            })
            .collect();
        Ok(FrameEmbeddings { matrix, views })
    }

    /// Stacks per-view embeddings computed separately (`None`: the view did not report).
    /// Errors when the widths differ.
    pub fn from_views(views: &[Option<Array2<f32>>]) -> Result<Self> {
        let dim = views
            .iter()
            .flatten()
            .map(|v| v.ncols())
            .next()
            .unwrap_or(0);
        if let Some(v) = views.iter().flatten().find(|v| v.ncols() != dim) {
            return Err(Error::Encoder(format!(
                "embedding widths differ across views: {dim} and {}",
                v.ncols()
            )));
        }
        let rows: Vec<Option<usize>> = views
            .iter()
            .map(|v| v.as_ref().map(|v| v.nrows()))
            .collect();
        let total: usize = rows.iter().flatten().sum();
        let mut data = Vec::with_capacity(total * dim);
        for v in views.iter().flatten() {
            data.extend(v.iter());
        }
        let matrix = Array2::from_shape_vec((total, dim), data).expect("sized from the views");
        FrameEmbeddings::new(matrix, &rows)
    }

    /// The same frame with only the first `width` columns of every row (the embedding's leading
    /// block, [`crate::Encoder::leading_width`]); unchanged, not copied, when `width` covers
    /// every column.
    pub fn leading(self, width: usize) -> FrameEmbeddings {
        if width >= self.matrix.ncols() {
            return self;
        }
        FrameEmbeddings {
            matrix: self.matrix.slice(s![.., ..width]).to_owned(),
            views: self.views,
        }
    }

    /// Number of views (reported or not).
    pub fn num_views(&self) -> usize {
        self.views.len()
    }

    /// Embedding width `G`.
    pub fn dim(&self) -> usize {
        self.matrix.ncols()
    }

    /// The embeddings of view `camera` (`[n, G]`), `None` when it did not report (or is out
    /// of range).
    pub fn view(&self, camera: usize) -> Option<ArrayView2<'_, f32>> {
        let r = self.rows(camera)?;
        Some(self.matrix.slice(s![r, ..]))
    }

    /// The rows of view `camera` in [`Self::matrix`].
    pub fn rows(&self, camera: usize) -> Option<Range<usize>> {
        self.views.get(camera)?.clone()
    }

    /// All rows, every view's back to back in camera order.
    pub fn matrix(&self) -> ArrayView2<'_, f32> {
        self.matrix.view()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    #[test]
    fn views_are_row_ranges_of_one_matrix() {
        let m = array![[1.0f32, 2.0], [3.0, 4.0], [5.0, 6.0]];
        let e = FrameEmbeddings::new(m, &[Some(2), None, Some(0), Some(1)]).unwrap();
        assert_eq!(e.num_views(), 4);
        assert_eq!(e.dim(), 2);
        assert_eq!(e.view(0).unwrap(), array![[1.0f32, 2.0], [3.0, 4.0]]);
        assert!(e.view(1).is_none());
        assert_eq!(e.view(2).unwrap().nrows(), 0);
        assert_eq!(e.rows(3), Some(2..3));
        assert!(e.view(9).is_none());
        let err = FrameEmbeddings::new(Array2::zeros((2, 2)), &[Some(3)]).unwrap_err();
        assert!(
            err.to_string().contains("2 embedding rows for 3 boxes"),
            "{err}"
        );
    }

    #[test]
    fn the_leading_block_keeps_every_view_and_the_first_columns() {
        let m = array![[1.0f32, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
        let e = FrameEmbeddings::new(m, &[Some(2), None, Some(1)]).unwrap();
        let lead = e.clone().leading(1);
        assert_eq!(lead.dim(), 1);
        assert_eq!(lead.view(0).unwrap(), array![[1.0f32], [4.0]]);
        assert!(lead.view(1).is_none());
        assert_eq!(lead.view(2).unwrap(), array![[7.0f32]]);
        assert_eq!(e.clone().leading(3), e);
        assert_eq!(e.clone().leading(99), e);
    }

    #[test]
    fn from_views_stacks_and_checks_widths() {
        // A transposed (non-standard layout) view is stacked by rows like any other.
        let t = array![[5.0f32, 7.0], [6.0, 8.0]];
        let views = vec![Some(array![[1.0f32, 2.0]]), None, Some(t.t().to_owned())];
        let e = FrameEmbeddings::from_views(&views).unwrap();
        assert_eq!(e.matrix(), array![[1.0f32, 2.0], [5.0, 6.0], [7.0, 8.0]]);
        assert_eq!(e.view(2).unwrap(), t.t());
        let bad = vec![
            Some(Array2::<f32>::zeros((1, 2))),
            Some(Array2::zeros((1, 3))),
        ];
        assert!(FrameEmbeddings::from_views(&bad).is_err());
        let none = FrameEmbeddings::from_views(&[None, None]).unwrap();
        assert_eq!((none.num_views(), none.dim()), (2, 0));
    }
}

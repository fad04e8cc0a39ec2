//! Test-only encoders and scene helpers shared by the unit tests of this and the downstream
//! crates (feature `testing`).
use ndarray::Array2;

use crate::CameraSpec;
use crate::Encoder;
use crate::Result;

/// Embeds a box as its normalised bottom-centre `(cx, y2)`: the same ground point matches
/// across cameras that share an image frame (a stand-in for a trained encoder).
pub struct BottomCentre;

impl Encoder for BottomCentre {
    fn embed(&mut self, boxes: &[[f32; 4]], _cameras: &[i64]) -> Result<Array2<f32>> {
        Ok(Array2::from_shape_fn((boxes.len(), 2), |(i, k)| {
            if k == 0 {
                (boxes[i][0] + boxes[i][2]) / 2.0
            } else {
                boxes[i][3]
            }
        }))
    }
    fn dim(&self) -> usize {
        2
    }
}

/// `n` cameras named `c0`, `c1`, … with one image size.
pub fn cameras(n: usize, width: u32, height: u32) -> Vec<CameraSpec> {
    (0..n)
        .map(|i| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: format!("c{i}"),
            width,
            height,
        })
        .collect()
}

/// Whether `pairs` is a complete one-to-one assignment of an `n × m` matrix: `min(n, m)`
/// pairs, sorted by row, no row or column twice, all in range (the assignment tests' oracle).
pub fn is_valid_assignment(pairs: &[(usize, usize)], n: usize, m: usize) -> bool {
    let mut rows = vec![false; n];
    let mut cols = vec![false; m];
    for &(r, c) in pairs {
        if r >= n || c >= m || rows[r] || cols[c] {
            return false;
        }
        rows[r] = true;
        cols[c] = true;
    }
    pairs.len() == n.min(m) && pairs.windows(2).all(|w| w[0].0 < w[1].0)
}

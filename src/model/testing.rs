//! Test-only encoders and scene helpers shared by unit tests across modules.
use ndarray::Array2;

use crate::Result;
use crate::core::CameraSpec;
use crate::model::Encoder;

/// Embeds a box as its normalised bottom-centre `(cx, y2)`: the same ground point matches
/// across cameras that share an image frame (a stand-in for a trained encoder).
pub(crate) struct BottomCentre;

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
pub(crate) fn cameras(n: usize, width: u32, height: u32) -> Vec<CameraSpec> {
    (0..n)
        .map(|i| CameraSpec {
            name: format!("c{i}"),
            width,
            height,
        })
        .collect()
}

//! Property: the ONNX encoder never panics on arbitrary inputs — finite, sane boxes embed to finite
//! values equal to the reference forward pass; anything else is `InvalidArgument`.
use crossview_core::CameraSpec;
use crossview_core::Encoder;
use crossview_core::Error;
use crossview_model::{EncoderConfig, EncoderWeights, ModelMetadata, OnnxEncoder, to_onnx_bytes};
use proptest::prelude::*;

fn any_coord() -> impl Strategy<Value = f32> {
    prop_oneof![
        8 => -0.2f32..1.2,
        1 => prop::num::f32::ANY,
        1 => -1e6f32..1e6,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    #[test]
    fn embed_never_panics(
        items in prop::collection::vec((prop::array::uniform4(any_coord()), -1i64..4), 0..12)
    ) {
        let config = EncoderConfig { fourier_features: 8, camera_dim: 8, width: 24, blocks: 2 };
        let weights = EncoderWeights::random(3, config, 2).unwrap();
        let meta = ModelMetadata::new(
            (0..3)
                .map(|i| CameraSpec { offset: 0, offset_ms: 0, name: format!("c{i}"), width: 10, height: 10 })
                .collect(),
        );
        let mut enc =
            OnnxEncoder::from_bytes("p.onnx", &to_onnx_bytes(&weights, &meta).unwrap()).unwrap();
        let boxes: Vec<[f32; 4]> = items.iter().map(|(b, _)| *b).collect();
        let cams: Vec<i64> = items.iter().map(|(_, c)| *c).collect();
        let valid = boxes
            .iter()
            .flatten()
            .all(|v| v.is_finite() && v.abs() <= crossview_model::weights::MAX_NORMALIZED_COORD)
            && cams.iter().all(|c| (0..3).contains(c));
        match enc.embed(&boxes, &cams) {
            Ok(y) => {
                prop_assert!(valid);
                prop_assert_eq!(y.dim(), (boxes.len(), 24));
                prop_assert!(y.iter().all(|v| v.is_finite()));
                // Moderate coordinates: ONNX equals the reference forward pass.
                if boxes.iter().flatten().all(|v| v.abs() < 10.0) {
                    let want = weights.forward(&boxes, &cams).unwrap();
                    let diff = y.iter().zip(want.iter()).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
                    prop_assert!(diff < 1e-4, "diff {}", diff);
                }
            }
            Err(Error::InvalidArgument { .. }) => prop_assert!(!valid),
            Err(e) => prop_assert!(false, "unexpected error {}", e),
        }
    }
}

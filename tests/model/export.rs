//! The exported ONNX file, run through the real ONNX Runtime, computes exactly the reference
//! forward pass; files round-trip; corrupt or contract-violating files give clear errors.
use crossview_core::CameraSpec;
use crossview_core::Encoder;
use crossview_core::Error;
use crossview_model::onnx::{Dimension, ModelProto, ValueInfoProto};
use crossview_model::{
    EncoderConfig, EncoderOptions, EncoderWeights, ModelMetadata, OnnxEncoder, read_weights,
    to_onnx_bytes, write_onnx,
};
use prost::Message;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

pub(super) fn metadata(n: usize) -> ModelMetadata {
    ModelMetadata::new(
        (0..n)
            .map(|i| CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: format!("cam{i}"),
                width: 1920,
                height: 1080,
            })
            .collect(),
    )
}

/// Random boxes slightly beyond [0, 1] (normalised boxes are not clamped) on mixed cameras.
fn inputs(n: usize, num_cameras: usize, seed: u64) -> (Vec<[f32; 4]>, Vec<i64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let boxes = (0..n)
        .map(|_| {
            let x1 = rng.random_range(-0.05f32..0.9);
            let y1 = rng.random_range(-0.05f32..0.8);
            [
                x1,
                y1,
                x1 + rng.random_range(0.01f32..0.15),
                y1 + rng.random_range(0.05f32..0.3),
            ]
        })
        .collect();
    let cams = (0..n)
        .map(|_| rng.random_range(0..num_cameras as i64))
        .collect();
    (boxes, cams)
}

pub(super) fn max_abs_diff(a: &ndarray::Array2<f32>, b: &ndarray::Array2<f32>) -> f32 {
    assert_eq!(a.dim(), b.dim());
    a.iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn check_matches_reference(config: EncoderConfig, num_cameras: usize, seed: u64) {
    let weights = EncoderWeights::random(num_cameras, config, seed).unwrap();
    let bytes = to_onnx_bytes(&weights, &metadata(num_cameras)).unwrap();
    let mut enc = OnnxEncoder::from_bytes("mem.onnx", &bytes).unwrap();
    assert_eq!(enc.dim(), config.width);
    for n in [1usize, 2, 37] {
        let (boxes, cams) = inputs(n, num_cameras, seed + n as u64);
        let got = enc.embed(&boxes, &cams).unwrap();
        let want = weights.forward(&boxes, &cams).unwrap();
        let diff = max_abs_diff(&got, &want);
        assert!(diff < 1e-4, "n={n} config={config:?}: max abs diff {diff}");
    }
    let empty = enc.embed(&[], &[]).unwrap();
    assert_eq!(empty.dim(), (0, config.width));
}

#[test]
fn onnx_matches_reference_default_config() {
    check_matches_reference(EncoderConfig::default(), 7, 11);
}

#[test]
fn onnx_matches_reference_narrow_config_with_input_proj() {
    let config = EncoderConfig {
        fourier_features: 16,
        camera_dim: 8,
        width: 48,
        blocks: 2,
    };
    assert!(config.has_input_proj());
    check_matches_reference(config, 3, 5);
}

#[test]
fn write_load_and_read_back_round_trip() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("enc.onnx");
    let config = EncoderConfig {
        fourier_features: 8,
        camera_dim: 8,
        width: 32,
        blocks: 3,
    };
    let weights = EncoderWeights::random(2, config, 3).unwrap();
    let mut meta = metadata(2);
    meta.threshold = 0.25;
    meta.extra.insert("crossview.epochs".into(), "7".into());
    write_onnx(&path, &weights, &meta).unwrap();
    let (w2, m2) = read_weights(&path).unwrap();
    assert_eq!(w2, weights);
    assert_eq!(m2, meta);
    let mut enc = OnnxEncoder::load_with(&path, EncoderOptions { intra_threads: 2 }).unwrap();
    assert_eq!(enc.metadata(), &meta);
    let (boxes, cams) = inputs(5, 2, 1);
    let diff = max_abs_diff(
        &enc.embed(&boxes, &cams).unwrap(),
        &weights.forward(&boxes, &cams).unwrap(),
    );
    assert!(diff < 1e-4, "{diff}");
}

fn assert_model_error(
    result: crossview_core::Result<OnnxEncoder>,
    path_part: &str,
    reason_part: &str,
) {
    match result {
        Err(Error::Model { path, reason }) => {
            assert!(path.contains(path_part), "path {path} lacks {path_part}");
            assert!(
                reason.contains(reason_part),
                "reason '{reason}' lacks '{reason_part}'"
            );
        }
        Err(other) => panic!("expected Error::Model, got {other}"),
        Ok(_) => panic!("expected Error::Model, got a loaded encoder"),
    }
}

#[test]
fn corrupt_files_are_model_errors_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.onnx");
    assert_model_error(OnnxEncoder::load(&missing), "missing.onnx", "cannot read");
    assert!(matches!(read_weights(&missing), Err(Error::Model { .. })));

    let empty = dir.path().join("empty.onnx");
    std::fs::write(&empty, b"").unwrap();
    assert_model_error(OnnxEncoder::load(&empty), "empty.onnx", "empty");

    let random = dir.path().join("random.onnx");
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let noise: Vec<u8> = (0..4096).map(|_| rng.random()).collect();
    std::fs::write(&random, &noise).unwrap();
    assert_model_error(OnnxEncoder::load(&random), "random.onnx", "");

    let weights = EncoderWeights::random(2, EncoderConfig::default(), 0).unwrap();
    let bytes = to_onnx_bytes(&weights, &metadata(2)).unwrap();
    for cut in [10, bytes.len() / 3, bytes.len() / 2, bytes.len() - 7] {
        let truncated = dir.path().join(format!("truncated{cut}.onnx"));
        std::fs::write(&truncated, &bytes[..cut]).unwrap();
        assert_model_error(OnnxEncoder::load(&truncated), "truncated", "");
        assert!(matches!(read_weights(&truncated), Err(Error::Model { .. })));
    }
}

fn small_model() -> ModelProto {
    let config = EncoderConfig {
        fourier_features: 4,
        camera_dim: 4,
        width: 20,
        blocks: 1,
    };
    let weights = EncoderWeights::random(2, config, 0).unwrap();
    let bytes = to_onnx_bytes(&weights, &metadata(2)).unwrap();
    ModelProto::decode(bytes.as_slice()).unwrap()
}

#[test]
fn renamed_input_or_wrong_shape_is_a_clear_error() {
    let mut model = small_model();
    let graph = model.graph.as_mut().unwrap();
    graph.input[0].name = "bboxes".into();
    for node in &mut graph.node {
        for i in &mut node.input {
            if i == "boxes" {
                *i = "bboxes".into();
            }
        }
    }
    let r = OnnxEncoder::from_bytes("renamed.onnx", &model.encode_to_vec());
    assert_model_error(r, "renamed.onnx", "bboxes");

    let mut model = small_model();
    let graph = model.graph.as_mut().unwrap();
    graph.input[0] = ValueInfoProto::tensor(
        "boxes",
        crossview_model::onnx::DT_FLOAT,
        vec![Dimension::symbolic("N"), Dimension::fixed(5)],
    );
    let r = OnnxEncoder::from_bytes("shape.onnx", &model.encode_to_vec());
    assert_model_error(r, "shape.onnx", "boxes");

    let mut model = small_model();
    model.graph.as_mut().unwrap().output[0].name = "features".into();
    let r = OnnxEncoder::from_bytes("output.onnx", &model.encode_to_vec());
    assert_model_error(r, "output.onnx", "embedding");
}

#[test]
fn bad_metadata_names_the_key() {
    for (key, value) in [
        ("crossview.threshold", "2"),
        ("crossview.cameras", "[]"),
        ("crossview.alpha", "x"),
    ] {
        let mut model = small_model();
        for e in &mut model.metadata_props {
            if e.key == key {
                e.value = value.into();
            }
        }
        let r = OnnxEncoder::from_bytes("meta.onnx", &model.encode_to_vec());
        assert_model_error(r, "meta.onnx", key);
    }
    let mut model = small_model();
    model
        .metadata_props
        .retain(|e| e.key != "crossview.version");
    let r = OnnxEncoder::from_bytes("meta.onnx", &model.encode_to_vec());
    assert_model_error(r, "meta.onnx", "crossview.version");

    // Three cameras in metadata but two rows in the camera table.
    let mut model = small_model();
    for e in &mut model.metadata_props {
        if e.key == "crossview.cameras" {
            e.value = serde_json::to_string(&metadata(3).cameras).unwrap();
        }
    }
    let r = OnnxEncoder::from_bytes("cams.onnx", &model.encode_to_vec());
    assert_model_error(r, "cams.onnx", "camera");
}

#[test]
fn bad_inputs_are_invalid_arguments() {
    let model = small_model();
    let mut enc = OnnxEncoder::from_bytes("m.onnx", &model.encode_to_vec()).unwrap();
    let b = [[0.1, 0.1, 0.2, 0.3]];
    for cams in [[2i64], [-1]] {
        let err = enc.embed(&b, &cams).unwrap_err();
        assert!(matches!(err, Error::InvalidArgument { .. }), "{err}");
        assert!(err.to_string().contains("out of range"), "{err}");
    }
    let err = enc.embed(&[[0.1, f32::NAN, 0.2, 0.3]], &[0]).unwrap_err();
    assert!(matches!(err, Error::InvalidArgument { .. }), "{err}");
    let err = enc
        .embed(&[[0.1, 0.1, f32::INFINITY, 0.3]], &[0])
        .unwrap_err();
    assert!(matches!(err, Error::InvalidArgument { .. }), "{err}");
    let err = enc.embed(&b, &[0, 1]).unwrap_err();
    assert!(matches!(err, Error::InvalidArgument { .. }), "{err}");
    // Still usable after rejected calls.
    assert_eq!(enc.embed(&b, &[1]).unwrap().dim(), (1, 20));
}

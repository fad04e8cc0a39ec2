//! An ensemble model file, run through the real ONNX Runtime, computes the members' reference
//! forward passes scaled by 1/√M and concatenated; it round-trips member by member; a file
//! of one encoder is unchanged by the ensemble path; single-encoder readers refuse it clearly;
//! its leading block (what the live clock watch keeps) is the first member's.
use crossview_core::{Encoder, Error};
use crossview_model::{
    EncoderConfig, EncoderWeights, Ensemble, OnnxEncoder, read_ensemble, read_weights,
    to_onnx_bytes, write_ensemble_onnx, write_onnx,
};

use super::export::{max_abs_diff, metadata};

fn member(seed: u64, width: usize, blocks: usize) -> EncoderWeights {
    let cfg = EncoderConfig {
        fourier_features: 8,
        camera_dim: 8,
        width,
        blocks,
    };
    EncoderWeights::random(3, cfg, seed).unwrap()
}

fn boxes() -> (Vec<[f32; 4]>, Vec<i64>) {
    let b = (0..11)
        .map(|i| {
            let x = i as f32 * 0.08;
            [x, 0.1 + x / 3.0, x + 0.05, 0.4 + x / 2.0]
        })
        .collect();
    (b, (0..11).map(|i| i % 3).collect())
}

#[test]
fn ensemble_file_runs_the_members_scaled_and_concatenated() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("e.onnx");
    // Members of different shapes: one with an input projection, one without blocks' width
    // equal to the input (no projection), three blocks against two.
    let e = Ensemble::new(vec![member(1, 24, 2), member(2, 40, 3), member(3, 16, 1)]).unwrap();
    let mut meta = metadata(3);
    meta.extra
        .insert("crossview.ensemble".into(), "[0,1,2]".into());
    write_ensemble_onnx(&path, &e, &meta).unwrap();
    let mut onnx = OnnxEncoder::load(&path).unwrap();
    assert_eq!(onnx.dim(), 80);
    let (b, c) = boxes();
    let got = onnx.embed(&b, &c).unwrap();
    let want = e.forward(&b, &c).unwrap();
    let diff = max_abs_diff(&got, &want);
    assert!(diff < 1e-4, "max abs diff {diff}");
    // Each part is that member's embedding over √3.
    let first = e.members()[0].forward(&b, &c).unwrap();
    let part = got.slice(ndarray::s![.., 0..24]);
    assert!((part[(4, 5)] - first[(4, 5)] / 3f32.sqrt()).abs() < 1e-4);
    let (back, m2) = read_ensemble(&path).unwrap();
    assert_eq!(back, e);
    assert_eq!(m2, meta);
    // The leading block is the first member's (what the live clock watch keeps), in the
    // file as in memory.
    assert_eq!((onnx.leading_width(), e.leading_width()), (24, 24));
}

#[test]
fn one_encoder_through_the_ensemble_path_is_the_plain_file() {
    let dir = tempfile::tempdir().unwrap();
    let w = member(4, 24, 2);
    let (a, b) = (dir.path().join("a.onnx"), dir.path().join("b.onnx"));
    write_onnx(&a, &w, &metadata(3)).unwrap();
    write_ensemble_onnx(&b, &Ensemble::single(w.clone()), &metadata(3)).unwrap();
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    assert_eq!(
        std::fs::read(&a).unwrap(),
        to_onnx_bytes(&w, &metadata(3)).unwrap()
    );
    let (e, _) = read_ensemble(&a).unwrap();
    assert_eq!(e.members(), std::slice::from_ref(&w));
    // One encoder is one block: its whole width leads.
    let onnx = OnnxEncoder::load(&a).unwrap();
    assert_eq!((onnx.leading_width(), onnx.dim()), (24, 24));
}

#[test]
fn single_encoder_readers_refuse_an_ensemble_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("two.onnx");
    let e = Ensemble::new(vec![member(1, 24, 2), member(2, 24, 2)]).unwrap();
    write_ensemble_onnx(&path, &e, &metadata(3)).unwrap();
    match read_weights(&path) {
        Err(Error::Model { path, reason }) => {
            assert!(path.ends_with("two.onnx"), "{path}");
            assert!(reason.contains("ensemble of 2"), "{reason}");
        }
        other => panic!("expected a model error, got {other:?}"),
    }
}

#[test]
fn members_for_other_cameras_are_refused() {
    let other = EncoderWeights::random(2, member(1, 24, 2).config, 9).unwrap();
    assert!(Ensemble::new(vec![member(1, 24, 2), other]).is_err());
    let e = Ensemble::new(vec![member(1, 24, 2), member(2, 24, 2)]).unwrap();
    let dir = tempfile::tempdir().unwrap();
    assert!(write_ensemble_onnx(dir.path().join("x.onnx"), &e, &metadata(2)).is_err());
}

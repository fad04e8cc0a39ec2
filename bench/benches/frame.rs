//! The whole per-frame cost of association, as the offline tools and the server pay it: the
//! ONNX Runtime encoder call over every box of the frame (one intra-op thread), the 21 camera
//! pairs' matchings and the identities (`embed_frame` + `frame_identities`), with the two
//! parts measured alone beside it.
//!
//! Frames: the throughput issue's recording, `crossview simulate --preset wildtrack --people 95
//! --seed 11 --clean` (7 cameras × ~35 boxes), first 40 frames, cycled; a random encoder
//! (`crossview model init --width 64 --fourier 32 --camera-dim 32 --seed 3`, the demo
//! model's architecture and the issue's ≈ 11 MFLOP per frame) at widths 64 and 768, and
//! ensembles of 2, 4 and 6 such width-64 encoders (`crossview train --ensemble`, width 128 /
//! 256 / 384; 6 is the trainer's default), and the shapes of distilled students (one encoder
//! of width 96 or 128, or of width 64 with 6 residual blocks).
use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use crossview_core::association::{embed_frame, frame_identities};
use crossview_data::sim::{DetectorNoise, SimConfig, simulate};
use crossview_model::export::ensemble_to_onnx_bytes;
use crossview_model::{
    EncoderConfig, EncoderOptions, EncoderWeights, Ensemble, ModelMetadata, OnnxEncoder,
};

fn bench_frame(c: &mut Criterion) {
    let mut sim = SimConfig::preset("wildtrack").unwrap();
    sim.people.count = 95;
    sim.seed = 11;
    sim.frames = 40;
    sim.detector = DetectorNoise::none();
    sim.render.shrink_occluded = false;
    let rec = simulate(&sim).unwrap();
    let scene = &rec.scene;
    let boxes: usize = rec
        .frames
        .iter()
        .flat_map(|f| f.views.iter().flatten())
        .map(Vec::len)
        .sum();
    println!(
        "{} frames, {:.1} boxes per frame",
        rec.frames.len(),
        boxes as f64 / rec.frames.len() as f64
    );
    let mut g = c.benchmark_group("whole_frame_wildtrack_p95");
    // (label, width, residual blocks, members); w96, w128 and w64b6: distilled students'
    // shapes (`crossview model distil --width / --blocks`).
    for (label, width, blocks, members) in [
        ("w64", 64usize, 3usize, 1u64),
        ("w96", 96, 3, 1),
        ("w128", 128, 3, 1),
        ("w64b6", 64, 6, 1),
        ("w768", 768, 3, 1),
        ("w64x2", 64, 3, 2),
        ("w64x4", 64, 3, 4),
        ("w64x6", 64, 3, 6),
    ] {
        let config = EncoderConfig {
            width,
            blocks,
            fourier_features: 32,
            camera_dim: 32,
        };
        let ensemble = Ensemble::new(
            (0..members)
                .map(|k| EncoderWeights::random(scene.cameras.len(), config, 3 + k).unwrap())
                .collect(),
        )
        .unwrap();
        let meta = ModelMetadata::new(scene.cameras.clone());
        let bytes = ensemble_to_onnx_bytes(&ensemble, &meta).unwrap();
        let mut enc =
            OnnxEncoder::from_bytes_with("bench", &bytes, EncoderOptions { intra_threads: 1 })
                .unwrap();
        let cfg = meta.association_config();
        let embedded: Vec<_> = rec
            .frames
            .iter()
            .map(|f| embed_frame(&mut enc, scene, f).unwrap())
            .collect();
        let mut k = 0usize;
        let mut next = || {
            k = (k + 1) % rec.frames.len();
            k
        };
        g.bench_function(format!("{label}/encoder_and_association"), |b| {
            b.iter(|| {
                let f = &rec.frames[next()];
                let e = embed_frame(&mut enc, scene, f).unwrap();
                black_box(frame_identities(f, &e, &cfg))
            })
        });
        g.bench_function(format!("{label}/encoder_only"), |b| {
            b.iter(|| black_box(embed_frame(&mut enc, scene, &rec.frames[next()]).unwrap()))
        });
        g.bench_function(format!("{label}/association_only"), |b| {
            b.iter(|| {
                let i = next();
                black_box(frame_identities(&rec.frames[i], &embedded[i], &cfg))
            })
        });
    }
    g.finish();
}

criterion_group!(benches, bench_frame);
criterion_main!(benches);

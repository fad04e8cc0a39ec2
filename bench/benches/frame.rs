//! The whole per-frame cost of association, as the offline tools and the server pay it: the
//! ONNX Runtime encoder call over every box of the frame (one intra-op thread), the 21 camera
//! pairs' matchings and the identities (`embed_frame` + `frame_identities`), with the two
//! parts measured alone beside it.
//!
//! Frames: the throughput issue's recording, `crossview simulate --preset wildtrack --people 95
//! --seed 11 --clean` (7 cameras × ~35 boxes), first 40 frames, cycled; a random encoder
//! (`crossview model init --width 64 --fourier 32 --camera-dim 32 --seed 3`, the demo
//! model's architecture and the issue's ≈ 11 MFLOP per frame) at widths 64 and 768.
use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use crossview_core::association::{embed_frame, frame_identities};
use crossview_data::sim::{DetectorNoise, SimConfig, simulate};
use crossview_model::{
    EncoderConfig, EncoderOptions, EncoderWeights, ModelMetadata, OnnxEncoder, to_onnx_bytes,
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
    for width in [64usize, 768] {
        let config = EncoderConfig {
            width,
            fourier_features: 32,
            camera_dim: 32,
            ..EncoderConfig::default()
        };
        let weights = EncoderWeights::random(scene.cameras.len(), config, 3).unwrap();
        let meta = ModelMetadata::new(scene.cameras.clone());
        let bytes = to_onnx_bytes(&weights, &meta).unwrap();
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
        g.bench_function(format!("w{width}/encoder_and_association"), |b| {
            b.iter(|| {
                let f = &rec.frames[next()];
                let e = embed_frame(&mut enc, scene, f).unwrap();
                black_box(frame_identities(f, &e, &cfg))
            })
        });
        g.bench_function(format!("w{width}/encoder_only"), |b| {
            b.iter(|| black_box(embed_frame(&mut enc, scene, &rec.frames[next()]).unwrap()))
        });
        g.bench_function(format!("w{width}/association_only"), |b| {
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

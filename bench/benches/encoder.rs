//! One WILDTRACK-sized frame (7 cameras × 35 boxes = 245 boxes) through the ONNX Runtime
//! encoder with one intra-op thread, at widths 768 (reference, 3 blocks), 384 and 192
//! (with an input projection from the 768-wide x0). Reports FLOP/s as criterion throughput
//! (elements = FLOPs) and a direct GFLOP/s line per width.
use std::hint::black_box;
use std::time::Instant;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use crossview_core::CameraSpec;
use crossview_core::Encoder;
use crossview_model::{
    EncoderConfig, EncoderOptions, EncoderWeights, ModelMetadata, OnnxEncoder, to_onnx_bytes,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const CAMERAS: usize = 7;
const BOXES_PER_CAMERA: usize = 35;

/// Multiply-adds ×2 of the matrix products: Fourier (2 corners × N × 2 × F), input
/// projection (N × in × G), blocks (blocks × N × G²). Element-wise ops are ignored.
fn flops_per_call(c: &EncoderConfig, n: usize) -> u64 {
    let (n, f, g) = (n as u64, c.fourier_features as u64, c.width as u64);
    let fourier = 2 * 2 * n * 2 * f;
    let proj = if c.has_input_proj() {
        2 * n * c.input_dim() as u64 * g
    } else {
        0
    };
    fourier + proj + c.blocks as u64 * 2 * n * g * g
}

fn frame() -> (Vec<[f32; 4]>, Vec<i64>) {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut boxes = Vec::new();
    let mut cams = Vec::new();
    for c in 0..CAMERAS {
        for _ in 0..BOXES_PER_CAMERA {
            let x = rng.random_range(0.0f32..0.9);
            let y = rng.random_range(0.0f32..0.7);
            boxes.push([x, y, x + 0.05, y + 0.25]);
            cams.push(c as i64);
        }
    }
    (boxes, cams)
}

fn bench_encoder(c: &mut Criterion) {
    let (boxes, cams) = frame();
    let n = boxes.len();
    let meta = ModelMetadata::new(
        (0..CAMERAS)
            .map(|i| CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: format!("C{}", i + 1),
                width: 1920,
                height: 1080,
            })
            .collect(),
    );
    let mut group = c.benchmark_group("encoder_245_boxes_1_thread");
    group.sample_size(30);
    for width in [768usize, 384, 192] {
        let config = EncoderConfig {
            width,
            ..EncoderConfig::default()
        };
        let weights = EncoderWeights::random(CAMERAS, config, 0).unwrap();
        let bytes = to_onnx_bytes(&weights, &meta).unwrap();
        let mut enc =
            OnnxEncoder::from_bytes_with("bench", &bytes, EncoderOptions { intra_threads: 1 })
                .unwrap();
        let flops = flops_per_call(&config, n);

        // Direct measurement for the GFLOP/s line (after a warm-up).
        for _ in 0..20 {
            black_box(enc.embed(&boxes, &cams).unwrap());
        }
        let iters = 200;
        let t = Instant::now();
        for _ in 0..iters {
            black_box(enc.embed(&boxes, &cams).unwrap());
        }
        let per_call = t.elapsed().as_secs_f64() / iters as f64;
        println!(
            "width {width}: {n} boxes, {:.1} MFLOP/call, {:.3} ms/call, {:.2} GFLOP/s",
            flops as f64 / 1e6,
            per_call * 1e3,
            flops as f64 / per_call / 1e9
        );

        group.throughput(Throughput::Elements(flops));
        group.bench_with_input(BenchmarkId::new("width", width), &width, |b, _| {
            b.iter(|| black_box(enc.embed(black_box(&boxes), black_box(&cams)).unwrap()))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_encoder);
criterion_main!(benches);

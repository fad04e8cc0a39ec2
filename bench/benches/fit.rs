//! Cost of the live camera fit against the clock watch it rides on: one 7-camera scene, a
//! window of 300 frames of 15 boxes per camera, 64-dim embeddings (a leading member's width).
//! `profiles` is the clock watch's work per estimate (every pair's shift profile, ±10 steps);
//! `fit look` is what the fit adds to it (each pair's contrast over the newest 60 frames from
//! those profiles, and the cameras' scores and states).
use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use crossview_core::fit::{FitConfig, FitWatch, contrast};
use crossview_core::offsets::{CameraSeries, OffsetConfig, profiles};
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

const CAMERAS: usize = 7;
const FRAMES: i64 = 300;
const BOXES: usize = 15;
const DIM: usize = 64;

/// People walking: each frame's embeddings are the previous frame's plus a small step, seen by
/// every camera with per-view noise.
fn window() -> Vec<CameraSeries> {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut people = Array2::from_shape_fn((BOXES, DIM), |_| rng.sample::<f32, _>(StandardNormal));
    let mut series = vec![CameraSeries::new(); CAMERAS];
    for t in 0..FRAMES {
        people.mapv_inplace(|v| v + 0.1 * rng.sample::<f32, _>(StandardNormal));
        for s in &mut series {
            let seen = &people
                + &Array2::from_shape_fn((BOXES, DIM), |_| {
                    0.05 * rng.sample::<f32, _>(StandardNormal)
                });
            s.insert(t, seen);
        }
    }
    series
}

fn fit(c: &mut Criterion) {
    let series = window();
    let cfg = OffsetConfig {
        max_offset: 10,
        ..OffsetConfig::default()
    };
    c.bench_function(
        "profiles (clock watch, 21 pairs x 300 frames x 21 shifts)",
        |b| b.iter(|| black_box(profiles(black_box(&series), 1, &cfg))),
    );
    let pairs = profiles(&series, 1, &cfg);
    let fit = FitConfig::default();
    let since = FRAMES - fit.recent as i64;
    let mut watch = FitWatch::new(CAMERAS, fit);
    c.bench_function(
        "fit look (contrast of 21 pairs over 60 frames, scores)",
        |b| {
            b.iter(|| {
                let contrasts: Vec<_> = pairs
                    .iter()
                    .map(|(_, _, p)| contrast(black_box(p), since, fit.min_frames))
                    .collect();
                black_box(watch.look(&contrasts, &[false; CAMERAS]))
            })
        },
    );
}

criterion_group!(benches, fit);
criterion_main!(benches);

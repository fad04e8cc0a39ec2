//! The estimate on synthetic embeddings: every camera "embeds" each person as their true
//! ground position plus noise, so a camera's frames match the others' exactly at its true
//! lag. What the encoder adds is tested with real models in the CLI tests.
use ndarray::Array2;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::*;

/// Positions of `people` walkers over `frames` frames (static when `speed` is 0).
fn walk(people: usize, frames: usize, speed: f32, seed: u64) -> Vec<Vec<[f32; 2]>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut pos: Vec<[f32; 2]> = (0..people)
        .map(|_| [rng.random_range(0.0..10.0), rng.random_range(0.0..10.0)])
        .collect();
    let mut vel: Vec<[f32; 2]> = (0..people)
        .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
        .collect();
    (0..frames)
        .map(|_| {
            for (p, v) in pos.iter_mut().zip(vel.iter_mut()) {
                v[0] = (v[0] + rng.random_range(-0.3..0.3)).clamp(-1.0, 1.0);
                v[1] = (v[1] + rng.random_range(-0.3..0.3)).clamp(-1.0, 1.0);
                p[0] = (p[0] + speed * v[0]).rem_euclid(10.0);
                p[1] = (p[1] + speed * v[1]).rem_euclid(10.0);
            }
            pos.clone()
        })
        .collect()
}

/// One camera's series: it sees `world` with its frame ids `lag` frames late (frame id
/// `(t + lag) × step` shows time `t`), noise `sigma` on every coordinate.
fn camera(world: &[Vec<[f32; 2]>], lag: i64, step: i64, sigma: f32, seed: u64) -> CameraSeries {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut series = CameraSeries::new();
    for (t, people) in world.iter().enumerate() {
        let mut m = Array2::zeros((people.len(), 2));
        for (i, p) in people.iter().enumerate() {
            m[(i, 0)] = p[0] + sigma * rng.random_range(-1.0..1.0);
            m[(i, 1)] = p[1] + sigma * rng.random_range(-1.0..1.0);
        }
        series.insert((t as i64 + lag) * step, m);
    }
    series
}

fn estimate(cams: &[CameraSeries], step: i64, reference: Option<usize>) -> OffsetEstimate {
    let cfg = OffsetConfig {
        max_offset: 12,
        ..OffsetConfig::default()
    };
    let mut pairs = Vec::new();
    for a in 0..cams.len() {
        for b in a + 1..cams.len() {
            pairs.push((a, b, profile(&cams[a], &cams[b], step, &cfg)));
        }
    }
    let frames: Vec<usize> = cams.iter().map(CameraSeries::len).collect();
    solve(cams.len(), &pairs, &frames, step, reference, &cfg)
}

fn offsets(e: &OffsetEstimate) -> Vec<Option<i64>> {
    e.cameras.iter().map(|c| c.frames).collect()
}

#[test]
fn in_sync_cameras_report_zero() {
    let world = walk(12, 150, 0.2, 1);
    let cams: Vec<_> = (0..4).map(|c| camera(&world, 0, 1, 0.05, c)).collect();
    let e = estimate(&cams, 1, None);
    assert_eq!(offsets(&e), vec![Some(0); 4]);
    assert!(e.cameras.iter().all(|c| c.confidence > 0.5), "{e:?}");
}

#[test]
fn lagging_cameras_are_found_with_sign_and_step() {
    let world = walk(12, 150, 0.2, 2);
    let lags = [0, 3, 0, -2, 0];
    let cams: Vec<_> = lags
        .iter()
        .enumerate()
        .map(|(c, &lag)| camera(&world, lag, 5, 0.05, c as u64))
        .collect();
    let e = estimate(&cams, 5, None);
    assert_eq!(e.step, 5);
    assert_eq!(
        offsets(&e),
        lags.iter().map(|l| Some(l * 5)).collect::<Vec<_>>()
    );
    assert!(e.pairs.iter().filter(|p| p.used).count() >= 8, "{e:?}");
}

#[test]
fn an_explicit_reference_is_the_zero() {
    let world = walk(10, 120, 0.2, 3);
    let lags = [0, 4, 0];
    let cams: Vec<_> = lags
        .iter()
        .enumerate()
        .map(|(c, &lag)| camera(&world, lag, 1, 0.05, c as u64))
        .collect();
    let e = estimate(&cams, 1, Some(1));
    assert_eq!(e.reference, 1);
    assert_eq!(offsets(&e), vec![Some(-4), Some(0), Some(-4)]);
}

#[test]
fn a_camera_that_overlaps_with_none_is_unknown() {
    let world = walk(12, 150, 0.2, 4);
    let elsewhere = walk(12, 150, 0.2, 99);
    let mut cams: Vec<_> = (0..3).map(|c| camera(&world, 0, 1, 0.05, c)).collect();
    cams.push(camera(&elsewhere, 0, 1, 0.05, 3));
    let e = estimate(&cams, 1, None);
    assert_eq!(offsets(&e), vec![Some(0), Some(0), Some(0), None]);
    assert_eq!(e.cameras[3].unknown, Some(Unknown::NoConfidentPair));
    assert_eq!(e.cameras[3].confidence, 0.0);
}

#[test]
fn a_static_scene_is_unknown_everywhere() {
    let world = walk(12, 150, 0.0, 5);
    let cams: Vec<_> = (0..3).map(|c| camera(&world, 0, 1, 0.05, c)).collect();
    let e = estimate(&cams, 1, None);
    assert_eq!(offsets(&e), vec![None; 3], "{e:?}");
}

#[test]
fn too_few_frames_is_unknown() {
    let world = walk(12, 10, 0.2, 6);
    let cams: Vec<_> = (0..2).map(|c| camera(&world, 0, 1, 0.05, c)).collect();
    let e = estimate(&cams, 1, None);
    assert!(e.cameras.iter().all(|c| c.frames.is_none()), "{e:?}");
    assert_eq!(e.cameras[0].unknown, Some(Unknown::TooFewFrames));
}

#[test]
fn an_outlier_pair_is_dropped_by_the_fit() {
    let world = walk(12, 150, 0.2, 7);
    let cams: Vec<_> = (0..4).map(|c| camera(&world, 0, 1, 0.05, c)).collect();
    let cfg = OffsetConfig::default();
    let mut pairs = Vec::new();
    for a in 0..4 {
        for b in a + 1..4 {
            pairs.push((a, b, profile(&cams[a], &cams[b], 1, &cfg)));
        }
    }
    // A pair that claims camera 3 runs 6 frames ahead of camera 0 (weaker than the rest).
    pairs[2].2.refined = Some(6.0);
    pairs[2].2.z = cfg.min_z + 1.0;
    let e = solve(4, &pairs, &[150; 4], 1, None, &cfg);
    assert_eq!(offsets(&e), vec![Some(0); 4]);
    assert!(!e.pairs[2].used);
}

#[test]
fn frame_step_is_the_gcd_of_gaps() {
    assert_eq!(frame_step([0, 5, 15, 30]), 5);
    assert_eq!(frame_step([7]), 1);
    assert_eq!(frame_step([3, 3, 9]), 6);
    assert_eq!(frame_step(Vec::<i64>::new()), 1);
}

#[test]
fn wild_frame_ids_do_not_overflow() {
    let world = walk(5, 40, 0.2, 8);
    let mut a = CameraSeries::new();
    let mut b = CameraSeries::new();
    for (t, people) in world.iter().enumerate() {
        let m = Array2::from_shape_fn((people.len(), 2), |(i, k)| people[i][k]);
        a.insert(i64::MAX - 40 + t as i64, m.clone());
        b.insert(i64::MAX - 40 + t as i64, m);
    }
    let p = profile(&a, &b, 1, &OffsetConfig::default());
    assert_eq!(p.delta(), Some(0));
}

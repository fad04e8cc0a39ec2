//! The small synthetic scene every training test uses, and a small recipe.
use crossview_core::{CameraSpec, Detection, Frame, SceneSpec};
use crossview_data::Recording;
use crossview_train::trainer::TrainConfig;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const W: u32 = 640;
const H: u32 = 480;

/// A ground plane in [0,1]² seen by three cameras from different sides; people random-walk.
/// Box bottom-centre and size follow from the position (nearer = lower and bigger).
pub fn synthetic(frames: usize, people: usize, seed: u64) -> Recording {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let cams: Vec<CameraSpec> = ["left", "front", "right"]
        .iter()
        .map(|n| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: n.to_string(),
            width: W,
            height: H,
        })
        .collect();
    let mut pos: Vec<(f32, f32)> = (0..people)
        .map(|_| (rng.random::<f32>(), rng.random::<f32>()))
        .collect();
    let mut out = Vec::new();
    for f in 0..frames {
        for p in &mut pos {
            p.0 = (p.0 + rng.random_range(-0.03f32..0.03)).clamp(0.0, 1.0);
            p.1 = (p.1 + rng.random_range(-0.03f32..0.03)).clamp(0.0, 1.0);
        }
        let mut frame = Frame::new(f as u64 * 5, cams.len());
        for c in 0..cams.len() {
            let mut dets = Vec::new();
            for (id, &(x, y)) in pos.iter().enumerate() {
                let (u, d) = match c {
                    0 => (x, y),
                    1 => (y, 1.0 - x),
                    _ => (1.0 - x, 1.0 - y),
                };
                let h = 0.1 + 0.25 * d;
                let v = 0.35 + 0.6 * d;
                let w = 0.4 * h;
                let u = 0.1 + 0.8 * u;
                let mut det = Detection::new([
                    (u - w / 2.0) * W as f32,
                    (v - h) * H as f32,
                    (u + w / 2.0) * W as f32,
                    v * H as f32,
                ]);
                det.id = Some(id as u64);
                dets.push(det);
            }
            frame.views[c] = Some(dets);
        }
        out.push(frame);
    }
    Recording {
        scene: SceneSpec {
            name: "synthetic".into(),
            cameras: cams,
        },
        frames: out,
        fps: None,
    }
}

pub fn small_config(epochs: usize) -> TrainConfig {
    TrainConfig {
        fourier_features: 16,
        camera_dim: 16,
        width: 48,
        blocks: 3,
        epochs,
        triplets_per_step: 8,
        lr: 3e-3,
        max_edges: 8,
        seed: 7,
        ..TrainConfig::default()
    }
}

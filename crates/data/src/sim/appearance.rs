//! Synthetic Re-ID appearance vectors: one unit-length prototype per identity, observed with
//! per-camera and per-detection noise. `similarity` = 1 dresses everyone the same (the
//! paper's hard case, where appearance cannot tell people apart).
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

use crossview_core::{Error, Result};

/// Appearance vector settings.
#[derive(Debug, Clone, PartialEq)]
pub struct AppearanceConfig {
    /// Vector length.
    pub dim: usize,
    /// How alike people look, in `[0, 1]`: the share of every prototype that is common to
    /// all people (0 = unrelated, 1 = identical).
    pub similarity: f64,
    /// Per-detection noise: norm of the random vector added before re-normalising.
    pub noise: f64,
    /// Per-camera shift (lighting, viewpoint): norm of a fixed random vector per camera.
    pub camera_shift: f64,
}

impl Default for AppearanceConfig {
    fn default() -> Self {
        AppearanceConfig {
            dim: 64,
            similarity: 0.5,
            noise: 0.35,
            camera_shift: 0.2,
        }
    }
}

impl AppearanceConfig {
    /// Checks every field.
    pub fn validate(&self) -> Result<()> {
        if self.dim == 0 || self.dim > 4096 {
            return Err(Error::invalid(
                "appearance.dim",
                format!("must be in 1..=4096, got {}", self.dim),
            ));
        }
        if !(0.0..=1.0).contains(&self.similarity) {
            return Err(Error::invalid(
                "appearance.similarity",
                format!("must be in [0, 1], got {}", self.similarity),
            ));
        }
        for (name, v) in [
            ("appearance.noise", self.noise),
            ("appearance.camera_shift", self.camera_shift),
        ] {
            if !v.is_finite() || !(0.0..=10.0).contains(&v) {
                return Err(Error::invalid(name, format!("must be in [0, 10], got {v}")));
            }
        }
        Ok(())
    }
}

/// Generates prototypes and observations deterministically from a seed.
#[derive(Debug, Clone)]
pub(crate) struct AppearanceModel {
    cfg: AppearanceConfig,
    shared: Vec<f64>,
    camera_shifts: Vec<Vec<f64>>,
    seed: u64,
}

fn random_unit(dim: usize, rng: &mut ChaCha8Rng) -> Vec<f64> {
    let mut v: Vec<f64> = (0..dim).map(|_| StandardNormal.sample(rng)).collect();
    normalize(&mut v);
    v
}

fn normalize(v: &mut [f64]) {
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if n > 1e-12 {
        v.iter_mut().for_each(|x| *x /= n);
    }
}

impl AppearanceModel {
    /// A model for `num_cameras` cameras; `seed` fixes everything it draws.
    pub fn new(cfg: &AppearanceConfig, num_cameras: usize, seed: u64) -> Result<Self> {
        cfg.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let shared = random_unit(cfg.dim, &mut rng);
        let camera_shifts = (0..num_cameras)
            .map(|_| {
                let mut v = random_unit(cfg.dim, &mut rng);
                v.iter_mut().for_each(|x| *x *= cfg.camera_shift);
                v
            })
            .collect();
        Ok(AppearanceModel {
            cfg: cfg.clone(),
            shared,
            camera_shifts,
            seed,
        })
    }

    /// The unit prototype of identity `id` (a pure function of the seed and the id).
    pub(crate) fn prototype(&self, id: u64) -> Vec<f64> {
        let mut rng = ChaCha8Rng::seed_from_u64(self.seed ^ 0x5EED_0F1D);
        rng.set_stream(id.wrapping_add(1));
        let own = random_unit(self.cfg.dim, &mut rng);
        let (a, b) = (
            self.cfg.similarity.sqrt(),
            (1.0 - self.cfg.similarity).sqrt(),
        );
        let mut v: Vec<f64> = self
            .shared
            .iter()
            .zip(&own)
            .map(|(s, o)| a * s + b * o)
            .collect();
        normalize(&mut v);
        v
    }

    /// One observation in `camera` of a person with prototype `proto`, or of clutter when
    /// `proto` is `None` (a false positive looks like a random passer-by).
    pub fn observe(&self, proto: Option<&[f64]>, camera: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
        let dim = self.cfg.dim;
        let base = match proto {
            Some(p) => p.to_vec(),
            None => {
                let own = random_unit(dim, rng);
                let (a, b) = (
                    self.cfg.similarity.sqrt(),
                    (1.0 - self.cfg.similarity).sqrt(),
                );
                self.shared
                    .iter()
                    .zip(&own)
                    .map(|(s, o)| a * s + b * o)
                    .collect()
            }
        };
        let scale = self.cfg.noise / (dim as f64).sqrt();
        let shift = self.camera_shifts.get(camera);
        let mut v: Vec<f64> = base
            .iter()
            .enumerate()
            .map(|(k, x)| {
                let n: f64 = StandardNormal.sample(rng);
                x + n * scale + shift.map_or(0.0, |s| s[k])
            })
            .collect();
        normalize(&mut v);
        v.iter().map(|x| ((x * 1e4).round() / 1e4) as f32).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dist(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f32>()
            .sqrt()
    }

    fn gap(similarity: f64) -> f32 {
        let cfg = AppearanceConfig {
            similarity,
            ..AppearanceConfig::default()
        };
        let m = AppearanceModel::new(&cfg, 2, 9).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let (mut same, mut diff) = (0.0, 0.0);
        for id in 0..50u64 {
            let p = m.prototype(id);
            let q = m.prototype(id + 100);
            let a = m.observe(Some(&p), 0, &mut rng);
            let b = m.observe(Some(&p), 1, &mut rng);
            let c = m.observe(Some(&q), 1, &mut rng);
            same += dist(&a, &b);
            diff += dist(&a, &c);
        }
        (diff - same) / 50.0
    }

    #[test]
    fn similarity_knob_controls_separability() {
        let easy = gap(0.0);
        let hard = gap(1.0);
        assert!(easy > 0.5, "distinct people should be far apart: {easy}");
        assert!(
            hard.abs() < 0.05,
            "identical dress should be inseparable: {hard}"
        );
        let m = AppearanceModel::new(&AppearanceConfig::default(), 1, 1).unwrap();
        assert_eq!(m.prototype(3), m.prototype(3));
        assert!(
            AppearanceConfig {
                dim: 0,
                ..AppearanceConfig::default()
            }
            .validate()
            .is_err()
        );
    }
}

//! Synthetic multi-camera scene simulator with ground-truth identities.
//!
//! People walk on a ground plane ([`crowd`]), static pinhole cameras ([`camera`], laid out by
//! a [`scene`] preset or JSON file) see them as projected cylinders clipped at the image
//! border and hidden by nearer people ([`render`]); a detector model adds jitter, misses,
//! false positives and duplicates ([`detector`]); optional Re-ID vectors come from
//! [`appearance`]. Output is the SPEC §7 recording: [`simulate`] for a whole
//! [`Recording`], [`Simulator`] for streaming frame by frame.
//!
//! Determinism: everything is drawn from ChaCha8 streams of one seed; motion, detector noise
//! and appearance use separate streams, so the same seed gives the same people and
//! trajectories whatever the noise or appearance settings (clean ground truth and noisy
//! detections of one scene come from two runs with one seed).
//!
//! Ids: real people carry their identity (unique over the run); a false positive has no
//! `id`; a duplicate box carries the id of the person it duplicates. With `ids = false` every
//! `id` is left out.

pub mod appearance;
pub mod camera;
pub mod crowd;
pub mod detector;
pub mod ground;
pub mod render;
pub mod scene;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

pub use appearance::AppearanceConfig;
pub use camera::{Camera, CameraConfig, CameraMove};
pub use crowd::{PeopleConfig, Person};
pub use detector::DetectorNoise;
pub use ground::{BODY_RADIUS_M, ground_distances};
pub use render::RenderConfig;
pub use scene::SceneConfig;

use crate::Recording;
use crossview_core::{Error, Result};
use crossview_core::{Frame, SceneSpec};

/// Everything that defines a simulated recording.
#[derive(Debug, Clone, PartialEq)]
pub struct SimConfig {
    /// Area and cameras.
    pub scene: SceneConfig,
    /// Number of frames to emit.
    pub frames: u64,
    /// Seed of every random draw.
    pub seed: u64,
    /// Frames per second of the simulated cameras (the motion time step is `1 / fps`).
    pub fps: f64,
    /// Frame id of the first frame.
    pub first_frame_id: u64,
    /// Increment between consecutive frame ids (e.g. 5 to mimic WILDTRACK's annotation).
    pub frame_step: u64,
    /// Seconds of motion simulated before the first frame (so people are already walking).
    pub warmup_s: f64,
    /// Crowd size and walking behaviour.
    pub people: PeopleConfig,
    /// Projection, clipping and occlusion rules.
    pub render: RenderConfig,
    /// Detector errors; [`DetectorNoise::none`] for ground-truth boxes.
    pub detector: DetectorNoise,
    /// Re-ID vectors on every detection, or none.
    pub appearance: Option<AppearanceConfig>,
    /// Write ground-truth `id`s.
    pub ids: bool,
    /// Cameras that move during the recording (a bump, a re-aim, a zoom), in any order.
    pub moves: Vec<CameraMove>,
}

impl SimConfig {
    /// Defaults for a scene: 10 fps, 100 frames, seed 0, a moderately noisy detector, ids on,
    /// no appearance, and a crowd of about one person per 12 m² (at least 4).
    pub fn new(scene: SceneConfig) -> Self {
        let count = ((scene.area[0] * scene.area[1]) / 12.0).round().max(4.0) as usize;
        SimConfig {
            scene,
            frames: 100,
            seed: 0,
            fps: 10.0,
            first_frame_id: 0,
            frame_step: 1,
            warmup_s: 3.0,
            people: PeopleConfig {
                count,
                ..PeopleConfig::default()
            },
            render: RenderConfig::default(),
            detector: DetectorNoise::default(),
            appearance: None,
            ids: true,
            moves: Vec::new(),
        }
    }

    /// [`SimConfig::new`] on a built-in scene (`square4`, `wildtrack`, `pair`). The `wildtrack` preset
    /// gets 30 people, which gives about as many boxes per view as WILDTRACK's annotations
    /// (about 15 on average).
    pub fn preset(name: &str) -> Result<Self> {
        let mut cfg = Self::new(SceneConfig::preset(name)?);
        if name == "wildtrack" {
            cfg.people.count = 30;
        }
        Ok(cfg)
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<()> {
        self.scene.validate()?;
        crossview_core::types::check_fps(self.fps).map_err(|m| Error::invalid("fps", m))?;
        if self.frame_step == 0 {
            return Err(Error::invalid("frame_step", "must be at least 1"));
        }
        if self.frames > 0
            && self
                .frame_step
                .checked_mul(self.frames - 1)
                .and_then(|d| d.checked_add(self.first_frame_id))
                .is_none()
        {
            return Err(Error::invalid("frames", "frame ids would overflow u64"));
        }
        if !self.warmup_s.is_finite() || !(0.0..=3600.0).contains(&self.warmup_s) {
            return Err(Error::invalid(
                "warmup_s",
                format!("must be in [0, 3600], got {}", self.warmup_s),
            ));
        }
        self.people.validate()?;
        self.render.validate()?;
        self.detector.validate()?;
        if let Some(a) = &self.appearance {
            a.validate()?;
        }
        let spec = self.scene.spec();
        for m in &self.moves {
            m.validate()?;
            spec.camera_index(&m.camera)?;
        }
        Ok(())
    }
}

/// Streaming simulator: yields one complete [`Frame`] (a batch for every camera, empty ones
/// included) per call, so arbitrarily long recordings never sit in memory.
#[derive(Debug, Clone)]
pub struct Simulator {
    cfg: SimConfig,
    spec: SceneSpec,
    cameras: Vec<Camera>,
    crowd: crowd::Crowd,
    world_rng: ChaCha8Rng,
    detector_rng: ChaCha8Rng,
    appearance_rng: ChaCha8Rng,
    appearance: Option<appearance::AppearanceModel>,
    prototypes: Vec<Vec<f64>>,
    emitted: u64,
    /// Moves not yet made: (frame index, camera index, move), latest first.
    moves: Vec<(u64, usize, CameraMove)>,
}

fn stream(seed: u64, k: u64) -> ChaCha8Rng {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(k);
    rng
}

impl Simulator {
    /// Validates `cfg`, places the crowd and runs the warm-up.
    pub fn new(cfg: &SimConfig) -> Result<Self> {
        cfg.validate()?;
        let cameras = cfg.scene.build_cameras()?;
        let mut world_rng = stream(cfg.seed, 0);
        let mut crowd = crowd::Crowd::new(&cfg.people, cfg.scene.area, &mut world_rng)?;
        let dt = 1.0 / cfg.fps;
        let warm_steps = (cfg.warmup_s / dt).round() as u64;
        for _ in 0..warm_steps {
            crowd.step(dt, &mut world_rng);
        }
        let appearance = match &cfg.appearance {
            Some(a) => Some(appearance::AppearanceModel::new(
                a,
                cameras.len(),
                cfg.seed ^ 0xA99E_A7A7_CE00_0001,
            )?),
            None => None,
        };
        tracing::debug!(
            scene = %cfg.scene.name,
            cameras = cameras.len(),
            people = crowd.people().len(),
            "simulator ready"
        );
        let spec = cfg.scene.spec();
        let mut moves: Vec<(u64, usize, CameraMove)> = cfg
            .moves
            .iter()
            .map(|m| {
                let at = (m.at_s * cfg.fps).round() as u64;
                Ok((at, spec.camera_index(&m.camera)?, m.clone()))
            })
            .collect::<Result<_>>()?;
        moves.sort_by_key(|m| std::cmp::Reverse(m.0));
        Ok(Simulator {
            spec,
            cfg: cfg.clone(),
            cameras,
            crowd,
            world_rng,
            detector_rng: stream(cfg.seed, 1),
            appearance_rng: stream(cfg.seed, 2),
            appearance,
            prototypes: Vec::new(),
            emitted: 0,
            moves,
        })
    }

    /// The recording's scene header.
    pub fn scene(&self) -> &SceneSpec {
        &self.spec
    }

    /// The calibrated cameras, in camera-index order (the ground truth geometry).
    pub fn cameras(&self) -> &[Camera] {
        &self.cameras
    }

    /// The people as they will appear in the next frame (ground-truth positions).
    pub fn people(&self) -> &[Person] {
        self.crowd.people()
    }

    /// The configuration this simulator runs.
    pub fn config(&self) -> &SimConfig {
        &self.cfg
    }

    /// Frames still to come.
    pub fn remaining(&self) -> u64 {
        self.cfg.frames - self.emitted
    }

    fn prototype(&mut self, id: u64) -> &[f64] {
        let model = self.appearance.as_ref().expect("appearance enabled");
        let idx = id as usize;
        while self.prototypes.len() <= idx {
            let next = self.prototypes.len() as u64;
            self.prototypes.push(model.prototype(next));
        }
        &self.prototypes[idx]
    }

    /// Renders the current state into a frame and advances time; `None` after the last frame.
    pub fn next_frame(&mut self) -> Option<Frame> {
        if self.emitted >= self.cfg.frames {
            return None;
        }
        while self.moves.last().is_some_and(|m| m.0 <= self.emitted) {
            let (_, c, m) = self.moves.pop().expect("checked");
            // Validated with the configuration; a failure leaves the camera where it was.
            match self.cameras[c].moved(&m) {
                Ok(moved) => self.cameras[c] = moved,
                Err(e) => tracing::warn!(camera = %m.camera, error = %e, "move not made"),
            }
        }
        let frame_id = self.cfg.first_frame_id + self.emitted * self.cfg.frame_step;
        let mut frame = Frame::new(frame_id, self.cameras.len());
        for c in 0..self.cameras.len() {
            let cam = &self.cameras[c];
            let truth = render::render_camera(cam, self.crowd.people(), &self.cfg.render);
            let boxes = detector::detect(
                &truth,
                cam.spec.width,
                cam.spec.height,
                &self.cfg.detector,
                &mut self.detector_rng,
            );
            let mut dets = Vec::with_capacity(boxes.len());
            for b in &boxes {
                let mut det = detector::to_detection(b);
                let id = b.truth.map(|i| truth[i].id);
                if self.cfg.ids {
                    det.id = id;
                }
                if self.appearance.is_some() {
                    let proto = id.map(|id| self.prototype(id).to_vec());
                    let model = self.appearance.as_ref().expect("appearance enabled");
                    det.appearance =
                        Some(model.observe(proto.as_deref(), c, &mut self.appearance_rng));
                }
                dets.push(det);
            }
            frame.views[c] = Some(dets);
        }
        self.crowd.step(1.0 / self.cfg.fps, &mut self.world_rng);
        self.emitted += 1;
        Some(frame)
    }
}

impl Iterator for Simulator {
    type Item = Frame;

    fn next(&mut self) -> Option<Frame> {
        self.next_frame()
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let n = usize::try_from(self.remaining()).unwrap_or(usize::MAX);
        (n, usize::try_from(self.remaining()).ok())
    }
}

/// Simulates the whole recording in memory (use [`Simulator`] to stream long ones).
pub fn simulate(cfg: &SimConfig) -> Result<Recording> {
    let sim = Simulator::new(cfg)?;
    let scene = sim.scene().clone();
    let frames = sim.collect();
    Ok(Recording {
        scene,
        frames,
        fps: Some(cfg.fps),
    })
}

//! `crossview simulate`: write a synthetic multi-camera recording (SPEC §7 JSONL).
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crossview_data::recording::RecordingWriter;
use crossview_data::sim::{
    AppearanceConfig, CameraMove, DetectorNoise, SceneConfig, SimConfig, Simulator,
};

/// Options of `crossview simulate`.
#[derive(Debug, Args)]
pub struct SimulateArgs {
    /// Built-in scene layout: square4 (4 cameras, 12x12 m), wildtrack (7 cameras, 12x36 m,
    /// 1920x1080) or pair (2 cameras, 8x8 m).
    #[arg(
        long,
        env = "CROSSVIEW_SIM_PRESET",
        default_value = "square4",
        conflicts_with = "scene"
    )]
    pub preset: String,
    /// JSON scene file (area and cameras) instead of a preset.
    #[arg(long, env = "CROSSVIEW_SIM_SCENE")]
    pub scene: Option<PathBuf>,
    /// Number of frames.
    #[arg(long, default_value_t = 100)]
    pub frames: u64,
    /// Random seed: the same seed and options give byte-identical output.
    #[arg(long, env = "CROSSVIEW_SIM_SEED", default_value_t = 0)]
    pub seed: u64,
    /// Output file ("-" for standard output).
    #[arg(long)]
    pub out: PathBuf,
    /// Leave out the ground-truth ids.
    #[arg(long)]
    pub no_ids: bool,
    /// Target number of people (default: 30 for wildtrack, otherwise about one per 12 m² of
    /// the area).
    #[arg(long, conflicts_with = "density")]
    pub people: Option<usize>,
    /// Target crowd density in people per m² of the area (instead of --people).
    #[arg(long)]
    pub density: Option<f64>,
    /// Probability that a person reaching a goal joins the nearest person within 6 m and walks
    /// beside them for 5–20 s before leaving on their own (groups that form and split; 0 =
    /// everyone walks alone).
    #[arg(long, default_value_t = 0.0)]
    pub groups: f64,
    /// Frames per second, declared in the recording's header (`crossview train` reads it
    /// there).
    #[arg(long, default_value_t = 10.0)]
    pub fps: f64,
    /// Id of the first frame.
    #[arg(long, default_value_t = 0)]
    pub first_frame_id: u64,
    /// Increment between frame ids.
    #[arg(long, default_value_t = 1)]
    pub frame_step: u64,
    /// Annotation-style ground truth: a perfect detector and full (not shrunk) boxes for
    /// partly occluded people, as WILDTRACK's annotations (overrides the rate options).
    #[arg(long)]
    pub clean: bool,
    /// Box edge jitter as a fraction of the box size.
    #[arg(long)]
    pub jitter: Option<f64>,
    /// Probability of missing a visible person.
    #[arg(long)]
    pub miss_rate: Option<f64>,
    /// Mean false positives per camera image.
    #[arg(long)]
    pub false_positives: Option<f64>,
    /// Probability of a duplicate box on a detected person.
    #[arg(long)]
    pub duplicate_rate: Option<f64>,
    /// Attach appearance vectors of this length.
    #[arg(long)]
    pub appearance_dim: Option<usize>,
    /// How alike people look, 0 (distinct) to 1 (everyone dressed the same).
    #[arg(long, default_value_t = 0.5)]
    pub appearance_similarity: f64,
    /// Per-detection appearance noise.
    #[arg(long, default_value_t = 0.35)]
    pub appearance_noise: f64,
    /// Also write the scene layout (area and cameras) as a JSON scene file, e.g. to start a
    /// custom layout from a preset.
    #[arg(long)]
    pub write_scene: Option<PathBuf>,
    /// Move a camera mid-recording, as a bump, a re-aim or a zoom would
    /// (`CAMERA@SECONDS:pan=P,tilt=T,zoom=Z`; pan and tilt in degrees, or with `%` in percent
    /// of the image width / height that the image centre moves; repeatable), e.g.
    /// `C2@60:pan=5%` or `C2@60:zoom=1.2`.
    #[arg(long = "move", value_name = "CAMERA@SECONDS:CHANGES")]
    pub moves: Vec<String>,
}

impl SimulateArgs {
    /// The simulator configuration these options describe.
    pub fn config(&self) -> anyhow::Result<SimConfig> {
        let mut cfg = match &self.scene {
            Some(path) => SimConfig::new(SceneConfig::from_json_file(path)?),
            None => SimConfig::preset(&self.preset)?,
        };
        cfg.frames = self.frames;
        cfg.seed = self.seed;
        cfg.fps = self.fps;
        cfg.first_frame_id = self.first_frame_id;
        cfg.frame_step = self.frame_step;
        cfg.ids = !self.no_ids;
        if let Some(n) = self.people {
            cfg.people.count = n;
        }
        if let Some(d) = self.density {
            if !d.is_finite() || !(0.0..=4.0).contains(&d) {
                anyhow::bail!("--density must be within [0, 4] people per m², got {d}");
            }
            cfg.people.count = (d * cfg.scene.area[0] * cfg.scene.area[1]).round() as usize;
        }
        cfg.people.group_prob = self.groups;
        if self.clean {
            cfg.detector = DetectorNoise::none();
            cfg.render.shrink_occluded = false;
        } else {
            let d = &mut cfg.detector;
            d.jitter = self.jitter.unwrap_or(d.jitter);
            d.miss_rate = self.miss_rate.unwrap_or(d.miss_rate);
            d.false_positives = self.false_positives.unwrap_or(d.false_positives);
            d.duplicate_rate = self.duplicate_rate.unwrap_or(d.duplicate_rate);
        }
        if let Some(dim) = self.appearance_dim {
            cfg.appearance = Some(AppearanceConfig {
                dim,
                similarity: self.appearance_similarity,
                noise: self.appearance_noise,
                ..AppearanceConfig::default()
            });
        }
        cfg.moves = self
            .moves
            .iter()
            .map(|m| parse_move(&cfg.scene, m))
            .collect::<anyhow::Result<_>>()?;
        cfg.validate()?;
        Ok(cfg)
    }
}

/// `CAMERA@SECONDS:pan=P,tilt=T,zoom=Z` → a [`CameraMove`] of a camera of `scene`.
pub(crate) fn parse_move(scene: &SceneConfig, spec: &str) -> anyhow::Result<CameraMove> {
    let bad = || anyhow::anyhow!("--move wants CAMERA@SECONDS:pan=P,tilt=T,zoom=Z, got '{spec}'");
    let (camera, rest) = spec.split_once('@').ok_or_else(bad)?;
    let (at, changes) = rest.split_once(':').ok_or_else(bad)?;
    let config = scene
        .cameras
        .iter()
        .find(|c| c.name == camera)
        .with_context(|| format!("--move: no camera '{camera}' in the scene"))?;
    let mut m = CameraMove {
        camera: camera.to_string(),
        at_s: at
            .parse()
            .with_context(|| format!("--move: '{at}' is not a number of seconds"))?,
        pan_deg: 0.0,
        tilt_deg: 0.0,
        zoom: 1.0,
    };
    for change in changes.split(',') {
        let (key, value) = change.split_once('=').ok_or_else(bad)?;
        let (number, percent) = match value.strip_suffix('%') {
            Some(v) => (v, true),
            None => (value, false),
        };
        let v: f64 = number
            .parse()
            .with_context(|| format!("--move: '{value}' is not a number"))?;
        match (key, percent) {
            ("pan", false) => m.pan_deg = v,
            ("pan", true) => {
                m.pan_deg = CameraMove::pan_for(v / 100.0, config.width, config.focal_px)
            }
            ("tilt", false) => m.tilt_deg = v,
            ("tilt", true) => {
                m.tilt_deg = CameraMove::pan_for(v / 100.0, config.height, config.focal_px)
            }
            ("zoom", false) => m.zoom = v,
            _ => return Err(bad()),
        }
    }
    m.validate()?;
    Ok(m)
}

/// Runs `crossview simulate`.
pub fn run(args: SimulateArgs) -> anyhow::Result<()> {
    let cfg = args.config()?;
    if let Some(path) = &args.write_scene {
        let text = serde_json::to_string_pretty(&cfg.scene)?;
        std::fs::write(path, text + "\n")
            .with_context(|| format!("cannot write scene file {}", path.display()))?;
    }
    let mut sim = Simulator::new(&cfg)?;
    let start = std::time::Instant::now();
    let mut writer = RecordingWriter::create(&args.out, sim.scene(), Some(cfg.fps))?;
    let mut boxes = 0usize;
    while let Some(frame) = sim.next_frame() {
        boxes += frame.num_boxes();
        writer.write_frame(&frame)?;
    }
    writer.finish()?;
    tracing::info!(
        out = %args.out.display(),
        frames = cfg.frames,
        cameras = sim.scene().cameras.len(),
        boxes,
        seconds = start.elapsed().as_secs_f64(),
        "simulated recording written"
    );
    Ok(())
}

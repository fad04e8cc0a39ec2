//! `crossview demo`: the newcomer's tour. Starts the real server in-process on a loopback port
//! with the built-in model (or talks to a running one with `--server`), streams a simulated
//! multi-camera scene into it over gRPC and prints each frame's identities with the running
//! SPEC §5 accuracy against the simulator's ground truth, then shuts the server down.
use std::io::Write;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use crate::demo::{DemoConfig, DemoSummary, FrameReport, start_local_server, stream_scene};
use crossview_data::sim::{DetectorNoise, SimConfig};
use crossview_serve::{ModelSpec, ServeConfig};

/// Stream a simulated scene through the server and watch the association live.
#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Model to serve in-process (`[NAME=]path.onnx`; the scene name defaults to the file stem).
    #[arg(
        long,
        env = "CROSSVIEW_DEMO_MODEL",
        default_value = "models/demo.onnx",
        conflicts_with = "server"
    )]
    pub model: String,
    /// Use an already running server (e.g. `http://127.0.0.1:8080`) instead of starting one;
    /// needs `--scene`.
    #[arg(long, env = "CROSSVIEW_DEMO_SERVER", requires = "scene")]
    pub server: Option<String>,
    /// Scene name on the server (default: the served model's scene).
    #[arg(long, env = "CROSSVIEW_DEMO_SCENE")]
    pub scene: Option<String>,
    /// Simulator preset; it must be the scene the model was trained on.
    #[arg(long, env = "CROSSVIEW_DEMO_PRESET", default_value = "square4")]
    pub preset: String,
    /// Frames to stream before stopping (Ctrl-C stops earlier).
    #[arg(long, env = "CROSSVIEW_DEMO_FRAMES", default_value_t = 150)]
    pub frames: u64,
    /// Simulator seed (models/demo.onnx was trained on seed 1, validated on seed 2, tested on seed 3).
    #[arg(long, env = "CROSSVIEW_DEMO_SEED", default_value_t = 7)]
    pub seed: u64,
    /// Frames per second to send (0 = as fast as the server answers).
    #[arg(long, env = "CROSSVIEW_DEMO_FPS", default_value_t = 10.0)]
    pub fps: f64,
    /// Send noisy detector boxes (jitter, misses, false positives, duplicates) instead of the
    /// default annotation-style ground-truth boxes (SPEC §6 evaluates on ground-truth boxes).
    /// A false positive is scored as a person of its own.
    #[arg(long, env = "CROSSVIEW_DEMO_NOISY")]
    pub noisy: bool,
    /// Loopback address of the in-process server (port 0 = any free port).
    #[arg(long, env = "CROSSVIEW_DEMO_LISTEN", default_value = "127.0.0.1:0")]
    pub listen: String,
}

fn pct(x: f64) -> String {
    format!("{:5.1}%", 100.0 * x)
}

/// One line per frame.
fn frame_line(r: &FrameReport) -> String {
    format!(
        "frame {:>5} | boxes {:>3} | identities {:>3} ({:>2} multi-view, {:>3} links){} | frame ACC {} | running P {} R {} ACC {} IPAA-100 {} | {:>6.1} ms",
        r.frame_id,
        r.boxes,
        r.identities,
        r.multi_view,
        r.links,
        if r.complete { "" } else { " partial" },
        pct(r.frame.acc),
        pct(r.running.precision),
        pct(r.running.recall),
        pct(r.running.acc),
        pct(r.running.ipaa_100),
        r.latency_ms,
    )
}

fn summary_text(s: &DemoSummary) -> String {
    let m = &s.metrics;
    format!(
        "{} after {} frames ({} image pairs): P {}  R {}  ACC {}  IPAA-100 {}  IPAA-90 {}  IPAA-80 {}",
        if s.interrupted { "stopped" } else { "done" },
        s.frames,
        m.pairs,
        pct(m.precision),
        pct(m.recall),
        pct(m.acc),
        pct(m.ipaa_100),
        pct(m.ipaa_90),
        pct(m.ipaa_80),
    )
}

/// Runs `crossview demo`.
pub fn run(args: DemoArgs) -> anyhow::Result<()> {
    if !(args.fps.is_finite() && args.fps >= 0.0) {
        anyhow::bail!("--fps must be a finite number >= 0, got {}", args.fps);
    }
    if args.frames == 0 {
        anyhow::bail!("--frames must be at least 1");
    }
    let mut sim = SimConfig::preset(&args.preset)?;
    sim.frames = args.frames;
    sim.seed = args.seed;
    if !args.noisy {
        sim.detector = DetectorNoise::none();
        sim.render.shrink_occluded = false;
    }
    let pace = (args.fps > 0.0).then(|| Duration::from_secs_f64(1.0 / args.fps));
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async move {
        let stop = async {
            let _ = tokio::signal::ctrl_c().await;
        };
        match &args.server {
            Some(url) => {
                let cfg = DemoConfig {
                    sim,
                    scene: args.scene.clone().unwrap_or_default(),
                    pace,
                };
                println!("crossview demo: streaming {} frames of '{}' to {url}, scene '{}'", args.frames, args.preset, cfg.scene);
                let summary = stream_scene(url, &cfg, stop, print_frame).await?;
                println!("{}", summary_text(&summary));
                Ok(())
            }
            None => {
                let spec = ModelSpec::parse(&args.model)?;
                if !spec.path.is_file() {
                    anyhow::bail!(
                        "model file {} not found (run from the repository root, or pass --model)",
                        spec.path.display()
                    );
                }
                let scene = args.scene.clone().unwrap_or_else(|| spec.name.clone());
                let config = ServeConfig {
                    models: vec![spec],
                    ..ServeConfig::default()
                };
                let server = start_local_server(config, &args.listen).await?;
                let endpoint = server.endpoint();
                println!(
                    "crossview demo: server on {endpoint} (gRPC + HTTP), model {}; streaming {} frames of simulated '{}' (seed {}, {} boxes) over gRPC; ground-truth ids stay here",
                    args.model, args.frames, args.preset, args.seed, if args.noisy { "noisy detector" } else { "ground-truth" }
                );
                println!("crossview demo: watch it in a browser at {endpoint}/ (the live viewer; --listen 127.0.0.1:8080 for a fixed port)");
                let cfg = DemoConfig { sim, scene, pace };
                let outcome = stream_scene(&endpoint, &cfg, stop, print_frame).await;
                // Shut the server down whatever happened to the stream.
                let down = server.shutdown().await;
                let summary = outcome?;
                down.context("server shutdown")?;
                println!("{}", summary_text(&summary));
                println!("server shut down cleanly");
                Ok(())
            }
        }
    })
}

fn print_frame(r: &FrameReport) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{}", frame_line(r));
    let _ = out.flush();
}

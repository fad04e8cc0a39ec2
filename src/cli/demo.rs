//! `crossview demo`: the newcomer's tour. Starts the real server in-process on a loopback port
//! with the built-in model (or talks to a running one with `--server`), streams a simulated
//! multi-camera scene into it over gRPC and prints each frame's identities with the running
//! SPEC §5 accuracy against the simulator's ground truth. Midway one camera is bumped (a real
//! change of its simulated pose): the server notices that it no longer fits the model and fences
//! it, and the running accuracy of the other cameras holds. The in-process server then keeps
//! serving the viewer until Ctrl-C (`--exit`: shut down at once).
use std::io::Write;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use super::simulate::parse_move;
use crate::demo::{DemoConfig, DemoSummary, FrameReport, start_local_server, stream_scene};
use crossview_data::sim::{DetectorNoise, SimConfig};
use crossview_serve::{ModelSpec, ServeConfig};

/// The in-process server's clock watch looks this often (the server's default is 10 s): the
/// demo's bumped camera is named and fenced within seconds.
const DEMO_WATCH_INTERVAL: Duration = Duration::from_secs(2);

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
    #[arg(long, env = "CROSSVIEW_DEMO_FRAMES", default_value_t = 600)]
    pub frames: u64,
    /// Move a camera mid-stream, as `crossview simulate --move` does
    /// (`CAMERA@SECONDS:pan=P,tilt=T,zoom=Z`; repeatable) [default: the second camera panned
    /// by 5 % of the width halfway through, when the scene has at least three cameras].
    #[arg(
        long = "move",
        value_name = "CAMERA@SECONDS:CHANGES",
        conflicts_with = "no_move"
    )]
    pub moves: Vec<String>,
    /// No camera moves.
    #[arg(long, env = "CROSSVIEW_DEMO_NO_MOVE")]
    pub no_move: bool,
    /// Shut the in-process server down once the stream is done, instead of serving the viewer
    /// until Ctrl-C.
    #[arg(long, env = "CROSSVIEW_DEMO_EXIT")]
    pub exit: bool,
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
        "frame {:>5} | boxes {:>3} | identities {:>3} ({:>2} multi-view, {:>3} links){}{} | frame ACC {} | running P {} R {} ACC {} IPAA-100 {} | {:>6.1} ms",
        r.frame_id,
        r.boxes,
        r.identities,
        r.multi_view,
        r.links,
        if r.complete { "" } else { " partial" },
        if r.fenced.is_empty() {
            String::new()
        } else {
            format!(
                " | fenced: {} (moved; scored without it)",
                r.fenced.join(", ")
            )
        },
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
    sim.moves = if args.no_move {
        Vec::new()
    } else if args.moves.is_empty() {
        default_move(&sim).into_iter().collect()
    } else {
        args.moves
            .iter()
            .map(|m| parse_move(&sim.scene, m))
            .collect::<anyhow::Result<_>>()?
    };
    for m in &sim.moves {
        println!(
            "crossview demo: camera '{}' will be bumped {:.0} s in (pan {:.1}°, tilt {:.1}°, zoom {:.2}×); \
             the server should notice it no longer fits the model and fence it (--no-move: none)",
            m.camera, m.at_s, m.pan_deg, m.tilt_deg, m.zoom
        );
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
                if !cfg.sim.moves.is_empty() {
                    println!("crossview demo: the fence shows once the server's clock watch has looked (every --clock-watch-interval)");
                }
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
                let mut config = ServeConfig {
                    models: vec![spec],
                    ..ServeConfig::default()
                };
                config.limits.clock_watch.interval = DEMO_WATCH_INTERVAL;
                let server = start_local_server(config, &args.listen).await?;
                let endpoint = server.endpoint();
                println!(
                    "crossview demo: server on {endpoint} (gRPC + HTTP), model {}; streaming {} frames of simulated '{}' (seed {}, {} boxes) over gRPC; ground-truth ids stay here",
                    args.model, args.frames, args.preset, args.seed, if args.noisy { "noisy detector" } else { "ground-truth" }
                );
                println!("crossview demo: watch it in a browser at {endpoint}/ (the live viewer; --listen 127.0.0.1:8080 for a fixed port)");
                let cfg = DemoConfig { sim, scene, pace };
                let outcome = stream_scene(&endpoint, &cfg, stop, print_frame).await;
                if let Ok(summary) = &outcome {
                    println!("{}", summary_text(summary));
                    if !args.exit && !summary.interrupted {
                        println!(
                            "crossview demo: the server keeps serving the viewer at {endpoint}/ \
                             until Ctrl-C (--exit: stop now)"
                        );
                        let _ = tokio::signal::ctrl_c().await;
                    }
                }
                // Shut the server down whatever happened to the stream.
                let down = server.shutdown().await;
                outcome?;
                down.context("server shutdown")?;
                println!("server shut down cleanly");
                Ok(())
            }
        }
    })
}

/// The demo's bump: the second camera panned by 5 % of the width halfway through the stream,
/// when the scene has at least three cameras (the fit needs a majority that still fits).
fn default_move(sim: &SimConfig) -> Option<crossview_data::sim::CameraMove> {
    let camera = sim
        .scene
        .cameras
        .get(1)
        .filter(|_| sim.scene.cameras.len() >= 3)?;
    // Simulated seconds: frame index / the simulator's rate.
    let at_s = sim.frames as f64 / sim.fps / 2.0;
    Some(crossview_data::sim::CameraMove::pan(camera, at_s, 0.05))
}

fn print_frame(r: &FrameReport) {
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{}", frame_line(r));
    let _ = out.flush();
}

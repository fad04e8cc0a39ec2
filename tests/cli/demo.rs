//! `crossview demo` end to end: the real server (in-process, 127.0.0.1:0), real ONNX Runtime,
//! real gRPC. The binary prints identities and a running accuracy and shuts the server down;
//! the running accuracy the client computes from the served identities equals what
//! `crossview eval --mode global` computes on the same simulated frames; the shipped
//! `models/demo.onnx` serves the default preset.
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crossview::demo::{DemoConfig, start_local_server, stream_scene};
use crossview_core::association::{AssociationConfig, Mode};
use crossview_core::memory::MemoryConfig;
use crossview_data::sim::{DetectorNoise, SimConfig, simulate};
use crossview_eval::driver::evaluate_settings_with;
use crossview_model::export::write_onnx;
use crossview_model::{EncoderConfig, EncoderWeights, ModelMetadata, OnnxEncoder};
use crossview_serve::{ModelSpec, ServeConfig};

const THRESHOLD: f32 = 0.3;

/// Hang guard (not a timing assertion).
const GUARD: Duration = Duration::from_secs(120);

/// A small random encoder for the `square4` preset's cameras at `dir/square4.onnx`.
fn square4_model(dir: &Path) -> PathBuf {
    let spec = SimConfig::preset("square4").unwrap().scene.spec();
    let config = EncoderConfig {
        fourier_features: 8,
        camera_dim: 16,
        width: 32,
        blocks: 2,
    };
    let weights = EncoderWeights::random(spec.cameras.len(), config, 5).unwrap();
    let mut meta = ModelMetadata::new(spec.cameras);
    meta.threshold = THRESHOLD;
    let path = dir.join("square4.onnx");
    write_onnx(&path, &weights, &meta).unwrap();
    path
}

fn clean_sim(frames: u64, seed: u64) -> SimConfig {
    let mut sim = SimConfig::preset("square4").unwrap();
    sim.frames = frames;
    sim.seed = seed;
    sim.detector = DetectorNoise::none();
    sim.render.shrink_occluded = false;
    sim
}

#[test]
fn the_demo_command_streams_frames_and_shows_identities_and_running_accuracy() {
    let dir = tempfile::tempdir().unwrap();
    let model = square4_model(dir.path());
    let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["demo", "--frames", "4", "--fps", "0", "--exit", "--model"])
        .arg(&model)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "stdout:\n{stdout}\nstderr:\n{stderr}");
    let frames: Vec<&str> = stdout.lines().filter(|l| l.starts_with("frame ")).collect();
    assert_eq!(frames.len(), 4, "{stdout}");
    for line in &frames {
        assert!(line.contains("identities"), "{line}");
        assert!(line.contains("running P") && line.contains("ACC"), "{line}");
    }
    assert!(stdout.contains("done after 4 frames"), "{stdout}");
    // Halfway the second camera is bumped (the server's fit would fence it; too few frames
    // here for a look: tests/serve/camera_fit.rs shows the fence).
    assert!(stdout.contains("camera 'cam1' will be bumped"), "{stdout}");
    assert!(stdout.contains("server shut down cleanly"), "{stdout}");
}

#[test]
fn the_demo_command_refuses_a_model_of_another_scene() {
    let dir = tempfile::tempdir().unwrap();
    let model = square4_model(dir.path());
    let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["demo", "--preset", "pair", "--frames", "2", "--fps", "0"])
        .args(["--model".as_ref(), model.as_os_str()])
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("cameras"), "{stderr}");
    let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["demo", "--move", "nobody@1:pan=2", "--exit"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no camera 'nobody'"));
    let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["demo", "--model", "/nonexistent/model.onnx"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("not found"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn running_accuracy_over_the_network_equals_eval_global_mode() {
    let dir = tempfile::tempdir().unwrap();
    let model = square4_model(dir.path());
    let sim = clean_sim(6, 3);
    let server = start_local_server(
        ServeConfig {
            models: vec![ModelSpec::parse(&format!("lab={}", model.display())).unwrap()],
            ..ServeConfig::default()
        },
        "127.0.0.1:0",
    )
    .await
    .unwrap();
    let cfg = DemoConfig {
        sim: sim.clone(),
        scene: "lab".into(),
        pace: None,
    };
    let mut seen = Vec::new();
    let summary = tokio::time::timeout(
        GUARD,
        stream_scene(&server.endpoint(), &cfg, std::future::pending(), |r| {
            seen.push((r.frame_id, r.identities, r.running.pairs));
        }),
    )
    .await
    .expect("hang guard")
    .unwrap();
    server.shutdown().await.unwrap();
    assert_eq!(summary.frames, 6);
    assert!(!summary.interrupted);
    assert_eq!(
        seen.iter().map(|s| s.0).collect::<Vec<_>>(),
        (0..6).collect::<Vec<u64>>()
    );
    assert!(seen.iter().all(|s| s.1 > 0));
    assert!(
        seen.windows(2).all(|w| w[0].2 < w[1].2),
        "running pairs grow"
    );

    // The same frames through the evaluation driver, scoring the identities with the
    // model's own settings and the server's default memory (what the server uses).
    let recording = simulate(&sim).unwrap();
    let mut encoder = OnnxEncoder::load(&model).unwrap();
    let cfg = AssociationConfig {
        mode: Mode::Identities,
        ..encoder.metadata().association_config()
    };
    assert_eq!(cfg.threshold, THRESHOLD);
    let setting = [(Mode::Identities, cfg.identity.link_threshold)];
    let memory = MemoryConfig::default();
    let runs = evaluate_settings_with(
        &mut [&mut encoder],
        &recording,
        &cfg,
        &setting,
        Some(&memory),
    )
    .unwrap();
    let expected = runs[0].metrics;
    let got = summary.metrics;
    assert_eq!(
        (
            got.pairs,
            got.kept,
            got.correct,
            got.common,
            got.union,
            got.true_negatives
        ),
        (
            expected.pairs,
            expected.kept,
            expected.correct,
            expected.common,
            expected.union,
            expected.true_negatives
        )
    );
    assert_eq!(got.acc, expected.acc);
    assert_eq!(got.ipaa_100, expected.ipaa_100);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_shipped_demo_model_serves_the_default_preset_accurately() {
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/demo.onnx");
    let server = start_local_server(
        ServeConfig {
            models: vec![ModelSpec::parse(model.to_str().unwrap()).unwrap()],
            ..ServeConfig::default()
        },
        "127.0.0.1:0",
    )
    .await
    .unwrap();
    let cfg = DemoConfig {
        sim: clean_sim(10, 7),
        scene: "demo".into(),
        pace: None,
    };
    let summary = tokio::time::timeout(
        GUARD,
        stream_scene(&server.endpoint(), &cfg, std::future::pending(), |_| {}),
    )
    .await
    .expect("hang guard")
    .unwrap();
    server.shutdown().await.unwrap();
    // A trained model, far above chance (an untrained encoder scores well below this).
    assert!(summary.metrics.acc > 0.8, "ACC {:.3}", summary.metrics.acc);
}

//! `crossview associate` and `crossview eval` deal the frames to `--workers` threads (one ONNX
//! Runtime session each) and collect them in frame order: through the real ONNX Runtime on a
//! simulated WILDTRACK-shaped recording, 1 worker and 3 workers (and `CROSSVIEW_WORKERS`) give
//! byte-identical associations, tables, reports and pair dumps, and the library driver gives
//! identical runs.
use std::path::Path;
use std::process::Command;

use crossview_core::Encoder;
use crossview_core::association::{AssociationConfig, Mode};
use crossview_data::Recording;
use crossview_data::recording::write_recording;
use crossview_data::sim::{DetectorNoise, SimConfig, simulate};
use crossview_eval::{evaluate_settings, evaluate_settings_on};
use crossview_model::{EncoderConfig, EncoderWeights, ModelMetadata, OnnxEncoder, write_onnx};

/// A 7-camera, 30-person simulated recording of `frames` frames; `noisy` adds the default
/// detector noise (misses, false positives without ids, duplicates).
fn recording(frames: u64, noisy: bool) -> Recording {
    let mut cfg = SimConfig::preset("wildtrack").unwrap();
    cfg.frames = frames;
    cfg.seed = 5;
    cfg.people.count = 30;
    if !noisy {
        cfg.detector = DetectorNoise::none();
    }
    simulate(&cfg).unwrap()
}

/// A random width-64 encoder for `rec`'s cameras (the demo model's architecture).
fn write_model(path: &Path, rec: &Recording) {
    let config = EncoderConfig {
        fourier_features: 32,
        camera_dim: 32,
        width: 64,
        blocks: 3,
    };
    let weights = EncoderWeights::random(rec.scene.cameras.len(), config, 3).unwrap();
    write_onnx(
        path,
        &weights,
        &ModelMetadata::new(rec.scene.cameras.clone()),
    )
    .unwrap();
}

/// Runs the binary with `args` (and `env`); its stdout.
fn crossview(args: &[&str], env: &[(&str, &str)]) -> String {
    crossview_testing::run_crossview(env!("CARGO_BIN_EXE_crossview"), args, env)
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

#[test]
fn associate_output_is_identical_for_any_number_of_workers() {
    let dir = tempfile::tempdir().unwrap();
    let (model, data) = (dir.path().join("m.onnx"), dir.path().join("rec.jsonl"));
    let rec = recording(61, true);
    write_model(&model, &rec);
    write_recording(&data, &rec).unwrap();
    let run = |name: &str, workers: Option<&str>, env: &[(&str, &str)]| {
        let out = dir.path().join(name);
        let mut args = vec![
            "associate".to_string(),
            "--model".into(),
            s(&model),
            "--data".into(),
            s(&data),
            "--out".into(),
            s(&out),
            "--mode".into(),
            "identities".into(),
        ];
        if let Some(w) = workers {
            args.extend(["--workers".into(), w.into()]);
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        crossview(&args, env);
        std::fs::read_to_string(out).unwrap()
    };
    let one = run("w1.jsonl", Some("1"), &[]);
    let three = run("w3.jsonl", Some("3"), &[]);
    let from_env = run("env.jsonl", None, &[("CROSSVIEW_WORKERS", "2")]);

    // Frame by frame: the lines are the recording's frames in order, each frame's line the
    // same whatever the number of workers.
    let parse = |text: &str| -> Vec<serde_json::Value> {
        text.lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect()
    };
    let (a, b, c) = (parse(&one), parse(&three), parse(&from_env));
    assert_eq!(a.len(), rec.frames.len());
    for (k, frame) in rec.frames.iter().enumerate() {
        assert_eq!(a[k]["frame_id"], frame.frame_id, "line {k}");
        assert_eq!(
            a[k], b[k],
            "frame {} differs with 3 workers",
            frame.frame_id
        );
        assert_eq!(
            a[k], c[k],
            "frame {} differs with 2 workers",
            frame.frame_id
        );
    }
    // The frames really differ from each other (a reordering could not go unnoticed).
    let identities: Vec<&serde_json::Value> = a.iter().map(|l| &l["identities"]).collect();
    assert!(identities.windows(2).all(|w| w[0] != w[1]));
    assert!(a.iter().all(|l| !l["pairs"].as_array().unwrap().is_empty()));
    // And the files are byte-identical.
    assert_eq!(one, three);
    assert_eq!(one, from_env);

    // --workers 0 is refused.
    let zero = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["associate", "--model", &s(&model), "--data", &s(&data)])
        .args(["--out", &s(&dir.path().join("z.jsonl")), "--workers", "0"])
        .output()
        .unwrap();
    assert!(!zero.status.success());
}

#[test]
fn eval_table_report_and_dump_are_identical_for_any_number_of_workers() {
    let dir = tempfile::tempdir().unwrap();
    let (model, data) = (dir.path().join("m.onnx"), dir.path().join("gt.jsonl"));
    let rec = recording(41, false);
    write_model(&model, &rec);
    write_recording(&data, &rec).unwrap();
    let run = |tag: &str, workers: &str| {
        let (dump, report) = (
            dir.path().join(format!("pairs{tag}.jsonl")),
            dir.path().join(format!("report{tag}.json")),
        );
        let table = crossview(
            &[
                "eval",
                "--model",
                &s(&model),
                "--data",
                &s(&data),
                "--sweep",
                "0.3",
                "--dump-pairs",
                &s(&dump),
                "--report",
                &s(&report),
                "--workers",
                workers,
            ],
            &[],
        );
        (
            table,
            std::fs::read_to_string(dump).unwrap(),
            std::fs::read_to_string(report).unwrap(),
        )
    };
    let (table1, dump1, report1) = run("1", "1");
    let (table3, dump3, report3) = run("3", "3");
    assert!(table1.contains("identities t=0.30"), "{table1}");
    assert_eq!(table1, table3);
    assert_eq!(report1, report3);
    // The dump is frame by frame, camera pair by camera pair, in order.
    let frames: Vec<u64> = dump1
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l).unwrap()["frame_id"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert!(
        frames.windows(2).all(|w| w[0] <= w[1]),
        "dump not in frame order"
    );
    assert_eq!(
        frames
            .iter()
            .collect::<std::collections::BTreeSet<_>>()
            .len(),
        rec.frames.len()
    );
    assert_eq!(dump1, dump3);

    // The library driver: three encoder sessions give the same runs as one.
    let settings = [
        (Mode::Pairwise, 0.4),
        (Mode::Identities, 0.4),
        (Mode::Pairwise, 0.2),
    ];
    let cfg = AssociationConfig::default();
    let mut one = OnnxEncoder::load(&model).unwrap();
    let expected = evaluate_settings(&mut one, &rec, &cfg, &settings).unwrap();
    let mut sessions: Vec<OnnxEncoder> =
        (0..3).map(|_| OnnxEncoder::load(&model).unwrap()).collect();
    let mut encoders: Vec<&mut dyn Encoder> =
        sessions.iter_mut().map(|e| e as &mut dyn Encoder).collect();
    let runs = evaluate_settings_on(&mut encoders, &rec, &cfg, &settings).unwrap();
    assert_eq!(runs, expected);
    assert!(expected[0].metrics.pairs > 0 && expected[1].identities.frames == rec.frames.len());
}

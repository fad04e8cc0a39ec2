//! End to end through the real ONNX Runtime: export a (random) model, write a small recording
//! with ground-truth ids, evaluate it with `crossview eval`, dump the pairs, recompute the
//! table from the dump alone and compare; `crossview associate` covers every box once.
use std::path::Path;
use std::process::Command;

use crossview_core::association::{AssociationConfig, Mode};
use crossview_core::{CameraSpec, Detection, Frame, SceneSpec};
use crossview_data::Recording;
use crossview_data::recording::write_recording;
use crossview_eval::dump::read_dump;
use crossview_eval::{compute_metrics, evaluate};
use crossview_model::{EncoderConfig, EncoderWeights, ModelMetadata, OnnxEncoder, write_onnx};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn cameras() -> Vec<CameraSpec> {
    (0..3)
        .map(|i| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: format!("cam{i}"),
            width: 640,
            height: 480,
        })
        .collect()
}

fn write_model(path: &Path) {
    let config = EncoderConfig {
        fourier_features: 16,
        camera_dim: 32,
        width: 96,
        blocks: 2,
    };
    let weights = EncoderWeights::random(3, config, 11).unwrap();
    write_onnx(path, &weights, &ModelMetadata::new(cameras())).unwrap();
}

/// Six frames; persons 0..5 walk around, each visible to a random subset of cameras; one
/// camera sometimes sees nobody, and frame 5 lacks camera 2 entirely.
fn recording() -> Recording {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let scene = SceneSpec {
        name: "e2e".into(),
        cameras: cameras(),
    };
    let frames = (0..6u64)
        .map(|f| {
            let mut frame = Frame::new(f * 5, 3);
            for c in 0..3 {
                if f == 5 && c == 2 {
                    continue;
                }
                let mut dets = Vec::new();
                for id in 0..5u64 {
                    if !rng.random_bool(0.7) || (f == 2 && c == 1) {
                        continue;
                    }
                    let x = rng.random_range(0.0f32..560.0);
                    let y = rng.random_range(0.0f32..300.0);
                    dets.push(Detection {
                        id: Some(id),
                        ..Detection::new([x, y, x + 40.0, y + 120.0])
                    });
                }
                frame.views[c] = Some(dets);
            }
            frame
        })
        .collect();
    Recording {
        scene,
        frames,
        fps: None,
    }
}

fn crossview(args: &[&str]) -> String {
    crossview_testing::run_crossview(env!("CARGO_BIN_EXE_crossview"), args, &[])
}

/// The numeric columns of the table's data row (the label column differs).
fn numbers(table: &str) -> Vec<String> {
    let row = table.lines().nth(1).expect("a data row");
    let cols: Vec<&str> = row.split_whitespace().collect();
    cols[cols.len() - 10..]
        .iter()
        .map(|s| s.to_string())
        .collect()
}

/// A temporary directory holding the random model `m.onnx` and the labelled recording
/// `gt.jsonl` (the setup every end-to-end test here starts from).
struct Fixture {
    dir: tempfile::TempDir,
    model: std::path::PathBuf,
    data: std::path::PathBuf,
    rec: Recording,
}

impl Fixture {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("m.onnx");
        let data = dir.path().join("gt.jsonl");
        write_model(&model);
        let rec = recording();
        write_recording(&data, &rec).unwrap();
        Fixture {
            dir,
            model,
            data,
            rec,
        }
    }

    /// A path in the fixture's directory.
    fn path(&self, name: &str) -> std::path::PathBuf {
        self.dir.path().join(name)
    }
}

#[test]
fn eval_dump_and_recompute_give_the_same_table() {
    let f = Fixture::new();
    let (model, data, rec) = (f.model.clone(), f.data.clone(), f.rec.clone());
    let (dump, report) = (f.path("pairs.jsonl"), f.path("report.json"));
    let s = |p: &Path| p.display().to_string();

    let table = crossview(&[
        "eval",
        "--model",
        &s(&model),
        "--data",
        &s(&data),
        "--threshold",
        "0.3",
        "--dump-pairs",
        &s(&dump),
        "--report",
        &s(&report),
    ]);
    assert!(table.contains("pairwise S>=0.30"), "{table}");
    let again = crossview(&["eval", "--from-dump", &s(&dump)]);
    assert_eq!(numbers(&table), numbers(&again), "\n{table}\n{again}");

    // The library path agrees with the CLI, and the dump reproduces the metrics exactly.
    let mut enc = OnnxEncoder::load(&model).unwrap();
    let cfg = AssociationConfig {
        threshold: 0.3,
        ..Default::default()
    };
    let (metrics, records) = evaluate(&mut enc, &rec, &cfg).unwrap();
    let dumped = read_dump(&dump).unwrap();
    assert_eq!(dumped, records);
    assert_eq!(compute_metrics(&dumped), metrics);
    // Pairs only where both cameras have boxes: frame 10 (camera 1 empty) has at most 1 pair,
    // frame 25 (camera 2 missing) at most 1.
    assert!(
        records
            .iter()
            .all(|r| !r.ids_a.is_empty() && !r.ids_b.is_empty())
    );
    assert!(records.iter().filter(|r| r.frame_id == 10).count() <= 1);
    assert!(
        records
            .iter()
            .all(|r| r.frame_id != 25 || r.camera_b != "cam2")
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(json["units"], "fraction");
    let acc = json["runs"][0]["metrics"]["acc"].as_f64().unwrap();
    assert!((acc - metrics.acc).abs() < 1e-12);
}

#[test]
fn pairwise_and_identity_rows_and_associate_cover_every_box() {
    let f = Fixture::new();
    let (model, data, rec) = (f.model.clone(), f.data.clone(), f.rec.clone());
    let out = f.path("assoc.jsonl");
    let s = |p: &Path| p.display().to_string();

    let table = crossview(&[
        "eval",
        "--model",
        &s(&model),
        "--data",
        &s(&data),
        "--sweep",
        "0.2",
        // Each frame alone: the identity rows read the same score matrices as the pairwise
        // ones (with memory they read the remembered distances' scores).
        "--memory",
        "0",
    ]);
    for label in [
        "pairwise S>=0.40",
        "identities t=0.40",
        "pairwise S>=0.20",
        "identities t=0.20",
        "frames with every identity right",
        "identity precision by confidence",
    ] {
        assert!(table.contains(label), "{table}");
    }
    // AP and FPR-95 depend on the scores only: equal across modes.
    let rows: Vec<Vec<&str>> = table
        .lines()
        .skip(1)
        .take(2)
        .map(|l| l.split_whitespace().collect())
        .collect();
    assert_eq!(rows[0][2..4], rows[1][2..4]);

    crossview(&[
        "associate",
        "--model",
        &s(&model),
        "--data",
        &s(&data),
        "--out",
        &s(&out),
        "--mode",
        "identities",
    ]);
    let text = std::fs::read_to_string(&out).unwrap();
    let lines: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), rec.frames.len());
    for (line, frame) in lines.iter().zip(&rec.frames) {
        assert_eq!(line["frame_id"], frame.frame_id);
        let mut seen = std::collections::HashSet::new();
        for ident in line["identities"].as_array().unwrap() {
            let conf = ident["confidence"].as_f64().unwrap();
            assert!((0.0..=1.0).contains(&conf));
            let mut cams = std::collections::HashSet::new();
            for m in ident["members"].as_array().unwrap() {
                let cam = m["camera"].as_str().unwrap().to_string();
                assert!(cams.insert(cam.clone()), "two boxes of one camera: {ident}");
                assert!(seen.insert((cam, m["detection"].as_u64().unwrap())));
            }
        }
        assert_eq!(seen.len(), frame.num_boxes());
    }
    // A bad mode is rejected by the CLI.
    let bad = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args([
            "associate",
            "--model",
            &s(&model),
            "--data",
            &s(&data),
            "--out",
            &s(&out),
            "--mode",
            "bogus",
        ])
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert_eq!("identities".parse::<Mode>().unwrap(), Mode::Identities);
}

#[test]
fn tracking_scores_and_associate_track_ids_agree_on_every_box() {
    let f = Fixture::new();
    let (model, data, rec) = (f.model.clone(), f.data.clone(), f.rec.clone());
    let out = f.path("tracks.jsonl");
    let s = |p: &Path| p.display().to_string();
    let table = crossview(&[
        "eval",
        "--model",
        &s(&model),
        "--data",
        &s(&data),
        "--tracking",
    ]);
    let line = |name: &str| {
        table
            .lines()
            .find(|l| l.trim_start().starts_with(name))
            .unwrap_or_else(|| panic!("no {name} row in {table}"))
            .to_string()
    };
    let boxes: usize = rec.frames.iter().map(Frame::num_boxes).sum();
    assert!(
        line("multi-camera").contains(&format!("({boxes} boxes")),
        "{table}"
    );
    for cam in ["cam0", "cam1", "cam2"] {
        let idf1: f64 = line(cam)
            .split_whitespace()
            .nth(2)
            .unwrap()
            .parse()
            .unwrap();
        assert!((0.0..=100.0).contains(&idf1), "{table}");
    }
    // `associate --tracking` gives every identity a track id, unique within a frame.
    crossview(&[
        "associate",
        "--model",
        &s(&model),
        "--data",
        &s(&data),
        "--out",
        &s(&out),
        "--tracking",
    ]);
    let text = std::fs::read_to_string(&out).unwrap();
    let mut tracked = 0;
    for l in text.lines() {
        let v: serde_json::Value = serde_json::from_str(l).unwrap();
        let mut ids = std::collections::HashSet::new();
        for ident in v["identities"].as_array().unwrap() {
            assert!(ids.insert(ident["track_id"].as_u64().expect("track_id")));
            tracked += ident["members"].as_array().unwrap().len();
        }
    }
    assert_eq!(tracked, boxes);
}

#[test]
fn eval_rejects_data_without_ids() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("m.onnx");
    let data = dir.path().join("noid.jsonl");
    write_model(&model);
    write_recording(&data, &recording().without_ids()).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args([
            "eval",
            "--model",
            &model.display().to_string(),
            "--data",
            &data.display().to_string(),
        ])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains(".id") && err.contains("ground-truth ids"),
        "{err}"
    );
}

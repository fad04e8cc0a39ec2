//! `crossview train` as a user runs it: writes the ONNX model (with metadata; the epoch chosen
//! without labels on held-out frames), the SVG curve and the history; records the training-box
//! filter and the declared frame rate; fits the calibration on every frame, held-out ones
//! included; refuses a one-camera recording, a filter that leaves no boxes and a rate that
//! leaves too few frames clearly.
use std::path::Path;
use std::process::{Command, Output};

use crossview_core::{CameraSpec, Detection, Frame, SceneSpec};
use crossview_data::Recording;
use crossview_data::recording::write_recording;
use crossview_model::{ModelMetadata, read_ensemble};
use crossview_testing::run_crossview;

/// A small recording of 3 people walking past `cameras` cameras (ids when `ids`).
pub(crate) fn recording(cameras: usize, frames: usize, ids: bool) -> Recording {
    let cams: Vec<CameraSpec> = (0..cameras)
        .map(|c| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: format!("cam{c}"),
            width: 100,
            height: 100,
        })
        .collect();
    let frames = (0..frames)
        .map(|f| {
            let mut fr = Frame::new(f as u64, cameras);
            for c in 0..cameras {
                fr.views[c] = Some(
                    (0..3)
                        .map(|p| {
                            let x = 10.0 + 25.0 * p as f32 + (f % 7) as f32 + 3.0 * c as f32;
                            let mut d = Detection::new([x, 20.0, x + 10.0, 60.0 + p as f32]);
                            d.id = ids.then_some(p);
                            d
                        })
                        .collect(),
                );
            }
            fr
        })
        .collect();
    Recording {
        scene: SceneSpec {
            name: "tiny".into(),
            cameras: cams,
        },
        frames,
        fps: None,
    }
}

/// A one-epoch run of a tiny encoder (for tests of what the trainer reads and writes).
const TINY: &[&str] = &[
    "--epochs",
    "1",
    "--width",
    "16",
    "--fourier-features",
    "8",
    "--camera-dim",
    "8",
    "--self-train-epochs",
    "0",
];

/// Runs `crossview train --quiet ARGS --data DATA --out OUT` and returns what it printed.
pub(crate) fn train(data: &Path, out: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["train", "--quiet"])
        .args(args)
        .arg("--data")
        .arg(data)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

/// The population record a trained model file carries (`crossview.population`).
pub(crate) fn population(meta: &ModelMetadata) -> serde_json::Value {
    serde_json::from_str(&meta.extra["crossview.population"]).unwrap()
}

/// Every member of the population record `pop` trained to the end (none was dropped).
pub(crate) fn assert_none_dropped(pop: &serde_json::Value) {
    assert!(
        pop["members"]
            .as_array()
            .unwrap()
            .iter()
            .all(|m| m["dropped_at"].is_null()),
        "{pop}"
    );
}

/// [`train`], which must succeed (its log is the failure message).
pub(crate) fn train_ok(data: &Path, out: &Path, args: &[&str]) -> Output {
    succeeded(train(data, out, args))
}

/// `st`, which must be a success (its log is the failure message).
fn succeeded(st: Output) -> Output {
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    st
}

#[test]
fn train_writes_model_curve_and_history() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    let val = dir.path().join("val.jsonl");
    write_recording(&data, &recording(2, 24, false)).unwrap();
    write_recording(&val, &recording(2, 12, true)).unwrap();
    let out = dir.path().join("m.onnx");
    let st = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args([
            "train",
            "--quiet",
            "--epochs",
            "3",
            "--triplets-per-step",
            "4",
        ])
        .args([
            "--width",
            "24",
            "--fourier-features",
            "8",
            "--camera-dim",
            "8",
        ])
        .args(["--max-edges", "4", "--val-every", "1", "--seed", "3"])
        .args(["--self-train-epochs", "2"])
        .arg("--data")
        .arg(&data)
        .arg("--val")
        .arg(&val)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let st = succeeded(st);
    assert!(String::from_utf8_lossy(&st.stdout).contains("val ACC"));
    // The default population (one member per core, at least 6) trains every member to the
    // end and exports them all together; each is width 24.
    let (e, meta) = read_ensemble(&out).unwrap();
    assert_eq!(e.members().len(), 6);
    assert!(e.members().iter().all(|w| w.config.width == 24));
    let pop = population(&meta);
    assert_none_dropped(&pop);
    assert_eq!(pop["members"].as_array().unwrap().len(), 6);
    assert_eq!(pop["ensemble"].as_array().unwrap().len(), 6);
    assert_eq!(meta.cameras.len(), 2);
    assert!((0.0..=0.9).contains(&meta.threshold));
    assert_eq!(meta.extra["crossview.training_data"], "train.jsonl");
    assert!(meta.extra["crossview.validation"].contains("\"acc\""));
    assert!(meta.extra.contains_key("crossview.steps"));
    let svg = std::fs::read_to_string(dir.path().join("m.svg")).unwrap();
    assert!(svg.starts_with("<svg"));
    let hist: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("m.history.json")).unwrap()).unwrap();
    // 3 first-stage epochs and 2 of self-training, each scored.
    let hist = hist.as_array().unwrap();
    assert_eq!(hist.len(), 5);
    assert!(
        hist.iter()
            .all(|r| !r["label_free"].is_null() && !r["val"].is_null())
    );
    assert!(meta.extra["crossview.selection"].contains("label-free"));
}

#[test]
fn without_validation_the_given_threshold_is_kept() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 20, true)).unwrap();
    let out = dir.path().join("m.onnx");
    let args = ["--epochs", "1", "--width", "16", "--self-train-epochs", "0"];
    let threshold = [
        "--fourier-features",
        "4",
        "--camera-dim",
        "4",
        "--threshold",
        "0.3",
    ];
    train_ok(&data, &out, &[&args[..], &threshold[..]].concat());
    let (_, meta) = read_ensemble(&out).unwrap();
    assert!((meta.threshold - 0.3).abs() < 1e-6);
    assert!(!meta.extra.contains_key("crossview.validation"));
}

#[test]
fn one_camera_is_refused_with_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("one.jsonl");
    write_recording(&data, &recording(1, 30, false)).unwrap();
    let st = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["train", "--quiet", "--epochs", "1"])
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(dir.path().join("m.onnx"))
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("at least two"), "{err}");
    assert!(!dir.path().join("m.onnx").exists());
}

#[test]
fn box_filter_is_recorded_and_an_empty_result_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(2, 24, false)).unwrap();
    let train = |extra: &[&str], out: &Path| train(&data, out, &[TINY, extra].concat());
    // Boxes are 40-43 px of a 100 px image: 0.3 keeps them all and is stored in the model.
    let out = dir.path().join("kept.onnx");
    succeeded(train(
        &["--min-box-height", "0.3", "--drop-static-iou", "0.95"],
        &out,
    ));
    let (_, meta) = read_ensemble(&out).unwrap();
    let filter = &meta.extra["crossview.train_box_filter"];
    assert!(filter.contains("\"min_height\":0.3"), "{filter}");
    assert!(filter.contains("\"static_iou\":0.95"), "{filter}");
    // 0.5 removes every box: a clear refusal, no model written.
    let out = dir.path().join("empty.onnx");
    let st = train(&["--min-box-height", "0.5"], &out);
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("no training boxes left"), "{err}");
    assert!(!out.exists());
    let st = train(&["--min-box-height", "1.5"], &out);
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("--min-box-height"));
}

#[test]
fn a_faster_recording_trains_on_every_nth_frame_and_records_its_rate_given_or_declared() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(2, 60, false)).unwrap();
    let small = [TINY, &["--population", "1"]].concat();
    // 10 frames per second: one frame in 5, 12 of 60 (too few to hold any out: a warning).
    let out = dir.path().join("m.onnx");
    let st = train_ok(&data, &out, &[&small[..], &["--fps", "10"]].concat());
    let log = String::from_utf8_lossy(&st.stderr);
    assert!(log.contains("one frame in 5"), "{log}");
    let (_, meta) = read_ensemble(&out).unwrap();
    let rate: serde_json::Value = serde_json::from_str(&meta.extra["crossview.train_fps"]).unwrap();
    assert_eq!(rate["fps"], 10.0);
    assert_eq!(rate["frame_step"], 5);
    // The same rate declared in the recording's header needs no flag; a flag overrides it.
    let declared = dir.path().join("declared.jsonl");
    let mut rec = recording(2, 60, false);
    rec.fps = Some(10.0);
    write_recording(&declared, &rec).unwrap();
    for (flag, step) in [(&[][..], 5), (&["--fps", "2"][..], 1)] {
        let out = dir.path().join(format!("declared-{step}.onnx"));
        let st = train_ok(&declared, &out, &[&small[..], flag].concat());
        let log = String::from_utf8_lossy(&st.stderr);
        assert_eq!(log.contains("one frame in 5"), step == 5, "{flag:?}: {log}");
        let (_, meta) = read_ensemble(&out).unwrap();
        let rate: serde_json::Value =
            serde_json::from_str(&meta.extra["crossview.train_fps"]).unwrap();
        assert_eq!(rate["frame_step"], step, "{flag:?}");
    }
    // 30 per second leaves 4 frames: refused, naming the rate; so is a rate that is no rate.
    for (fps, says) in [("30", "30 fps"), ("0", "fps"), ("NaN", "fps")] {
        let out = dir.path().join(format!("no-{fps}.onnx"));
        let st = train(&data, &out, &[&small[..], &["--fps", fps]].concat());
        assert!(!st.status.success(), "--fps {fps}");
        let err = String::from_utf8_lossy(&st.stderr);
        assert!(err.contains(says), "--fps {fps}: {err}");
        assert!(!out.exists());
    }
}

#[test]
fn the_exported_calibration_is_fitted_on_every_frame_held_out_ones_included() {
    // The last 10 % of the frames are held out of training for the label-free score; the
    // calibration needs no labels, so it is fitted on all of them: the same table that
    // `crossview model calibrate` fits on the whole recording with the run's seed.
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 60, false)).unwrap();
    let out = dir.path().join("m.onnx");
    let args = [TINY, &["--population", "1", "--seed", "4"]].concat();
    let log = String::from_utf8_lossy(&train_ok(&data, &out, &args).stderr).into_owned();
    assert!(log.contains("held out"), "{log}");
    let again = dir.path().join("again.onnx");
    succeeded(
        Command::new(env!("CARGO_BIN_EXE_crossview"))
            .args(["model", "calibrate", "--seed", "4", "--model"])
            .arg(&out)
            .arg("--data")
            .arg(&data)
            .arg("--out")
            .arg(&again)
            .output()
            .unwrap(),
    );
    let exported = read_ensemble(&out)
        .unwrap()
        .1
        .calibration
        .expect("calibrated");
    let whole = read_ensemble(&again).unwrap().1.calibration.unwrap();
    assert_eq!(exported, whole);
}

#[test]
fn model_calibrate_thins_a_recording_at_the_rate_its_header_declares() {
    // Trained at the reference rate (an undeclared recording); calibrated on a copy that
    // declares 10 frames per second: the same table as the flag `--fps 10` gives, not the
    // model's own rate.
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain.jsonl");
    let declared = dir.path().join("declared.jsonl");
    let path = |p: &Path| p.to_str().unwrap().to_string();
    let bin = env!("CARGO_BIN_EXE_crossview");
    let sim = [
        "simulate", "--preset", "square4", "--frames", "300", "--no-ids",
    ];
    run_crossview(bin, &[&sim[..], &["--out", &path(&declared)]].concat(), &[]);
    let mut rec = crossview_data::read_recording(&declared).unwrap();
    assert_eq!(rec.fps, Some(10.0), "the simulator declares its rate");
    rec.fps = None;
    write_recording(&plain, &rec).unwrap();
    let model = dir.path().join("m.onnx");
    train_ok(&plain, &model, &[TINY, &["--population", "1"]].concat());
    let calibrate = |data: &Path, extra: &[&str], name: &str| {
        let out = dir.path().join(name);
        let (model, data, out_s) = (path(&model), path(data), path(&out));
        let args = [
            "model",
            "calibrate",
            "--model",
            &model,
            "--data",
            &data,
            "--out",
            &out_s,
        ];
        run_crossview(bin, &[&args[..], extra].concat(), &[]);
        read_ensemble(&out).unwrap().1.calibration.unwrap()
    };
    let by_header = calibrate(&declared, &[], "header.onnx");
    let by_flag = calibrate(&plain, &["--fps", "10"], "flag.onnx");
    let by_model = calibrate(&plain, &[], "model.onnx");
    assert_eq!(by_header, by_flag);
    assert!(
        by_model.samples[0] > 4 * by_header.samples[0],
        "{by_model:?} vs {by_header:?}"
    );
}

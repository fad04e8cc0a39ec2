//! `crossview model init` writes a loadable encoder for a recording's scene; `model info`
//! describes it; `model combine` joins encoders into one calibrated ensemble; `model distil`
//! teaches one encoder an ensemble's distances; a bad recording header is a clear error.
use std::process::Command;

use crossview_core::Encoder;
use crossview_model::OnnxEncoder;

fn crossview() -> Command {
    Command::new(env!("CARGO_BIN_EXE_crossview"))
}

#[test]
fn init_then_info() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec.jsonl");
    std::fs::write(
        &rec,
        concat!(
            r#"{"scene": {"name": "lab", "cameras": [{"name": "a", "width": 640, "height": 480}, {"name": "b", "width": 1280, "height": 720}]}}"#,
            "\n",
            r#"{"camera": "a", "frame_id": 0, "detections": []}"#,
            "\n"
        ),
    )
    .unwrap();
    let out = dir.path().join("m.onnx");
    let status = crossview()
        .args(["model", "init", "--scene-from"])
        .arg(&rec)
        .arg("--out")
        .arg(&out)
        .args([
            "--width",
            "64",
            "--fourier",
            "8",
            "--camera-dim",
            "16",
            "--blocks",
            "2",
        ])
        .args(["--threshold", "0.3", "--seed", "4"])
        .output()
        .unwrap();
    assert!(status.status.success(), "{status:?}");

    let mut enc = OnnxEncoder::load(&out).unwrap();
    assert_eq!(enc.dim(), 64);
    assert_eq!(enc.metadata().threshold, 0.3);
    assert_eq!(enc.metadata().cameras[1].name, "b");
    assert_eq!(enc.metadata().extra["crossview.scene"], "lab");
    assert_eq!(
        enc.embed(&[[0.1, 0.2, 0.3, 0.4]], &[1]).unwrap().dim(),
        (1, 64)
    );

    let info = crossview()
        .args(["model", "info"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(info.status.success(), "{info:?}");
    let text = String::from_utf8(info.stdout).unwrap();
    for needle in [
        "width G:   64",
        "boxes float32 [N, 4]",
        "camera int64 [N]",
        "embedding float32 [N, 64]",
        "[1] b 1280x720",
    ] {
        assert!(text.contains(needle), "missing '{needle}' in:\n{text}");
    }
}

#[test]
fn init_with_bad_header_fails_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("bad.jsonl");
    std::fs::write(&rec, "{\"camera\": \"a\"}\n").unwrap();
    let out = crossview()
        .args(["model", "init", "--scene-from"])
        .arg(&rec)
        .arg("--out")
        .arg(dir.path().join("m.onnx"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.jsonl"), "{err}");
}

#[test]
fn info_on_garbage_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("junk.onnx");
    std::fs::write(&path, b"definitely not protobuf \xff\xff\xff").unwrap();
    let out = crossview()
        .args(["model", "info"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("junk.onnx"));
}

/// A two-camera recording whose boxes move, so calibration has synchronized and shifted pairs.
fn moving_recording(path: &std::path::Path, cams: &[&str]) {
    let mut text = format!(
        r#"{{"scene": {{"name": "lab", "cameras": [{}]}}}}"#,
        cams.iter()
            .map(|c| format!(r#"{{"name": "{c}", "width": 100, "height": 100}}"#))
            .collect::<Vec<_>>()
            .join(", ")
    );
    text.push('\n');
    for f in 0..40 {
        for c in cams {
            let boxes: Vec<String> = (0..3)
                .map(|k| {
                    let x = ((f * (2 + k) + 25 * k) % 80) as f32;
                    format!(r#"{{"bbox": [{x}, 10, {}, 60]}}"#, x + 12.0)
                })
                .collect();
            text += &format!(
                r#"{{"camera": "{c}", "frame_id": {f}, "detections": [{}]}}"#,
                boxes.join(", ")
            );
            text.push('\n');
        }
    }
    std::fs::write(path, text).unwrap();
}

fn init_model(rec: &std::path::Path, out: &std::path::Path, seed: &str, width: &str) {
    let st = crossview()
        .args(["model", "init", "--scene-from"])
        .arg(rec)
        .arg("--out")
        .arg(out)
        .args(["--width", width, "--fourier", "8", "--camera-dim", "8"])
        .args(["--blocks", "1", "--seed", seed])
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
}

#[test]
fn combine_joins_encoders_into_one_calibrated_ensemble() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec.jsonl");
    moving_recording(&rec, &["a", "b"]);
    let (a, b) = (dir.path().join("a.onnx"), dir.path().join("b.onnx"));
    init_model(&rec, &a, "1", "16");
    init_model(&rec, &b, "2", "24");
    let out = dir.path().join("e.onnx");
    let st = crossview()
        .args(["model", "combine"])
        .args([&a, &b])
        .arg("--out")
        .arg(&out)
        .arg("--data")
        .arg(&rec)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    let mut e = OnnxEncoder::load(&out).unwrap();
    assert_eq!(e.dim(), 40);
    assert!(e.metadata().calibration.is_some());
    assert!(e.metadata().extra["crossview.ensemble"].contains("b.onnx"));
    // The first 16 columns are a's embedding over √2.
    let boxes = [[0.2, 0.1, 0.3, 0.6], [0.6, 0.2, 0.7, 0.7]];
    let got = e.embed(&boxes, &[0, 1]).unwrap();
    let first = OnnxEncoder::load(&a)
        .unwrap()
        .embed(&boxes, &[0, 1])
        .unwrap();
    for r in 0..2 {
        for c in 0..16 {
            let want = first[(r, c)] / 2f32.sqrt();
            assert!((got[(r, c)] - want).abs() < 1e-4, "{r},{c}");
        }
    }
    // Without --data the ensemble carries no calibration, and says so.
    let plain = dir.path().join("plain.onnx");
    let st = crossview()
        .args(["model", "combine"])
        .args([&a, &b])
        .arg("--out")
        .arg(&plain)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    assert!(String::from_utf8_lossy(&st.stderr).contains("no calibration"));
    assert!(
        OnnxEncoder::load(&plain)
            .unwrap()
            .metadata()
            .calibration
            .is_none()
    );
}

#[test]
fn combine_refuses_models_of_other_cameras() {
    let dir = tempfile::tempdir().unwrap();
    let (r1, r2) = (dir.path().join("r1.jsonl"), dir.path().join("r2.jsonl"));
    moving_recording(&r1, &["a", "b"]);
    moving_recording(&r2, &["a", "c"]);
    let (a, b) = (dir.path().join("a.onnx"), dir.path().join("b.onnx"));
    init_model(&r1, &a, "1", "16");
    init_model(&r2, &b, "2", "16");
    let st = crossview()
        .args(["model", "combine"])
        .args([&a, &b])
        .arg("--out")
        .arg(dir.path().join("e.onnx"))
        .output()
        .unwrap();
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(
        err.contains("other cameras") && err.contains("b.onnx"),
        "{err}"
    );
    assert!(!dir.path().join("e.onnx").exists());
}

/// `crossview model gate`: a candidate no better than the serving model is refused with exit
/// status 3 and the reason (here the serving model against itself, on frames where one camera
/// turned); an untrained candidate is refused; a camera the scene lacks, a corrupt candidate
/// and a tolerance outside [0, 1] are errors (exit 1) that say what is wrong.
#[test]
fn gate_refuses_a_candidate_that_is_no_better_and_names_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("moved.jsonl");
    let st = crossview()
        .args([
            "simulate", "--preset", "square4", "--frames", "300", "--seed", "4",
        ])
        .args(["--no-ids", "--move", "cam1@5:pan=5%", "--out"])
        .arg(&rec)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    let demo = crossview_testing::repo_root().join("models/demo.onnx");
    let untrained = dir.path().join("untrained.onnx");
    let st = crossview()
        .args(["model", "init", "--scene-from"])
        .arg(&rec)
        .arg("--out")
        .arg(&untrained)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    let gate = |candidate: &std::path::Path, extra: &[&str]| {
        crossview()
            .args(["model", "gate", "--json", "--serving"])
            .arg(&demo)
            .arg("--candidate")
            .arg(candidate)
            .arg("--data")
            .arg(&rec)
            .args(extra)
            .output()
            .unwrap()
    };
    for candidate in [&demo, &untrained] {
        let out = gate(candidate, &["--camera", "cam1"]);
        assert_eq!(out.status.code(), Some(3), "{out:?}");
        let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(v["accepted"], false, "{v}");
        assert!(v["reason"].as_str().unwrap().contains("key"), "{v}");
        // The turned camera is the one that stands out under the serving model.
        let cams = v["serving"]["cameras"].as_array().unwrap();
        let cam1 = cams[1].as_f64().unwrap();
        assert!(cams.iter().all(|c| c.as_f64().unwrap() >= cam1), "{v}");
    }
    let junk = dir.path().join("junk.onnx");
    std::fs::write(&junk, b"not a model").unwrap();
    for (candidate, extra, says) in [
        (&demo, vec!["--camera", "nope"], "nope"),
        (&junk, vec![], "junk.onnx"),
        (&demo, vec!["--tolerance", "2"], "--tolerance"),
    ] {
        let out = gate(candidate, &extra);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{extra:?}: {err}");
        assert!(err.contains(says), "{extra:?}: {err}");
    }
}

#[test]
fn distil_writes_one_calibrated_encoder_that_records_its_teacher() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("rec.jsonl");
    moving_recording(&rec, &["a", "b"]);
    let (a, b, e) = (
        dir.path().join("a.onnx"),
        dir.path().join("b.onnx"),
        dir.path().join("e.onnx"),
    );
    init_model(&rec, &a, "1", "16");
    init_model(&rec, &b, "2", "16");
    let st = crossview()
        .args(["model", "combine"])
        .args([&a, &b])
        .arg("--out")
        .arg(&e)
        .output()
        .unwrap();
    assert!(st.status.success(), "{st:?}");
    let out = dir.path().join("s.onnx");
    let distil = |teacher: &std::path::Path, data: &std::path::Path, extra: &[&str]| {
        crossview()
            .args(["model", "distil", "--teacher"])
            .arg(teacher)
            .arg("--data")
            .arg(data)
            .arg("--out")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap()
    };
    let st = distil(&e, &rec, &["--epochs", "2", "--all-boxes", "--width", "8"]);
    assert!(st.status.success(), "{st:?}");
    assert_eq!(OnnxEncoder::load(&out).unwrap().dim(), 8);
    let st = distil(&e, &rec, &["--epochs", "8"]);
    assert!(st.status.success(), "{st:?}");
    let stdout = String::from_utf8_lossy(&st.stdout);
    // The default shape: one and a half times the members' width, their depth.
    assert!(stdout.contains("one member of width 24"), "{stdout}");
    // 40 frames hold out 4: too few for the label-free scores, and it says so.
    assert!(stdout.contains("cannot be scored"), "{stdout}");
    let mut s = OnnxEncoder::load(&out).unwrap();
    assert_eq!(s.dim(), 24);
    let meta = s.metadata().clone();
    assert!(meta.calibration.is_some(), "the student is calibrated");
    let record: serde_json::Value =
        serde_json::from_str(&meta.extra["crossview.distilled"]).unwrap();
    assert_eq!(record["teacher"], "e.onnx");
    assert_eq!(record["teacher_members"], 2);
    assert_eq!(record["teacher_width"], 32);
    assert!(!meta.extra.contains_key("crossview.ensemble"));
    assert_eq!(
        s.embed(&[[0.1, 0.1, 0.3, 0.6]], &[1]).unwrap().dim(),
        (1, 24)
    );

    // Bad input: named, nothing written.
    std::fs::remove_file(&out).unwrap();
    let st = distil(&e, &rec, &["--epochs", "0"]);
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("must be positive"));
    let other = dir.path().join("other.jsonl");
    moving_recording(&other, &["c", "d"]);
    let st = distil(&e, &other, &[]);
    assert!(!st.status.success());
    let junk = dir.path().join("junk.onnx");
    std::fs::write(&junk, b"not a model").unwrap();
    let st = distil(&junk, &rec, &[]);
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("junk.onnx"));
    let st = distil(&e, &rec, &["--match-threshold", "1.5"]);
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("--match-threshold"));
    let st = distil(&e, &rec, &["--loss", "cosine"]);
    assert!(!st.status.success());
    assert!(!out.exists());
}

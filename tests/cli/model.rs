//! `crossview model init` writes a loadable encoder for a recording's scene; `model info`
//! describes it; a bad recording header is a clear error.
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

//! Guarantee: a recording carries its frame rate. The header's optional `"fps"` survives a
//! write and a read, is absent when unknown, is checked like every other header field (a rate
//! that is no frame rate is an error on line 1), must agree across the files of one recording,
//! and the writers that know the rate — the simulator and the WILDTRACK importers — write it.
use std::io::Write;

use crossview_core::{CameraSpec, Detection, Error, Frame, SceneSpec};
use crossview_data::sim::{SimConfig, simulate};
use crossview_data::{
    Recording, RecordingWriter, read_recording, read_recordings, write_recording,
};

fn scene() -> SceneSpec {
    SceneSpec {
        name: "lab".into(),
        cameras: ["a", "b"]
            .iter()
            .map(|n| CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: (*n).into(),
                width: 640,
                height: 480,
            })
            .collect(),
    }
}

fn recording(fps: Option<f64>) -> Recording {
    let frames = (0..3u64)
        .map(|t| {
            let mut f = Frame::new(t, 2);
            let det = Detection::new([10.0 + t as f32, 10.0, 40.0, 90.0]);
            f.views = vec![Some(vec![det.clone()]), Some(vec![det])];
            f
        })
        .collect();
    Recording {
        scene: scene(),
        frames,
        fps,
    }
}

fn header_json(path: &std::path::Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap();
    serde_json::from_str(text.lines().next().unwrap()).unwrap()
}

#[test]
fn a_declared_rate_round_trips_and_an_unknown_one_is_left_out() {
    let dir = tempfile::tempdir().unwrap();
    for fps in [Some(10.0), Some(2.5), None] {
        let path = dir.path().join("rec.jsonl");
        write_recording(&path, &recording(fps)).unwrap();
        let header = header_json(&path);
        match fps {
            Some(f) => assert_eq!(header["fps"], f, "{header}"),
            None => assert!(header.get("fps").is_none(), "{header}"),
        }
        let back = read_recording(&path).unwrap();
        assert_eq!(back, recording(fps));
        assert_eq!(back.filter_frames(1..).fps, fps, "a part keeps the rate");
    }
}

#[test]
fn a_rate_that_is_no_frame_rate_is_refused_on_line_one() {
    let dir = tempfile::tempdir().unwrap();
    let cams = r#""cameras": [{"name": "a", "width": 640, "height": 480}]"#;
    for bad in ["0", "-10", "1e300", "1001", "\"ten\"", "[10]"] {
        let path = dir.path().join("bad.jsonl");
        let mut f = std::fs::File::create(&path).unwrap();
        writeln!(f, r#"{{"scene": {{"name": "lab", {cams}}}, "fps": {bad}}}"#).unwrap();
        match read_recording(&path) {
            Err(Error::Format { line, message, .. }) => {
                assert_eq!(line, 1, "fps {bad}");
                assert!(message.contains("fps"), "fps {bad}: {message}");
            }
            other => panic!("fps {bad}: expected a format error, got {other:?}"),
        }
    }
    // `null` is the same as no rate.
    let path = dir.path().join("null.jsonl");
    std::fs::write(
        &path,
        format!("{{\"scene\": {{\"name\": \"lab\", {cams}}}, \"fps\": null}}\n"),
    )
    .unwrap();
    assert_eq!(read_recording(&path).unwrap().fps, None);
    // A writer refuses to declare such a rate.
    for bad in [0.0, f64::NAN, f64::INFINITY, -1.0] {
        let e = RecordingWriter::new(Vec::new(), "mem", &scene(), Some(bad))
            .err()
            .expect("refused");
        assert!(e.to_string().contains("fps"), "{e}");
    }
}

#[test]
fn the_files_of_one_recording_must_declare_the_same_rate() {
    let dir = tempfile::tempdir().unwrap();
    let part = |name: &str, fps: Option<f64>, first: u64| {
        let mut rec = recording(fps);
        for f in &mut rec.frames {
            f.frame_id += first;
        }
        let path = dir.path().join(name);
        write_recording(&path, &rec).unwrap();
        path
    };
    let a = part("a.jsonl", Some(10.0), 0);
    let b = part("b.jsonl", Some(10.0), 100);
    let (rec, _) = read_recordings(&[&a, &b], true).unwrap();
    assert_eq!((rec.fps, rec.frames.len()), (Some(10.0), 6));
    for (name, fps) in [("c.jsonl", Some(5.0)), ("d.jsonl", None)] {
        let other = part(name, fps, 200);
        match read_recordings(&[&a, &other], true) {
            Err(Error::Format {
                source_name,
                line,
                message,
            }) => {
                assert_eq!(source_name, other.display().to_string());
                assert_eq!(line, 1);
                assert!(message.contains("frame rate"), "{message}");
            }
            r => panic!("{name}: expected a format error, got {r:?}"),
        }
    }
}

#[test]
fn the_simulator_declares_its_rate() {
    let mut cfg = SimConfig::preset("square4").unwrap();
    cfg.frames = 5;
    cfg.fps = 25.0;
    assert_eq!(simulate(&cfg).unwrap().fps, Some(25.0));

    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sim.jsonl");
    let out_s = out.to_str().unwrap();
    let args = [
        "simulate", "--preset", "square4", "--frames", "3", "--fps", "12.5", "--out", out_s,
    ];
    crossview_testing::run_crossview(env!("CARGO_BIN_EXE_crossview"), &args, &[]);
    assert_eq!(header_json(&out)["fps"], 12.5);
    assert_eq!(read_recording(&out).unwrap().fps, Some(12.5));
}

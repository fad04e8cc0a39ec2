//! Recording format (SPEC §7): round trips and the error for each kind of malformed line.
use std::io::Write;

use crossview_core::Error;
use crossview_core::{Batch, CameraSpec, Detection, Frame, SceneSpec};
use crossview_data::{
    Recording, RecordingReader, RecordingWriter, read_recording, read_recording_with,
    write_recording,
};

fn scene() -> SceneSpec {
    SceneSpec {
        name: "lab".into(),
        cameras: vec![
            CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: "a".into(),
                width: 640,
                height: 480,
            },
            CameraSpec {
                offset: 0,
                offset_ms: 0,
                name: "b".into(),
                width: 1920,
                height: 1080,
            },
        ],
    }
}

const HEADER: &str = r#"{"scene": {"name": "lab", "cameras": [{"name": "a", "width": 640, "height": 480}, {"name": "b", "width": 1920, "height": 1080}]}}"#;

fn det(x: f32, id: Option<u64>) -> Detection {
    Detection {
        bbox: [x, 10.0, x + 20.0, 80.0],
        score: 0.5,
        id,
        appearance: None,
    }
}

fn write_file(dir: &tempfile::TempDir, name: &str, text: &str) -> std::path::PathBuf {
    let path = dir.path().join(name);
    let mut f = std::fs::File::create(&path).unwrap();
    f.write_all(text.as_bytes()).unwrap();
    path
}

/// Reads `lines` (joined with newlines) and returns the format error's line and message.
fn format_error(lines: &[&str]) -> (usize, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = write_file(&dir, "bad.jsonl", &(lines.join("\n") + "\n"));
    match read_recording(&path) {
        Err(Error::Format {
            source_name,
            line,
            message,
        }) => {
            assert_eq!(source_name, path.display().to_string());
            (line, message)
        }
        other => panic!("expected a format error, got {other:?}"),
    }
}

#[test]
fn round_trip_keeps_frames_views_and_empty_batches() {
    let batches = vec![
        Batch {
            camera: "b".into(),
            frame_id: 10,
            time: None,
            detections: vec![det(5.0, Some(3)), det(50.0, None)],
        },
        Batch {
            camera: "a".into(),
            frame_id: 10,
            time: None,
            detections: vec![],
        },
        Batch {
            camera: "a".into(),
            frame_id: 5,
            time: None,
            detections: vec![det(1.0, Some(1))],
        },
    ];
    let rec = Recording::from_batches(scene(), batches).unwrap();
    assert_eq!(rec.frame_ids(), vec![5, 10]);
    assert_eq!(
        rec.frames[0].views[1], None,
        "camera b did not report frame 5"
    );
    assert!(!rec.frames[0].is_complete());
    assert_eq!(rec.frames[1].views[0], Some(vec![]));
    assert!(
        rec.frames[1].is_complete(),
        "an empty batch completes a frame"
    );
    assert_eq!(rec.num_boxes(), 3);

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rec.jsonl");
    write_recording(&path, &rec).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert_eq!(text.lines().count(), 4, "header + 3 batches:\n{text}");
    assert!(text.contains(r#""camera":"a","frame_id":10,"detections":[]"#));
    let back = read_recording(&path).unwrap();
    assert_eq!(back, rec);
    assert!(back.frames[1].is_complete());
}

/// A camera declared `@+2` (its clock runs two frame ids ahead): its batch `N` is grouped
/// with the other cameras' frame `N − 2`, and writing gives back the camera's own ids.
#[test]
fn clock_offsets_group_batches_and_round_trip() {
    let mut lagged = scene();
    lagged.cameras[1].offset = 2;
    let batch = |camera: &str, frame_id: u64, x: f32| Batch {
        camera: camera.into(),
        frame_id,
        time: None,
        detections: vec![det(x, None)],
    };
    let batches = vec![
        batch("a", 10, 1.0),
        batch("b", 12, 2.0),
        batch("a", 11, 3.0),
        batch("b", 13, 4.0),
    ];
    let rec = Recording::from_batches(lagged.clone(), batches.clone()).unwrap();
    assert_eq!(
        rec.frame_ids(),
        vec![10, 11],
        "b's 12 and 13 are frames 10 and 11"
    );
    assert!(rec.frames.iter().all(Frame::is_complete));
    assert_eq!(rec.frames[0].views[1].as_ref().unwrap()[0].bbox[0], 2.0);

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rec.jsonl");
    write_recording(&path, &rec).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(
        text.contains(r#""offset":2"#),
        "the header keeps the offset:\n{text}"
    );
    assert!(
        text.contains(r#""camera":"b","frame_id":12"#),
        "b's own ids:\n{text}"
    );
    let back = read_recording(&path).unwrap();
    assert_eq!(back, rec);
    let mut again: Vec<Batch> = back.batches().collect();
    again.sort_by_key(|b| (b.frame_id, b.camera.clone()));
    let mut sent = batches;
    sent.sort_by_key(|b| (b.frame_id, b.camera.clone()));
    assert_eq!(again, sent, "batches() gives each camera's own ids");

    // An offset that would put a batch before frame 0 is an error, not a wrapped id.
    lagged.cameras[1].offset = 20;
    let err = Recording::from_batches(lagged, vec![batch("b", 3, 1.0)]).unwrap_err();
    assert!(err.to_string().contains("clock offset"), "{err}");
}

#[test]
fn streaming_reader_and_writer_agree() {
    let mut writer = RecordingWriter::new(Vec::new(), "memory", &scene(), None).unwrap();
    for f in 0..50u64 {
        let batch = Batch {
            camera: if f % 2 == 0 { "a" } else { "b" }.into(),
            frame_id: f,
            time: None,
            detections: vec![det(f as f32, Some(f))],
        };
        writer.write_batch(&batch).unwrap();
    }
    let bytes = writer.finish().unwrap();
    let reader = RecordingReader::new(bytes.as_slice(), "memory").unwrap();
    assert_eq!(reader.scene(), &scene());
    let batches: Vec<Batch> = reader.collect::<Result<_, _>>().unwrap();
    assert_eq!(batches.len(), 50);
    assert_eq!(batches[7].frame_id, 7);
    assert_eq!(batches[7].camera, "b");
    assert_eq!(batches[7].detections[0].id, Some(7));
}

#[test]
fn writer_rejects_unknown_camera() {
    let mut writer = RecordingWriter::new(Vec::new(), "memory", &scene(), None).unwrap();
    let err = writer
        .write_batch(&Batch {
            camera: "zz".into(),
            frame_id: 0,
            time: None,
            detections: vec![],
        })
        .unwrap_err();
    assert!(err.to_string().contains("zz"), "{err}");
}

#[test]
fn defaults_and_blank_lines() {
    let (dir, text) = (
        tempfile::tempdir().unwrap(),
        format!(
            "{HEADER}\n\n{}\n  \n{}\n",
            r#"{"camera": "a", "frame_id": 3, "detections": [{"bbox": [1, 2, 3, 4]}]}"#,
            r#"{"camera": "b", "frame_id": 3, "detections": [{"bbox": [1, 2, 3, 4], "id": 9, "appearance": [0.5, 1]}]}"#
        ),
    );
    let path = write_file(&dir, "ok.jsonl", &text);
    let rec = read_recording(&path).unwrap();
    let a = &rec.frames[0].views[0].as_ref().unwrap()[0];
    assert_eq!(a.score, 1.0);
    assert_eq!(a.id, None);
    let b = &rec.frames[0].views[1].as_ref().unwrap()[0];
    assert_eq!(b.id, Some(9));
    assert_eq!(b.appearance.as_deref(), Some(&[0.5, 1.0][..]));
}

#[test]
fn empty_file_is_missing_header() {
    let (line, msg) = format_error(&[]);
    assert_eq!(line, 1);
    assert!(msg.contains("missing the scene header"), "{msg}");
}

#[test]
fn batch_as_first_line_is_invalid_header() {
    let (line, msg) = format_error(&[r#"{"camera": "a", "frame_id": 0, "detections": []}"#]);
    assert_eq!(line, 1);
    assert!(msg.contains("invalid scene header"), "{msg}");
}

#[test]
fn header_with_duplicate_camera_names_is_rejected() {
    let (line, msg) = format_error(&[
        r#"{"scene": {"name": "x", "cameras": [{"name": "a", "width": 1, "height": 1}, {"name": "a", "width": 1, "height": 1}]}}"#,
    ]);
    assert_eq!(line, 1);
    assert!(msg.contains("'a' is used twice"), "{msg}");
}

#[test]
fn header_with_zero_size_is_rejected() {
    let (line, msg) = format_error(&[
        r#"{"scene": {"name": "x", "cameras": [{"name": "a", "width": 0, "height": 10}]}}"#,
    ]);
    assert_eq!(line, 1);
    assert!(msg.contains("zero image size"), "{msg}");
}

#[test]
fn malformed_json_names_its_line() {
    let (line, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": []}"#,
        r#"{"camera": "a", "frame_id": 5, "detections": [}"#,
    ]);
    assert_eq!(line, 3);
    assert!(msg.contains("malformed batch"), "{msg}");
}

#[test]
fn negative_frame_id_is_malformed() {
    let (line, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": -1, "detections": []}"#,
    ]);
    assert_eq!(line, 2);
    assert!(msg.contains("malformed batch"), "{msg}");
}

#[test]
fn unknown_camera_is_named() {
    let (line, msg) = format_error(&[
        HEADER,
        "",
        r#"{"camera": "ghost", "frame_id": 0, "detections": []}"#,
    ]);
    assert_eq!(line, 3, "blank lines count");
    assert!(msg.contains("unknown camera 'ghost'"), "{msg}");
    assert!(msg.contains("a, b"), "lists the scene's cameras: {msg}");
}

#[test]
fn duplicate_batch_is_rejected() {
    let (line, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": []}"#,
        r#"{"camera": "b", "frame_id": 0, "detections": []}"#,
        r#"{"camera": "a", "frame_id": 0, "detections": []}"#,
    ]);
    assert_eq!(line, 4);
    assert!(
        msg.contains("duplicate batch: camera 'a' already reported frame 0"),
        "{msg}"
    );
}

#[test]
fn duplicate_check_can_be_switched_off_for_streams() {
    let line = r#"{"camera": "b", "frame_id": 70, "detections": []}"#;
    let text = format!("{HEADER}\n{line}\n{line}\n");
    let reader = RecordingReader::new(text.as_bytes(), "mem").unwrap();
    let results: Vec<_> = reader.collect();
    assert!(
        results[1]
            .as_ref()
            .unwrap_err()
            .to_string()
            .contains("duplicate batch")
    );
    let reader = RecordingReader::new(text.as_bytes(), "mem")
        .unwrap()
        .without_duplicate_check();
    assert_eq!(reader.filter(Result::is_ok).count(), 2);
}

#[test]
fn invalid_detection_names_the_field() {
    let (line, msg) = format_error(&[
        HEADER,
        r#"{"camera": "b", "frame_id": 2, "detections": [{"bbox": [1, 2, 3, 4]}, {"bbox": [1, 2, 3, 4]}, {"bbox": [1, 2, 3, 4]}, {"bbox": [5, 2, 3, 4]}]}"#,
    ]);
    assert_eq!(line, 2);
    assert!(msg.contains("detections[3].bbox"), "{msg}");
    assert!(msg.contains("camera 'b' frame 2"), "{msg}");
}

#[test]
fn box_outside_the_image_and_bad_score_are_rejected() {
    let (_, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [-9, 2, -3, 4]}]}"#,
    ]);
    assert!(
        msg.contains("detections[0].bbox") && msg.contains("entirely outside"),
        "{msg}"
    );
    let (_, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [1, 2, 3, 4], "score": 1.5}]}"#,
    ]);
    assert!(msg.contains("detections[0].score"), "{msg}");
}

#[test]
fn inconsistent_appearance_length_is_rejected() {
    let (line, msg) = format_error(&[
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [1, 2, 3, 4], "appearance": [1, 2, 3]}]}"#,
        r#"{"camera": "b", "frame_id": 0, "detections": [{"bbox": [1, 2, 3, 4], "appearance": [1, 2, 3]}, {"bbox": [1, 2, 3, 4], "appearance": [1, 2]}]}"#,
    ]);
    assert_eq!(line, 3);
    assert!(
        msg.contains("detections[1].appearance") && msg.contains("expected 3 values, got 2"),
        "{msg}"
    );
}

#[test]
fn reader_stops_after_first_error() {
    let text = format!(
        "{HEADER}\n{}\n{}\n",
        r#"{"camera": "x", "frame_id": 0, "detections": []}"#,
        r#"{"camera": "a", "frame_id": 0, "detections": []}"#
    );
    let mut reader = RecordingReader::new(text.as_bytes(), "mem").unwrap();
    assert!(reader.next().unwrap().is_err());
    assert!(reader.next().is_none());
}

#[test]
fn from_batches_errors() {
    let dup = vec![
        Batch {
            camera: "a".into(),
            frame_id: 1,
            time: None,
            detections: vec![],
        };
        2
    ];
    assert!(matches!(
        Recording::from_batches(scene(), dup),
        Err(Error::DuplicateBatch { frame_id: 1, .. })
    ));
    let unknown = vec![Batch {
        camera: "q".into(),
        frame_id: 1,
        time: None,
        detections: vec![],
    }];
    assert!(matches!(
        Recording::from_batches(scene(), unknown),
        Err(Error::UnknownCamera { .. })
    ));
    let nan = vec![Batch {
        camera: "a".into(),
        frame_id: 1,
        time: None,
        detections: vec![Detection::new([f32::NAN, 0.0, 1.0, 1.0])],
    }];
    match Recording::from_batches(scene(), nan) {
        Err(Error::InvalidArgument { field, .. }) => assert_eq!(field, "a@1.detections[0].bbox"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn helpers_filter_strip_and_write_back() {
    let mut frames = Vec::new();
    for f in [0u64, 5, 10, 15] {
        let mut frame = Frame::new(f, 2);
        frame.views[0] = Some(vec![det(1.0, Some(f))]);
        if f != 5 {
            frame.views[1] = Some(vec![]);
        }
        frames.push(frame);
    }
    let rec = Recording {
        scene: scene(),
        frames,
        fps: None,
    };
    assert_eq!(rec.filter_frames(5..=10).frame_ids(), vec![5, 10]);
    assert_eq!(rec.filter_frames(11..).frame_ids(), vec![15]);
    let stripped = rec.without_ids();
    assert!(
        stripped
            .frames
            .iter()
            .flat_map(|f| f.views.iter().flatten().flatten())
            .all(|d| d.id.is_none())
    );
    assert_eq!(stripped.num_boxes(), 4);
    let batches: Vec<Batch> = rec.batches().collect();
    assert_eq!(
        batches.len(),
        7,
        "frame 5's camera b did not report and is omitted"
    );
    assert!(
        batches
            .iter()
            .any(|b| b.camera == "b" && b.frame_id == 0 && b.detections.is_empty())
    );
    assert_eq!(Recording::from_batches(scene(), batches).unwrap(), rec);
}

#[test]
fn missing_file_is_io_error() {
    let err = read_recording("/nonexistent/rec.jsonl").unwrap_err();
    assert!(matches!(err, Error::Io { .. }), "{err}");
}

#[test]
fn duplicates_are_found_with_more_than_64_cameras() {
    let cameras: Vec<CameraSpec> = (0..70)
        .map(|i| CameraSpec {
            offset: 0,
            offset_ms: 0,
            name: format!("c{i}"),
            width: 10,
            height: 10,
        })
        .collect();
    let scene = SceneSpec {
        name: "wide".into(),
        cameras,
    };
    let mut writer = RecordingWriter::new(Vec::new(), "mem", &scene, None).unwrap();
    for cam in ["c1", "c65", "c66", "c65"] {
        writer
            .write_batch(&Batch {
                camera: cam.into(),
                frame_id: 3,
                time: None,
                detections: vec![],
            })
            .unwrap();
    }
    let bytes = writer.finish().unwrap();
    let results: Vec<_> = RecordingReader::new(bytes.as_slice(), "mem")
        .unwrap()
        .collect();
    assert!(results[..3].iter().all(Result::is_ok));
    match &results[3] {
        Err(Error::Format { line, message, .. }) => {
            assert_eq!(*line, 5);
            assert!(
                message.contains("camera 'c65' already reported frame 3"),
                "{message}"
            );
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn cli_split_reads_stdin_and_writes_stdout() {
    use std::process::{Command, Stdio};
    let mut frames = Vec::new();
    for f in 0..20u64 {
        let mut frame = Frame::new(f, 2);
        frame.views[0] = Some(vec![det(1.0, Some(f))]);
        frame.views[1] = Some(vec![]);
        frames.push(frame);
    }
    let rec = Recording {
        scene: scene(),
        frames,
        fps: None,
    };
    let mut input = RecordingWriter::new(Vec::new(), "mem", &rec.scene, None).unwrap();
    for frame in &rec.frames {
        input.write_frame(frame).unwrap();
    }
    let input = input.finish().unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["split", "--data", "-", "--part", "test", "--out", "-"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    child.stdin.take().unwrap().write_all(&input).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // 20 frames: test = ceil(20/10) = 2 frames (18, 19); summary goes to stderr.
    let back = RecordingReader::new(out.stdout.as_slice(), "stdout").unwrap();
    let batches: Vec<Batch> = back.collect::<Result<_, _>>().unwrap();
    assert_eq!(
        Recording::from_batches(scene(), batches).unwrap(),
        rec.filter_frames(18..)
    );
    let summary = String::from_utf8_lossy(&out.stderr);
    assert!(
        summary.contains("2 frames (18..=19)") && summary.contains("2 cameras"),
        "{summary}"
    );
}

#[test]
fn boxes_overlapping_the_image_edge_are_clipped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let text = [
        HEADER,
        // WILDTRACK-style y1 = -1, and one sticking out right and below (camera a is 640x480).
        r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [10, -1, 50, 90]}, {"bbox": [600, 400, 642, 481]}]}"#,
    ]
    .join("\n");
    let path = write_file(&dir, "edge.jsonl", &text);
    let (rec, stats) = read_recording_with(&path, true).unwrap();
    let boxes: Vec<[f32; 4]> = rec.frames[0].views[0]
        .as_ref()
        .unwrap()
        .iter()
        .map(|d| d.bbox)
        .collect();
    assert_eq!(
        boxes,
        vec![[10.0, 0.0, 50.0, 90.0], [600.0, 400.0, 640.0, 480.0]]
    );
    assert_eq!(stats.clipped_boxes, 2);
    assert_eq!(stats.skipped_boxes + stats.skipped_lines, 0);
}

#[test]
fn a_lenient_reader_skips_broken_boxes_and_lines_with_a_count() {
    let dir = tempfile::tempdir().unwrap();
    let text = [
        HEADER,
        r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [10, 10, 50, 90]}, {"bbox": [50, 10, 40, 90]}]}"#,
        r#"{"camera": "b", "frame_id": 0, "detections": [{"bbox": [5000, 10, 6000, 90]}, {"bbox": [1, 1, 9, 9]}]}"#,
        r#"{"camera": "a", "frame_id": 1, "detections": [{"bbox": [1, 1, 9"#,
        r#"{"camera": "zz", "frame_id": 1, "detections": []}"#,
        r#"{"camera": "a", "frame_id": 0, "detections": []}"#,
        r#"{"camera": "a", "frame_id": 2, "detections": [{"bbox": [1, 1, 9, 9]}]}"#,
    ]
    .join("\n");
    let path = write_file(&dir, "careless.jsonl", &text);
    // Strict: the first broken box aborts.
    assert!(read_recording_with(&path, true).is_err());
    let (rec, stats) = read_recording_with(&path, false).unwrap();
    assert_eq!(stats.skipped_boxes, 2, "{stats:?}");
    assert_eq!(stats.skipped_lines, 3, "{stats:?}");
    assert!(stats.first_problem.unwrap().contains("detections[1].bbox"));
    assert_eq!(rec.frame_ids(), vec![0, 2]);
    assert_eq!(rec.num_boxes(), 3);
}

#[test]
fn a_torn_last_line_is_dropped_and_counted() {
    let dir = tempfile::tempdir().unwrap();
    let a0 = r#"{"camera": "a", "frame_id": 0, "detections": [{"bbox": [1, 1, 9, 9]}]}"#;
    // Cut short by a crash: no newline, not complete JSON (also mid-character).
    for tail in [
        r#"{"camera": "b", "frame_id": 0, "detec"#.as_bytes(),
        b"{\"camera\": \"\xc3",
        b"\0\0\0\0",
    ] {
        let mut text = format!("{HEADER}\n{a0}\n").into_bytes();
        text.extend_from_slice(tail);
        let path = dir.path().join("torn.jsonl");
        std::fs::write(&path, &text).unwrap();
        let (rec, stats) = read_recording_with(&path, true).unwrap();
        assert_eq!(stats.torn_lines, 1, "{tail:?}");
        assert_eq!(rec.num_boxes(), 1);
    }
    // A complete last line without its newline is kept.
    let b0 = r#"{"camera": "b", "frame_id": 0, "detections": []}"#;
    let path = write_file(&dir, "no-newline.jsonl", &format!("{HEADER}\n{a0}\n{b0}"));
    let (rec, stats) = read_recording_with(&path, true).unwrap();
    assert_eq!(stats.torn_lines, 0);
    assert!(rec.frames[0].views[1].is_some());
    // The same broken line anywhere but last (or with its newline) stays an error.
    let bad = r#"{"camera": "b", "frame_id": 0, "detec"#;
    let path = write_file(&dir, "middle.jsonl", &format!("{HEADER}\n{bad}\n{a0}"));
    match read_recording(&path) {
        Err(Error::Format { line, .. }) => assert_eq!(line, 2),
        other => panic!("{other:?}"),
    }
    let path = write_file(
        &dir,
        "terminated.jsonl",
        &format!("{HEADER}\n{a0}\n{bad}\n"),
    );
    assert!(read_recording(&path).is_err());
    // The streaming reader drops it too.
    let text = format!("{HEADER}\n{a0}\n{bad}");
    let mut reader = RecordingReader::new(text.as_bytes(), "mem").unwrap();
    assert!(reader.next().unwrap().is_ok());
    assert!(reader.next().is_none());
    assert_eq!(reader.stats().torn_lines, 1);
}

/// A server whose `--auto-align` changed a camera's clock offset starts a new file with it:
/// each file's batches are grouped by its own header's offsets, so the files read together
/// group them as the server did.
#[test]
fn files_whose_offsets_differ_are_grouped_each_by_its_own_header() {
    let dir = tempfile::tempdir().unwrap();
    let line = |cam: &str, frame: u64, x: f32| {
        format!(
            r#"{{"camera": "{cam}", "frame_id": {frame}, "detections": [{{"bbox": [{x}, 10, {}, 80]}}]}}"#,
            x + 20.0
        )
    };
    // Camera b runs 3 frames late: in sync in the first file, declared +3 in the second.
    let late = HEADER.replace(
        r#"{"name": "b", "width": 1920, "height": 1080}"#,
        r#"{"name": "b", "width": 1920, "height": 1080, "offset": 3}"#,
    );
    assert_ne!(late, HEADER);
    let one = format!("{HEADER}\n{}\n{}\n", line("a", 0, 1.0), line("b", 0, 2.0));
    let two = format!("{late}\n{}\n{}\n", line("a", 5, 3.0), line("b", 8, 4.0));
    std::fs::write(dir.path().join("0001.jsonl"), one).unwrap();
    std::fs::write(dir.path().join("0002.jsonl"), two).unwrap();
    let rec = read_recording(dir.path()).unwrap();
    assert_eq!(rec.frame_ids(), vec![0, 5]);
    let x = |f: usize, c: usize| rec.frames[f].views[c].as_ref().unwrap()[0].bbox[0];
    assert_eq!((x(0, 0), x(0, 1)), (1.0, 2.0));
    assert_eq!(
        (x(1, 0), x(1, 1)),
        (3.0, 4.0),
        "b's batch 8 belongs to frame 5"
    );
    // Written back, the recording reads the same (one header, one set of offsets).
    let out = dir.path().join("merged.out");
    write_recording(&out, &rec).unwrap();
    assert_eq!(read_recording(&out).unwrap().frames, rec.frames);
    // Other cameras (here: another image size) are still another scene.
    let other = HEADER.replace("1080", "1081");
    std::fs::write(dir.path().join("0003.jsonl"), format!("{other}\n")).unwrap();
    let err = read_recording(dir.path()).unwrap_err().to_string();
    assert!(err.contains("same scene"), "{err}");
}

#[test]
fn a_directory_or_several_files_read_as_one_recording() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("lab");
    std::fs::create_dir(&sub).unwrap();
    let line = |cam: &str, f: u64| {
        format!(
            r#"{{"camera": "{cam}", "frame_id": {f}, "detections": [{{"bbox": [1, 1, 9, 9], "id": {f}}}]}}"#
        )
    };
    // Frame 1 is split across the rotation; the second file ends torn; an empty file and a
    // file with only a torn header add nothing; other files are ignored.
    let one = format!(
        "{HEADER}\n{}\n{}\n{}\n",
        line("a", 0),
        line("b", 0),
        line("a", 1)
    );
    let two = format!(
        "{HEADER}\n{}\n{}\n{{\"camera\": \"a\"",
        line("b", 1),
        line("a", 2)
    );
    std::fs::write(sub.join("0001.jsonl"), one).unwrap();
    std::fs::write(sub.join("0002.jsonl"), two.clone()).unwrap();
    std::fs::write(sub.join("0003.jsonl"), "").unwrap();
    std::fs::write(sub.join("0004.jsonl"), "{\"scene\": {\"na").unwrap();
    std::fs::write(sub.join("notes.txt"), "not a recording").unwrap();
    let (rec, stats) = read_recording_with(dir.path(), true).unwrap();
    assert_eq!(rec.frame_ids(), vec![0, 1, 2]);
    assert!(
        rec.frames[1].views.iter().all(Option::is_some),
        "frame 1 merged"
    );
    assert_eq!((stats.torn_lines, stats.empty_files), (2, 1));
    let files = crossview_data::recording_files(&[dir.path()]).unwrap();
    assert_eq!(files.len(), 4);
    // Several files given one by one: the same recording.
    let (again, _) =
        crossview_data::read_recordings(&[sub.join("0001.jsonl"), sub.join("0002.jsonl")], true)
            .unwrap();
    assert_eq!(again, rec);
    // A camera twice for one frame across files is a duplicate, naming the later file.
    std::fs::write(
        sub.join("0005.jsonl"),
        format!("{HEADER}\n{}\n", line("b", 1)),
    )
    .unwrap();
    let err = read_recording(dir.path()).unwrap_err().to_string();
    assert!(
        err.contains("0005.jsonl") && err.contains("duplicate"),
        "{err}"
    );
    // Another scene is a clear error.
    let other = HEADER.replace("\"lab\"", "\"yard\"");
    std::fs::write(sub.join("0005.jsonl"), format!("{other}\n")).unwrap();
    let err = read_recording(dir.path()).unwrap_err().to_string();
    assert!(err.contains("same scene") && err.contains("yard"), "{err}");
    // A directory without recordings.
    let empty = tempfile::tempdir().unwrap();
    let err = read_recording(empty.path()).unwrap_err().to_string();
    assert!(err.contains("no recording"), "{err}");
}

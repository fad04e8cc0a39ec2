//! MVOR importers on small files written in the dataset's own formats: frame numbering, ids,
//! the repairs counted, errors that name what is wrong, and the two recordings cut alike by
//! `crossview split`.

use std::path::{Path, PathBuf};
use std::process::Command;

use crossview_core::Error;
use crossview_data::mvor::{self, CAMERA_NAMES, FRAMES, import_detections, import_ground_truth};
use crossview_data::{Recording, read_recording};
use serde_json::{Value, json};

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// An annotation file of `frames` triples (image ids `1000 * frame + cam_id`) and `annotations`
/// given as (frame, cam_id, bbox, person_id).
fn annotation_file(frames: u64, annotations: &[(u64, i64, [f64; 4], i64)]) -> String {
    let triples: Vec<Value> = (0..frames)
        .map(|f| {
            let images: Vec<Value> = (1..=3)
                .map(|c| {
                    json!({"id": 1000 * f + c, "cam_id": c, "width": 640, "height": 480,
                                "file_name": format!("day1/cam{c}/color/{f:06}.png")})
                })
                .collect();
            json!({"id": f, "images": images})
        })
        .collect();
    let anns: Vec<Value> = annotations
        .iter()
        .enumerate()
        .map(|(k, &(f, cam, bbox, person))| {
            json!({"id": k, "image_id": 1000 * f + cam as u64, "bbox": bbox,
                   "person_id": person, "category_id": "1"})
        })
        .collect();
    json!({"info": {}, "multiview_images": triples, "annotations": anns}).to_string()
}

fn assert_mvor_scene(rec: &Recording) {
    let names: Vec<&str> = rec.scene.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, CAMERA_NAMES);
    assert_eq!(rec.scene.name, mvor::SCENE_NAME);
    assert!(
        rec.scene
            .cameras
            .iter()
            .all(|c| (c.width, c.height) == (640, 480))
    );
    assert!(rec.frames.iter().all(|f| f.is_complete()));
    // Frames seconds to hours apart: no rate to declare.
    assert_eq!(rec.fps, None);
}

#[test]
fn ground_truth_numbers_frames_in_file_order_and_keeps_person_ids() {
    let tmp = tempfile::tempdir().unwrap();
    let file = write(
        tmp.path(),
        "gt.json",
        &annotation_file(
            2,
            &[
                (0, 1, [10.0, 20.0, 30.0, 40.0], 0),
                (0, 2, [600.0, 400.0, 100.0, 100.0], 0), // past the corner: clipped
                (0, 3, [5.0, 5.0, 10.0, 10.0], -1),      // linked to nobody: dropped
                (1, 3, [-20.0, 0.0, 10.0, 50.0], 4),     // empty once clipped: dropped
                (1, 3, [100.5, 50.0, 20.25, 60.0], 7),
            ],
        ),
    );
    let imp = import_ground_truth(&file).unwrap();
    let rec = &imp.recording;
    assert_mvor_scene(rec);
    assert_eq!(rec.frame_ids(), vec![0, 1]);
    let view = |f: usize, c: usize| rec.frames[f].views[c].as_ref().unwrap();
    assert_eq!(view(0, 0)[0].bbox, [10.0, 20.0, 40.0, 60.0]);
    assert_eq!(view(0, 0)[0].id, Some(0));
    assert_eq!(view(0, 1)[0].bbox, [600.0, 400.0, 640.0, 480.0]);
    assert_eq!(view(0, 1)[0].id, Some(0));
    assert!(view(0, 2).is_empty() && view(1, 0).is_empty() && view(1, 1).is_empty());
    assert_eq!(view(1, 2).len(), 1);
    assert_eq!(view(1, 2)[0].bbox, [100.5, 50.0, 120.75, 110.0]);
    assert_eq!(view(1, 2)[0].id, Some(7));
    assert_eq!((imp.clipped, imp.dropped), (2, 2));
}

#[test]
fn ground_truth_errors_name_what_is_wrong() {
    let tmp = tempfile::tempdir().unwrap();
    let good = annotation_file(1, &[(0, 1, [1.0, 2.0, 3.0, 4.0], 0)]);
    let mut v: Value = serde_json::from_str(&good).unwrap();
    let mut wrong_cam = v.clone();
    wrong_cam["multiview_images"][0]["images"][2]["cam_id"] = json!(4);
    let mut wrong_size = v.clone();
    wrong_size["multiview_images"][0]["images"][0]["width"] = json!(1920);
    let mut twice = v.clone();
    twice["multiview_images"][0]["images"][1]["id"] = json!(1);
    v["annotations"][0]["image_id"] = json!(99);
    for (text, needle) in [
        (wrong_cam.to_string(), "cam_id 4 is outside 1..=3"),
        (
            wrong_size.to_string(),
            "1920x480, MVOR's cameras are 640x480",
        ),
        (twice.to_string(), "image 1 appears twice"),
        (v.to_string(), "image 99 is in no multi-view frame"),
        (
            json!({"multiview_images": [], "annotations": []}).to_string(),
            "no multi-view frame",
        ),
        ("[1, 2]".to_string(), "expected MVOR's annotation file"),
    ] {
        let p = write(tmp.path(), "bad.json", &text);
        let err = import_ground_truth(&p).unwrap_err();
        assert!(matches!(err, Error::Format { .. }), "{err}");
        assert!(err.to_string().contains(needle), "{needle}: {err}");
    }
    assert!(matches!(
        import_ground_truth(&tmp.path().join("nope.json")),
        Err(Error::Io { .. })
    ));
}

#[test]
fn detections_fill_every_frame_of_the_sequence() {
    let tmp = tempfile::tempdir().unwrap();
    let file = write(
        tmp.path(),
        "det.json",
        r#"{"0": [[10, 20, 30, 40, -1, 0]], "5": [[630, 2, 30, 4, -1, 2], [1, 1, 1, 1, -1, 1]]}"#,
    );
    let imp = import_detections(&file).unwrap();
    let rec = &imp.recording;
    assert_mvor_scene(rec);
    assert_eq!(rec.frame_ids(), (0..FRAMES).collect::<Vec<_>>());
    assert_eq!(rec.num_boxes(), 3);
    let f5 = &rec.frames[5];
    assert_eq!(
        f5.views[2].as_ref().unwrap()[0].bbox,
        [630.0, 2.0, 640.0, 6.0]
    );
    assert_eq!(f5.views[1].as_ref().unwrap().len(), 1);
    assert_eq!(rec.frames[0].views[0].as_ref().unwrap()[0].id, None);
    assert_eq!(imp.clipped, 1);

    for (text, needle) in [
        (r#"{"732": []}"#, "frame 732 is past MVOR's 732"),
        (
            r#"{"0": [[1, 2, 3, 4, -1, 3]]}"#,
            "viewNum 3 is outside 0..=2",
        ),
        (r#"{"0": [[1, 2, 3]]}"#, "expected 6 values"),
    ] {
        let p = write(tmp.path(), "bad.json", text);
        let err = import_detections(&p).unwrap_err();
        assert!(matches!(err, Error::Format { .. }), "{err}");
        assert!(err.to_string().contains(needle), "{text}: {err}");
    }
}

/// The subcommands, then `crossview split`: ground truth and detections share one frame
/// sequence, so a part of one holds the same frames as that part of the other.
#[test]
fn import_subcommands_and_split_cut_both_recordings_alike() {
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    let people: Vec<_> = (0..FRAMES)
        .step_by(3)
        .map(|f| (f, 1 + (f % 3) as i64, [50.0, 60.0, 40.0, 120.0], 1))
        .collect();
    write(tmp.path(), "gt.json", &annotation_file(FRAMES, &people));
    write(tmp.path(), "det.json", r#"{"3": [[1, 2, 30, 40, -1, 0]]}"#);
    let run = |args: &[&str]| {
        let out = Command::new(bin)
            .args(args)
            .current_dir(tmp.path())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    let line = run(&[
        "import", "mvor-gt", "--file", "gt.json", "--out", "gt.jsonl",
    ]);
    assert!(
        line.contains("732 frames (0..=731)") && line.contains("244 boxes"),
        "{line}"
    );
    run(&[
        "import",
        "mvor-detections",
        "--file",
        "det.json",
        "--out",
        "det.jsonl",
    ]);
    for part in ["train", "val", "test"] {
        run(&[
            "split", "--part", part, "--data", "gt.jsonl", "--out", "g.jsonl",
        ]);
        run(&[
            "split",
            "--part",
            part,
            "--data",
            "det.jsonl",
            "--out",
            "d.jsonl",
        ]);
        let g = read_recording(tmp.path().join("g.jsonl")).unwrap();
        let d = read_recording(tmp.path().join("d.jsonl")).unwrap();
        assert_eq!(g.frame_ids(), d.frame_ids(), "{part}");
    }
    // SPEC §6 on 732 frames: the last 74 test, the 132 before them validation.
    let g = read_recording(tmp.path().join("g.jsonl")).unwrap();
    assert_eq!(g.frame_ids(), (658..=731).collect::<Vec<_>>());
}

//! WILDTRACK importers and the chronological split on the real data in
//! `<CARGO_MANIFEST_DIR>/../shared/data/wildtrack` or `$CROSSVIEW_WILDTRACK_DIR` (skipped, with a note, when it is absent),
//! plus importer error handling on small synthetic files.

use std::collections::HashSet;
use std::path::PathBuf;
use std::process::Command;

use crossview_core::Error;
use crossview_data::wildtrack::{
    self, CAMERA_NAMES, import_detections, import_ground_truth, part_bounds,
};
use crossview_data::{Part, Recording, read_recording, split_frames};

fn assert_well_formed(rec: &Recording) {
    let names: Vec<&str> = rec.scene.cameras.iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, CAMERA_NAMES);
    assert_eq!(rec.scene.name, "wildtrack");
    assert!(
        rec.scene
            .cameras
            .iter()
            .all(|c| (c.width, c.height) == (1920, 1080))
    );
    for f in &rec.frames {
        assert!(f.is_complete(), "frame {} incomplete", f.frame_id);
        for d in f.views.iter().flatten().flatten() {
            d.validate("det", None).unwrap();
        }
    }
    assert!(rec.frames.windows(2).all(|w| w[0].frame_id < w[1].frame_id));
    // One annotated frame every 0.5 s, declared so that training need not be told.
    assert_eq!(rec.fps, Some(wildtrack::ANNOTATED_FPS));
}

#[test]
fn split_boundaries_on_the_wildtrack_sequence() {
    let ids = wildtrack::sequence_frame_ids();
    assert_eq!(ids.len(), 400);
    assert_eq!((ids[0], ids[399]), (0, 1995));
    let train = split_frames(&ids, Part::Train).unwrap();
    let val = split_frames(&ids, Part::Val).unwrap();
    let test = split_frames(&ids, Part::Test).unwrap();
    assert_eq!((train.len(), val.len(), test.len()), (288, 72, 40));
    assert_eq!(part_bounds(Part::Train), (0, 1435));
    assert_eq!(part_bounds(Part::Val), (1440, 1795));
    assert_eq!(part_bounds(Part::Test), (1800, 1995));
}

#[test]
fn ground_truth_full_folder() {
    let Some(dir) = crossview_testing::wildtrack_dir() else {
        return;
    };
    let imp = import_ground_truth(&dir.join("annotations_positions"), None, None).unwrap();
    let rec = &imp.recording;
    assert_well_formed(rec);
    assert_eq!(rec.frames.len(), 360);
    assert_eq!(rec.frame_ids(), (0..=1795).step_by(5).collect::<Vec<u64>>());
    assert_eq!(rec.num_boxes(), 37548);
    assert_eq!(imp.dropped, 0);
    assert!(
        imp.clipped > 0,
        "WILDTRACK has boxes with negative xmin/ymin"
    );
    let boxes: Vec<_> = rec
        .frames
        .iter()
        .flat_map(|f| f.views.iter().flatten().flatten())
        .collect();
    assert!(
        boxes.iter().all(|d| d.id.is_some()),
        "every GT box has an id"
    );
    let ids: HashSet<u64> = boxes.iter().filter_map(|d| d.id).collect();
    assert!(ids.len() > 100, "{} distinct people", ids.len());
    // First person of frame 0 (personID 122) is in CVLab1 at [1510, 139, 1561, 299].
    let first = &rec.frames[0].views[0].as_ref().unwrap();
    assert!(
        first
            .iter()
            .any(|d| d.id == Some(122) && d.bbox == [1510.0, 139.0, 1561.0, 299.0])
    );
}

#[test]
fn ground_truth_validation_split_and_bounds() {
    let Some(dir) = crossview_testing::wildtrack_dir() else {
        return;
    };
    let gt = dir.join("annotations_positions");
    let (lo, hi) = part_bounds(Part::Val);
    let val = import_ground_truth(&gt, Some(lo), Some(hi))
        .unwrap()
        .recording;
    assert_well_formed(&val);
    assert_eq!(val.frames.len(), 72);
    assert_eq!(
        (val.frames[0].frame_id, val.frames[71].frame_id),
        (1440, 1795)
    );
    let (lo, hi) = part_bounds(Part::Train);
    let train = import_ground_truth(&gt, Some(lo), Some(hi))
        .unwrap()
        .recording;
    assert_eq!(train.frames.len(), 288);
    assert_eq!(train.num_boxes() + val.num_boxes(), 37548);
    // The test frames are not in the public folder: a clear error, not an empty recording.
    let (lo, hi) = part_bounds(Part::Test);
    let err = import_ground_truth(&gt, Some(lo), Some(hi)).unwrap_err();
    assert!(
        err.to_string()
            .contains("no annotated frame in 1800..=1995"),
        "{err}"
    );
}

#[test]
fn detections_train_file() {
    let Some(dir) = crossview_testing::wildtrack_dir() else {
        return;
    };
    let imp = import_detections(&dir.join("detections_train.json"), 5).unwrap();
    let rec = &imp.recording;
    assert_well_formed(rec);
    assert_eq!(rec.frames.len(), 288);
    assert_eq!(rec.frame_ids(), (0..=1435).step_by(5).collect::<Vec<u64>>());
    assert_eq!(rec.num_boxes(), 71019);
    assert!(
        rec.frames
            .iter()
            .flat_map(|f| f.views.iter().flatten().flatten())
            .all(|d| d.id.is_none()),
        "detections carry no ids (-1)"
    );
    // Stride changes the frame ids only.
    let imp1 = import_detections(&dir.join("detections_train.json"), 1).unwrap();
    assert_eq!(imp1.recording.frames.last().unwrap().frame_id, 287);
}

#[test]
fn cli_import_and_split_round_trip() {
    let Some(dir) = crossview_testing::wildtrack_dir() else {
        return;
    };
    let bin = env!("CARGO_BIN_EXE_crossview");
    let tmp = tempfile::tempdir().unwrap();
    let all = tmp.path().join("gt.jsonl");
    let val = tmp.path().join("val.jsonl");
    let out = Command::new(bin)
        .args(["import", "wildtrack-gt", "--dir"])
        .arg(dir.join("annotations_positions"))
        .arg("--out")
        .arg(&all)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let line = String::from_utf8_lossy(&out.stdout);
    assert!(
        line.contains("360 frames") && line.contains("37548 boxes") && line.contains("7 cameras"),
        "{line}"
    );
    let out = Command::new(bin)
        .args(["split", "--part", "val", "--data"])
        .arg(&all)
        .arg("--out")
        .arg(&val)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let split = read_recording(&val).unwrap();
    let direct = import_ground_truth(&dir.join("annotations_positions"), Some(1440), Some(1795))
        .unwrap()
        .recording;
    assert_eq!(
        split, direct,
        "split of the whole GT equals importing --split val"
    );
}

fn write(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
    let p = dir.path().join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn ground_truth_clipping_invisible_views_and_degenerate_boxes() {
    let tmp = tempfile::tempdir().unwrap();
    write(
        &tmp,
        "00000010.json",
        r#"[{"personID": 4, "positionID": 1, "views": [
            {"viewNum": 0, "xmin": -1, "ymin": -1, "xmax": -1, "ymax": -1},
            {"viewNum": 1, "xmin": -7, "ymin": -1, "xmax": 30, "ymax": 90},
            {"viewNum": 2, "xmin": 5, "ymin": 5, "xmax": 5, "ymax": 50}]}]"#,
    );
    write(&tmp, "00000005.json", "[]");
    write(&tmp, "notes.txt", "ignored");
    let imp = import_ground_truth(tmp.path(), None, None).unwrap();
    let rec = &imp.recording;
    assert_eq!(rec.frame_ids(), vec![5, 10]);
    assert!(rec.frames[0].is_complete() && rec.frames[0].num_boxes() == 0);
    let f = &rec.frames[1];
    assert_eq!(f.views[0], Some(vec![]));
    assert_eq!(f.views[1].as_ref().unwrap()[0].bbox, [0.0, 0.0, 30.0, 90.0]);
    assert_eq!(f.views[1].as_ref().unwrap()[0].id, Some(4));
    assert_eq!(f.views[2], Some(vec![]), "degenerate box dropped");
    assert_eq!((imp.clipped, imp.dropped), (1, 1));
    assert_eq!(
        import_ground_truth(tmp.path(), Some(6), None)
            .unwrap()
            .recording
            .frame_ids(),
        vec![10]
    );
}

#[test]
fn ground_truth_errors_name_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = write(
        &tmp,
        "00000000.json",
        r#"[{"personID": 1, "views": [{"viewNum": 9, "xmin": 1, "ymin": 1, "xmax": 5, "ymax": 5}]}]"#,
    );
    let err = import_ground_truth(tmp.path(), None, None).unwrap_err();
    assert!(
        matches!(&err, Error::Format { source_name, .. } if *source_name == bad.display().to_string()),
        "{err}"
    );
    assert!(err.to_string().contains("viewNum 9"), "{err}");
    std::fs::write(&bad, "[{\"personID\": 1,\n \"views\": oops}]").unwrap();
    match import_ground_truth(tmp.path(), None, None).unwrap_err() {
        Error::Format { line, message, .. } => {
            assert_eq!(line, 2);
            assert!(message.contains("malformed annotation file"), "{message}");
        }
        other => panic!("{other:?}"),
    }
    let empty = tempfile::tempdir().unwrap();
    assert!(
        import_ground_truth(empty.path(), None, None)
            .unwrap_err()
            .to_string()
            .contains("no annotation files")
    );
    assert!(matches!(
        import_ground_truth(&tmp.path().join("nope"), None, None),
        Err(Error::Io { .. })
    ));
}

#[test]
fn detections_conversion_and_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let ok = write(
        &tmp,
        "det.json",
        r#"{"0": [[10, 20, 30, 40, -1, 0], [-2, 5, 10, 10, 7, 6]], "2": []}"#,
    );
    let imp = import_detections(&ok, 5).unwrap();
    let rec = &imp.recording;
    assert_eq!(rec.frame_ids(), vec![0, 10]);
    let f0 = &rec.frames[0];
    assert_eq!(
        f0.views[0].as_ref().unwrap()[0].bbox,
        [10.0, 20.0, 40.0, 60.0]
    );
    assert_eq!(f0.views[0].as_ref().unwrap()[0].id, None);
    assert_eq!(f0.views[6].as_ref().unwrap()[0].bbox, [0.0, 5.0, 8.0, 15.0]);
    assert_eq!(f0.views[6].as_ref().unwrap()[0].id, Some(7));
    assert!(rec.frames.iter().all(|f| f.is_complete()));
    assert_eq!(imp.clipped, 1);

    for (text, needle) in [
        (r#"{"0": [[1, 2, 3]]}"#, "expected 6 values"),
        (r#"{"x": []}"#, "not a frame index"),
        (r#"{"0": [[1, 2, 3, 4, -1, 7]]}"#, "viewNum 7"),
        (r#"{"0": [[1, 2, 3, 4, -3, 1]]}"#, "id -3"),
        (r#"[1, 2]"#, "expected {"),
    ] {
        let p = write(&tmp, "bad.json", text);
        let err = import_detections(&p, 5).unwrap_err();
        assert!(matches!(err, Error::Format { .. }), "{err}");
        assert!(err.to_string().contains(needle), "{text}: {err}");
    }
    assert!(matches!(
        import_detections(&ok, 0),
        Err(Error::InvalidArgument { .. })
    ));
}

//! `crossview simulate --move` and `crossview fit-check` as a user runs them: the real binary,
//! the real ONNX Runtime, the shipped `models/demo.onnx`. A simulated `square4` recording in
//! which one camera zooms in at 20 s: fit-check names that camera and only it once the zoom is
//! in its newest frames; the same recording without the move raises nothing; bad arguments
//! are refused with a message.
use std::process::Command;

use crossview_testing::{repo_root, run_crossview};
use serde_json::Value;

const BIN: &str = env!("CARGO_BIN_EXE_crossview");

fn simulate(dir: &std::path::Path, name: &str, extra: &[&str]) -> String {
    simulate_frames(dir, name, "400", extra)
}

fn simulate_frames(dir: &std::path::Path, name: &str, frames: &str, extra: &[&str]) -> String {
    let rec = dir.join(name);
    let rec = rec.to_str().unwrap().to_string();
    let mut args = vec![
        "simulate", "--preset", "square4", "--frames", frames, "--seed", "6", "--out", &rec,
    ];
    args.extend_from_slice(extra);
    run_crossview(BIN, &args, &[]);
    rec
}

/// `crossview fit-check` with the shipped demo model on `rec`, `extra` arguments after; its
/// standard output.
fn fit_check(rec: &str, extra: &[&str]) -> String {
    let model = repo_root().join("models/demo.onnx");
    let mut args = vec![
        "fit-check",
        "--model",
        model.to_str().unwrap(),
        "--data",
        rec,
    ];
    args.extend_from_slice(extra);
    run_crossview(BIN, &args, &[("CROSSVIEW_WORKERS", "2")])
}

/// Every look of `fit-check --json`: per look, the newest frame id and each camera's state.
fn looks(rec: &str) -> Vec<(i64, Vec<String>)> {
    let out = fit_check(rec, &["--window", "200", "--every", "20", "--json"]);
    out.lines()
        .map(|l| {
            let look: Value = serde_json::from_str(l).unwrap();
            let states = look["cameras"]
                .as_array()
                .unwrap()
                .iter()
                .map(|c| c["state"].as_str().unwrap().to_string())
                .collect();
            (look["as_of_frame"].as_i64().unwrap(), states)
        })
        .collect()
}

#[test]
fn fit_check_names_the_camera_that_zoomed_and_only_it() {
    let dir = tempfile::tempdir().unwrap();
    let still = simulate(dir.path(), "still.jsonl", &[]);
    let zoomed = simulate(dir.path(), "zoomed.jsonl", &["--move", "cam2@20:zoom=1.2"]);
    let quiet = looks(&still);
    assert!(quiet.len() >= 10, "{quiet:?}");
    for (frame, states) in &quiet {
        assert!(
            states.iter().all(|s| s != "does_not_fit"),
            "frame {frame}: {states:?}"
        );
    }
    let moved = looks(&zoomed);
    for (frame, states) in &moved {
        if *frame < 200 {
            assert!(
                states.iter().all(|s| s == "fits"),
                "frame {frame}: {states:?}"
            );
        }
    }
    let (frame, last) = moved.last().unwrap();
    assert_eq!(*frame, 399);
    assert_eq!(last, &["fits", "fits", "does_not_fit", "fits"], "{moved:?}");
}

#[test]
fn the_table_marks_a_camera_that_does_not_fit() {
    let dir = tempfile::tempdir().unwrap();
    let zoomed = simulate(dir.path(), "zoomed.jsonl", &["--move", "cam0@20:pan=-5%"]);
    let table = fit_check(&zoomed, &[]);
    let last = table.lines().last().unwrap();
    assert!(last.trim_start().starts_with("399"), "{table}");
    let cells: Vec<&str> = last.split_whitespace().collect();
    // frame, seconds, then cam0's score followed by its mark.
    assert_eq!(cells[3], "!", "{table}");
    assert_eq!(cells.iter().filter(|c| **c == "!").count(), 1, "{table}");
}

#[test]
fn bad_moves_and_windows_are_refused_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.jsonl");
    for (args, want) in [
        (vec!["--move", "nobody@3:pan=2"], "no camera 'nobody'"),
        (vec!["--move", "cam1@3:pan=90"], "within ±60"),
        (vec!["--move", "cam1@-1:zoom=2"], "non-negative"),
        (vec!["--move", "cam1@3:roll=2"], "CAMERA@SECONDS"),
        (vec!["--move", "cam1:pan=2"], "CAMERA@SECONDS"),
        (vec!["--move", "cam1@3:zoom=NaN"], "zoom"),
    ] {
        let o = Command::new(BIN)
            .args(["simulate", "--preset", "square4", "--out"])
            .arg(&out)
            .args(&args)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && err.contains(want), "{args:?}: {err}");
    }
    let rec = simulate_frames(dir.path(), "r.jsonl", "50", &[]);
    let model = repo_root().join("models/demo.onnx");
    let o = Command::new(BIN)
        .args(["fit-check", "--model"])
        .arg(&model)
        .args(["--data", &rec, "--window", "50", "--recent", "60"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--recent"), "{err}");
}

//! `crossview train --population K`: K members trained side by side, the worse ones dropped
//! by the label-free key; the model file records every member and which one won; the best
//! finalists can be exported together (`--ensemble`) and each on its own (`--members-out`);
//! without held-out frames to rank them, the flag is refused; the ensemble's student is written
//! instead when asked, or when it scores within the tolerance of the ensemble (`--export auto`).
use crossview_core::Encoder;
use crossview_data::recording::write_recording;
use crossview_model::{OnnxEncoder, read_ensemble, read_weights};

use crate::train::{assert_none_dropped, population, recording, train, train_ok};

const SMALL: [&str; 14] = [
    "--width",
    "16",
    "--fourier-features",
    "4",
    "--camera-dim",
    "4",
    "--self-train-epochs",
    "0",
    "--epochs",
    "8",
    "--val-every",
    "2",
    "--seed",
    "2",
];

#[test]
fn a_population_records_its_members_and_the_winner() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 40, false)).unwrap();
    let out = dir.path().join("m.onnx");
    // One thread: halving goes down to one member (it keeps one per thread).
    let args = [
        "--population",
        "3",
        "--threads",
        "1",
        "--halve-at",
        "0.25,0.5",
        "--ensemble",
        "1",
    ];
    let st = train_ok(&data, &out, &[&args[..], &SMALL[..]].concat());
    let stdout = String::from_utf8_lossy(&st.stdout);
    assert!(stdout.contains("population: member"), "{stdout}");
    let (_, meta) = read_weights(&out).unwrap();
    let pop = population(&meta);
    let members = pop["members"].as_array().unwrap();
    assert_eq!(members.len(), 3);
    assert_eq!(members[0]["seed"], 2);
    // 3 -> 2 at epoch 2 (25 %), 2 -> 1 at epoch 4 (50 %).
    let dropped: Vec<u64> = members
        .iter()
        .filter_map(|m| m["dropped_at"].as_u64())
        .collect();
    assert_eq!(dropped.iter().filter(|&&e| e == 2).count(), 1, "{pop}");
    assert_eq!(dropped.iter().filter(|&&e| e == 4).count(), 1, "{pop}");
    let winner = pop["winner"].as_u64().unwrap() as usize;
    assert!(members[winner]["dropped_at"].is_null());
    assert!(!dir.path().join("m.checkpoint").exists());
}

#[test]
fn a_population_without_held_out_frames_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 20, false)).unwrap();
    let out = dir.path().join("m.onnx");
    let st = train(&data, &out, &["--population", "2", "--holdout", "0"]);
    assert!(!st.status.success());
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(err.contains("--holdout"), "{err}");
}

#[test]
fn the_best_finalists_are_exported_together_and_each_on_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 40, false)).unwrap();
    let out = dir.path().join("m.onnx");
    let members_out = dir.path().join("members");
    let args = [
        "--population",
        "3",
        "--threads",
        "2",
        "--halve-at",
        "none",
        "--ensemble",
        "2",
        "--export",
        "ensemble",
        "--members-out",
        members_out.to_str().unwrap(),
    ];
    let st = train_ok(&data, &out, &[&args[..], &SMALL[..]].concat());
    let stdout = String::from_utf8_lossy(&st.stdout);
    assert!(stdout.contains("together (width 32)"), "{stdout}");
    let (ensemble, meta) = read_ensemble(&out).unwrap();
    assert_eq!(ensemble.members().len(), 2);
    assert!(meta.calibration.is_some(), "the ensemble is calibrated");
    let export = export_record(&meta);
    assert_eq!(export["exported"], "ensemble");
    assert!(export["student"].is_null(), "no student trained: {export}");
    let pop = population(&meta);
    // `--halve-at none`: every member trains to the end.
    assert_none_dropped(&pop);
    let chosen = pop["ensemble"].as_array().unwrap();
    assert_eq!(chosen.len(), 2, "{pop}");
    assert_eq!(chosen[0]["member"], pop["winner"], "the winner comes first");
    assert!(
        chosen[0]["key"].as_f64() >= chosen[1]["key"].as_f64(),
        "{pop}"
    );
    // Each finalist on its own, and the ensemble's parts are those files' encoders.
    for (k, c) in chosen.iter().enumerate() {
        let file = members_out.join(format!("member-{}.onnx", c["member"]));
        let (w, m) = read_weights(&file).unwrap();
        assert_eq!(&w, &ensemble.members()[k]);
        assert!(m.extra["crossview.member"].contains("\"key\""));
    }
    assert_eq!(std::fs::read_dir(&members_out).unwrap().count(), 3);
    let mut enc = OnnxEncoder::load(&out).unwrap();
    assert_eq!(
        enc.embed(&[[0.1, 0.2, 0.3, 0.5]], &[1]).unwrap().dim(),
        (1, 32)
    );
}

#[test]
fn bad_halving_points_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 20, false)).unwrap();
    let out = dir.path().join("m.onnx");
    for bad in ["1.5", "0", "half", ""] {
        let st = train(&data, &out, &["--halve-at", bad]);
        assert!(!st.status.success(), "{bad}");
        let err = String::from_utf8_lossy(&st.stderr);
        assert!(err.contains("--halve-at"), "{bad}: {err}");
    }
}

#[test]
fn an_ensemble_initialises_the_members_of_the_next_run() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 40, false)).unwrap();
    let first = dir.path().join("e.onnx");
    let pop = ["--population", "2", "--threads", "2", "--halve-at", "none"];
    train_ok(
        &data,
        &first,
        &[&pop[..], &["--ensemble", "2"], &SMALL[..]].concat(),
    );
    let (start, _) = read_ensemble(&first).unwrap();
    // With a learning rate of 1e-30 and no moving average nothing moves: each member ends
    // where the ensemble's member it started from was.
    let again = dir.path().join("again.onnx");
    let frozen = [
        "--ensemble",
        "2",
        "--lr",
        "1e-30",
        "--ema-decay",
        "0",
        "--init",
        first.to_str().unwrap(),
    ];
    train_ok(&data, &again, &[&pop[..], &frozen[..], &SMALL[..]].concat());
    let (end, _) = read_ensemble(&again).unwrap();
    assert_eq!(end.members().len(), 2);
    for m in end.members() {
        assert!(
            start.members().contains(m),
            "a member did not start from the ensemble"
        );
    }
    assert_ne!(end.members()[0], end.members()[1]);
    // A single run starts from the ensemble's first member.
    let single = dir.path().join("single.onnx");
    let one = [
        "--population",
        "1",
        "--lr",
        "1e-30",
        "--ema-decay",
        "0",
        "--init",
        first.to_str().unwrap(),
    ];
    train_ok(&data, &single, &[&one[..], &SMALL[..]].concat());
    let (w, _) = read_weights(&single).unwrap();
    assert_eq!(&w, &start.members()[0]);
}

/// What the model file says about the ensemble-or-student choice (`crossview.export`).
fn export_record(meta: &crossview_model::ModelMetadata) -> serde_json::Value {
    serde_json::from_str(&meta.extra["crossview.export"]).unwrap()
}

#[test]
fn the_student_is_written_when_asked_or_when_it_scores_within_the_tolerance() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 40, false)).unwrap();
    let base = ["--population", "2", "--threads", "2", "--ensemble", "2"];
    let run = |export: &str, out: &std::path::Path| {
        let args = [
            &base[..],
            &["--export", export, "--student-epochs", "10"],
            &SMALL[..],
        ];
        train_ok(&data, out, &args.concat())
    };
    // Asked for: one encoder one and a half times the members' width (the default shape), with
    // both label-free scores recorded.
    let out = dir.path().join("student.onnx");
    let st = run("student", &out);
    assert!(String::from_utf8_lossy(&st.stdout).contains("exported the student"));
    let (model, meta) = read_ensemble(&out).unwrap();
    assert_eq!((model.members().len(), model.width()), (1, 24));
    assert!(meta.calibration.is_some(), "the student is calibrated");
    let export = export_record(&meta);
    assert_eq!(export["exported"], "student", "{export}");
    assert_eq!(export["student"]["width"], 24);
    for side in ["ensemble_scores", "student_scores"] {
        let acc = export[side]["expected_acc"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&acc), "{export}");
    }
    // Auto: whichever it wrote agrees with the scores it recorded.
    let out = dir.path().join("auto.onnx");
    run("auto", &out);
    let (model, meta) = read_ensemble(&out).unwrap();
    let export = export_record(&meta);
    let score = |side: &str, what: &str| export[side][what].as_f64().unwrap();
    let within = ["cycle", "expected_acc"]
        .iter()
        .all(|w| score("student_scores", w) >= score("ensemble_scores", w) - 0.003);
    let want = if within {
        ("student", 24)
    } else {
        ("ensemble", 32)
    };
    assert_eq!(export["exported"], want.0, "{export}");
    assert_eq!(model.width(), want.1);
    // A bad choice is refused before anything trains.
    let st = crate::train::train(&data, &dir.path().join("x.onnx"), &["--export", "both"]);
    assert!(!st.status.success());
    assert!(String::from_utf8_lossy(&st.stderr).contains("--export"));
}

//! Ctrl-C during `crossview train`: the run ends after its epoch in progress, exits 0 with the
//! best model so far written, and leaves a checkpoint (beside the output when no
//! `--checkpoint-dir` was given) that `--resume` continues from.
use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crossview_data::recording::write_recording;
use crossview_model::read_weights;
use crossview_testing::signal;

use crate::train::{recording, train_ok};

const SMALL: [&str; 12] = [
    "--width",
    "16",
    "--fourier-features",
    "4",
    "--camera-dim",
    "4",
    "--self-train-epochs",
    "0",
    "--holdout",
    "0",
    "--seed",
    "5",
];

#[test]
fn ctrl_c_keeps_the_best_model_so_far_and_a_checkpoint_that_resumes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 30, false)).unwrap();
    let out = dir.path().join("m.onnx");
    // Far more epochs than the test waits for: only Ctrl-C ends this run.
    let mut child = Command::new(env!("CARGO_BIN_EXE_crossview"))
        .args(["train", "--quiet", "--epochs", "1000000"])
        .args(SMALL)
        .arg("--data")
        .arg(&data)
        .arg("--out")
        .arg(&out)
        .env("RUST_LOG", "info")
        .stderr(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    // Drain stderr on a thread (a full pipe would block the run's logging); the "training"
    // log line comes after the Ctrl-C handler is installed and before the first epoch.
    let stderr = BufReader::new(child.stderr.take().unwrap());
    let (tx, rx) = std::sync::mpsc::channel::<String>();
    let reader = std::thread::spawn(move || {
        for line in stderr.lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let mut seen = String::new();
    while !seen.contains("training") {
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(line) => seen.push_str(&(line + "\n")),
            Err(e) => panic!("no start-up log ({e}): {seen}"),
        }
    }
    std::thread::sleep(Duration::from_millis(500));
    signal(&child, "INT");
    // Bounded: a run that ignores Ctrl-C fails the test instead of hanging it.
    let deadline = Instant::now() + Duration::from_secs(60);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            child.kill().unwrap();
            panic!("train still running 60 s after Ctrl-C");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    reader.join().unwrap();
    let rest: String = rx.try_iter().map(|l| l + "\n").collect();
    assert!(status.success(), "exit {status:?}: {seen}{rest}");
    assert!(rest.contains("--resume"), "{rest}");

    // The best model so far is written, and the default checkpoint beside it.
    let (_, meta) = read_weights(&out).unwrap();
    let done: usize = meta.extra["crossview.epochs_run"].parse().unwrap();
    assert!((1..1_000_000).contains(&done), "{done} epochs");
    let ckpt = dir.path().join("m.checkpoint");
    let state: serde_json::Value =
        serde_json::from_slice(&std::fs::read(ckpt.join("state.json")).unwrap()).unwrap();
    assert_eq!(state["epoch"].as_u64(), Some(done as u64));

    // Resuming continues from there to the end of a (now shorter) run.
    let total = (done + 2).to_string();
    let resume = [
        "--epochs",
        &total,
        "--checkpoint-dir",
        ckpt.to_str().unwrap(),
        "--resume",
    ];
    train_ok(&data, &out, &[&resume[..], &SMALL[..]].concat());
    let (_, meta) = read_weights(&out).unwrap();
    assert_eq!(meta.extra["crossview.epochs_run"], total);
    let hist: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("m.history.json")).unwrap()).unwrap();
    assert_eq!(hist.as_array().unwrap().len(), done + 2);
}

/// A run that completes leaves no checkpoint behind unless one was asked for.
#[test]
fn a_completed_run_removes_its_default_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("train.jsonl");
    write_recording(&data, &recording(3, 20, false)).unwrap();
    let out = dir.path().join("m.onnx");
    train_ok(&data, &out, &[&["--epochs", "2"][..], &SMALL[..]].concat());
    assert!(out.is_file());
    assert!(!dir.path().join("m.checkpoint").exists());
}

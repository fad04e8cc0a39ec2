//! `crossview sync-check` as a user runs it: the real binary, the real ONNX Runtime, the
//! shipped `models/demo.onnx` and a simulated `square4` recording. In sync, every camera is
//! at 0; with one camera's ids shifted (`--simulate-lag`), that camera and only it is found at
//! the shift; a recording whose header declares the shift (`@+N`) is back in sync; an ensemble
//! is estimated by its leading member alone (as the server's live watch); bad arguments are
//! refused with a message. A recording of capture times instead of frame ids reads into the
//! same frames (`eval` scores it line for line as its frame-id twin) and has its cameras'
//! clocks read in milliseconds.
use std::process::Command;

use crossview_testing::{demo_with_untrained_member, repo_root, run_crossview};
use serde_json::Value;

const BIN: &str = env!("CARGO_BIN_EXE_crossview");

fn simulate(dir: &std::path::Path) -> String {
    let rec = dir.join("sim.jsonl");
    let rec = rec.to_str().unwrap().to_string();
    run_crossview(
        BIN,
        &[
            "simulate", "--preset", "square4", "--frames", "300", "--seed", "4", "--out", &rec,
        ],
        &[],
    );
    rec
}

fn check(rec: &str, extra: &[&str]) -> Value {
    check_with(&repo_root().join("models/demo.onnx"), rec, extra)
}

fn check_with(model: &std::path::Path, rec: &str, extra: &[&str]) -> Value {
    let mut args = vec![
        "sync-check",
        "--model",
        model.to_str().unwrap(),
        "--data",
        rec,
        "--json",
    ];
    args.extend_from_slice(extra);
    serde_json::from_str(&run_crossview(BIN, &args, &[("CROSSVIEW_WORKERS", "2")])).unwrap()
}

fn offsets(report: &Value) -> Vec<Option<i64>> {
    report["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["frames"].as_i64())
        .collect()
}

#[test]
fn sync_check_finds_a_lagging_camera_and_its_declared_offset_removes_it() {
    let dir = tempfile::tempdir().unwrap();
    let rec = simulate(dir.path());
    let report = check(&rec, &[]);
    assert_eq!(offsets(&report), vec![Some(0); 4], "{report}");
    assert_eq!(report["step"], 1);
    // The simulator declares its rate in the header: offsets come in seconds unasked.
    assert_eq!(report["fps"], 10.0, "{report}");
    assert_eq!(report["cameras"][1]["seconds"], 0.0, "{report}");

    let report = check(&rec, &["--simulate-lag", "cam1:-3", "--fps", "10"]);
    assert_eq!(
        offsets(&report),
        vec![Some(0), Some(-3), Some(0), Some(0)],
        "{report}"
    );
    let cam1 = &report["cameras"][1];
    assert_eq!(cam1["name"], "cam1");
    assert!(
        (cam1["seconds"].as_f64().unwrap() + 0.3).abs() < 0.05,
        "{cam1}"
    );
    assert!(cam1["confidence"].as_f64().unwrap() > 0.0, "{cam1}");
    assert!(report["pairs"].as_array().unwrap().len() == 6, "{report}");

    // The same lag written into the recording, then declared in its header: in sync again.
    let text = std::fs::read_to_string(&rec).unwrap();
    let mut lines = text.lines();
    let mut header: Value = serde_json::from_str(lines.next().unwrap()).unwrap();
    let mut out = Vec::new();
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let mut batch: Value = serde_json::from_str(line).unwrap();
        if batch["camera"] == "cam1" {
            let f = batch["frame_id"].as_u64().unwrap();
            batch["frame_id"] = (f + 5).into();
        }
        out.push(batch.to_string());
    }
    let lagged = dir.path().join("lagged.jsonl");
    let write = |header: &Value, path: &std::path::Path| {
        std::fs::write(path, format!("{header}\n{}\n", out.join("\n"))).unwrap();
    };
    write(&header, &lagged);
    let report = check(lagged.to_str().unwrap(), &[]);
    assert_eq!(
        offsets(&report),
        vec![Some(0), Some(5), Some(0), Some(0)],
        "{report}"
    );
    header["scene"]["cameras"][1]["offset"] = 5.into();
    let declared = dir.path().join("declared.jsonl");
    write(&header, &declared);
    let report = check(declared.to_str().unwrap(), &[]);
    assert_eq!(offsets(&report), vec![Some(0); 4], "{report}");

    // A table for people.
    let model = repo_root().join("models/demo.onnx");
    let table = run_crossview(
        BIN,
        &[
            "sync-check",
            "--model",
            model.to_str().unwrap(),
            "--data",
            &rec,
            "--simulate-lag",
            "cam2:2",
        ],
        &[],
    );
    assert!(table.contains("cam2") && table.contains("+2"), "{table}");
}

#[test]
fn sync_check_refuses_bad_arguments_with_a_message() {
    let dir = tempfile::tempdir().unwrap();
    let rec = simulate(dir.path());
    let model = repo_root().join("models/demo.onnx");
    let model = model.to_str().unwrap();
    for (extra, says) in [
        (vec!["--simulate-lag", "nosuch:2"], "nosuch"),
        (vec!["--simulate-lag", "cam1:x"], "whole number"),
        (vec!["--max-offset", "0"], "--max-offset"),
        (vec!["--max-offset", "100000"], "--max-offset"),
        (vec!["--fps", "NaN"], "--fps"),
        (vec!["--reference", "nosuch"], "nosuch"),
    ] {
        let mut args = vec!["sync-check", "--model", model, "--data", &rec];
        args.extend_from_slice(&extra);
        let out = Command::new(BIN).args(&args).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{extra:?} was accepted");
        assert!(stderr.contains(says), "{extra:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{extra:?}: {stderr}");
    }
}

#[test]
fn an_ensemble_is_estimated_by_its_leading_member_alone() {
    // The estimate is demo's own (the ensemble's leading block is demo's embedding over √2,
    // and offsets do not depend on the scale).
    let dir = tempfile::tempdir().unwrap();
    let rec = simulate(dir.path());
    let demo = repo_root().join("models/demo.onnx");
    let wide = demo_with_untrained_member(dir.path(), "wide");
    let lag = ["--simulate-lag", "cam1:-3"];
    let (alone, both) = (check_with(&demo, &rec, &lag), check_with(&wide, &rec, &lag));
    assert_eq!(
        offsets(&both),
        vec![Some(0), Some(-3), Some(0), Some(0)],
        "{both}"
    );
    for (a, b) in alone["cameras"]
        .as_array()
        .unwrap()
        .iter()
        .zip(both["cameras"].as_array().unwrap())
    {
        for key in ["refined", "confidence"] {
            let (x, y) = (a[key].as_f64().unwrap(), b[key].as_f64().unwrap());
            assert!((x - y).abs() < 1e-3, "{key}: {a} vs {b}");
        }
    }
}

/// The clocks of [`timed_copy`]'s cameras, seconds: cam1 230 ms ahead, cam2 120 ms behind.
const CLOCK: [f64; 4] = [0.0, 0.230, -0.120, 0.0];

/// `rec` as its cameras' capture times would stamp it (10 frames/s, [`CLOCK`], every capture
/// ±20 ms), no frame ids; with `declare`, the header declares each camera's offset in ms.
fn timed_copy(rec: &str, out: &std::path::Path, declare: bool) -> String {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(9);
    let text = std::fs::read_to_string(rec).unwrap();
    let mut lines = String::new();
    for (i, line) in text.lines().enumerate() {
        let mut v: Value = serde_json::from_str(line).unwrap();
        if i == 0 && declare {
            for (c, cam) in v["scene"]["cameras"]
                .as_array_mut()
                .unwrap()
                .iter_mut()
                .enumerate()
            {
                cam["offset_ms"] = serde_json::json!((CLOCK[c] * 1e3).round() as i64);
            }
        } else if i > 0 {
            let k = v["frame_id"].as_u64().unwrap() as f64;
            let c: usize = v["camera"].as_str().unwrap()[3..].parse().unwrap();
            let t = 1_796_515_200.0 + k / 10.0 + CLOCK[c] + rng.random_range(-0.02..0.02);
            let o = v.as_object_mut().unwrap();
            o.remove("frame_id");
            o.insert("time".into(), serde_json::json!(t));
        }
        lines.push_str(&v.to_string());
        lines.push('\n');
    }
    std::fs::write(out, lines).unwrap();
    out.to_str().unwrap().to_string()
}

#[test]
fn a_recording_of_capture_times_evaluates_as_its_frame_id_twin() {
    let dir = tempfile::tempdir().unwrap();
    // Ground-truth ids on every box (no false detections): what `eval` scores.
    let rec = dir.path().join("clean.jsonl").to_str().unwrap().to_string();
    run_crossview(
        BIN,
        &[
            "simulate", "--preset", "square4", "--frames", "300", "--seed", "4", "--clean",
            "--out", &rec,
        ],
        &[],
    );
    let timed = timed_copy(&rec, &dir.path().join("times.jsonl"), true);
    let demo = repo_root().join("models/demo.onnx");
    let eval = |data: &str| {
        run_crossview(
            BIN,
            &["eval", "--model", demo.to_str().unwrap(), "--data", data],
            &[("CROSSVIEW_WORKERS", "2")],
        )
    };
    // The same frames (ticks for ids), the same boxes: the same table, line for line.
    let (by_time, by_id) = (eval(&timed), eval(&rec));
    assert!(by_id.contains("identities t="), "{by_id}");
    assert_eq!(by_time, by_id);
}

#[test]
fn a_recording_of_capture_times_is_grouped_by_them_and_its_clocks_read_in_milliseconds() {
    let dir = tempfile::tempdir().unwrap();
    let rec = simulate(dir.path());
    let timed = timed_copy(&rec, &dir.path().join("times.jsonl"), false);
    let clock = CLOCK;
    let report = check(&timed, &[]);
    let reference = report["reference"].as_str().unwrap();
    let at = |name: &str| 1e3 * clock[name[3..].parse::<usize>().unwrap()];
    for c in report["cameras"].as_array().unwrap() {
        let name = c["name"].as_str().unwrap();
        let k = &c["capture"];
        let got = k["offset_ms"]
            .as_f64()
            .unwrap_or_else(|| panic!("{report}"));
        let want = at(name) - at(reference);
        assert!(
            (got - want).abs() < 15.0,
            "{name}: {got} ms, not {want}: {report}"
        );
        // Uniform ±20 ms: a standard deviation of 11.5 ms.
        let jitter = k["jitter_ms"].as_f64().unwrap();
        assert!((jitter - 11.5).abs() < 3.0, "{name}: jitter {jitter}");
    }
}

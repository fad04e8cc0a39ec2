//! `crossview serve` fails closed: a key source that yields no key (a blank `--api-key`, an
//! empty or `,` `CROSSVIEW_API_KEYS`, a key file of comments only) stops the start instead of
//! serving with authentication off, and a server without keys listens beyond loopback only
//! when told so explicitly.

use std::process::{Command, Stdio};
use std::time::Duration;

use crossview_testing::*;

/// Runs `crossview serve` with `args` and `env` on a free loopback port; returns its exit
/// status and stderr when it stops on its own within the bound, or `None` when it is still
/// running (then it is killed).
fn serve_exits(args: &[&str], env: &[(&str, &str)]) -> Option<(bool, String)> {
    let mut child = ChildGuard(
        Command::new(env!("CARGO_BIN_EXE_crossview"))
            .arg("serve")
            .args(args)
            .env_remove("CROSSVIEW_API_KEYS")
            .envs(env.iter().copied())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start crossview serve"),
    );
    // A refusal comes at once; still running after this long means it serves.
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while std::time::Instant::now() < deadline {
        if let Some(status) = child.try_wait().unwrap() {
            let mut err = String::new();
            use std::io::Read;
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            return Some((status.success(), err));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    None
}

/// Extra flags and environment of one start-up that must be refused.
type Case<'a> = (Vec<&'a str>, Vec<(&'a str, &'a str)>);

#[test]
fn a_key_source_that_yields_no_key_stops_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let model = export_model(dir.path(), "lab");
    let model = model.to_str().unwrap();
    let comments = dir.path().join("keys.txt");
    std::fs::write(
        &comments,
        "# rotated out 2026-11-30\n\n   \n# old: s3cret\n",
    )
    .unwrap();
    let comments = comments.to_str().unwrap();
    let base = ["--model", model, "--listen", "127.0.0.1:0"];
    let cases: Vec<Case> = vec![
        (vec!["--api-key", " "], vec![]),
        (vec!["--api-key", ""], vec![]),
        (vec!["--api-key", "good", "--api-key", " "], vec![]),
        (vec![], vec![("CROSSVIEW_API_KEYS", "")]),
        (vec![], vec![("CROSSVIEW_API_KEYS", ",")]),
        (vec![], vec![("CROSSVIEW_API_KEYS", " , ")]),
        (vec!["--api-key-file", comments], vec![]),
    ];
    for (extra, env) in cases {
        let args: Vec<&str> = base.iter().copied().chain(extra.iter().copied()).collect();
        let got = serve_exits(&args, &env);
        let (ok, err) = got.unwrap_or_else(|| panic!("{extra:?} {env:?}: the server started"));
        assert!(!ok, "{extra:?} {env:?}: exit status success");
        assert!(
            err.contains("refusing to start") || err.contains("blank"),
            "{extra:?} {env:?}: {err}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_keys_only_loopback_unless_told_so() {
    let dir = tempfile::tempdir().unwrap();
    let model = export_model(dir.path(), "lab");
    let model = model.to_str().unwrap();
    let refused = tokio::task::block_in_place(|| {
        serve_exits(&["--model", model, "--listen", "0.0.0.0:0"], &[])
    });
    let (ok, err) = refused.expect("a keyless server on 0.0.0.0 must not start");
    assert!(!ok && err.contains("--allow-unauthenticated"), "{err}");
    // With a key it starts on every interface (and answers on loopback).
    let (mut child, _) =
        spawn_serve_on(&["--model", model, "--listen", "0.0.0.0:0", "--api-key", "k"]).await;
    let _ = child.kill();
    let (mut child, _) = spawn_serve_on(&[
        "--model",
        model,
        "--listen",
        "0.0.0.0:0",
        "--allow-unauthenticated",
    ])
    .await;
    let _ = child.kill();
}

/// Starts `crossview serve ARGS` and waits for its "serving" line (any address).
async fn spawn_serve_on(args: &[&str]) -> (ChildGuard, String) {
    use std::io::{BufRead, BufReader};
    let mut child = ChildGuard(
        Command::new(env!("CARGO_BIN_EXE_crossview"))
            .arg("serve")
            .args(args)
            .env_remove("CROSSVIEW_API_KEYS")
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let stderr = child.stderr.take().unwrap();
    let (tx, rx) = tokio::sync::oneshot::channel();
    std::thread::spawn(move || {
        let mut tx = Some(tx);
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("server: {line}");
            if line.contains("serving")
                && let Some(tx) = tx.take()
            {
                let _ = tx.send(line);
            }
        }
    });
    let line = guard("server start", rx).await.expect("serving log line");
    (child, line)
}

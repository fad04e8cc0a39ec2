//! Signals are handled from the first instant: a SIGHUP that arrives while the models are
//! still loading (the port already bound) neither ends the process nor is lost — the reload
//! it asks for runs once the server serves.

use std::process::{Command, Stdio};
use std::time::Duration;

use crossview_testing::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sighup_while_models_load_is_served_not_fatal() {
    let dir = tempfile::tempdir().unwrap();
    // Several scenes, so loading takes a while after the port is bound.
    let mut args: Vec<String> = vec!["serve".into()];
    for k in 0..8 {
        let m = export_model_with(dir.path(), &format!("s{k}"), k, cameras());
        args.extend(["--model".into(), m.display().to_string()]);
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    args.extend(["--listen".into(), format!("127.0.0.1:{port}")]);
    let mut child = ChildGuard(
        Command::new(env!("CARGO_BIN_EXE_crossview"))
            .args(&args)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    // The moment the port accepts connections (the kernel queues them before the server
    // serves), send SIGHUP.
    guard("the port is bound", async {
        while tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_err()
        {
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
    })
    .await;
    signal(&child, "HUP");
    let base = format!("http://127.0.0.1:{port}");
    let http = reqwest::Client::new();
    guard("ready after the early SIGHUP", async {
        loop {
            if let Some(status) = child.try_wait().unwrap() {
                panic!("the server ended on an early SIGHUP: {status}");
            }
            if let Ok(r) = http.get(format!("{base}/readyz")).send().await
                && r.status().is_success()
            {
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    })
    .await;
    // The reload it asked for ran: every scene's file re-read, none changed.
    wait_for_metric(
        &base,
        "crossview_model_reloads_total{scene=\"s7\",outcome=\"unchanged\"}",
        1.0,
    )
    .await;
    assert!(child.try_wait().unwrap().is_none());
}

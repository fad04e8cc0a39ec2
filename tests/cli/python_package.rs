//! The Python client package (`clients/python`, installed editable into `.cache/venv` by
//! `make setup`) passes its pytest suite against this build's `crossview` binary: push,
//! subscribe, associate, scenes and reload over gRPC and HTTP, sync and asyncio; error
//! mapping; TLS + API key; a server restart; slow subscribers; the README's "From Python"
//! steps and the examples. Without the venv it skips locally and fails under `CI=true`.

use std::process::Command;

use crossview_testing::{repo_root, skip};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn python_package_tests_pass_against_the_real_server() {
    let root = repo_root();
    let python = root.join(".cache/venv/bin/python");
    let ready = python.is_file()
        && Command::new(&python)
            .args([
                "-c",
                "import crossview_client, pytest, cryptography, grpc_tools",
            ])
            .status()
            .is_ok_and(|s| s.success());
    if !ready {
        // The environment comes from `make setup` (scripts/setup.sh), never from a test.
        skip(
            "the Python client tests need .cache/venv with clients/python[test]: run `make setup`",
        );
        return;
    }
    // pytest bounds every wait itself; this outer bound is for a hang (well above the ~1.5
    // minutes the suite takes on 2 busy cores).
    let output = tokio::time::timeout(
        std::time::Duration::from_secs(600),
        tokio::task::spawn_blocking(move || {
            Command::new(python)
                .args([
                    "-m",
                    "pytest",
                    "clients/python/tests",
                    "-q",
                    "-p",
                    "no:cacheprovider",
                ])
                .current_dir(&root)
                .env("CROSSVIEW_BIN", env!("CARGO_BIN_EXE_crossview"))
                .env("PYTHONDONTWRITEBYTECODE", "1")
                .output()
                .expect("run pytest")
        }),
    )
    .await
    .expect("hang guard: the Python client tests did not finish in 10 minutes")
    .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        output.status.success(),
        "pytest failed\nstdout:\n{stdout}\nstderr:\n{stderr}"
    );
    eprintln!("{}", stdout.lines().last().unwrap_or_default());
}

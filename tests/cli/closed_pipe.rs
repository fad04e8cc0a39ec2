//! A command piped into a reader that has already gone (`crossview … | head`) ends quietly,
//! as Unix tools do: no panic message about a broken pipe.
use std::os::unix::process::ExitStatusExt;
use std::process::{Command, Stdio};

#[test]
fn output_into_a_closed_pipe_ends_without_a_panic() {
    let model = concat!(env!("CARGO_MANIFEST_DIR"), "/models/demo.onnx");
    let commands: [&[&str]; 2] = [&["openapi"], &["model", "info", model]];
    for args in commands {
        // The reading end is closed before the command starts: every write to stdout fails.
        let (reader, writer) = std::io::pipe().unwrap();
        drop(reader);
        let out = Command::new(env!("CARGO_BIN_EXE_crossview"))
            .args(args)
            .stdout(Stdio::from(writer))
            .stderr(Stdio::piped())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert!(!err.contains("Broken pipe"), "{args:?}: {err}");
        // Ended by the signal, as `head`'s writers are.
        assert_eq!(out.status.signal(), Some(libc::SIGPIPE), "{args:?}: {err}");
    }
}

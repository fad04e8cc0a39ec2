//! A real Kafka-protocol broker for the Kafka-mode tests: the pinned `tansu` binary
//! (`make setup` puts it in `.cache/tansu/`; `CROSSVIEW_TANSU` overrides) on a free loopback
//! port with in-memory storage, killed when dropped.
use std::net::TcpListener;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use crate::{ChildGuard, repo_root, skip};

/// A running broker.
pub struct Broker {
    /// `127.0.0.1:<port>`, for `bootstrap.servers`.
    pub addr: String,
    bin: PathBuf,
    _child: ChildGuard,
}

/// The tansu binary, or `None` (after [`skip`]) when it is missing.
fn tansu() -> Option<PathBuf> {
    let bin = std::env::var_os("CROSSVIEW_TANSU")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo_root().join(".cache/tansu/tansu"));
    if bin.is_file() {
        Some(bin)
    } else {
        skip(&format!(
            "no Kafka broker: tansu not found at {} (run `make setup` or set CROSSVIEW_TANSU)",
            bin.display()
        ));
        None
    }
}

impl Broker {
    /// Starts tansu on a free port of 127.0.0.1 and waits until it accepts connections;
    /// `None` (after [`skip`], which fails under `CI=true`) without the binary.
    pub fn start() -> Option<Broker> {
        let bin = tansu()?;
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        let addr = format!("127.0.0.1:{port}");
        let url = format!("tcp://{addr}");
        let child = ChildGuard(
            std::process::Command::new(&bin)
                .args([
                    "broker",
                    "--listener-url",
                    &url,
                    "--advertised-listener-url",
                    &url,
                ])
                .args(["--storage-engine", "memory://tansu/"])
                .env("RUST_LOG", "warn")
                .stdout(std::process::Stdio::null())
                .spawn()
                .expect("start tansu"),
        );
        let t = Instant::now();
        while std::net::TcpStream::connect(&addr).is_err() {
            assert!(
                t.elapsed() < crate::HANG_GUARD,
                "tansu did not start on {addr}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        Some(Broker {
            addr,
            bin,
            _child: child,
        })
    }

    /// Creates topic `name` with `partitions` partitions (tansu's own client).
    pub fn create_topic(&self, name: &str, partitions: u32) {
        let out = std::process::Command::new(&self.bin)
            .args([
                "topic",
                "create",
                name,
                "--partitions",
                &partitions.to_string(),
            ])
            .args(["--broker", &format!("tcp://{}", self.addr)])
            .output()
            .expect("run tansu topic create");
        assert!(
            out.status.success(),
            "tansu topic create {name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
}

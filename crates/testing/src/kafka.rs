//! A real Apache Kafka broker for the Kafka-mode tests: the pinned single-node KRaft broker of
//! `scripts/kafka/broker.sh` (its jars resolved from Maven Central by `make setup` into
//! `.cache/kafka/`), on a free loopback port, with its storage in a temporary folder.
//!
//! [`Broker::shared`] starts one per test binary (a JVM takes seconds to start; tests keep
//! apart by [`Broker::topics`], which names fresh topics); [`Broker::start`] one of a test's
//! own, for tests that stop or restart it. A broker's process ends with its [`Broker`], and a
//! shared one with the test binary (the script watches its parent).
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use crate::{ChildGuard, repo_root, skip};

/// How long a broker may take to start (a JVM on a loaded 2-core machine).
const START_GUARD: Duration = Duration::from_secs(120);

/// A broker (running unless [`Broker::stopped`] or [`Broker::kill`]).
pub struct Broker {
    /// `127.0.0.1:<port>`, for `bootstrap.servers`.
    pub addr: String,
    dir: tempfile::TempDir,
    script: PathBuf,
    runner: Option<ChildGuard>,
}

/// Topics of one test on a shared broker: fresh names, created with their partitions.
#[derive(Debug, Clone)]
pub struct Topics {
    /// The input topic (camera batches keyed by scene).
    pub batches: String,
    /// The output topic (frame results).
    pub results: String,
    /// The dead-letter topic.
    pub dead: String,
}

/// The broker script, or `None` (after [`skip`]) when `make setup` has not resolved the jars.
fn script() -> Option<PathBuf> {
    let root = repo_root();
    let script = root.join("scripts/kafka/broker.sh");
    let home = std::env::var_os("CROSSVIEW_KAFKA_HOME").map(PathBuf::from);
    let has_jars = match home {
        Some(h) => h.join("libs").is_dir(),
        None => std::fs::read_dir(root.join(".cache/kafka"))
            .map(|d| d.flatten().any(|e| e.path().join("libs").is_dir()))
            .unwrap_or(false),
    };
    if has_jars {
        Some(script)
    } else {
        skip("no Kafka broker: run `make setup` (it resolves Apache Kafka into .cache/kafka/)");
        None
    }
}

impl Broker {
    /// Starts a broker of the caller's own and waits until it is ready; `None` (after
    /// [`skip`], which fails under `CI=true`) without the jars.
    pub fn start() -> Option<Broker> {
        let mut broker = Broker::stopped()?;
        broker.restart();
        Some(broker)
    }

    /// A broker of the caller's own with its address chosen (a free port) but not started
    /// yet: for a client that starts before its broker. [`restart`](Self::restart) starts it.
    pub fn stopped() -> Option<Broker> {
        let script = script()?;
        let dir = tempfile::Builder::new()
            .prefix("crossview-kafka-")
            .tempdir()
            .expect("broker folder");
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("free port")
            .port();
        Some(Broker {
            addr: format!("127.0.0.1:{port}"),
            dir,
            script,
            runner: None,
        })
    }

    /// (Re)starts the broker on its address and storage (what it held before is kept) and
    /// waits until it is ready.
    pub fn restart(&mut self) {
        self.kill();
        let port = self.addr.rsplit(':').next().unwrap_or("0").to_string();
        let _ = std::fs::remove_file(self.dir.path().join("broker.log"));
        self.runner = Some(ChildGuard(
            std::process::Command::new("bash")
                .arg(&self.script)
                .arg("run")
                .arg(self.dir.path())
                .arg(port)
                .arg("--parent")
                .arg(std::process::id().to_string())
                .stdin(std::process::Stdio::null())
                .stdout(std::process::Stdio::null())
                .spawn()
                .expect("start the Kafka broker script"),
        ));
        self.addr = self.wait_ready();
    }

    /// The test binary's shared broker, started by the first caller; `None` as for
    /// [`start`](Self::start).
    pub fn shared() -> Option<&'static Broker> {
        static SHARED: OnceLock<Option<Broker>> = OnceLock::new();
        let b = SHARED.get_or_init(Broker::start).as_ref();
        if b.is_none() {
            skip("no Kafka broker");
        }
        b
    }

    /// Waits until the broker logged its start and accepts connections; its address.
    fn wait_ready(&mut self) -> String {
        let (log, addr_file) = (
            self.dir.path().join("broker.log"),
            self.dir.path().join("addr"),
        );
        let t = Instant::now();
        loop {
            let started =
                std::fs::read_to_string(&log).is_ok_and(|l| l.contains("Kafka Server started"));
            if started && let Ok(addr) = std::fs::read_to_string(&addr_file) {
                let addr = addr.trim().to_string();
                if std::net::TcpStream::connect(&addr).is_ok() {
                    return addr;
                }
            }
            if let Some(Ok(Some(status))) = self.runner.as_mut().map(|r| r.0.try_wait()) {
                panic!(
                    "the Kafka broker exited ({status}): {}",
                    tail(&log).unwrap_or_default()
                );
            }
            assert!(
                t.elapsed() < START_GUARD,
                "the Kafka broker did not start in {START_GUARD:?}: {}",
                tail(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Fresh topics for one test: `batches` with `partitions` partitions, `results` and
    /// `dead` with one each.
    pub fn topics(&self, partitions: u32) -> Topics {
        static NEXT: AtomicU32 = AtomicU32::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let t = Topics {
            batches: format!("batches-{n}"),
            results: format!("results-{n}"),
            dead: format!("dead-{n}"),
        };
        self.create_topic(&t.batches, partitions);
        self.create_topic(&t.results, 1);
        self.create_topic(&t.dead, 1);
        t
    }

    /// Creates topic `name` with `partitions` partitions (Kafka's own `TopicCommand`) and
    /// waits until it exists.
    pub fn create_topic(&self, name: &str, partitions: u32) {
        let out = self
            .tool("org.apache.kafka.tools.TopicCommand")
            .args([
                "--bootstrap-server",
                &self.addr,
                "--create",
                "--if-not-exists",
            ])
            .args(["--topic", name, "--partitions", &partitions.to_string()])
            .args(["--replication-factor", "1"])
            .output()
            .expect("run kafka TopicCommand");
        assert!(
            out.status.success(),
            "create topic {name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }

    /// A Kafka command-line tool by class name, against this broker's jars.
    pub fn tool(&self, class: &str) -> std::process::Command {
        let mut c = std::process::Command::new("bash");
        c.arg(repo_root().join("scripts/kafka/broker.sh"))
            .args(["tool", class]);
        c
    }

    /// The broker's folder (configuration, data, log).
    pub fn dir(&self) -> &Path {
        self.dir.path()
    }

    /// Stops the broker at once (SIGKILL: a crash); [`restart`](Self::restart) brings it back
    /// with what it held.
    pub fn kill(&mut self) {
        if let Ok(pid) = std::fs::read_to_string(self.dir.path().join("pid")) {
            let _ = std::process::Command::new("kill")
                .args(["-9", pid.trim()])
                .status();
            let _ = std::fs::remove_file(self.dir.path().join("pid"));
        }
        if let Some(mut r) = self.runner.take() {
            let _ = r.0.kill();
            let _ = r.0.wait();
        }
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        self.kill();
    }
}

/// The last lines of the broker's log, for a failure message.
fn tail(log: &Path) -> Option<String> {
    let text = std::fs::read_to_string(log).ok()?;
    let lines: Vec<&str> = text.lines().collect();
    Some(lines[lines.len().saturating_sub(20)..].join("\n"))
}

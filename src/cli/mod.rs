//! The `crossview` command line: argument parsing (clap, with environment fallbacks) and one
//! handler per subcommand. Kept thin: each handler calls into the library.
use clap::{Parser, Subcommand};

pub mod compute;
pub mod demo;
pub mod distil;
pub mod eval;
pub mod fit_check;
pub mod gate;
pub mod import;
pub mod model;
pub mod retrain;
pub mod serve;
pub mod simulate;
pub mod sync_check;
pub mod train;

/// Self-supervised multi-view person association: train, evaluate, serve.
#[derive(Debug, Parser)]
#[command(name = "crossview", version, about)]
pub struct Cli {
    /// Log format: human-readable text or one JSON object per line.
    #[arg(
        long,
        global = true,
        value_enum,
        env = "CROSSVIEW_LOG_FORMAT",
        default_value = "text"
    )]
    pub log_format: LogFormat,

    /// Run at this CPU niceness (0 = normal … 19 = lowest priority): a training or a check
    /// beside a server that must not be slowed (`serve --auto-retrain` runs its retrains
    /// with 19).
    #[arg(long, global = true, env = "CROSSVIEW_NICE", value_parser = clap::value_parser!(i32).range(0..=19))]
    pub nice: Option<i32>,

    #[command(subcommand)]
    pub command: Command,
}

/// How log lines are written (to stderr). The level filter comes from `RUST_LOG`
/// (default `info`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    Text,
    Json,
}

/// Installs the global `tracing` subscriber.
fn init_logging(format: LogFormat) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Serve association over gRPC and HTTP JSON (streaming, cross-camera synchronization).
    Serve(serve::ServeArgs),
    /// Convert a dataset (WILDTRACK ground truth or detections) into a recording.
    Import(import::ImportArgs),
    /// Keep the train, val or test part of a recording (chronological split, SPEC §6).
    Split(import::SplitArgs),
    /// Model file tools: create a random encoder, inspect a file.
    Model(model::ModelArgs),
    /// SPEC §5 metrics of a model on a recording with ids (or recomputed from a pair dump).
    Eval(eval::EvalArgs),
    /// Global identities for every frame of a recording, one JSON line per frame.
    Associate(eval::AssociateArgs),
    /// Generate a synthetic multi-camera recording (SPEC §7) with ground-truth ids.
    Simulate(simulate::SimulateArgs),
    /// Train an encoder self-supervised on a recording and export it as ONNX.
    Train(train::TrainArgs),
    /// Stream a simulated scene through the server and show the association and its accuracy live.
    Demo(demo::DemoArgs),
    /// Each camera's clock offset, estimated from a recording's detections with the model.
    SyncCheck(sync_check::SyncCheckArgs),
    /// Whether each camera still fits the model over a recording, label-free (a camera that
    /// moved, was re-aimed or zoomed stops fitting).
    FitCheck(fit_check::FitCheckArgs),
    /// Print the OpenAPI 3.1 description of the HTTP API (what `GET /openapi.json` serves);
    /// `crossview openapi > docs/openapi.json` regenerates the committed copy.
    Openapi,
}

/// Entry point used by `main`.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging(cli.log_format);
    if let Some(n) = cli.nice {
        lower_priority(n);
    }
    if !matches!(
        cli.command,
        Command::Serve(_) | Command::Demo(_) | Command::Train(_)
    ) {
        end_quietly_when_the_reader_leaves();
    }
    match cli.command {
        Command::Serve(args) => serve::run(args),
        Command::Import(args) => import::run(args),
        Command::Split(args) => import::run_split(args),
        Command::Model(args) => model::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Associate(args) => eval::run_associate(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Train(args) => train::run(args),
        Command::Demo(args) => demo::run(args),
        Command::SyncCheck(args) => sync_check::run(args),
        Command::FitCheck(args) => fit_check::run(args),
        Command::Openapi => {
            println!("{}", crossview_serve::openapi_json());
            Ok(())
        }
    }
}

/// Lowers this process's CPU priority to niceness `n` before it starts any thread (threads
/// inherit it). Best effort: a refusal is logged and the command runs on.
fn lower_priority(n: i32) {
    #[cfg(unix)]
    {
        // SAFETY: setpriority only changes the scheduling priority of the calling process
        // (its one thread so far); no memory is shared with the call.
        #[allow(unsafe_code)]
        let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, n) };
        if rc != 0 {
            tracing::warn!(nice = n, error = %std::io::Error::last_os_error(), "cannot lower the CPU priority");
        }
    }
    #[cfg(not(unix))]
    tracing::warn!(nice = n, "--nice is not supported on this platform");
}

/// A command whose output is piped into a reader that stops early (`crossview eval … | head`)
/// ends the way Unix tools do, at once and silently, instead of panicking on the failed
/// write: Rust ignores SIGPIPE, so every print would fail with "Broken pipe". Not for the
/// long-running commands (a server's clients leaving is an error they handle).
fn end_quietly_when_the_reader_leaves() {
    #[cfg(unix)]
    // SAFETY: restores the default disposition of one signal; no handler is installed and
    // no other thread depends on SIGPIPE being ignored (the commands that get here use no
    // sockets).
    #[allow(unsafe_code)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

//! The `crossview` command line: argument parsing (clap, with environment fallbacks) and one
//! handler per subcommand. Kept thin: each handler calls into the library.
use clap::{Parser, Subcommand};

pub mod serve;

/// Self-supervised multi-view person association: train, evaluate, serve.
#[derive(Debug, Parser)]
#[command(name = "crossview", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Serve association over gRPC and HTTP JSON (streaming, cross-camera synchronization).
    Serve(serve::ServeArgs),
}

/// Entry point used by `main`.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Serve(args) => serve::run(args),
    }
}

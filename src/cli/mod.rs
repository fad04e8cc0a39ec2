//! The `crossview` command line: argument parsing (clap, with environment fallbacks) and one
//! handler per subcommand. Kept thin: each handler calls into the library.
use clap::{Parser, Subcommand};

pub mod import;

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
    /// Convert a dataset (WILDTRACK ground truth or detections) into a recording.
    Import(import::ImportArgs),
    /// Keep the train, val or test part of a recording (chronological split, SPEC §6).
    Split(import::SplitArgs),
}

/// Entry point used by `main`.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Import(args) => import::run(args),
        Command::Split(args) => import::run_split(args),
    }
}

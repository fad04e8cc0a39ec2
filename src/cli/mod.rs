//! The `crossview` command line: argument parsing (clap, with environment fallbacks) and one
//! handler per subcommand. Kept thin: each handler calls into the library.
use clap::{Parser, Subcommand};

pub mod model;

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
    /// Model file tools: create a random encoder, inspect a file.
    Model(model::ModelArgs),
}

/// Entry point used by `main`.
pub fn run() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.command {
        Command::Model(args) => model::run(args),
    }
}

//! `crossview-loadtest`: open-loop load and soak generator for the crossview server.
//! See loadtest/README.md.
mod args;
mod driver;
mod grpc;
mod http;
mod kafka;
mod promtext;
mod recording;
mod report;
mod rss;
mod target;
mod tracker;
mod transport;

#[cfg(test)]
mod tests;

use clap::Parser;

fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = args::Args::parse();
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let report = match runtime.block_on(driver::run(&args)) {
        Ok(r) => r,
        Err(e) => {
            // Could not run at all (bad options, unreachable server, unknown scene): exit 2,
            // distinct from a run whose verdict failed (1).
            eprintln!("crossview-loadtest: {e:#}");
            std::process::exit(2);
        }
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.to_text());
    }
    // Background tasks (abandoned streams) must not keep the process alive.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    std::process::exit(if report.passed { 0 } else { 1 });
}

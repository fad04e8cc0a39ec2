//! The `crossview` command line: a thin edge over the library.
fn main() -> anyhow::Result<()> {
    crossview::cli::run()
}

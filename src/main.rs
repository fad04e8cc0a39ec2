//! The `crossview` command line: a thin edge over the library.

/// mimalloc's per-thread heaps instead of the C library's shared arenas: under overload a
/// server thread that reads batches never waits on an arena lock held by an encoder thread
/// that is itself waiting for a core (`crossview serve` runs its encoders below intake).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> anyhow::Result<()> {
    crossview::cli::run()
}

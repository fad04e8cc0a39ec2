//! The `crossview` command line: a thin edge over the library.

/// jemalloc instead of the C library's allocator: the serving path allocates and frees small
/// buffers on every frame, and jemalloc's per-thread caches serve more frames per second for
/// a little more memory (BENCHMARKS.md, "Memory allocator").
#[global_allocator]
static ALLOCATOR: tikv_jemallocator::Jemalloc = tikv_jemallocator::Jemalloc;

fn main() -> anyhow::Result<()> {
    crossview::cli::run()
}

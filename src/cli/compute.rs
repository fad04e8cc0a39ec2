//! How the commands that train (`crossview train`, `crossview model distil`) use the cores.

/// One compute thread per trained model: candle reads `RAYON_NUM_THREADS` when it first sizes
/// its thread pool, and on its small matrices a second thread spins more than it computes
/// (`model distil`, 30 epochs on 2 cores: 35.3 s with candle's default pool, 18.9 s with one
/// thread, the same weights; BENCHMARKS.md, "One student"). `crossview train` gets its
/// parallelism from its members, each on a thread of its own.
///
/// Call it first thing in the command, before any thread of the process exists.
pub fn one_compute_thread_per_model() {
    // SAFETY: called before the command starts any thread (the environment is not read or
    // written concurrently).
    #[allow(unsafe_code)]
    unsafe {
        std::env::set_var("RAYON_NUM_THREADS", "1")
    };
}

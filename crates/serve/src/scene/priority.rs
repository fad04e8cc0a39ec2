//! The CPU priority of background analysis. Intake (reading, validating and synchronizing
//! batches) and inference run at normal priority — inference on a pool of one thread per core,
//! so intake's threads always get their share of the cores, and a server sharing its machine
//! with other programs (a detector) is not starved by them. Background analysis (the clock
//! watch's looks) runs at the lowest priority: under load it waits instead of taking cores.

/// Lowers the calling thread (a clock watch) to the lowest normal CPU priority (nice 19).
/// Best effort: a platform that refuses keeps the thread's priority (logged at debug).
pub(crate) fn run_in_background() {
    use thread_priority::{ThreadPriority, set_current_thread_priority};
    if let Err(e) = set_current_thread_priority(ThreadPriority::Min) {
        tracing::debug!(error = ?e, "background thread keeps its CPU priority");
    }
}

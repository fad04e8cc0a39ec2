//! The CPU priorities of a scene's work threads relative to intake, which must never wait for
//! a core: intake (reading, validating and synchronizing batches) runs at normal priority,
//! inference below it, background analysis below that.

/// Where a scene's work threads run relative to intake (reading, validating and synchronizing
/// camera batches: cheap, and on time only if it never waits for a core).
#[derive(Debug, Clone, Copy)]
pub(crate) enum Priority {
    /// Inference (the encoder thread): the lowest normal priority, so that under overload a
    /// batch that reached the server in time is never refused as late because the encoders
    /// held the cores.
    Inference,
    /// Background analysis (the clock watch): only cores nothing else wants (`SCHED_IDLE`),
    /// so under overload it waits instead of taking cores from inference.
    Background,
}

/// Puts the calling thread at `priority`. Best effort: a platform that refuses keeps the
/// thread's priority (logged at debug).
pub(crate) fn run_at(priority: Priority) {
    use thread_priority::{ThreadPriority, set_current_thread_priority};
    let set = match priority {
        Priority::Inference => set_current_thread_priority(ThreadPriority::Min),
        #[cfg(target_os = "linux")]
        Priority::Background => {
            use thread_priority::unix::{
                NormalThreadSchedulePolicy, ThreadSchedulePolicy, set_thread_priority_and_policy,
                thread_native_id,
            };
            set_thread_priority_and_policy(
                thread_native_id(),
                ThreadPriority::Min,
                ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Idle),
            )
        }
        #[cfg(not(target_os = "linux"))]
        Priority::Background => set_current_thread_priority(ThreadPriority::Min),
    };
    if let Err(e) = set {
        tracing::debug!(error = ?e, ?priority, "work thread keeps its CPU priority");
    }
}

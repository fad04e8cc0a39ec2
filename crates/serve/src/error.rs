//! The server's error: the method's errors ([`crossview_core::Error`], as [`Error::Core`]) plus
//! what only serving can run into — a late or out-of-range batch, a full queue, a missed
//! deadline, a stalled subscriber, missing credentials, shutdown, a scene without a model.
//! Each transport maps it exactly once (gRPC status codes in `transport::grpc::status`, HTTP
//! statuses in `transport::http::status_of`) and `metrics` counts it by [`Error::kind`] in one
//! place. A cross-cutting module: every layer may return it, it imports none of them.

/// Result alias of the serve crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong while serving, phrased so the message names the problem.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An error of the method (invalid input, unknown scene, model, runtime, I/O …).
    #[error(transparent)]
    Core(#[from] crossview_core::Error),
    /// A batch arrived for a frame that was already emitted.
    #[error(
        "late batch: frame {frame_id} of scene '{scene}' was already emitted (camera '{camera}')"
    )]
    LateBatch {
        scene: String,
        camera: String,
        frame_id: u64,
    },
    /// A batch's frame id is too far from the scene's current frame ids (the frame-id window,
    /// `crossview serve --frame-window`); it was refused and changed nothing.
    #[error(
        "frame id {frame_id} of camera '{camera}' is out of range for scene '{scene}': {reason}"
    )]
    FrameOutOfRange {
        scene: String,
        camera: String,
        frame_id: u64,
        reason: String,
    },
    /// A bounded queue or limit is full; the caller should back off and retry.
    #[error("resource exhausted: {0}")]
    ResourceExhausted(String),
    /// The scene is over its queue budget (`crossview serve --max-queue-delay`): the batch was
    /// refused — its frame shed whole, or (a Kafka-fed scene) to be retried; retry after
    /// `retry_after`, when the queue should be back within its budget.
    #[error("overloaded: {message}")]
    Overloaded {
        message: String,
        retry_after: std::time::Duration,
    },
    /// A unary request waited in the inference queue longer than the budget
    /// (`crossview serve --max-queue-delay`) and was not associated; back off.
    #[error("deadline exceeded: {0}")]
    DeadlineExceeded(String),
    /// A result subscriber stopped reading and was dropped (`--subscriber-stall-timeout`).
    #[error("subscriber stalled: {0}")]
    SubscriberStalled(String),
    /// Missing or wrong credentials.
    #[error("unauthenticated: {0}")]
    Unauthenticated(String),
    /// The service is not (or no longer) accepting work, e.g. during shutdown.
    #[error("unavailable: {0}")]
    Unavailable(String),
    /// The scene was declared by its cameras and has no model yet: batches are accepted and
    /// published unassociated, an `associate` call cannot be answered.
    #[error("scene '{0}' has no model yet (declared by its cameras; load one and reload)")]
    NoModel(String),
}

impl Error {
    /// [`crossview_core::Error::InvalidArgument`], the most common refusal.
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        crossview_core::Error::invalid(field, reason).into()
    }

    /// [`crossview_core::Error::Internal`] keeping `source` (a task that could not run).
    pub fn internal_from(
        context: impl Into<String>,
        source: impl Into<Box<dyn std::error::Error + Send + Sync + 'static>>,
    ) -> Self {
        crossview_core::Error::internal_from(context, source).into()
    }

    /// The message followed by its chain of sources, `a: b: c`: what clients and logs see.
    pub fn report(&self) -> String {
        crossview_core::report_chain(self)
    }

    /// A short, stable kind label (used for metrics and logs); a core error keeps its own.
    pub fn kind(&self) -> &'static str {
        match self {
            Error::Core(e) => e.kind(),
            Error::LateBatch { .. } => "late",
            Error::FrameOutOfRange { .. } => "out_of_range",
            Error::ResourceExhausted(_) => "resource_exhausted",
            Error::Overloaded { .. } => "overloaded",
            Error::DeadlineExceeded(_) => "deadline_exceeded",
            Error::SubscriberStalled(_) => "subscriber_stalled",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::Unavailable(_) => "unavailable",
            Error::NoModel(_) => "no_model",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_core_error_keeps_its_message_kind_and_sources() {
        let e: Error =
            crossview_core::Error::internal_from("shutdown task failed", "it panicked").into();
        assert_eq!(e.kind(), "internal");
        assert_eq!(e.to_string(), "internal error: shutdown task failed");
        assert_eq!(
            e.report(),
            "internal error: shutdown task failed: it panicked"
        );
        let e = Error::invalid("body", "not JSON");
        assert_eq!(
            (e.kind(), e.to_string().as_str()),
            ("invalid_argument", "invalid body: not JSON")
        );
    }

    #[test]
    fn serving_errors_keep_their_labels() {
        let late = Error::LateBatch {
            scene: "lab".into(),
            camera: "c0".into(),
            frame_id: 3,
        };
        assert_eq!(late.kind(), "late");
        assert_eq!(
            late.report(),
            "late batch: frame 3 of scene 'lab' was already emitted (camera 'c0')"
        );
        assert_eq!(Error::Unavailable("x".into()).kind(), "unavailable");
        assert_eq!(Error::NoModel("lab".into()).kind(), "no_model");
    }
}

//! What the driver hands a sender, and the errors it can see: shared by the HTTP and gRPC
//! transports.
use std::sync::Arc;

use crossview_core::Batch;
use tokio::sync::OwnedSemaphorePermit;

use crate::tracker::FrameKey;

/// One batch to push: its scene (index and name) and the batch itself (frame id already
/// shifted for the current replay pass). The permit bounds in-flight batches and is released
/// when the server answers.
pub struct Outgoing {
    pub key: FrameKey,
    pub scene: Arc<str>,
    pub batch: Batch,
    pub permit: OwnedSemaphorePermit,
}

/// Maps a server rejection to a short stable kind. The server's own kind (`late`,
/// `duplicate`, ...) wins when it sent one.
pub fn rejection_kind(server_kind: Option<&str>, fallback: impl FnOnce() -> String) -> String {
    match server_kind {
        Some(k) if !k.is_empty() => k.to_string(),
        _ => fallback(),
    }
}

//! The wire format, owned in one place: the gRPC API `crossview.v1` ([`pb`], compiled from
//! `proto/` by `build.rs`), the JSON request and result types of the HTTP API ([`types`]), and
//! every conversion between them and the core types ([`convert`]). The server, the demo client
//! and the load generator all speak through this crate.

pub mod convert;
pub mod duration;
pub mod format;
pub mod types;

/// Generated protobuf and tonic code for `crossview.v1`.
#[allow(missing_docs, clippy::all, clippy::pedantic)]
pub mod pb {
    tonic::include_proto!("crossview.v1");
    /// The encoded file descriptor set (for gRPC reflection).
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        tonic::include_file_descriptor_set!("crossview_descriptor");
}

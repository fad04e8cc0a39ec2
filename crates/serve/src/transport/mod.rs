//! The transports: each turns its wire format into calls of the one domain API
//! ([`crate::service::Service`]) and maps the one server error ([`crate::Error`]) once, in its
//! own way. A new transport goes in a folder here, beside these.
//!
//! - [`grpc`]: tonic, the `crossview.v1.Association` service, with the `Push`/`Stream`
//!   request framing of its own ([`grpc::push`]) so a bad message is refused alone;
//! - [`http`]: axum JSON routes, Server-Sent Events, and the live viewer ([`http::viewer`]);
//! - [`kafka`]: batches consumed from a topic, results produced to another, offsets
//!   committed once a frame's results are out.
pub mod grpc;
pub mod http;
pub mod kafka;

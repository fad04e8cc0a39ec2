//! The streaming association service: gRPC (tonic) and HTTP JSON (axum) over one port.

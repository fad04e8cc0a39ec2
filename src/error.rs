//! The crate's one error type. Every layer returns it; each transport maps it exactly once
//! (gRPC status codes in `serve::grpc`, HTTP statuses in `serve::http`).
use std::path::PathBuf;

/// Result alias used across the crate.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Everything that can go wrong in crossview, phrased so the message names the problem.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A malformed line or document in an input file (`line` is 1-based; 0 when not line-based).
    #[error("{source_name}:{line}: {message}")]
    Format {
        source_name: String,
        line: usize,
        message: String,
    },
    /// A request or input value is invalid; `field` names it (e.g. `detections[3].bbox`).
    #[error("invalid {field}: {reason}")]
    InvalidArgument { field: String, reason: String },
    /// No scene with this name is loaded.
    #[error("unknown scene '{0}'")]
    UnknownScene(String),
    /// The scene has no camera with this name.
    #[error("unknown camera '{camera}' in scene '{scene}'")]
    UnknownCamera { scene: String, camera: String },
    /// A model file is missing, corrupt or violates the SPEC §8 contract.
    #[error("model {path}: {reason}")]
    Model { path: String, reason: String },
    /// ONNX Runtime failed (library not found, session or run error).
    #[error("ONNX Runtime: {0}")]
    Runtime(String),
    /// A batch arrived for a frame that was already emitted.
    #[error(
        "late batch: frame {frame_id} of scene '{scene}' was already emitted (camera '{camera}')"
    )]
    LateBatch {
        scene: String,
        camera: String,
        frame_id: u64,
    },
    /// A second batch for the same camera and frame.
    #[error(
        "duplicate batch: camera '{camera}' already reported frame {frame_id} of scene '{scene}'"
    )]
    DuplicateBatch {
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
    /// Missing or wrong credentials.
    #[error("unauthenticated: {0}")]
    Unauthenticated(String),
    /// The service is not (or no longer) accepting work, e.g. during shutdown.
    #[error("unavailable: {0}")]
    Unavailable(String),
    /// Training could not run on the given data or configuration.
    #[error("training: {0}")]
    Training(String),
}

impl Error {
    /// Shorthand for [`Error::InvalidArgument`].
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::InvalidArgument {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// Shorthand for [`Error::Io`].
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.into(),
            source,
        }
    }

    /// Shorthand for [`Error::Model`].
    pub fn model(path: impl Into<String>, reason: impl Into<String>) -> Self {
        Error::Model {
            path: path.into(),
            reason: reason.into(),
        }
    }

    /// A short, stable kind label (used for metrics and logs).
    pub fn kind(&self) -> &'static str {
        match self {
            Error::Io { .. } => "io",
            Error::Format { .. } => "format",
            Error::InvalidArgument { .. } => "invalid_argument",
            Error::UnknownScene(_) => "unknown_scene",
            Error::UnknownCamera { .. } => "unknown_camera",
            Error::Model { .. } => "model",
            Error::Runtime(_) => "runtime",
            Error::LateBatch { .. } => "late",
            Error::DuplicateBatch { .. } => "duplicate",
            Error::FrameOutOfRange { .. } => "out_of_range",
            Error::ResourceExhausted(_) => "resource_exhausted",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::Unavailable(_) => "unavailable",
            Error::Training(_) => "training",
        }
    }
}

//! The method's error type: what the model, the data readers, training, evaluation and the
//! association itself can run into. The library crates return it; the server wraps it in its
//! own error (`crossview_serve::Error::Core`), next to what only serving can run into (late
//! batches, full queues, missed deadlines, credentials, shutdown), and maps that once per
//! transport.
use std::path::PathBuf;

/// Result alias used across the crates.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// A boxed error kept as the `source` of a wrapping variant.
pub(crate) type BoxError = Box<dyn std::error::Error + Send + Sync + 'static>;

/// Everything that can go wrong in the method, phrased so the message names the problem.
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
    /// ONNX Runtime failed: the library could not be found or loaded, or a session could not
    /// be built or run. `context` says what was being done; the runtime's own error is the
    /// source.
    #[error("ONNX Runtime: {context}")]
    Runtime {
        context: String,
        #[source]
        source: Option<BoxError>,
    },
    /// An encoder returned output that breaks its contract (wrong shape or row count).
    #[error("encoder: {0}")]
    Encoder(String),
    /// A bug or a failure of the process itself (a panic caught, a task or thread that could
    /// not run); never the caller's fault.
    #[error("internal error: {context}")]
    Internal {
        context: String,
        #[source]
        source: Option<BoxError>,
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

    /// [`Error::Runtime`] for `context`, keeping the runtime's error as the source.
    pub fn runtime(context: impl Into<String>, source: impl Into<BoxError>) -> Self {
        Error::Runtime {
            context: context.into(),
            source: Some(source.into()),
        }
    }

    /// [`Error::Internal`] without a source (e.g. a caught panic).
    pub fn internal(context: impl Into<String>) -> Self {
        Error::Internal {
            context: context.into(),
            source: None,
        }
    }

    /// [`Error::Internal`] keeping `source`.
    pub fn internal_from(context: impl Into<String>, source: impl Into<BoxError>) -> Self {
        Error::Internal {
            context: context.into(),
            source: Some(source.into()),
        }
    }

    /// The message followed by its chain of sources, `a: b: c`: what clients and logs see,
    /// so a wrapped runtime error still says what went wrong.
    pub fn report(&self) -> String {
        report_chain(self)
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
            Error::Runtime { .. } => "runtime",
            Error::Encoder(_) => "encoder",
            Error::Internal { .. } => "internal",
            Error::DuplicateBatch { .. } => "duplicate",
            Error::Training(_) => "training",
        }
    }
}

/// Any error's message followed by its chain of sources, `a: b: c` (what [`Error::report`]
/// and the server's own error type show).
pub fn report_chain(e: &(dyn std::error::Error + 'static)) -> String {
    let mut out = e.to_string();
    let mut next = e.source();
    while let Some(e) = next {
        out.push_str(": ");
        out.push_str(&e.to_string());
        next = e.source();
    }
    out
}

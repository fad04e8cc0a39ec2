//! ONNX Runtime: one process-wide environment (the shared library is loaded once) and
//! [`OnnxEncoder`], the [`Encoder`] that runs a SPEC §8 model file.
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ndarray::Array2;
use ort::environment::Environment;
use ort::session::Session;
use ort::value::TensorRef;

use super::export::{decode_model, model_metadata, read_model_file};
use super::graph::{INIT_CAMERA_EMBEDDING, INPUT_BOXES, INPUT_CAMERA, OUTPUT_EMBEDDING};
use super::onnx::{DT_FLOAT, DT_INT64, DimensionValue, ModelProto, ValueInfoProto};
use crossview_core::Encoder;

use super::{EncoderWeights, ModelMetadata};
use crossview_core::{Error, Result};

/// File name of the ONNX Runtime release crossview is built against.
pub(crate) const ORT_LIBRARY_NAME: &str = "libonnxruntime.so.1.31.1";

static ENVIRONMENT: OnceLock<std::result::Result<Environment, String>> = OnceLock::new();

/// Where the ONNX Runtime library is looked for, in order: `$ORT_DYLIB_PATH`, the project's
/// `.cache/onnxruntime/` (from `make setup`), next to the executable, `/usr/local/lib`, `/usr/lib`.
pub(crate) fn library_candidates() -> Vec<PathBuf> {
    let mut out = Vec::new();
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(p));
    }
    out.push(
        Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
            .join(".cache/onnxruntime")
            .join(ORT_LIBRARY_NAME),
    );
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf))
    {
        out.push(dir.join(ORT_LIBRARY_NAME));
        out.push(dir.join("libonnxruntime.so"));
    }
    for dir in ["/usr/local/lib", "/usr/lib"] {
        out.push(Path::new(dir).join(ORT_LIBRARY_NAME));
        out.push(Path::new(dir).join("libonnxruntime.so"));
    }
    out
}

/// The first existing file among `candidates`, or the "not found" message listing them all.
pub(crate) fn find_library(candidates: &[PathBuf]) -> std::result::Result<PathBuf, String> {
    candidates.iter().find(|p| p.is_file()).cloned().ok_or_else(|| {
        let looked: Vec<String> = candidates.iter().map(|p| p.display().to_string()).collect();
        format!(
            "ONNX Runtime library not found (looked in {}); run `make setup` or set ORT_DYLIB_PATH",
            looked.join(", ")
        )
    })
}

fn init_environment() -> std::result::Result<Environment, String> {
    let path = &find_library(&library_candidates())?;
    tracing::debug!(path = %path.display(), "loading ONNX Runtime");
    let builder =
        ort::init_from(path).map_err(|e| format!("cannot load {}: {e}", path.display()))?;
    builder
        .with_name("crossview")
        .build()
        .map_err(|e| format!("cannot create environment from {}: {e}", path.display()))
}

/// The process-wide ONNX Runtime environment, created on first use.
pub fn environment() -> Result<&'static Environment> {
    match ENVIRONMENT.get_or_init(init_environment) {
        Ok(env) => Ok(env),
        Err(msg) => Err(Error::Runtime {
            context: msg.clone(),
            source: None,
        }),
    }
}

/// Session options for [`OnnxEncoder`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncoderOptions {
    /// Threads ONNX Runtime may use inside one operator (default 1: the server runs one
    /// encoder per scene and the machines are small).
    pub intra_threads: usize,
}

impl Default for EncoderOptions {
    fn default() -> Self {
        EncoderOptions { intra_threads: 1 }
    }
}

/// An [`Encoder`] backed by an ONNX Runtime session over a SPEC §8 model file.
pub struct OnnxEncoder {
    session: Session,
    metadata: ModelMetadata,
    dim: usize,
    /// [`Encoder::leading_width`]: the first member's width when the graph is a crossview
    /// ensemble, else `dim`.
    leading: usize,
    source: String,
}

impl std::fmt::Debug for OnnxEncoder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnnxEncoder")
            .field("source", &self.source)
            .field("dim", &self.dim)
            .field("cameras", &self.metadata.cameras.len())
            .finish()
    }
}

impl OnnxEncoder {
    /// Loads a model file with default options.
    pub fn load(path: impl AsRef<Path>) -> Result<Self> {
        Self::load_with(path, EncoderOptions::default())
    }

    /// Loads a model file. A missing, corrupt or contract-violating file is [`Error::Model`]
    /// naming the path.
    pub fn load_with(path: impl AsRef<Path>, options: EncoderOptions) -> Result<Self> {
        let path = path.as_ref();
        let bytes = read_model_file(path)?;
        Self::from_bytes_with(&path.display().to_string(), &bytes, options)
    }

    /// Loads model bytes with default options; `name` identifies them in errors.
    pub fn from_bytes(name: &str, bytes: &[u8]) -> Result<Self> {
        Self::from_bytes_with(name, bytes, EncoderOptions::default())
    }

    /// Loads model bytes: checks the graph contract and metadata first, then creates the session.
    pub fn from_bytes_with(name: &str, bytes: &[u8], options: EncoderOptions) -> Result<Self> {
        let model = decode_model(name, bytes)?;
        let metadata = model_metadata(name, &model)?;
        let dim = check_contract(&model, metadata.cameras.len())
            .map_err(|reason| Error::model(name, reason))?;
        let env = environment()?;
        let threads = options.intra_threads.max(1);
        let mut builder = Session::builder(env)
            .map_err(|e| Error::runtime("cannot create a session builder", e))?
            .with_intra_threads(threads)
            .map_err(builder_err)?
            .with_inter_threads(1)
            .map_err(builder_err)?;
        let session = builder
            .commit_from_memory(bytes)
            .map_err(|e| Error::model(name, format!("ONNX Runtime rejected the model: {e}")))?;
        tracing::info!(
            model = name,
            dim,
            cameras = metadata.cameras.len(),
            threads,
            "loaded encoder"
        );
        // A crossview ensemble's members are readable from its graph; any other file that
        // keeps the contract is one block.
        let leading = crate::export::ensemble_from_model(name, &model, &metadata)
            .ok()
            .map(|e| e.members()[0].width())
            .filter(|&w| w > 0 && w <= dim)
            .unwrap_or(dim);
        Ok(OnnxEncoder {
            session,
            metadata,
            dim,
            leading,
            source: name.to_string(),
        })
    }

    /// The model's metadata (cameras, threshold, alpha, version, extras).
    pub fn metadata(&self) -> &ModelMetadata {
        &self.metadata
    }

    /// Embedding width G.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Where the model came from (path or name given to [`OnnxEncoder::from_bytes`]).
    pub fn source(&self) -> &str {
        &self.source
    }
}

/// A session builder's error (which carries the builder, not `Send`) with its message kept.
fn builder_err<R>(e: ort::Error<R>) -> Error {
    Error::runtime("cannot set the session's threads", e.to_string())
}

impl Encoder for OnnxEncoder {
    fn embed(&mut self, boxes: &[[f32; 4]], cameras: &[i64]) -> Result<Array2<f32>> {
        EncoderWeights::check_inputs(boxes, cameras, self.metadata.cameras.len())?;
        let n = boxes.len();
        if n == 0 {
            return Ok(Array2::zeros((0, self.dim)));
        }
        let flat: Vec<f32> = boxes.iter().flatten().copied().collect();
        let run_err =
            |e: ort::Error| Error::runtime(format!("{}: cannot pass the inputs", self.source), e);
        let boxes_t = TensorRef::from_array_view(([n, 4], flat.as_slice())).map_err(run_err)?;
        let cams_t = TensorRef::from_array_view(([n], cameras)).map_err(run_err)?;
        let source = &self.source;
        let outputs = self
            .session
            .run(ort::inputs![INPUT_BOXES => boxes_t, INPUT_CAMERA => cams_t])
            .map_err(|e| Error::runtime(format!("{source}: the session failed"), e))?;
        let (shape, data) = outputs[OUTPUT_EMBEDDING]
            .try_extract_tensor::<f32>()
            .map_err(|e| Error::runtime(format!("{source}: cannot read the output"), e))?;
        let dims: Vec<i64> = shape.iter().copied().collect();
        if dims != [n as i64, self.dim as i64] {
            return Err(Error::Encoder(format!(
                "{source}: output {OUTPUT_EMBEDDING} has shape {dims:?}, expected [{n}, {}]",
                self.dim
            )));
        }
        Ok(Array2::from_shape_vec((n, self.dim), data.to_vec()).expect("shape checked above"))
    }

    fn dim(&self) -> usize {
        self.dim
    }

    fn leading_width(&self) -> usize {
        self.leading
    }
}

/// `(elem_type, dims)` of a tensor value; `None` dims are symbolic or unknown.
fn tensor_sig(v: &ValueInfoProto) -> std::result::Result<(i32, Vec<Option<i64>>), String> {
    let t = v
        .r#type
        .as_ref()
        .and_then(|t| t.tensor_type.as_ref())
        .ok_or_else(|| format!("'{}' is not a tensor", v.name))?;
    let shape = t
        .shape
        .as_ref()
        .ok_or_else(|| format!("'{}' has no shape", v.name))?;
    let dims = shape
        .dim
        .iter()
        .map(|d| match d.value {
            Some(DimensionValue::DimValue(n)) => Some(n),
            _ => None,
        })
        .collect();
    Ok((t.elem_type, dims))
}

/// Checks the SPEC §8 graph contract; returns the embedding width G.
pub fn check_contract(
    model: &ModelProto,
    num_cameras: usize,
) -> std::result::Result<usize, String> {
    let graph = model.graph.as_ref().ok_or("no graph")?;
    let inits: std::collections::HashSet<&str> =
        graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs: Vec<&ValueInfoProto> = graph
        .input
        .iter()
        .filter(|v| !inits.contains(v.name.as_str()))
        .collect();
    let names: Vec<&str> = inputs.iter().map(|v| v.name.as_str()).collect();
    let mut sorted = names.clone();
    sorted.sort_unstable();
    if sorted != [INPUT_BOXES, INPUT_CAMERA] {
        return Err(format!(
            "graph inputs are {names:?}; expected exactly '{INPUT_BOXES}' (float32 [N, 4]) and '{INPUT_CAMERA}' (int64 [N])"
        ));
    }
    for v in inputs {
        let (ty, dims) = tensor_sig(v)?;
        let ok = if v.name == INPUT_BOXES {
            ty == DT_FLOAT && dims.len() == 2 && matches!(dims[1], None | Some(4))
        } else {
            ty == DT_INT64 && dims.len() == 1
        };
        if !ok {
            return Err(format!(
                "input '{}' has element type {ty} and dims {dims:?}; expected {}",
                v.name,
                if v.name == INPUT_BOXES {
                    "float32 [N, 4]"
                } else {
                    "int64 [N]"
                }
            ));
        }
    }
    let out = graph
        .output
        .iter()
        .find(|v| v.name == OUTPUT_EMBEDDING)
        .ok_or_else(|| {
            let names: Vec<&str> = graph.output.iter().map(|v| v.name.as_str()).collect();
            format!("graph outputs are {names:?}; expected '{OUTPUT_EMBEDDING}' (float32 [N, G])")
        })?;
    let (ty, dims) = tensor_sig(out)?;
    let dim = match dims[..] {
        [_, Some(g)] if ty == DT_FLOAT && g > 0 => g as usize,
        _ => {
            return Err(format!(
                "output '{OUTPUT_EMBEDDING}' has element type {ty} and dims {dims:?}; expected float32 [N, G] with a fixed G"
            ));
        }
    };
    // Every camera table (one per member of an ensemble) has a row per camera.
    let suffix = format!(".{INIT_CAMERA_EMBEDDING}");
    if let Some(t) = graph.initializer.iter().find(|t| {
        (t.name == INIT_CAMERA_EMBEDDING || t.name.ends_with(&suffix))
            && t.dims.first() != Some(&(num_cameras as i64))
    }) {
        return Err(format!(
            "{num_cameras} cameras in metadata but {} has dims {:?}",
            t.name, t.dims
        ));
    }
    Ok(dim)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_library_message_lists_places_and_fix() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("nope.so");
        let err = find_library(std::slice::from_ref(&a)).unwrap_err();
        assert!(
            err.contains("not found") && err.contains("nope.so"),
            "{err}"
        );
        assert!(
            err.contains("make setup") && err.contains("ORT_DYLIB_PATH"),
            "{err}"
        );
        std::fs::write(&a, b"x").unwrap();
        assert_eq!(
            find_library(&[dir.path().join("b.so"), a.clone()]).unwrap(),
            a
        );
    }

    #[test]
    fn candidates_start_with_env_then_project_cache() {
        let c = library_candidates();
        assert!(
            c.iter()
                .any(|p| p.ends_with(format!(".cache/onnxruntime/{ORT_LIBRARY_NAME}")))
        );
        assert!(c.iter().any(|p| p.starts_with("/usr/lib")));
    }
}

//! What a model file holds, for `crossview model info`: producer, opsets, the encoder's
//! width, its metadata, the graph's inputs and outputs, its size, and whether ONNX Runtime
//! accepts it.
use std::collections::HashSet;
use std::path::Path;

use crossview_core::{Error, Result};

use crate::onnx::{DimensionValue, ValueInfoProto};
use crate::{ModelMetadata, OnnxEncoder, export, runtime};

/// A model file, described.
#[derive(Debug, Clone)]
pub struct ModelSummary {
    /// `producer version (IR n, opsets domain:version,...)`.
    pub producer: String,
    /// Embedding width G (the graph's contract).
    pub dim: usize,
    /// The crossview metadata (cameras, threshold, alpha, calibration, version, extras).
    pub metadata: ModelMetadata,
    /// Graph inputs (initializers left out) and outputs: `name type [dims]`.
    pub inputs: Vec<String>,
    pub outputs: Vec<String>,
    /// Graph nodes and parameters.
    pub nodes: usize,
    pub parameters: usize,
    /// The width ONNX Runtime reports once it loaded the file.
    pub runtime_dim: usize,
}

/// Reads, decodes and checks the model file at `path` (the graph contract, the metadata, and
/// an ONNX Runtime session).
pub fn inspect(path: &Path) -> Result<ModelSummary> {
    let name = path.display().to_string();
    let bytes = export::read_model_file(path)?;
    let model = export::decode_model(&name, &bytes)?;
    let metadata = export::model_metadata(&name, &model)?;
    let dim = runtime::check_contract(&model, metadata.cameras.len())
        .map_err(|reason| Error::model(&name, reason))?;
    let graph = model
        .graph
        .as_ref()
        .ok_or_else(|| Error::model(&name, "no graph"))?;
    let opsets: Vec<String> = model
        .opset_import
        .iter()
        .map(|o| {
            let domain = if o.domain.is_empty() {
                "ai.onnx"
            } else {
                &o.domain
            };
            format!("{domain}:{}", o.version)
        })
        .collect();
    let producer = format!(
        "{} {} (IR {}, opsets {})",
        model.producer_name,
        model.producer_version,
        model.ir_version,
        opsets.join(",")
    );
    let inits: HashSet<&str> = graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs = graph
        .input
        .iter()
        .filter(|v| !inits.contains(v.name.as_str()))
        .map(describe)
        .collect();
    let outputs = graph.output.iter().map(describe).collect();
    let parameters = graph
        .initializer
        .iter()
        .map(|t| t.dims.iter().product::<i64>().max(0) as usize)
        .sum();
    let runtime_dim = OnnxEncoder::from_bytes(&name, &bytes)?.dim();
    Ok(ModelSummary {
        producer,
        dim,
        metadata,
        inputs,
        outputs,
        nodes: graph.node.len(),
        parameters,
        runtime_dim,
    })
}

/// `name type [dims]` of a graph value.
fn describe(v: &ValueInfoProto) -> String {
    let t = v.r#type.as_ref().and_then(|t| t.tensor_type.as_ref());
    let dims = t
        .and_then(|t| t.shape.as_ref())
        .map(|s| {
            s.dim
                .iter()
                .map(|d| match &d.value {
                    Some(DimensionValue::DimValue(n)) => n.to_string(),
                    Some(DimensionValue::DimParam(p)) => p.clone(),
                    None => "?".into(),
                })
                .collect::<Vec<_>>()
                .join(", ")
        })
        .unwrap_or_default();
    let ty = match t.map(|t| t.elem_type) {
        Some(1) => "float32".to_string(),
        Some(7) => "int64".to_string(),
        other => format!("type {other:?}"),
    };
    format!("{} {ty} [{dims}]", v.name)
}

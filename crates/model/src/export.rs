//! Writes [`EncoderWeights`] + [`ModelMetadata`] as one self-describing ONNX file (SPEC §8) and
//! reads such a file back (weights by initializer name, metadata from `metadata_props`).
//!
//! Graph (opset 17, IR version 8), for inputs `boxes` float32 `[N, 4]` and `camera` int64 `[N]`:
//! `tl = boxes[:, 0:2]`, `br = boxes[:, 2:4]`; per corner `p = ((2·v − 1) @ fourier_B) · 2π`,
//! `Sin(p)`, `Cos(p)`; `E = Gather(camera_embedding, camera)`;
//! `x0 = Concat(sin_tl, cos_tl, sin_br, cos_br, E)`; optional `Gemm(input_proj)`; per block
//! `Relu(LayerNormalization(Gemm(x, blocks.k) + x))`; output `embedding` float32 `[N, G]`.
use std::collections::BTreeMap;
use std::path::Path;

use prost::Message;

use super::onnx::{
    ATTR_FLOAT, ATTR_INT, AttributeProto, DT_FLOAT, DT_INT64, Dimension, GraphProto, ModelProto,
    NodeProto, OperatorSetIdProto, StringStringEntryProto, TensorProto, ValueInfoProto,
};
use super::{EncoderConfig, EncoderWeights, Linear, ModelMetadata};
use crossview_core::{Error, Result};

/// ONNX IR version written (IR 8 pairs with opset 17; ONNX Runtime 1.31 reads it).
pub(crate) const IR_VERSION: i64 = 8;
/// Default-domain opset written (LayerNormalization needs >= 17).
pub(crate) const OPSET_VERSION: i64 = 17;
/// Graph input: normalised boxes `[N, 4]`.
pub(crate) const INPUT_BOXES: &str = "boxes";
/// Graph input: camera indices `[N]`.
pub(crate) const INPUT_CAMERA: &str = "camera";
/// Graph output: embeddings `[N, G]`.
pub(crate) const OUTPUT_EMBEDDING: &str = "embedding";
/// Initializer names of the parameters (read back by [`read_weights`]).
pub(crate) const INIT_FOURIER: &str = "fourier_B";
/// Camera embedding table initializer.
pub(crate) const INIT_CAMERA_EMBEDDING: &str = "camera_embedding";
const INIT_INPUT_PROJ: &str = "input_proj";

fn block_name(k: usize) -> String {
    format!("blocks.{k}")
}

/// Serialises the encoder and its metadata as ONNX model bytes.
pub fn to_onnx_bytes(weights: &EncoderWeights, meta: &ModelMetadata) -> Result<Vec<u8>> {
    weights.validate()?;
    meta.validate("<export>")?;
    if meta.cameras.len() != weights.num_cameras {
        return Err(Error::invalid(
            "metadata.cameras",
            format!(
                "{} cameras in metadata but the encoder has {} camera embeddings",
                meta.cameras.len(),
                weights.num_cameras
            ),
        ));
    }
    let model = ModelProto {
        ir_version: IR_VERSION,
        producer_name: "crossview".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        doc_string: "Self-MVA box encoder (crossview SPEC §2, §8)".into(),
        graph: Some(build_graph(weights)),
        opset_import: vec![OperatorSetIdProto {
            domain: String::new(),
            version: OPSET_VERSION,
        }],
        metadata_props: meta
            .to_props()
            .into_iter()
            .map(|(key, value)| StringStringEntryProto { key, value })
            .collect(),
        ..Default::default()
    };
    Ok(model.encode_to_vec())
}

/// Writes the ONNX file atomically (temporary file + rename).
pub fn write_onnx(
    path: impl AsRef<Path>,
    weights: &EncoderWeights,
    meta: &ModelMetadata,
) -> Result<()> {
    let path = path.as_ref();
    let bytes = to_onnx_bytes(weights, meta)?;
    let tmp = path.with_extension("onnx.tmp");
    std::fs::write(&tmp, &bytes).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
    tracing::info!(path = %path.display(), bytes = bytes.len(), width = weights.width(), "wrote ONNX encoder");
    Ok(())
}

/// Reads an exported file back into weights and metadata (e.g. to resume training).
/// Any problem is [`Error::Model`] naming the path.
pub fn read_weights(path: impl AsRef<Path>) -> Result<(EncoderWeights, ModelMetadata)> {
    let path = path.as_ref();
    let name = path.display().to_string();
    let bytes = read_model_file(path)?;
    read_weights_from_bytes(&name, &bytes)
}

/// [`read_weights`] on in-memory bytes; `source_name` names them in errors.
pub(crate) fn read_weights_from_bytes(
    source_name: &str,
    bytes: &[u8],
) -> Result<(EncoderWeights, ModelMetadata)> {
    let model = decode_model(source_name, bytes)?;
    let meta = model_metadata(source_name, &model)?;
    let graph = model.graph.as_ref().expect("decode_model checks the graph");
    let weights = weights_from_graph(graph).map_err(|reason| Error::model(source_name, reason))?;
    weights
        .validate()
        .map_err(|e| Error::model(source_name, e.to_string()))?;
    if weights.num_cameras != meta.cameras.len() {
        return Err(Error::model(
            source_name,
            format!(
                "{} cameras in metadata but {} rows in {INIT_CAMERA_EMBEDDING}",
                meta.cameras.len(),
                weights.num_cameras
            ),
        ));
    }
    Ok((weights, meta))
}

/// Reads a model file, mapping every I/O problem to [`Error::Model`] naming the path.
pub fn read_model_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path)
        .map_err(|e| Error::model(path.display().to_string(), format!("cannot read: {e}")))
}

/// Decodes ONNX bytes; rejects empty input, undecodable bytes and a model without a graph.
pub fn decode_model(source_name: &str, bytes: &[u8]) -> Result<ModelProto> {
    if bytes.is_empty() {
        return Err(Error::model(source_name, "file is empty"));
    }
    let model = ModelProto::decode(bytes).map_err(|e| {
        Error::model(
            source_name,
            format!("not a valid ONNX model (protobuf decode failed: {e})"),
        )
    })?;
    if model.graph.is_none() || model.ir_version <= 0 {
        return Err(Error::model(
            source_name,
            "not an ONNX model (no graph or IR version)",
        ));
    }
    Ok(model)
}

/// Parses and validates the model's `metadata_props` (duplicate keys are an error).
pub fn model_metadata(source_name: &str, model: &ModelProto) -> Result<ModelMetadata> {
    let mut props = BTreeMap::new();
    for e in &model.metadata_props {
        if props.insert(e.key.clone(), e.value.clone()).is_some() {
            return Err(Error::model(
                source_name,
                format!("duplicate metadata key {}", e.key),
            ));
        }
    }
    ModelMetadata::from_props(source_name, &props)
}

// ---------------------------------------------------------------- graph construction

struct GraphBuilder {
    graph: GraphProto,
    counter: usize,
}

impl GraphBuilder {
    fn fresh(&mut self, hint: &str) -> String {
        self.counter += 1;
        format!("{hint}_{}", self.counter)
    }

    fn node(&mut self, op: &str, inputs: &[&str], output: &str, attrs: Vec<AttributeProto>) {
        let name = format!("{op}_{}", self.graph.node.len());
        self.graph.node.push(NodeProto {
            input: inputs.iter().map(|s| s.to_string()).collect(),
            output: vec![output.to_string()],
            name,
            op_type: op.to_string(),
            attribute: attrs,
            ..Default::default()
        });
    }

    /// Adds `op(inputs)` with a fresh output name and returns it.
    fn op(&mut self, op: &str, inputs: &[&str], attrs: Vec<AttributeProto>) -> String {
        let out = self.fresh(&op.to_lowercase());
        self.node(op, inputs, &out, attrs);
        out
    }

    fn f32_init(&mut self, name: &str, dims: &[usize], values: &[f32]) {
        let raw_data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.graph.initializer.push(TensorProto {
            dims: dims.iter().map(|&d| d as i64).collect(),
            data_type: DT_FLOAT,
            name: name.to_string(),
            raw_data,
            ..Default::default()
        });
    }

    fn i64_init(&mut self, name: &str, values: &[i64]) {
        let raw_data = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.graph.initializer.push(TensorProto {
            dims: vec![values.len() as i64],
            data_type: DT_INT64,
            name: name.to_string(),
            raw_data,
            ..Default::default()
        });
    }

    fn linear(&mut self, prefix: &str, lin: &Linear, x: &str) -> String {
        let (w, b) = (format!("{prefix}.weight"), format!("{prefix}.bias"));
        self.f32_init(&w, &[lin.out_dim, lin.in_dim], &lin.weight);
        self.f32_init(&b, &[lin.out_dim], &lin.bias);
        self.op("Gemm", &[x, &w, &b], vec![attr_int("transB", 1)])
    }
}

fn attr_int(name: &str, v: i64) -> AttributeProto {
    AttributeProto {
        name: name.into(),
        i: Some(v),
        r#type: ATTR_INT,
        ..Default::default()
    }
}

fn attr_float(name: &str, v: f32) -> AttributeProto {
    AttributeProto {
        name: name.into(),
        f: Some(v),
        r#type: ATTR_FLOAT,
        ..Default::default()
    }
}

fn build_graph(w: &EncoderWeights) -> GraphProto {
    let c = &w.config;
    let mut g = GraphBuilder {
        graph: GraphProto {
            name: "crossview_encoder".into(),
            ..Default::default()
        },
        counter: 0,
    };
    g.f32_init(INIT_FOURIER, &[2, c.fourier_features], &w.fourier);
    g.f32_init(
        INIT_CAMERA_EMBEDDING,
        &[w.num_cameras, c.camera_dim],
        &w.camera_embedding,
    );
    g.f32_init("const.two", &[], &[2.0]);
    g.f32_init("const.one", &[], &[1.0]);
    g.f32_init("const.two_pi", &[], &[2.0 * std::f32::consts::PI]);
    g.i64_init("const.idx0", &[0]);
    g.i64_init("const.idx1", &[1]);
    g.i64_init("const.idx2", &[2]);
    g.i64_init("const.idx4", &[4]);

    let mut features = Vec::new();
    for (start, end) in [("const.idx0", "const.idx2"), ("const.idx2", "const.idx4")] {
        let v = g.op("Slice", &[INPUT_BOXES, start, end, "const.idx1"], vec![]);
        let a = g.op("Mul", &[&v, "const.two"], vec![]);
        let u = g.op("Sub", &[&a, "const.one"], vec![]);
        let m = g.op("MatMul", &[&u, INIT_FOURIER], vec![]);
        let p = g.op("Mul", &[&m, "const.two_pi"], vec![]);
        features.push(g.op("Sin", &[&p], vec![]));
        features.push(g.op("Cos", &[&p], vec![]));
    }
    let e = g.op(
        "Gather",
        &[INIT_CAMERA_EMBEDDING, INPUT_CAMERA],
        vec![attr_int("axis", 0)],
    );
    features.push(e);
    let refs: Vec<&str> = features.iter().map(String::as_str).collect();
    let mut x = g.op("Concat", &refs, vec![attr_int("axis", 1)]);
    if let Some(p) = &w.input_proj {
        x = g.linear(INIT_INPUT_PROJ, p, &x);
    }
    if !w.blocks.is_empty() {
        g.f32_init("const.ln_scale", &[c.width], &vec![1.0; c.width]);
    }
    for (k, block) in w.blocks.iter().enumerate() {
        let h = g.linear(&block_name(k), block, &x);
        let s = g.op("Add", &[&h, &x], vec![]);
        let n = g.op(
            "LayerNormalization",
            &[&s, "const.ln_scale"],
            vec![
                attr_int("axis", -1),
                attr_float("epsilon", w.layer_norm_eps),
            ],
        );
        x = if k + 1 == w.blocks.len() {
            g.node("Relu", &[&n], OUTPUT_EMBEDDING, vec![]);
            OUTPUT_EMBEDDING.to_string()
        } else {
            g.op("Relu", &[&n], vec![])
        };
    }
    if x != OUTPUT_EMBEDDING {
        g.node("Identity", &[&x], OUTPUT_EMBEDDING, vec![]);
    }
    let n = || Dimension::symbolic("N");
    g.graph.input = vec![
        ValueInfoProto::tensor(INPUT_BOXES, DT_FLOAT, vec![n(), Dimension::fixed(4)]),
        ValueInfoProto::tensor(INPUT_CAMERA, DT_INT64, vec![n()]),
    ];
    g.graph.output = vec![ValueInfoProto::tensor(
        OUTPUT_EMBEDDING,
        DT_FLOAT,
        vec![n(), Dimension::fixed(c.width as i64)],
    )];
    g.graph
}

// ---------------------------------------------------------------- reading back

/// A float initializer's dims and values (raw little-endian or `float_data`).
fn float_tensor(t: &TensorProto) -> std::result::Result<(Vec<usize>, Vec<f32>), String> {
    if t.data_type != DT_FLOAT {
        return Err(format!(
            "initializer {} has data type {}, expected float32",
            t.name, t.data_type
        ));
    }
    if t.data_location != 0 || !t.external_data.is_empty() {
        return Err(format!(
            "initializer {} uses external data (unsupported)",
            t.name
        ));
    }
    if t.dims.iter().any(|&d| d < 0) {
        return Err(format!(
            "initializer {} has negative dims {:?}",
            t.name, t.dims
        ));
    }
    let dims: Vec<usize> = t.dims.iter().map(|&d| d as usize).collect();
    let count = dims
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or_else(|| format!("initializer {} is too large", t.name))?;
    let values: Vec<f32> = if !t.raw_data.is_empty() {
        if t.raw_data.len() != count * 4 {
            return Err(format!(
                "initializer {} holds {} bytes, expected {} for dims {:?}",
                t.name,
                t.raw_data.len(),
                count * 4,
                t.dims
            ));
        }
        t.raw_data
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect()
    } else {
        t.float_data.clone()
    };
    if values.len() != count {
        return Err(format!(
            "initializer {} holds {} values, expected {count} for dims {:?}",
            t.name,
            values.len(),
            t.dims
        ));
    }
    Ok((dims, values))
}

fn weights_from_graph(graph: &GraphProto) -> std::result::Result<EncoderWeights, String> {
    let inits: BTreeMap<&str, &TensorProto> = graph
        .initializer
        .iter()
        .map(|t| (t.name.as_str(), t))
        .collect();
    let get = |name: &str| -> std::result::Result<(Vec<usize>, Vec<f32>), String> {
        let t = inits
            .get(name)
            .ok_or_else(|| format!("initializer {name} is missing (not a crossview encoder?)"))?;
        float_tensor(t)
    };
    let matrix = |name: &str| -> std::result::Result<(usize, usize, Vec<f32>), String> {
        let (dims, v) = get(name)?;
        match dims[..] {
            [r, c] => Ok((r, c, v)),
            _ => Err(format!(
                "initializer {name} has dims {dims:?}, expected 2 axes"
            )),
        }
    };
    let linear = |prefix: &str| -> std::result::Result<Linear, String> {
        let (out_dim, in_dim, weight) = matrix(&format!("{prefix}.weight"))?;
        let (bdims, bias) = get(&format!("{prefix}.bias"))?;
        if bdims != [out_dim] {
            return Err(format!(
                "{prefix}.bias has dims {bdims:?}, expected [{out_dim}]"
            ));
        }
        Ok(Linear {
            in_dim,
            out_dim,
            weight,
            bias,
        })
    };
    let (two, fourier_features, fourier) = matrix(INIT_FOURIER)?;
    if two != 2 {
        return Err(format!("{INIT_FOURIER} has {two} rows, expected 2"));
    }
    let (num_cameras, camera_dim, camera_embedding) = matrix(INIT_CAMERA_EMBEDDING)?;
    let input_proj = if inits.contains_key(format!("{INIT_INPUT_PROJ}.weight").as_str()) {
        Some(linear(INIT_INPUT_PROJ)?)
    } else {
        None
    };
    let mut blocks = Vec::new();
    while inits.contains_key(format!("{}.weight", block_name(blocks.len())).as_str()) {
        blocks.push(linear(&block_name(blocks.len()))?);
    }
    let input_dim = 4 * fourier_features + camera_dim;
    let width = match (&input_proj, blocks.first()) {
        (Some(p), _) => p.out_dim,
        (None, Some(b)) => b.out_dim,
        (None, None) => input_dim,
    };
    let layer_norm_eps = graph
        .node
        .iter()
        .find(|n| n.op_type == "LayerNormalization")
        .and_then(|n| n.attribute.iter().find(|a| a.name == "epsilon"))
        .and_then(|a| a.f)
        .unwrap_or(super::weights::DEFAULT_LAYER_NORM_EPS);
    Ok(EncoderWeights {
        config: EncoderConfig {
            fourier_features,
            camera_dim,
            width,
            blocks: blocks.len(),
        },
        num_cameras,
        fourier,
        camera_embedding,
        input_proj,
        blocks,
        layer_norm_eps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crossview_core::testing::cameras;

    fn meta(n: usize) -> ModelMetadata {
        ModelMetadata::new(cameras(n, 100, 50))
    }

    #[test]
    fn bytes_round_trip() {
        for width in [20, 48] {
            let cfg = EncoderConfig {
                fourier_features: 8,
                camera_dim: 16,
                width,
                blocks: 2,
            };
            let w = EncoderWeights::random(3, cfg, 5).unwrap();
            let m = meta(3);
            let bytes = to_onnx_bytes(&w, &m).unwrap();
            let (w2, m2) = read_weights_from_bytes("x", &bytes).unwrap();
            assert_eq!(w2, w);
            assert_eq!(m2, m);
        }
    }

    #[test]
    fn camera_count_mismatch_is_rejected() {
        let w = EncoderWeights::random(3, EncoderConfig::default(), 5).unwrap();
        assert!(to_onnx_bytes(&w, &meta(2)).is_err());
    }
}

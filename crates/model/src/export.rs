//! Writes an encoder (or an [`Ensemble`] of them) + [`ModelMetadata`] as one self-describing
//! ONNX file (SPEC §8; the graph: [`crate::graph`]) and reads such a file back (weights by
//! initializer name, metadata from `metadata_props`).
use std::collections::BTreeMap;
use std::path::Path;

use prost::Message;

use super::ensemble::Ensemble;
use super::graph::{
    INIT_CAMERA_EMBEDDING, INIT_FOURIER, INIT_INPUT_PROJ, block_name, build_graph, member_prefix,
};
use super::onnx::{
    DT_FLOAT, GraphProto, ModelProto, OperatorSetIdProto, StringStringEntryProto, TensorProto,
};
use super::{EncoderConfig, EncoderWeights, Linear, ModelMetadata};
use crossview_core::{Error, Result};

/// ONNX IR version written (IR 8 pairs with opset 17; ONNX Runtime 1.31 reads it).
pub(crate) const IR_VERSION: i64 = 8;
/// Default-domain opset written (LayerNormalization needs >= 17).
pub(crate) const OPSET_VERSION: i64 = 17;

/// Serialises the encoder and its metadata as ONNX model bytes.
pub fn to_onnx_bytes(weights: &EncoderWeights, meta: &ModelMetadata) -> Result<Vec<u8>> {
    ensemble_to_onnx_bytes(&Ensemble::single(weights.clone()), meta)
}

/// Serialises an ensemble (one encoder or several) and its metadata as ONNX model bytes.
pub fn ensemble_to_onnx_bytes(ensemble: &Ensemble, meta: &ModelMetadata) -> Result<Vec<u8>> {
    for w in ensemble.members() {
        w.validate()?;
    }
    meta.validate("<export>")?;
    if meta.cameras.len() != ensemble.num_cameras() {
        return Err(Error::invalid(
            "metadata.cameras",
            format!(
                "{} cameras in metadata but the encoder has {} camera embeddings",
                meta.cameras.len(),
                ensemble.num_cameras()
            ),
        ));
    }
    let model = ModelProto {
        ir_version: IR_VERSION,
        producer_name: "crossview".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        doc_string: "Self-MVA box encoder (crossview SPEC §2, §8)".into(),
        graph: Some(build_graph(ensemble)),
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

/// Writes the ONNX file of one encoder atomically (temporary file + rename).
pub fn write_onnx(
    path: impl AsRef<Path>,
    weights: &EncoderWeights,
    meta: &ModelMetadata,
) -> Result<()> {
    write_ensemble_onnx(path, &Ensemble::single(weights.clone()), meta)
}

/// Writes the ONNX file of an ensemble atomically (temporary file + rename).
pub fn write_ensemble_onnx(
    path: impl AsRef<Path>,
    ensemble: &Ensemble,
    meta: &ModelMetadata,
) -> Result<()> {
    let path = path.as_ref();
    let bytes = ensemble_to_onnx_bytes(ensemble, meta)?;
    let tmp = path.with_extension("onnx.tmp");
    std::fs::write(&tmp, &bytes).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))?;
    tracing::info!(
        path = %path.display(),
        bytes = bytes.len(),
        width = ensemble.width(),
        members = ensemble.members().len(),
        "wrote ONNX encoder"
    );
    Ok(())
}

/// Reads an exported file of one encoder back into weights and metadata (e.g. to resume
/// training); an ensemble is refused. Any problem is [`Error::Model`] naming the path.
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
    let (ensemble, meta) = read_ensemble_from_bytes(source_name, bytes)?;
    let k = ensemble.members().len();
    match <[EncoderWeights; 1]>::try_from(ensemble.members().to_vec()) {
        Ok([only]) => Ok((only, meta)),
        Err(_) => Err(Error::model(
            source_name,
            format!("holds an ensemble of {k} encoders; this needs one encoder"),
        )),
    }
}

/// Reads an exported file (one encoder or an ensemble) back into its encoders and metadata.
/// Any problem is [`Error::Model`] naming the path.
pub fn read_ensemble(path: impl AsRef<Path>) -> Result<(Ensemble, ModelMetadata)> {
    let path = path.as_ref();
    let bytes = read_model_file(path)?;
    read_ensemble_from_bytes(&path.display().to_string(), &bytes)
}

/// [`read_ensemble`] on in-memory bytes; `source_name` names them in errors.
pub(crate) fn read_ensemble_from_bytes(
    source_name: &str,
    bytes: &[u8],
) -> Result<(Ensemble, ModelMetadata)> {
    let model = decode_model(source_name, bytes)?;
    let meta = model_metadata(source_name, &model)?;
    let ensemble = ensemble_from_model(source_name, &model, &meta)?;
    Ok((ensemble, meta))
}

/// The encoders of a decoded model file whose metadata is `meta` (see [`read_ensemble`]).
pub(crate) fn ensemble_from_model(
    source_name: &str,
    model: &ModelProto,
    meta: &ModelMetadata,
) -> Result<Ensemble> {
    let graph = model.graph.as_ref().expect("decode_model checks the graph");
    let inits: BTreeMap<&str, &TensorProto> = graph
        .initializer
        .iter()
        .map(|t| (t.name.as_str(), t))
        .collect();
    let prefixes: Vec<String> = if inits.contains_key(INIT_FOURIER) {
        vec![String::new()]
    } else {
        (0..)
            .map(member_prefix)
            .take_while(|p| inits.contains_key(format!("{p}{INIT_FOURIER}").as_str()))
            .collect()
    };
    if prefixes.is_empty() {
        return Err(Error::model(
            source_name,
            format!("initializer {INIT_FOURIER} is missing (not a crossview encoder?)"),
        ));
    }
    let members = prefixes
        .iter()
        .map(|p| weights_from_graph(graph, &inits, p))
        .collect::<std::result::Result<Vec<_>, String>>()
        .map_err(|reason| Error::model(source_name, reason))?;
    for w in &members {
        if w.num_cameras != meta.cameras.len() {
            return Err(Error::model(
                source_name,
                format!(
                    "{} cameras in metadata but {} rows in {INIT_CAMERA_EMBEDDING}",
                    meta.cameras.len(),
                    w.num_cameras
                ),
            ));
        }
    }
    Ensemble::new(members).map_err(|e| Error::model(source_name, e.to_string()))
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

/// The encoder whose initializers are named with `prefix` (`""` for a single encoder).
fn weights_from_graph(
    graph: &GraphProto,
    inits: &BTreeMap<&str, &TensorProto>,
    prefix: &str,
) -> std::result::Result<EncoderWeights, String> {
    let get = |name: &str| -> std::result::Result<(Vec<usize>, Vec<f32>), String> {
        let name = format!("{prefix}{name}");
        let t = inits
            .get(name.as_str())
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
    let linear = |layer: &str| -> std::result::Result<Linear, String> {
        let (out_dim, in_dim, weight) = matrix(&format!("{layer}.weight"))?;
        let (bdims, bias) = get(&format!("{layer}.bias"))?;
        if bdims != [out_dim] {
            return Err(format!(
                "{prefix}{layer}.bias has dims {bdims:?}, expected [{out_dim}]"
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
    let has = |name: String| inits.contains_key(format!("{prefix}{name}").as_str());
    let input_proj = if has(format!("{INIT_INPUT_PROJ}.weight")) {
        Some(linear(INIT_INPUT_PROJ)?)
    } else {
        None
    };
    let mut blocks = Vec::new();
    while has(format!("{}.weight", block_name(blocks.len()))) {
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

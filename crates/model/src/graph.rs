//! The ONNX graph of an encoder or an ensemble of encoders (SPEC §2, §8), built node by node.
//!
//! Graph (opset 17, IR version 8), for inputs `boxes` float32 `[N, 4]` and `camera` int64 `[N]`:
//! `tl = boxes[:, 0:2]`, `br = boxes[:, 2:4]`; per corner `p = ((2·v − 1) @ fourier_B) · 2π`,
//! `Sin(p)`, `Cos(p)`; `E = Gather(camera_embedding, camera)`;
//! `x0 = Concat(sin_tl, cos_tl, sin_br, cos_br, E)`; optional `Gemm(input_proj)`; per block
//! `Relu(LayerNormalization(Gemm(x, blocks.k) + x))`; output `embedding` float32 `[N, G]`.
//! An ensemble repeats this per member and concatenates the members' outputs, each times `1/√M`.
use super::ensemble::Ensemble;
use super::onnx::{
    ATTR_FLOAT, ATTR_INT, AttributeProto, DT_FLOAT, DT_INT64, Dimension, GraphProto, NodeProto,
    TensorProto, ValueInfoProto,
};
use super::{EncoderWeights, Linear};

/// Graph input: normalised boxes `[N, 4]`.
pub(crate) const INPUT_BOXES: &str = "boxes";
/// Graph input: camera indices `[N]`.
pub(crate) const INPUT_CAMERA: &str = "camera";
/// Graph output: embeddings `[N, G]`.
pub(crate) const OUTPUT_EMBEDDING: &str = "embedding";
/// Initializer names of the parameters (read back by `export::read_weights`).
pub(crate) const INIT_FOURIER: &str = "fourier_B";
/// Camera embedding table initializer.
pub(crate) const INIT_CAMERA_EMBEDDING: &str = "camera_embedding";
/// Input projection initializers' prefix.
pub(crate) const INIT_INPUT_PROJ: &str = "input_proj";

/// The initializer prefix of residual block `k`.
pub(crate) fn block_name(k: usize) -> String {
    format!("blocks.{k}")
}

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

/// The graph of one encoder (`members` of one: initializer names unprefixed, as SPEC §8
/// names them) or of an ensemble (member `k`'s initializers prefixed `m<k>.`; each member's
/// output scaled by `1/√M`, then concatenated).
pub(crate) fn build_graph(ensemble: &Ensemble) -> GraphProto {
    let mut g = GraphBuilder {
        graph: GraphProto {
            name: "crossview_encoder".into(),
            ..Default::default()
        },
        counter: 0,
    };
    add_constants(&mut g);
    match ensemble.members() {
        [only] => {
            add_encoder(&mut g, only, "", Some(OUTPUT_EMBEDDING));
        }
        members => {
            g.f32_init("const.ensemble_scale", &[], &[ensemble.scale()]);
            let parts: Vec<String> = members
                .iter()
                .enumerate()
                .map(|(k, w)| {
                    let x = add_encoder(&mut g, w, &member_prefix(k), None);
                    g.op("Mul", &[&x, "const.ensemble_scale"], vec![])
                })
                .collect();
            let refs: Vec<&str> = parts.iter().map(String::as_str).collect();
            g.node("Concat", &refs, OUTPUT_EMBEDDING, vec![attr_int("axis", 1)]);
        }
    }
    let n = || Dimension::symbolic("N");
    g.graph.input = vec![
        ValueInfoProto::tensor(INPUT_BOXES, DT_FLOAT, vec![n(), Dimension::fixed(4)]),
        ValueInfoProto::tensor(INPUT_CAMERA, DT_INT64, vec![n()]),
    ];
    g.graph.output = vec![ValueInfoProto::tensor(
        OUTPUT_EMBEDDING,
        DT_FLOAT,
        vec![n(), Dimension::fixed(ensemble.width() as i64)],
    )];
    g.graph
}

/// The prefix of member `k`'s initializer names in an ensemble's graph.
pub(crate) fn member_prefix(k: usize) -> String {
    format!("m{k}.")
}

/// Constants every encoder of the graph shares.
fn add_constants(g: &mut GraphBuilder) {
    g.f32_init("const.two", &[], &[2.0]);
    g.f32_init("const.one", &[], &[1.0]);
    g.f32_init("const.two_pi", &[], &[2.0 * std::f32::consts::PI]);
    g.i64_init("const.idx0", &[0]);
    g.i64_init("const.idx1", &[1]);
    g.i64_init("const.idx2", &[2]);
    g.i64_init("const.idx4", &[4]);
}

/// Adds one encoder's nodes (SPEC §2), its initializers named with `prefix`; its last node
/// writes `output` when given. Returns the name of its output value.
fn add_encoder(
    g: &mut GraphBuilder,
    w: &EncoderWeights,
    prefix: &str,
    output: Option<&str>,
) -> String {
    let c = &w.config;
    let fourier = format!("{prefix}{INIT_FOURIER}");
    let camera = format!("{prefix}{INIT_CAMERA_EMBEDDING}");
    g.f32_init(&fourier, &[2, c.fourier_features], &w.fourier);
    g.f32_init(&camera, &[w.num_cameras, c.camera_dim], &w.camera_embedding);
    let mut features = Vec::new();
    for (start, end) in [("const.idx0", "const.idx2"), ("const.idx2", "const.idx4")] {
        let v = g.op("Slice", &[INPUT_BOXES, start, end, "const.idx1"], vec![]);
        let a = g.op("Mul", &[&v, "const.two"], vec![]);
        let u = g.op("Sub", &[&a, "const.one"], vec![]);
        let m = g.op("MatMul", &[&u, &fourier], vec![]);
        let p = g.op("Mul", &[&m, "const.two_pi"], vec![]);
        features.push(g.op("Sin", &[&p], vec![]));
        features.push(g.op("Cos", &[&p], vec![]));
    }
    features.push(g.op(
        "Gather",
        &[&camera, INPUT_CAMERA],
        vec![attr_int("axis", 0)],
    ));
    let refs: Vec<&str> = features.iter().map(String::as_str).collect();
    let mut x = g.op("Concat", &refs, vec![attr_int("axis", 1)]);
    if let Some(p) = &w.input_proj {
        x = g.linear(&format!("{prefix}{INIT_INPUT_PROJ}"), p, &x);
    }
    let ln_scale = format!("{prefix}const.ln_scale");
    if !w.blocks.is_empty() {
        g.f32_init(&ln_scale, &[c.width], &vec![1.0; c.width]);
    }
    for (k, block) in w.blocks.iter().enumerate() {
        let h = g.linear(&format!("{prefix}{}", block_name(k)), block, &x);
        let s = g.op("Add", &[&h, &x], vec![]);
        let n = g.op(
            "LayerNormalization",
            &[&s, &ln_scale],
            vec![
                attr_int("axis", -1),
                attr_float("epsilon", w.layer_norm_eps),
            ],
        );
        x = match output {
            Some(out) if k + 1 == w.blocks.len() => {
                g.node("Relu", &[&n], out, vec![]);
                out.to_string()
            }
            _ => g.op("Relu", &[&n], vec![]),
        };
    }
    match output {
        Some(out) if x != out => {
            g.node("Identity", &[&x], out, vec![]);
            out.to_string()
        }
        _ => x,
    }
}

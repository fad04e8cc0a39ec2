//! The subset of the ONNX protobuf schema (`onnx/onnx.proto`, IR version 8) that crossview
//! writes and reads, declared by hand with `prost` derives. Field numbers follow the official
//! schema; fields we never use are left out (protobuf skips unknown fields when decoding).
//! Scalar fields use proto3-style defaults: an empty string or zero is simply not written.

/// `TensorProto.DataType.FLOAT`.
pub const DT_FLOAT: i32 = 1;
/// `TensorProto.DataType.INT64`.
pub(crate) const DT_INT64: i32 = 7;

/// `AttributeProto.AttributeType.FLOAT`.
pub(crate) const ATTR_FLOAT: i32 = 1;
/// `AttributeProto.AttributeType.INT`.
pub(crate) const ATTR_INT: i32 = 2;

/// A whole model file: IR version, opsets, graph and metadata.
#[derive(Clone, PartialEq, prost::Message)]
pub struct ModelProto {
    /// IR version of the file format.
    #[prost(int64, tag = "1")]
    pub ir_version: i64,
    /// Tool that wrote the file.
    #[prost(string, tag = "2")]
    pub producer_name: String,
    /// Version of that tool.
    #[prost(string, tag = "3")]
    pub producer_version: String,
    /// Reverse-DNS namespace (model) or operator domain (node/opset); empty = default ONNX domain.
    #[prost(string, tag = "4")]
    pub domain: String,
    /// Model version number.
    #[prost(int64, tag = "5")]
    pub model_version: i64,
    /// Human-readable documentation.
    #[prost(string, tag = "6")]
    pub doc_string: String,
    /// The computation graph.
    #[prost(message, optional, tag = "7")]
    pub graph: Option<GraphProto>,
    /// Operator sets used by the graph.
    #[prost(message, repeated, tag = "8")]
    pub opset_import: Vec<OperatorSetIdProto>,
    /// Free-form key/value metadata (SPEC §8 keys live here).
    #[prost(message, repeated, tag = "14")]
    pub metadata_props: Vec<StringStringEntryProto>,
}

/// An operator set the model relies on (empty domain = the default ONNX domain).
#[derive(Clone, PartialEq, prost::Message)]
pub struct OperatorSetIdProto {
    /// Reverse-DNS namespace (model) or operator domain (node/opset); empty = default ONNX domain.
    #[prost(string, tag = "1")]
    pub domain: String,
    /// Operator set version.
    #[prost(int64, tag = "2")]
    pub version: i64,
}

/// A key/value pair (ONNX's stand-in for a map).
#[derive(Clone, PartialEq, prost::Message)]
pub struct StringStringEntryProto {
    /// Entry key.
    #[prost(string, tag = "1")]
    pub key: String,
    /// Entry value, or the oneof value of a dimension.
    #[prost(string, tag = "2")]
    pub value: String,
}

/// A computation graph: nodes in topological order, constant initializers, inputs and outputs.
#[derive(Clone, PartialEq, prost::Message)]
pub struct GraphProto {
    /// Nodes in topological order.
    #[prost(message, repeated, tag = "1")]
    pub node: Vec<NodeProto>,
    /// Name (unique within its namespace).
    #[prost(string, tag = "2")]
    pub name: String,
    /// Constant tensors (the weights).
    #[prost(message, repeated, tag = "5")]
    pub initializer: Vec<TensorProto>,
    /// Human-readable documentation.
    #[prost(string, tag = "10")]
    pub doc_string: String,
    /// Graph inputs, or a node's input value names.
    #[prost(message, repeated, tag = "11")]
    pub input: Vec<ValueInfoProto>,
    /// Graph outputs, or a node's output value names.
    #[prost(message, repeated, tag = "12")]
    pub output: Vec<ValueInfoProto>,
    /// Optional types of intermediate values.
    #[prost(message, repeated, tag = "13")]
    pub value_info: Vec<ValueInfoProto>,
}

/// One operator application.
#[derive(Clone, PartialEq, prost::Message)]
pub struct NodeProto {
    /// Graph inputs, or a node's input value names.
    #[prost(string, repeated, tag = "1")]
    pub input: Vec<String>,
    /// Graph outputs, or a node's output value names.
    #[prost(string, repeated, tag = "2")]
    pub output: Vec<String>,
    /// Name (unique within its namespace).
    #[prost(string, tag = "3")]
    pub name: String,
    /// Operator name, e.g. `Gemm`.
    #[prost(string, tag = "4")]
    pub op_type: String,
    /// Operator attributes.
    #[prost(message, repeated, tag = "5")]
    pub attribute: Vec<AttributeProto>,
    /// Human-readable documentation.
    #[prost(string, tag = "6")]
    pub doc_string: String,
    /// Reverse-DNS namespace (model) or operator domain (node/opset); empty = default ONNX domain.
    #[prost(string, tag = "7")]
    pub domain: String,
}

/// A named operator attribute; `type` says which value field is in use.
#[derive(Clone, PartialEq, prost::Message)]
pub struct AttributeProto {
    /// Name (unique within its namespace).
    #[prost(string, tag = "1")]
    pub name: String,
    /// FLOAT value.
    #[prost(float, optional, tag = "2")]
    pub f: Option<f32>,
    /// INT value.
    #[prost(int64, optional, tag = "3")]
    pub i: Option<i64>,
    /// STRING value (bytes).
    #[prost(bytes = "vec", optional, tag = "4")]
    pub s: Option<Vec<u8>>,
    /// TENSOR value.
    #[prost(message, optional, tag = "5")]
    pub t: Option<TensorProto>,
    /// FLOATS value.
    #[prost(float, repeated, packed = "false", tag = "7")]
    pub floats: Vec<f32>,
    /// INTS value.
    #[prost(int64, repeated, packed = "false", tag = "8")]
    pub ints: Vec<i64>,
    /// Human-readable documentation.
    #[prost(string, tag = "13")]
    pub doc_string: String,
    /// Attribute type discriminator, or a value's type.
    #[prost(int32, tag = "20")]
    pub r#type: i32,
}

/// A serialized tensor. We write `raw_data` (little-endian); reading also accepts the typed
/// `float_data` / `int64_data` fields.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorProto {
    /// Tensor shape.
    #[prost(int64, repeated, packed = "false", tag = "1")]
    pub dims: Vec<i64>,
    /// Element type (`TensorProto.DataType`).
    #[prost(int32, tag = "2")]
    pub data_type: i32,
    /// Float payload (when `raw_data` is empty).
    #[prost(float, repeated, tag = "4")]
    pub float_data: Vec<f32>,
    /// Int64 payload (when `raw_data` is empty).
    #[prost(int64, repeated, tag = "7")]
    pub int64_data: Vec<i64>,
    /// Name (unique within its namespace).
    #[prost(string, tag = "8")]
    pub name: String,
    /// Little-endian fixed-width payload.
    #[prost(bytes = "vec", tag = "9")]
    pub raw_data: Vec<u8>,
    /// Human-readable documentation.
    #[prost(string, tag = "12")]
    pub doc_string: String,
    /// External-data location entries (unsupported when reading).
    #[prost(message, repeated, tag = "13")]
    pub external_data: Vec<StringStringEntryProto>,
    /// 0 = inline, 1 = external.
    #[prost(int32, tag = "14")]
    pub data_location: i32,
}

/// A graph input or output: name and type.
#[derive(Clone, PartialEq, prost::Message)]
pub struct ValueInfoProto {
    /// Name (unique within its namespace).
    #[prost(string, tag = "1")]
    pub name: String,
    /// Attribute type discriminator, or a value's type.
    #[prost(message, optional, tag = "2")]
    pub r#type: Option<TypeProto>,
    /// Human-readable documentation.
    #[prost(string, tag = "3")]
    pub doc_string: String,
}

/// A value type. Only tensors are modelled; sequence/map types decode as `tensor_type: None`.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TypeProto {
    /// Set when the value is a tensor.
    #[prost(message, optional, tag = "1")]
    pub tensor_type: Option<TypeProtoTensor>,
    /// Optional semantic denotation.
    #[prost(string, tag = "6")]
    pub denotation: String,
}

/// `TypeProto.Tensor`: element type and (optional) shape.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TypeProtoTensor {
    /// Element type (`TensorProto.DataType`).
    #[prost(int32, tag = "1")]
    pub elem_type: i32,
    /// Shape, when known.
    #[prost(message, optional, tag = "2")]
    pub shape: Option<TensorShapeProto>,
}

/// A tensor shape: one entry per axis.
#[derive(Clone, PartialEq, prost::Message)]
pub struct TensorShapeProto {
    /// One entry per axis.
    #[prost(message, repeated, tag = "1")]
    pub dim: Vec<Dimension>,
}

/// `TensorShapeProto.Dimension`: a fixed size, a symbolic name, or unknown.
#[derive(Clone, PartialEq, prost::Message)]
pub struct Dimension {
    /// Entry value, or the oneof value of a dimension.
    #[prost(oneof = "DimensionValue", tags = "1, 2")]
    pub value: Option<DimensionValue>,
    /// Optional semantic denotation.
    #[prost(string, tag = "3")]
    pub denotation: String,
}

/// The `value` oneof of a [`Dimension`].
#[derive(Clone, PartialEq, prost::Oneof)]
pub enum DimensionValue {
    /// A fixed size.
    #[prost(int64, tag = "1")]
    DimValue(i64),
    /// A symbolic size such as `"N"`.
    #[prost(string, tag = "2")]
    DimParam(String),
}

impl Dimension {
    /// A fixed-size axis.
    pub fn fixed(n: i64) -> Self {
        Dimension {
            value: Some(DimensionValue::DimValue(n)),
            denotation: String::new(),
        }
    }

    /// A symbolic (dynamic) axis.
    pub fn symbolic(name: &str) -> Self {
        Dimension {
            value: Some(DimensionValue::DimParam(name.to_string())),
            denotation: String::new(),
        }
    }
}

impl ValueInfoProto {
    /// A tensor-typed graph input/output.
    pub fn tensor(name: &str, elem_type: i32, dims: Vec<Dimension>) -> Self {
        ValueInfoProto {
            name: name.to_string(),
            r#type: Some(TypeProto {
                tensor_type: Some(TypeProtoTensor {
                    elem_type,
                    shape: Some(TensorShapeProto { dim: dims }),
                }),
                denotation: String::new(),
            }),
            doc_string: String::new(),
        }
    }
}

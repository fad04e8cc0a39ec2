//! The model file contract (SPEC §8) through the real ONNX Runtime: export, round trips,
//! corrupt files, and a property test over arbitrary inputs.

mod export;
mod props;

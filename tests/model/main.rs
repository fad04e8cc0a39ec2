//! The model file contract (SPEC §8) through the real ONNX Runtime: export, round trips,
//! corrupt files, ensembles of encoders, and a property test over arbitrary inputs.

mod ensemble;
mod export;
mod props;

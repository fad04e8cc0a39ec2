//! Self-supervised training (SPEC §2–§4) with candle, exporting SPEC §8 ONNX files.

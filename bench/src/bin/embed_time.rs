//! Embedding time per frame of exported encoders on a real recording: every frame's boxes
//! (all cameras) in one `OnnxEncoder::embed` call, single-threaded ONNX Runtime.
//!
//! `cargo run --release --example embed_time -- RECORDING.jsonl MODEL.onnx [MODEL.onnx ...]`
use std::time::Instant;

use crossview_core::Encoder;
use crossview_data::recording::read_recording;
use crossview_model::OnnxEncoder;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() >= 2,
        "usage: embed_time RECORDING.jsonl MODEL.onnx..."
    );
    let rec = read_recording(&args[0])?;
    let frames: Vec<(Vec<[f32; 4]>, Vec<i64>)> = rec
        .frames
        .iter()
        .map(|f| {
            let mut b = Vec::new();
            let mut c = Vec::new();
            for (i, v) in f.views.iter().enumerate() {
                for d in v.iter().flatten() {
                    b.push(d.normalized(&rec.scene.cameras[i]));
                    c.push(i as i64);
                }
            }
            (b, c)
        })
        .collect();
    let boxes: usize = frames.iter().map(|f| f.0.len()).sum();
    println!("| model | width | boxes/frame | ms/frame |");
    println!("|---|---:|---:|---:|");
    for path in &args[1..] {
        let mut enc = OnnxEncoder::load(path)?;
        for (b, c) in &frames {
            enc.embed(b, c)?; // warm-up
        }
        let reps = 5;
        let t = Instant::now();
        for _ in 0..reps {
            for (b, c) in &frames {
                enc.embed(b, c)?;
            }
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / (reps * frames.len()) as f64;
        println!(
            "| {path} | {} | {:.0} | {ms:.3} |",
            enc.dim(),
            boxes as f64 / frames.len() as f64
        );
    }
    Ok(())
}

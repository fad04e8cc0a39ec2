//! Dumps what the identity step sees, for method studies outside Rust: per frame, the box
//! counts, the ground-truth ids and every camera pair's raw geometric distance matrix (plus
//! the model's calibration table once).
//!
//! `cargo run --release -p crossview-bench --bin identity_dump -- MODEL.onnx RECORDING.jsonl OUT.jsonl`
use std::io::Write;

use crossview_core::association::embed_frame;
use crossview_core::distances::euclidean_distances;
use crossview_data::recording::read_recording;
use crossview_model::OnnxEncoder;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() == 3,
        "usage: identity_dump MODEL.onnx RECORDING.jsonl OUT.jsonl"
    );
    let mut enc = OnnxEncoder::load(&args[0])?;
    let rec = read_recording(&args[1])?;
    let mut out = std::io::BufWriter::new(std::fs::File::create(&args[2])?);
    let cal = enc.metadata().calibration.clone();
    writeln!(
        out,
        "{}",
        serde_json::json!({ "calibration": cal.as_deref() })
    )?;
    for frame in &rec.frames {
        let emb = embed_frame(&mut enc, &rec.scene, frame)?;
        let n = frame.views.len();
        let ids: Vec<Vec<u64>> = frame
            .views
            .iter()
            .map(|v| {
                v.iter()
                    .flatten()
                    .map(|d| d.id.unwrap_or(u64::MAX))
                    .collect()
            })
            .collect();
        let mut pairs = Vec::new();
        for a in 0..n {
            for b in a + 1..n {
                let (Some(x), Some(y)) = (emb.view(a), emb.view(b)) else {
                    continue;
                };
                if x.nrows() == 0 || y.nrows() == 0 {
                    continue;
                }
                let d = euclidean_distances(x, y);
                pairs.push(serde_json::json!({
                    "a": a, "b": b, "shape": [d.nrows(), d.ncols()],
                    "d": d.iter().copied().collect::<Vec<f32>>(),
                }));
            }
        }
        writeln!(
            out,
            "{}",
            serde_json::json!({ "frame": frame.frame_id, "ids": ids, "pairs": pairs })
        )?;
    }
    Ok(())
}

//! In-process frames/s of encoder + pairwise matchings (+ identities with `--identities`) on a
//! recording, the Rust side of `bench/compare_python.sh` (same work as the Python reference,
//! frames dealt to `--workers` threads).
//!
//! `cargo run --release -p crossview-bench --bin pipeline -- --model M.onnx --data R.jsonl`
use clap::Parser;

/// `pipeline`: in-process frames/s of encoder + pairwise matchings
/// (+ identities on request) on a recording (the Rust side of `bench/compare_python.sh`).
#[derive(Debug, Parser)]
struct BenchPipelineArgs {
    /// Model file (SPEC §8 ONNX) for the recording's scene.
    #[arg(long)]
    model: std::path::PathBuf,
    /// Recording (SPEC §7 JSONL); ids, if any, are ignored.
    #[arg(long)]
    data: std::path::PathBuf,
    /// ONNX Runtime intra-op threads per worker (inter-op is always 1).
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Worker threads, each with its own encoder session; frames are dealt round-robin.
    #[arg(long, default_value_t = 1)]
    workers: usize,
    /// Also build the global identities (work the reference pipeline does not do).
    #[arg(long)]
    identities: bool,
    /// Untimed warm-up frames (per worker).
    #[arg(long, default_value_t = 20)]
    warmup: usize,
    /// Timed passes over the recording.
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    /// Confidence threshold (default: the model's).
    #[arg(long)]
    threshold: Option<f32>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
}

fn main() -> anyhow::Result<()> {
    let args = BenchPipelineArgs::parse();
    run(args)
}

fn run(args: BenchPipelineArgs) -> anyhow::Result<()> {
    use crossview_model::{EncoderOptions, OnnxEncoder};
    let recording = crossview_data::read_recording(&args.data)?;
    let mut encoders = (0..args.workers.max(1))
        .map(|_| {
            OnnxEncoder::load_with(
                &args.model,
                EncoderOptions {
                    intra_threads: args.threads,
                },
            )
        })
        .collect::<crossview_core::Result<Vec<_>>>()?;
    let threshold = args.threshold.unwrap_or(encoders[0].metadata().threshold);
    let t = crossview_eval::throughput::measure(
        &mut encoders,
        &recording,
        threshold,
        args.identities,
        args.warmup,
        args.repeat,
    )?;
    if args.json {
        println!("{}", serde_json::to_string(&t)?);
    } else {
        println!(
            "rust: {:.1} frames/s ({} frames, {:.1} boxes and {:.1} camera pairs per frame, encoder {:.0}% of busy time, {:.2} s wall, {} worker(s) × {} ORT thread(s), identities {}); kept matches (one pass): {}",
            t.frames_per_second,
            t.frames,
            t.boxes_per_frame,
            t.pairs_per_frame,
            100.0 * t.encoder_seconds / t.worker_seconds.max(f64::MIN_POSITIVE),
            t.seconds,
            t.workers,
            args.threads,
            t.identities,
            t.kept_matches
        );
    }
    Ok(())
}

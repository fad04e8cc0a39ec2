//! How the capture-time phase follower ([`crossview_core::capture::CameraPhase`], the rule the
//! server places timed batches by) does with its block sizes moved ±50 %: synthetic cameras at
//! 10 frames/s for 10 minutes, each with a clock offset uniform over the period, jitter uniform
//! in ±`--jitter-ms` and a drift of `--drift` ms per minute, 200 cameras per setting. A capture
//! is *misplaced* when its tick is not the one its camera's numbering 15 s in gives it (a
//! constant renumbering is the clock watch's whole frames to fix; a change after it is not).
//! Prints a Markdown table.
//!
//! Usage: phase_sweep [--jitter-ms 40] [--drift 20] [--cameras 200]
use clap::Parser;
use crossview_core::capture::{CameraPhase, CaptureTime, PhaseTracker, Ticks, TrackerSettings};
use rand::{Rng, SeedableRng};

#[derive(Parser)]
struct Args {
    #[arg(long, default_value_t = 40.0)]
    jitter_ms: f64,
    #[arg(long, default_value_t = 20.0)]
    drift: f64,
    #[arg(long, default_value_t = 200)]
    cameras: u64,
    #[arg(long, default_value_t = 6000)]
    frames: u64,
}

/// Misplaced captures after 15 s, after 60 s, and the largest phase error after 60 s (ms).
fn run(args: &Args, settings: TrackerSettings, seed: u64) -> (usize, usize, f64) {
    let ticks = Ticks::new(10.0).expect("a rate");
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let offset = rng.random_range(0.0..100.0);
    let t0 = 1_796_515_200_000.0;
    let mut cam = CameraPhase::with_settings(0, settings);
    let (mut after15, mut after60, mut worst) = (0, 0, 0.0f64);
    let mut shift = None;
    for k in 0..args.frames {
        let clock = offset + args.drift * (k as f64 / 10.0) / 60.0;
        let jitter = rng.random_range(-args.jitter_ms..=args.jitter_ms);
        let ms = t0 + k as f64 * 100.0 + clock + jitter;
        let time = CaptureTime::from_unix_nanos((ms * 1e6) as i64).expect("a time");
        let p = cam.place(&ticks, time).expect("after 1970");
        let truth = (t0 / 100.0) as i64 + k as i64;
        // The numbering the camera has 15 s in (the watch's whole frames fix any constant
        // one; the first captures may still renumber it once, during the warm-up).
        if k == 150 {
            shift = Some(p.tick as i64 - truth);
        }
        let s = shift.unwrap_or(p.tick as i64 - truth);
        if k >= 150 && p.tick as i64 - truth != s {
            after15 += 1;
            after60 += usize::from(k >= 600);
        }
        cam.accept(&p);
        if k >= 600 {
            let err = cam.offset_ms() - (clock - 100.0 * s as f64);
            worst = worst.max(err.abs());
        }
    }
    (after15, after60, worst)
}

fn main() {
    let args = Args::parse();
    let d = TrackerSettings::default();
    let mut settings = vec![("default".to_string(), d)];
    for f in [0.5, 1.5] {
        let w = ((d.warmup as f64 * f).round() as usize).max(1);
        settings.push((format!("warm-up {w}"), TrackerSettings { warmup: w, ..d }));
        let g = d.gain * f;
        settings.push((format!("gain {g}"), TrackerSettings { gain: g, ..d }));
    }
    println!(
        "jitter ±{} ms, drift {} ms/min, {} cameras × {} frames at 10 frames/s (defaults: warm-up {}, gain {})",
        args.jitter_ms,
        args.drift,
        args.cameras,
        args.frames,
        PhaseTracker::WARMUP,
        PhaseTracker::GAIN
    );
    println!(
        "| setting | cameras with a misplaced capture after 15 s | captures misplaced after 15 s | after 60 s | worst phase error after 60 s, ms |"
    );
    println!("|---|---|---|---|---|");
    for (name, sizes) in settings {
        let sizes: TrackerSettings = sizes;
        let (mut cams, mut m15, mut m60, mut worst) = (0, 0, 0, 0.0f64);
        for seed in 0..args.cameras {
            let (a, b, w) = run(&args, sizes, seed);
            cams += usize::from(a > 0);
            m15 += a;
            m60 += b;
            worst = worst.max(w);
        }
        println!("| {name} | {cams} | {m15} | {m60} | {worst:.1} |");
    }
}

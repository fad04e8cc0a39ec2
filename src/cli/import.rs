//! `crossview import ...` (dataset importers) and `crossview split` (chronological split of a
//! recording). Both write SPEC §7 recordings and print a one-line summary.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, Subcommand, ValueEnum};

use crossview_data::{Part, Recording, read_recording, split_bounds, write_recording};
use crossview_data::{mvor, wildtrack};

/// `crossview import <dataset>`: convert a dataset into a recording.
#[derive(Debug, Args)]
pub struct ImportArgs {
    #[command(subcommand)]
    pub source: ImportSource,
}

/// The importable datasets.
#[derive(Debug, Subcommand)]
pub enum ImportSource {
    /// WILDTRACK ground truth from an `annotations_positions/` folder (boxes carry person ids).
    WildtrackGt(WildtrackGtArgs),
    /// WILDTRACK detector boxes from a Self-MVA detections JSON (e.g. `detections_train.json`).
    WildtrackDetections(WildtrackDetectionsArgs),
    /// MVOR ground truth from `camma_mvor_2018_v2.json` (boxes carry person ids; 732 frames).
    MvorGt(FileArgs),
    /// MVOR detector boxes from Self-MVA's `data/MVOR/sequence1/output/detections_train.json`.
    MvorDetections(FileArgs),
}

/// Options of an importer that reads one file.
#[derive(Debug, Args)]
pub struct FileArgs {
    /// The dataset's file.
    #[arg(long)]
    pub file: PathBuf,
    /// Output recording (`-` = stdout).
    #[arg(long)]
    pub out: PathBuf,
}

/// Options of `import wildtrack-gt`.
#[derive(Debug, Args)]
pub struct WildtrackGtArgs {
    /// The `annotations_positions/` folder.
    #[arg(long, env = "CROSSVIEW_WILDTRACK_GT_DIR")]
    pub dir: PathBuf,
    /// First frame id to import (inclusive).
    #[arg(long, conflicts_with = "split")]
    pub from: Option<u64>,
    /// Last frame id to import (inclusive).
    #[arg(long, conflicts_with = "split")]
    pub to: Option<u64>,
    /// Import one part of the chronological split of the full sequence 0..=1995
    /// (train 0..=1435, val 1440..=1795, test 1800..=1995).
    #[arg(long)]
    pub split: Option<Part>,
    /// Output recording (`-` = stdout).
    #[arg(long)]
    pub out: PathBuf,
}

/// Options of `import wildtrack-detections`.
#[derive(Debug, Args)]
pub struct WildtrackDetectionsArgs {
    /// The detections JSON `{"<index>": [[x, y, w, h, id, viewNum], ...]}`.
    #[arg(long)]
    pub file: PathBuf,
    /// Frame id = stride x index.
    #[arg(long, default_value_t = 5)]
    pub stride: u64,
    /// Output recording (`-` = stdout).
    #[arg(long)]
    pub out: PathBuf,
}

/// Which frame sequence `split` divides.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum SequenceChoice {
    /// WILDTRACK's full sequence when the scene is `wildtrack`, else the recording's frames.
    Auto,
    /// The recording's own frames.
    Recording,
    /// WILDTRACK's full sequence 0..=1995 step 5.
    Wildtrack,
}

/// `crossview split`: keep one part of the chronological split (SPEC §6) of a recording.
#[derive(Debug, Args)]
pub struct SplitArgs {
    /// Input recording (`-` = stdin).
    #[arg(long, env = "CROSSVIEW_DATA")]
    pub data: PathBuf,
    /// The part to keep.
    #[arg(long)]
    pub part: Part,
    /// The sequence to split. With `auto`, a `wildtrack` recording is split by the full
    /// 400-frame sequence (its GT folder lacks the test frames), anything else by its own frames.
    #[arg(long, value_enum, default_value_t = SequenceChoice::Auto)]
    pub sequence: SequenceChoice,
    /// Output recording (`-` = stdout).
    #[arg(long)]
    pub out: PathBuf,
}

/// One line: where it went, frames, boxes, cameras (to stderr when the output is stdout).
fn summarize(rec: &Recording, out: &std::path::Path, extra: &str) {
    let line = format!(
        "{}: {} frames ({}), {} boxes, {} cameras ({}){extra}",
        out.display(),
        rec.frames.len(),
        match (rec.frames.first(), rec.frames.last()) {
            (Some(a), Some(b)) => format!("{}..={}", a.frame_id, b.frame_id),
            _ => "none".to_string(),
        },
        rec.num_boxes(),
        rec.scene.cameras.len(),
        rec.scene
            .cameras
            .iter()
            .map(|c| c.name.as_str())
            .collect::<Vec<_>>()
            .join(", "),
    );
    if out == std::path::Path::new("-") {
        eprintln!("{line}");
    } else {
        println!("{line}");
    }
}

/// Runs `crossview import`.
pub fn run(args: ImportArgs) -> anyhow::Result<()> {
    let (imported, out) = match args.source {
        ImportSource::WildtrackGt(a) => {
            let (from, to) = match a.split {
                Some(part) => {
                    let (lo, hi) = wildtrack::part_bounds(part);
                    (Some(lo), Some(hi))
                }
                None => (a.from, a.to),
            };
            let imported = wildtrack::import_ground_truth(&a.dir, from, to).with_context(|| {
                format!("importing WILDTRACK ground truth from {}", a.dir.display())
            })?;
            (imported, a.out)
        }
        ImportSource::WildtrackDetections(a) => {
            let imported = wildtrack::import_detections(&a.file, a.stride).with_context(|| {
                format!("importing WILDTRACK detections from {}", a.file.display())
            })?;
            (imported, a.out)
        }
        ImportSource::MvorGt(a) => {
            let imported = mvor::import_ground_truth(&a.file).with_context(|| {
                format!("importing MVOR ground truth from {}", a.file.display())
            })?;
            (imported, a.out)
        }
        ImportSource::MvorDetections(a) => {
            let imported = mvor::import_detections(&a.file)
                .with_context(|| format!("importing MVOR detections from {}", a.file.display()))?;
            (imported, a.out)
        }
    };
    write_recording(&out, &imported.recording)
        .with_context(|| format!("writing {}", out.display()))?;
    summarize(
        &imported.recording,
        &out,
        &format!(
            "; clipped {} boxes, dropped {} (empty after clipping, or linked to no person)",
            imported.clipped, imported.dropped
        ),
    );
    Ok(())
}

/// Runs `crossview split`.
pub fn run_split(args: SplitArgs) -> anyhow::Result<()> {
    let rec =
        read_recording(&args.data).with_context(|| format!("reading {}", args.data.display()))?;
    let use_wildtrack = match args.sequence {
        SequenceChoice::Auto => rec.scene.name == wildtrack::SCENE_NAME,
        SequenceChoice::Recording => false,
        SequenceChoice::Wildtrack => true,
    };
    let (sequence, ids) = if use_wildtrack {
        ("wildtrack 0..=1995 step 5", wildtrack::sequence_frame_ids())
    } else {
        ("the recording's frames", rec.frame_ids())
    };
    let Some((lo, hi)) = split_bounds(&ids, args.part)? else {
        bail!(
            "the {} part of {} ({} frames) is empty",
            args.part,
            args.data.display(),
            ids.len()
        );
    };
    let part = rec.filter_frames(lo..=hi);
    if part.frames.is_empty() {
        bail!(
            "{} has no frame in the {} part {lo}..={hi} of {sequence}",
            args.data.display(),
            args.part
        );
    }
    write_recording(&args.out, &part).with_context(|| format!("writing {}", args.out.display()))?;
    summarize(
        &part,
        &args.out,
        &format!("; {} = {lo}..={hi} of {sequence}", args.part),
    );
    Ok(())
}

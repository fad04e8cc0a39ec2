//! The memory's measurement driver (BENCHMARKS.md, "Identities with memory"): every frame of a
//! recording with ground-truth ids embedded once, then associated in frame order under each
//! setting with a fresh [`Memory`], scored as `crossview eval` scores identities (ACC /
//! IPAA-100 of the identity-implied matches), with the per-camera links' precision and recall
//! and the tracker's IDF1 on top.
//!
//! `memory_sweep MODEL.onnx RECORDING.jsonl [--spread] [--oracle] SETTING...` where a SETTING
//! is `default`, `0` (every frame alone) or `CARRY:HOLD:WEIGHT:GATE:MARGIN` (the fields of
//! [`MemoryConfig`]); `--spread` adds each setting with one parameter at a time moved by −50 %
//! and +50 % (λ capped at 0.99); `--oracle` links each camera's boxes by their ground-truth ids
//! (the upper bound of the method). The last two columns count, over all frames, the pairs of
//! different people one identity merged, and those of them the frame alone did not merge.
use std::collections::HashMap;

use anyhow::bail;

use crossview_core::association::{AssociationConfig, Mode, associate_frame_with, embed_frame};
use crossview_core::memory::{Memory, MemoryConfig};
use crossview_core::tracking::{Tracker, TrackerConfig};
use crossview_core::{FrameEmbeddings, Result};
use crossview_data::Recording;
use crossview_data::recording::read_recording;
use crossview_eval::driver::{frame_ids, pair_records};
use crossview_eval::identities::IdentityStats;
use crossview_eval::metrics::compute_metrics;
use crossview_eval::tracking::{Observation, score_tracks};
use crossview_model::OnnxEncoder;

fn parse_setting(s: &str) -> anyhow::Result<Option<MemoryConfig>> {
    if s == "default" {
        return Ok(Some(MemoryConfig::default()));
    }
    let v: Vec<f32> = s.split(':').map(str::parse).collect::<Result<_, _>>()?;
    match v[..] {
        [0.0] => Ok(None),
        [carry, hold, link_weight, link_gate, link_margin] => Ok(Some(MemoryConfig {
            carry,
            hold,
            link_weight,
            link_gate,
            link_margin,
            ..MemoryConfig::default()
        })),
        _ => bail!("setting '{s}': expected default, 0 or CARRY:HOLD:WEIGHT:GATE:MARGIN"),
    }
}

/// One setting's scores.
struct Row {
    acc: f64,
    ipaa: f64,
    right: f64,
    link_precision: f64,
    link_recall: f64,
    idf1: f64,
    idf1_min: f64,
    /// Per frame, the pairs of ground-truth ids that one identity merged.
    merges: Vec<Vec<(u64, u64)>>,
    /// Mean time of `associate_frame_with` per frame (µs).
    micros: f64,
}

/// The pairs of distinct ground-truth ids that share an identity.
fn merged_pairs(
    identities: &[crossview_core::identity::Identity],
    ids: &[Option<Vec<u64>>],
) -> Vec<(u64, u64)> {
    let mut out = Vec::new();
    for ident in identities {
        let gts: Vec<u64> = ident
            .members
            .iter()
            .filter_map(|&(c, i)| ids.get(c)?.as_ref()?.get(i).copied())
            .collect();
        for (x, &p) in gts.iter().enumerate() {
            for &q in &gts[x + 1..] {
                if p != q {
                    out.push((p.min(q), p.max(q)));
                }
            }
        }
    }
    out.sort_unstable();
    out.dedup();
    out
}

fn run(
    rec: &Recording,
    embs: &[FrameEmbeddings],
    base: &AssociationConfig,
    mem: Option<&MemoryConfig>,
) -> Result<Row> {
    let mut memory = mem.map(|m| Memory::new(m.clone()));
    let mut tracker = Tracker::new(TrackerConfig::default());
    let (mut records, mut stats, mut obs) = (
        Vec::new(),
        IdentityStats::default(),
        Vec::<Observation>::new(),
    );
    let (mut linked, mut right, mut continuing, mut found) = (0usize, 0usize, 0usize, 0usize);
    let mut last_ids: HashMap<usize, Vec<u64>> = HashMap::new();
    let mut merges = Vec::new();
    let mut spent = std::time::Duration::ZERO;
    for (frame, emb) in rec.frames.iter().zip(embs) {
        let ids = frame_ids(&rec.scene, frame)?;
        let e = emb.clone();
        let t0 = std::time::Instant::now();
        let assoc = associate_frame_with(frame, e, base, memory.as_mut());
        spent += t0.elapsed();
        stats.add_frame(&assoc.identities, &ids);
        merges.push(merged_pairs(&assoc.identities, &ids));
        records.extend(pair_records(&rec.scene, &ids, &assoc));
        let tracks = tracker.update(frame, &assoc.identities, &assoc.embeddings);
        for (identity, track) in assoc.identities.iter().zip(tracks) {
            for &(c, i) in &identity.members {
                if let Some(gt) = ids.get(c).and_then(Option::as_ref).and_then(|v| v.get(i)) {
                    obs.push((c, *gt, track));
                }
            }
        }
        let links = memory.as_ref().map(Memory::links).unwrap_or_default();
        for (c, now) in ids.iter().enumerate() {
            let Some(now) = now else { continue };
            if let Some(before) = last_ids.get(&c) {
                for (i, id) in now.iter().enumerate() {
                    let had = before.contains(id);
                    continuing += had as usize;
                    if let Some(Some(j)) = links.get(c).and_then(|l| l.get(i)) {
                        linked += 1;
                        let ok = before.get(*j) == Some(id);
                        right += ok as usize;
                        found += (ok && had) as usize;
                    }
                }
            }
            last_ids.insert(c, now.clone());
        }
    }
    let m = compute_metrics(&records);
    let cameras: Vec<String> = rec.scene.cameras.iter().map(|c| c.name.clone()).collect();
    let t = score_tracks(&cameras, &obs);
    Ok(Row {
        acc: 100.0 * m.acc,
        ipaa: 100.0 * m.ipaa_100,
        right: 100.0 * stats.correct as f64 / stats.identities.max(1) as f64,
        link_precision: 100.0 * right as f64 / linked.max(1) as f64,
        link_recall: 100.0 * found as f64 / continuing.max(1) as f64,
        idf1: 100.0 * t.multi_camera.idf1,
        idf1_min: 100.0 * t.per_camera.iter().map(|(_, s)| s.idf1).fold(1.0, f64::min),
        merges,
        micros: spent.as_secs_f64() * 1e6 / rec.frames.len().max(1) as f64,
    })
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() >= 3,
        "usage: memory_sweep MODEL.onnx RECORDING.jsonl [--spread] CARRY:LINK_IOU:SPLIT..."
    );
    let mut enc = OnnxEncoder::load(&args[0])?;
    let mut rec = read_recording(&args[1])?;
    let (mut settings, mut spread, mut oracle) = (Vec::new(), false, false);
    for a in &args[2..] {
        match a.as_str() {
            "--spread" => spread = true,
            "--oracle" => oracle = true,
            s => settings.push(parse_setting(s)?),
        }
    }
    if spread {
        for m in settings.clone().into_iter().flatten() {
            for k in [0.5, 1.5] {
                let c = m.clone();
                settings.push(Some(MemoryConfig {
                    carry: (c.carry * k).min(0.99),
                    ..c.clone()
                }));
                settings.push(Some(MemoryConfig {
                    hold: c.hold * k,
                    ..c.clone()
                }));
                settings.push(Some(MemoryConfig {
                    link_weight: c.link_weight * k,
                    ..c.clone()
                }));
                settings.push(Some(MemoryConfig {
                    link_gate: c.link_gate * k,
                    ..c.clone()
                }));
                settings.push(Some(MemoryConfig {
                    link_margin: c.link_margin * k,
                    ..c
                }));
            }
        }
    }
    let mut base = enc.metadata().association_config();
    base.mode = Mode::Identities;
    let embs: Vec<FrameEmbeddings> = rec
        .frames
        .iter()
        .map(|f| embed_frame(&mut enc, &rec.scene, f))
        .collect::<Result<_>>()?;
    if oracle {
        // Perfect per-camera links: each box moved to a spot only its ground-truth id takes.
        for f in &mut rec.frames {
            for d in f.views.iter_mut().flatten().flatten() {
                let x = d.id.unwrap_or(0) as f32 * 10.0;
                d.bbox = [x, 0.0, x + 5.0, 5.0];
            }
        }
    }
    println!(
        "recording {} ({} frames), model {}",
        args[1],
        rec.frames.len(),
        args[0]
    );
    println!(
        "| carry λ | hold | link weight | link gate | link margin | ACC % | IPAA-100 % | identities right % | links precise % | links found % | IDF1 % | worst camera IDF1 % | merged pair-frames | of them not merged alone | association µs / frame |"
    );
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let alone = run(&rec, &embs, &base, None)?;
    for s in &settings {
        let r = run(&rec, &embs, &base, s.as_ref())?;
        let total: usize = r.merges.iter().map(Vec::len).sum();
        let extra: usize = r
            .merges
            .iter()
            .zip(&alone.merges)
            .map(|(m, a)| m.iter().filter(|p| a.binary_search(p).is_err()).count())
            .sum();
        let cols = s.as_ref().map_or("| 0 (alone) | | | | ".to_string(), |m| {
            format!(
                "| {} | {} | {} | {} | {} ",
                m.carry, m.hold, m.link_weight, m.link_gate, m.link_margin
            )
        });
        println!(
            "{cols}| {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {total} | {extra} | {:.0} |",
            r.acc, r.ipaa, r.right, r.link_precision, r.link_recall, r.idf1, r.idf1_min, r.micros
        );
    }
    Ok(())
}

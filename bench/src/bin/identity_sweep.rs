//! The identity step's measurement driver: scores identity methods and parameters on a
//! recording with ground-truth ids (identity-derived ACC / IPAA-100, whole-identity precision,
//! precision by confidence decile), beside SPEC §3 pairwise at the model's threshold, so the
//! selection sweeps in BENCHMARKS.md ("Identities") are reproducible.
//!
//! `identity_sweep MODEL.onnx RECORDING.jsonl [--cameras 0,1,2] [--spread] SETTING...`
//! where a SETTING is `clustering:T:B[:VETO]` (the veto as a share of `t`; `inf` = none) or
//! `union-find:T:B`; `--spread` adds each setting with one parameter at a time (`t`, `b`, and
//! the clustering's veto share) moved by −50 % and +50 %; `--cameras` empties every other
//! camera's views (a camera subset).
use anyhow::{Context, bail};

use crossview_core::association::Mode;
use crossview_core::identity::{IdentityConfig, IdentityMethod};
use crossview_data::recording::read_recording;
use crossview_eval::driver::evaluate_settings;
use crossview_model::OnnxEncoder;

/// One setting: method, `t`, `b` and the clustering's veto share (`None`: the default).
type Setting = (IdentityMethod, f32, f32, Option<f32>);

fn parse_setting(s: &str) -> anyhow::Result<Setting> {
    let parts: Vec<&str> = s.split(':').collect();
    match parts[..] {
        [m, t, b] => Ok((m.parse()?, t.parse()?, b.parse()?, None)),
        [m, t, b, v] => Ok((m.parse()?, t.parse()?, b.parse()?, Some(v.parse()?))),
        _ => bail!("setting '{s}': expected METHOD:T:B or METHOD:T:B:VETO"),
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        args.len() >= 3,
        "usage: identity_sweep MODEL.onnx RECORDING.jsonl [--cameras 0,1] [--spread] METHOD:T:B..."
    );
    let mut enc = OnnxEncoder::load(&args[0])?;
    let mut rec = read_recording(&args[1])?;
    let (mut settings, mut spread, mut cameras) = (Vec::new(), false, None);
    let mut rest = args[2..].iter();
    while let Some(a) = rest.next() {
        match a.as_str() {
            "--spread" => spread = true,
            "--cameras" => {
                let list = rest.next().context("--cameras needs a list")?;
                let cams: Vec<usize> = list.split(',').map(str::parse).collect::<Result<_, _>>()?;
                cameras = Some(cams);
            }
            s => settings.push(parse_setting(s)?),
        }
    }
    if let Some(cams) = &cameras {
        for f in &mut rec.frames {
            for (c, v) in f.views.iter_mut().enumerate() {
                if !cams.contains(&c) {
                    *v = Some(Vec::new());
                }
            }
        }
    }
    if spread {
        let base = settings.clone();
        for (m, t, b, v) in base {
            let veto = v.unwrap_or(IdentityConfig::default().veto);
            for k in [0.5, 1.5] {
                settings.push((m, t * k, b, v));
                settings.push((m, t, b * k, v));
                if m == IdentityMethod::Clustering {
                    settings.push((m, t, b, Some(veto * k)));
                }
            }
        }
    }
    let meta = enc.metadata().clone();
    let base = meta.association_config();
    let pairwise = evaluate_settings(&mut enc, &rec, &base, &[(Mode::Pairwise, base.threshold)])?;
    let p = &pairwise[0].metrics;
    println!(
        "recording {} ({} frames), cameras {:?}",
        args[1],
        rec.frames.len(),
        cameras.as_deref().unwrap_or(&[])
    );
    println!(
        "| method | t | b | veto | ACC % | IPAA-100 % | identities right % | deciles monotone (3 pts) | precision by decile |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---|---|");
    println!(
        "| pairwise S ≥ {:.2} | | | | {:.2} | {:.2} | | | |",
        base.threshold,
        100.0 * p.acc,
        100.0 * p.ipaa_100
    );
    for (method, t, b, veto) in settings {
        let mut cfg = base.clone();
        cfg.identity.method = method;
        cfg.identity.support = b;
        if let Some(v) = veto {
            cfg.identity.veto = v;
        }
        let run = evaluate_settings(&mut enc, &rec, &cfg, &[(Mode::Identities, t)])?;
        let (m, ids) = (&run[0].metrics, &run[0].identities);
        let deciles: Vec<String> = ids
            .deciles
            .iter()
            .enumerate()
            .filter(|(_, d)| d.identities > 0)
            .map(|(k, d)| {
                format!(
                    "{k}:{:.0}/{}",
                    100.0 * d.correct as f64 / d.identities as f64,
                    d.identities
                )
            })
            .collect();
        println!(
            "| {method} | {t:.3} | {b:.3} | {:.3} | {:.2} | {:.2} | {:.1} | {} | {} |",
            cfg.identity.veto,
            100.0 * m.acc,
            100.0 * m.ipaa_100,
            100.0 * ids.correct as f64 / ids.identities.max(1) as f64,
            if ids.monotone(3.0) { "yes" } else { "**no**" },
            deciles.join(" ")
        );
    }
    Ok(())
}

//! Bridge from a model to the evaluation metrics (SPEC §5).
//! TEMPORARY until `crate::eval` lands: a minimal ACC / IPAA-100 / P / R over the same
//! matching code; to be replaced by a call into `crate::eval`.
use ndarray::Array2;

use crate::Result;
use crate::core::matching::match_views;
use crate::io::Recording;
use crate::model::Encoder;
use crate::train::trainer::ValScores;

/// Scores `encoder` on `rec` at each threshold.
pub fn scores(
    rec: &Recording,
    encoder: &mut dyn Encoder,
    thresholds: &[f32],
    alpha: f32,
) -> Result<Vec<ValScores>> {
    // Embed every frame once.
    let mut frames: Vec<Vec<Option<(Array2<f32>, Vec<u64>)>>> = Vec::new();
    for f in &rec.frames {
        let mut boxes = Vec::new();
        let mut cams = Vec::new();
        for (c, v) in f.views.iter().enumerate() {
            for d in v.iter().flatten() {
                boxes.push(d.normalized(&rec.scene.cameras[c]));
                cams.push(c as i64);
            }
        }
        let emb = encoder.embed(&boxes, &cams)?;
        let mut row = Vec::new();
        let mut start = 0;
        for v in &f.views {
            match v {
                Some(d) if !d.is_empty() => {
                    let e = emb
                        .slice(ndarray::s![start..start + d.len(), ..])
                        .to_owned();
                    start += d.len();
                    row.push(Some((
                        e,
                        d.iter().map(|x| x.id.unwrap_or(u64::MAX)).collect(),
                    )));
                }
                _ => row.push(None),
            }
        }
        frames.push(row);
    }
    let mut out = Vec::new();
    for &th in thresholds {
        let (mut correct, mut kept, mut inter, mut union_, mut ok) = (0usize, 0, 0, 0, 0usize);
        let (mut full, mut pairs) = (0usize, 0usize);
        for row in &frames {
            for i in 0..row.len() {
                for j in i + 1..row.len() {
                    let (Some((ea, ia)), Some((eb, ib))) = (&row[i], &row[j]) else {
                        continue;
                    };
                    let m = match_views(ea.view(), eb.view(), None, None, alpha, th);
                    let sa: std::collections::HashSet<_> = ia.iter().collect();
                    let sb: std::collections::HashSet<_> = ib.iter().collect();
                    let n_inter = sa.intersection(&sb).count();
                    let n_union = sa.union(&sb).count();
                    let mut c = 0;
                    let mut ma = vec![false; ia.len()];
                    let mut mb = vec![false; ib.len()];
                    for x in &m.matches {
                        ma[x.a] = true;
                        mb[x.b] = true;
                        if ia[x.a] == ib[x.b] {
                            c += 1;
                        }
                    }
                    let tn = (0..ia.len())
                        .filter(|&a| !ma[a] && !sb.contains(&ia[a]))
                        .count()
                        + (0..ib.len())
                            .filter(|&b| !mb[b] && !sa.contains(&ib[b]))
                            .count();
                    correct += c;
                    kept += m.matches.len();
                    inter += n_inter;
                    union_ += n_union;
                    ok += tn + c;
                    pairs += 1;
                    if tn + c >= n_union {
                        full += 1;
                    }
                }
            }
        }
        let div = |a: usize, b: usize| if b == 0 { 0.0 } else { a as f64 / b as f64 };
        out.push(ValScores {
            acc: div(ok, union_),
            ipaa100: div(full, pairs),
            precision: div(correct, kept),
            recall: div(correct, inter),
            threshold: th,
        });
    }
    Ok(out)
}

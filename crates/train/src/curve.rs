//! The training curve as a self-contained SVG: losses per epoch (left) and, per scored epoch,
//! the label-free selection score (cycle consistency on held-out frames) beside the labelled
//! validation ACC and IPAA-100 when both exist (right).
use std::fmt::Write as _;
use std::path::Path;

use crate::state::EpochRecord;
use crossview_core::{Error, Result};

const W: f64 = 480.0;
const H: f64 = 300.0;
const PAD: f64 = 45.0;

/// One plotted line: name, colour and `(x, y)` points.
type Series<'a> = (&'a str, &'a str, Vec<(f64, f64)>);

/// Renders `history` as an SVG document.
pub(crate) fn render_svg(history: &[EpochRecord], title: &str) -> String {
    let mut s = String::new();
    let _ = write!(
        s,
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{}" height="{}" font-family="sans-serif" font-size="11">"#,
        2.0 * W,
        H + 30.0
    );
    let _ = write!(s, r#"<rect width="100%" height="100%" fill="white"/>"#);
    let _ = write!(
        s,
        r#"<text x="{}" y="16" text-anchor="middle" font-size="13">{}</text>"#,
        W,
        escape(title)
    );
    let epochs: Vec<f64> = history.iter().map(|r| r.epoch as f64).collect();
    let losses: [(&str, &str, Vec<f64>); 4] = [
        (
            "total",
            "#000000",
            history.iter().map(|r| r.total as f64).collect(),
        ),
        (
            "sync",
            "#1f77b4",
            history.iter().map(|r| r.syn as f64).collect(),
        ),
        (
            "re-projection",
            "#2ca02c",
            history.iter().map(|r| r.pro as f64).collect(),
        ),
        (
            "edge",
            "#d62728",
            history.iter().map(|r| r.edge as f64).collect(),
        ),
    ];
    let series: Vec<Series> = losses
        .iter()
        .map(|(n, c, v)| {
            (
                *n,
                *c,
                epochs.iter().copied().zip(v.iter().copied()).collect(),
            )
        })
        .collect();
    panel(&mut s, 0.0, "training loss", &series, None);
    let acc: Vec<(f64, f64)> = history
        .iter()
        .filter_map(|r| r.val.map(|v| (r.epoch as f64, 100.0 * v.acc)))
        .collect();
    let ipaa: Vec<(f64, f64)> = history
        .iter()
        .filter_map(|r| r.val.map(|v| (r.epoch as f64, 100.0 * v.ipaa100)))
        .collect();
    let free: Vec<(f64, f64)> = history
        .iter()
        .filter_map(|r| r.label_free.map(|v| (r.epoch as f64, 100.0 * v.key())))
        .collect();
    let mut scores: Vec<Series> = Vec::new();
    if !free.is_empty() {
        scores.push(("label-free (cycle consistency)", "#2ca02c", free));
    }
    if !acc.is_empty() {
        scores.push(("val ACC", "#1f77b4", acc));
        scores.push(("val IPAA-100", "#ff7f0e", ipaa));
    }
    panel(&mut s, W, "scores (%)", &scores, Some((0.0, 100.0)));
    s.push_str("</svg>\n");
    s
}

/// Writes the SVG to `path`.
pub fn write_svg(path: &Path, history: &[EpochRecord], title: &str) -> Result<()> {
    std::fs::write(path, render_svg(history, title)).map_err(|e| Error::io(path, e))
}

fn panel(s: &mut String, x0: f64, title: &str, series: &[Series], y_range: Option<(f64, f64)>) {
    let pts = series.iter().flat_map(|(_, _, p)| p.iter());
    let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in pts.filter(|(x, y)| x.is_finite() && y.is_finite()) {
        xmin = xmin.min(x);
        xmax = xmax.max(x);
        ymin = ymin.min(y);
        ymax = ymax.max(y);
    }
    if xmin > xmax {
        (xmin, xmax, ymin, ymax) = (0.0, 1.0, 0.0, 1.0);
    }
    if let Some((lo, hi)) = y_range {
        (ymin, ymax) = (lo, hi);
    }
    if xmax - xmin < 1e-9 {
        xmax = xmin + 1.0;
    }
    if ymax - ymin < 1e-9 {
        ymax = ymin + 1.0;
    }
    let (left, top, right, bottom) = (x0 + PAD, 30.0 + 10.0, x0 + W - 15.0, H - 15.0);
    let px = |x: f64| left + (x - xmin) / (xmax - xmin) * (right - left);
    let py = |y: f64| bottom - (y - ymin) / (ymax - ymin) * (bottom - top);
    let _ = write!(
        s,
        r##"<rect x="{left}" y="{top}" width="{}" height="{}" fill="none" stroke="#888"/>"##,
        right - left,
        bottom - top
    );
    let _ = write!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">{}</text>"#,
        (left + right) / 2.0,
        top - 4.0,
        escape(title)
    );
    for (v, y) in [(ymin, bottom), (ymax, top)] {
        let _ = write!(
            s,
            r#"<text x="{}" y="{}" text-anchor="end">{}</text>"#,
            left - 4.0,
            y + 4.0,
            fmt(v)
        );
    }
    for (v, x) in [(xmin, left), (xmax, right)] {
        let _ = write!(
            s,
            r#"<text x="{x}" y="{}" text-anchor="middle">{}</text>"#,
            bottom + 13.0,
            fmt(v)
        );
    }
    let _ = write!(
        s,
        r#"<text x="{}" y="{}" text-anchor="middle">epoch</text>"#,
        (left + right) / 2.0,
        bottom + 13.0
    );
    for (i, (name, color, p)) in series.iter().enumerate() {
        let path: Vec<String> = p
            .iter()
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|&(x, y)| format!("{:.1},{:.1}", px(x), py(y)))
            .collect();
        if path.len() == 1 {
            let _ = write!(
                s,
                r#"<circle cx="{}" cy="{}" r="2.5" fill="{color}"/>"#,
                px(p[0].0),
                py(p[0].1)
            );
        } else if !path.is_empty() {
            let _ = write!(
                s,
                r#"<polyline fill="none" stroke="{color}" stroke-width="1.5" points="{}"/>"#,
                path.join(" ")
            );
        }
        let ly = top + 14.0 + 13.0 * i as f64;
        let _ = write!(
            s,
            r#"<text x="{}" y="{ly}" text-anchor="end" fill="{color}">{}</text>"#,
            right - 6.0,
            escape(name)
        );
    }
}

fn fmt(v: f64) -> String {
    if v.abs() >= 100.0 || v == v.trunc() {
        format!("{v:.0}")
    } else {
        format!("{v:.2}")
    }
}

fn escape(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::state::ValScores;

    #[test]
    fn svg_has_a_line_per_loss_and_the_validation_points() {
        let rec = |e: usize, val: bool| EpochRecord {
            epoch: e,
            total: 3.0 / e as f32,
            syn: 1.0,
            pro: 1.0 / e as f32,
            edge: 1.0,
            id: 0.0,
            train_seconds: e as f64,
            val: val.then_some(ValScores {
                acc: 0.5 + 0.1 * e as f64,
                ipaa100: 0.2,
                precision: 0.9,
                recall: 0.9,
                threshold: 0.4,
            }),
            label_free: val.then_some(crate::label_free::LabelFreeScores {
                sync_acc: 0.9,
                cycle: 0.8,
                expected_acc: 0.4 + 0.1 * e as f64,
                threshold: 0.3,
                consistent: 0.5,
            }),
        };
        let h = vec![rec(1, false), rec(2, true), rec(3, false), rec(4, true)];
        let svg = render_svg(&h, "run <1>");
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"));
        assert_eq!(svg.matches("<polyline").count(), 7);
        assert!(svg.contains("label-free"));
        assert!(svg.contains("run &lt;1&gt;"));
        assert!(!svg.contains("NaN"));
        // An empty history still renders.
        assert!(render_svg(&[], "empty").contains("</svg>"));
    }
}

//! Presenting evaluation results: the text table printed by `crossview eval` and the JSON
//! report written by `--report`.
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::driver::EvalRun;
use crate::identities::IdentityStats;
use crate::metrics::Metrics;
use crossview_core::{Error, Result};

/// One labelled row of the results table.
#[derive(Debug, Clone, PartialEq)]
pub struct TableRow {
    /// Row label, e.g. `pairwise t=0.40` or the dump's file name.
    pub label: String,
    pub metrics: Metrics,
}

/// The metrics table as text: one row per setting, rates in percent (two decimals), then
/// the pair/frame counts. Deterministic, so a table recomputed from a dump can be compared
/// byte for byte.
pub fn format_table(rows: &[TableRow]) -> String {
    let label_w = rows
        .iter()
        .map(|r| r.label.chars().count())
        .chain(std::iter::once(7))
        .max()
        .unwrap_or(7);
    let mut out = format!(
        "{:<label_w$}  {:>7} {:>7} {:>7} {:>7} {:>7} {:>9} {:>8} {:>8} {:>7} {:>6}\n",
        "setting",
        "AP%",
        "FPR95%",
        "P%",
        "R%",
        "ACC%",
        "IPAA100%",
        "IPAA90%",
        "IPAA80%",
        "pairs",
        "frames"
    );
    for r in rows {
        let m = &r.metrics;
        let pct = |v: f64| format!("{:.2}", 100.0 * v);
        out.push_str(&format!(
            "{:<label_w$}  {:>7} {:>7} {:>7} {:>7} {:>7} {:>9} {:>8} {:>8} {:>7} {:>6}\n",
            r.label,
            pct(m.ap),
            pct(m.fpr95),
            pct(m.precision),
            pct(m.recall),
            pct(m.acc),
            pct(m.ipaa_100),
            pct(m.ipaa_90),
            pct(m.ipaa_80),
            m.pairs,
            m.frames
        ));
    }
    out
}

/// One setting in the JSON report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ReportRun {
    /// `pairwise`, `calibrated`, `identities`, or `from-dump` / `from-dump-identities`
    /// (setting unknown).
    pub mode: String,
    /// Confidence threshold (absent when recomputed from a dump).
    pub threshold: Option<f32>,
    /// Appearance weight (absent when recomputed from a dump).
    pub alpha: Option<f32>,
    /// SPEC §5 metrics as fractions in [0, 1], plus counts.
    pub metrics: Metrics,
    /// Whole-identity scores (identity rows; absent when recomputed from a dump).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identities: Option<IdentityStats>,
}

/// The `--report` JSON document.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalReport {
    /// Model file evaluated (empty when recomputed from a dump).
    pub model: String,
    /// Data file (recording or dump).
    pub data: String,
    /// Always `"fraction"`: every rate is in [0, 1].
    pub units: String,
    pub runs: Vec<ReportRun>,
}

impl EvalReport {
    /// A report over `runs` of `model` on `data`.
    pub fn new(model: &str, data: &str, runs: &[EvalRun]) -> Self {
        EvalReport {
            model: model.to_string(),
            data: data.to_string(),
            units: "fraction".into(),
            runs: runs
                .iter()
                .map(|r| ReportRun {
                    mode: r.mode.to_string(),
                    threshold: Some(r.threshold),
                    alpha: Some(r.alpha),
                    metrics: r.metrics,
                    identities: (r.mode == crossview_core::association::Mode::Identities)
                        .then_some(r.identities),
                })
                .collect(),
        }
    }

    /// Writes the report as pretty JSON to `path`.
    pub fn write(&self, path: impl AsRef<Path>) -> Result<()> {
        let path = path.as_ref();
        let text = serde_json::to_string_pretty(self).map_err(|e| Error::Format {
            source_name: path.display().to_string(),
            line: 0,
            message: format!("cannot encode report: {e}"),
        })?;
        std::fs::write(path, text + "\n").map_err(|e| Error::io(path, e))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_shows_percentages() {
        let m = Metrics {
            ap: 0.5,
            acc: 0.905,
            pairs: 3,
            frames: 1,
            ..Default::default()
        };
        let t = format_table(&[TableRow {
            label: "pairwise t=0.40".into(),
            metrics: m,
        }]);
        assert!(t.lines().next().unwrap().contains("ACC%"));
        assert!(t.contains("50.00") && t.contains("90.50"), "{t}");
    }
}

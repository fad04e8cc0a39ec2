//! The run's report: throughput, latency percentiles, errors, lost frames, the server-side
//! comparison and the verdict; printed for humans or as JSON.
use std::collections::BTreeMap;
use std::fmt::Write as _;

use hdrhistogram::Histogram;
use serde::Serialize;

use crate::args::Transport;
use crate::rss::RssSummary;

/// Push-to-result latency percentiles in milliseconds.
#[derive(Debug, Clone, Serialize)]
pub struct Latency {
    pub count: u64,
    pub min_ms: f64,
    pub mean_ms: f64,
    pub p50_ms: f64,
    pub p90_ms: f64,
    pub p99_ms: f64,
    pub p999_ms: f64,
    pub max_ms: f64,
}

impl Latency {
    /// Summarises a histogram recorded in microseconds.
    pub fn from_micros(h: &Histogram<u64>) -> Self {
        let ms = |v: u64| v as f64 / 1e3;
        Latency {
            count: h.len(),
            min_ms: if h.is_empty() { 0.0 } else { ms(h.min()) },
            mean_ms: h.mean() / 1e3,
            p50_ms: ms(h.value_at_quantile(0.5)),
            p90_ms: ms(h.value_at_quantile(0.9)),
            p99_ms: ms(h.value_at_quantile(0.99)),
            p999_ms: ms(h.value_at_quantile(0.999)),
            max_ms: ms(h.max()),
        }
    }
}

/// One count compared with the server's `/metrics`.
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    pub metric: String,
    pub ours: u64,
    /// The server's counter delta; `None` when the server does not expose the counter.
    pub server: Option<u64>,
    /// Equal, or not comparable (`server` is `None`).
    pub matches: bool,
}

/// What the soak mode injected.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SoakCounts {
    pub dropouts: u64,
    pub reconnects: u64,
    pub batches_skipped_while_down: u64,
    pub late_sent: u64,
    pub duplicates_sent: u64,
}

/// Everything measured in one run.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    pub target: String,
    pub transport: Transport,
    pub scenes: Vec<String>,
    pub cameras: usize,
    pub connections: usize,
    /// Frames per second per scene asked for; `null` = as fast as possible.
    pub rate_fps_per_scene: Option<f64>,
    pub soak: bool,
    pub frames_scheduled_per_scene: u64,
    pub send_seconds: f64,
    /// How far behind its schedule the sender fell at worst (open loop): large values
    /// mean the client, not the server, limited the offered load.
    pub max_schedule_lag_ms: f64,
    pub batches_sent: u64,
    pub batches_accepted: u64,
    pub batches_rejected: BTreeMap<String, u64>,
    pub errors: BTreeMap<String, u64>,
    pub offered_batches_per_s: f64,
    pub frames_accepted: u64,
    pub results: u64,
    pub results_complete: u64,
    /// Results with status `shed` (frames the server shed whole under overload).
    pub results_shed: u64,
    /// Partial results of frames whose every batch the server had accepted.
    pub partial_all_accepted: u64,
    /// Frames with batches both accepted and refused as `overloaded`; must be 0.
    pub frames_cut_by_overload: u64,
    pub results_per_s: f64,
    pub unexpected_results: u64,
    pub duplicate_results: u64,
    /// Kafka: results the live read of the output topic never delivered although they are
    /// in the topic (found by re-reading it after the run; a broker fault, not a lost frame).
    pub results_missed_live: u64,
    /// Frames with an accepted batch that never came back in a result: must be 0.
    pub frames_lost: u64,
    /// Up to 20 lost `(scene, frame id)`.
    pub lost_examples: Vec<(String, u64)>,
    pub latency_complete: Latency,
    pub latency_partial: Latency,
    pub server_comparison: Vec<Comparison>,
    pub soak_counts: Option<SoakCounts>,
    pub server_rss: Option<RssSummary>,
    pub passed: bool,
    pub failures: Vec<String>,
}

impl Report {
    /// Human-readable multi-line summary.
    pub fn to_text(&self) -> String {
        let mut s = String::new();
        let rate = self
            .rate_fps_per_scene
            .map_or("max".to_string(), |r| format!("{r} fps/scene"));
        let _ = writeln!(
            s,
            "crossview-loadtest: {:?} -> {}  scenes={} cameras={} connections={} rate={}{}",
            self.transport,
            self.target,
            self.scenes.len(),
            self.cameras,
            self.connections,
            rate,
            if self.soak { " (soak)" } else { "" }
        );
        let _ = writeln!(
            s,
            "  sent      {} batches in {:.2}s ({:.1}/s offered), {} accepted, max schedule lag {:.1} ms",
            self.batches_sent,
            self.send_seconds,
            self.offered_batches_per_s,
            self.batches_accepted,
            self.max_schedule_lag_ms
        );
        let _ = writeln!(
            s,
            "  results   {} ({} complete, {} shed) for {} accepted frames, {:.1} results/s",
            self.results,
            self.results_complete,
            self.results_shed,
            self.frames_accepted,
            self.results_per_s
        );
        if self.partial_all_accepted > 0 || self.frames_cut_by_overload > 0 {
            let _ = writeln!(
                s,
                "  cut       {} partial although every batch was accepted, {} cut by overload",
                self.partial_all_accepted, self.frames_cut_by_overload
            );
        }
        for (name, l) in [
            ("complete", &self.latency_complete),
            ("partial", &self.latency_partial),
        ] {
            if l.count > 0 {
                let _ = writeln!(
                    s,
                    "  latency   {name:<8} n={} p50={:.2}ms p90={:.2}ms p99={:.2}ms p99.9={:.2}ms max={:.2}ms",
                    l.count, l.p50_ms, l.p90_ms, l.p99_ms, l.p999_ms, l.max_ms
                );
            }
        }
        if !self.batches_rejected.is_empty() {
            let _ = writeln!(s, "  rejected  {:?}", self.batches_rejected);
        }
        if !self.errors.is_empty() {
            let _ = writeln!(s, "  errors    {:?}", self.errors);
        }
        let _ = writeln!(
            s,
            "  lost      {} frames {:?}",
            self.frames_lost, self.lost_examples
        );
        if self.results_missed_live > 0 {
            let _ = writeln!(
                s,
                "  broker    {} results published but skipped by the live read (found on re-read)",
                self.results_missed_live
            );
        }
        if self.unexpected_results + self.duplicate_results > 0 {
            let _ = writeln!(
                s,
                "  odd       {} results for unsent frames, {} repeated results",
                self.unexpected_results, self.duplicate_results
            );
        }
        if let Some(k) = &self.soak_counts {
            let _ = writeln!(
                s,
                "  soak      dropouts={} reconnects={} skipped_while_down={} late_sent={} duplicates_sent={}",
                k.dropouts,
                k.reconnects,
                k.batches_skipped_while_down,
                k.late_sent,
                k.duplicates_sent
            );
        }
        for c in &self.server_comparison {
            let _ = writeln!(
                s,
                "  server    {:<36} ours={:<8} server={:<8} {}",
                c.metric,
                c.ours,
                c.server.map_or("n/a".to_string(), |v| v.to_string()),
                match (c.server, c.matches) {
                    (None, _) => "not exposed",
                    (Some(_), true) => "ok",
                    (Some(_), false) => "MISMATCH",
                }
            );
        }
        if let Some(r) = &self.server_rss {
            let _ = writeln!(
                s,
                "  rss       pid {}: first={} KiB min={} max={} last={} ({} samples)",
                r.pid, r.first_kib, r.min_kib, r.max_kib, r.last_kib, r.samples
            );
        }
        let _ = writeln!(
            s,
            "  verdict   {}{}",
            if self.passed { "PASS" } else { "FAIL" },
            if self.failures.is_empty() {
                String::new()
            } else {
                format!(": {}", self.failures.join("; "))
            }
        );
        s
    }
}

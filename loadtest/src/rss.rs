//! Samples a process's resident memory (`VmRSS` in /proc/<pid>/status) during a soak run.
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde::Serialize;

/// Resident-set samples of one process.
#[derive(Debug, Clone, Default, Serialize)]
pub struct RssSummary {
    pub pid: u32,
    pub samples: usize,
    pub first_kib: u64,
    pub min_kib: u64,
    pub max_kib: u64,
    pub last_kib: u64,
    /// `(seconds since start, KiB)` every ~10 s, for a memory-growth plot.
    pub series: Vec<(f64, u64)>,
}

/// `VmRSS` of `pid` in KiB, or `None` when the process is gone.
pub fn read_rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next())
        .and_then(|v| v.parse().ok())
}

/// Samples `pid` every `every` until the returned handle's summary is taken.
pub fn spawn_sampler(pid: u32, every: Duration) -> Arc<Mutex<RssSummary>> {
    let out = Arc::new(Mutex::new(RssSummary {
        pid,
        ..Default::default()
    }));
    let o = out.clone();
    tokio::spawn(async move {
        let t0 = Instant::now();
        let mut last_series = None::<Instant>;
        let mut tick = tokio::time::interval(every);
        loop {
            tick.tick().await;
            let Some(kib) = read_rss_kib(pid) else { return };
            let mut s = o.lock().unwrap_or_else(|e| e.into_inner());
            if s.samples == 0 {
                s.first_kib = kib;
                s.min_kib = kib;
            }
            s.samples += 1;
            s.min_kib = s.min_kib.min(kib);
            s.max_kib = s.max_kib.max(kib);
            s.last_kib = kib;
            if last_series.is_none_or(|t| t.elapsed() >= Duration::from_secs(10)) {
                s.series.push((t0.elapsed().as_secs_f64(), kib));
                last_series = Some(Instant::now());
            }
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_own_rss() {
        let kib = read_rss_kib(std::process::id()).expect("own /proc status");
        assert!(kib > 0);
        assert_eq!(read_rss_kib(u32::MAX), None);
    }
}

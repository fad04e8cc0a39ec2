//! The healing settings (`serve --auto-retrain` and its bounds), apart from the healer so that
//! [`crate::config`] can hold them.
use std::path::PathBuf;
use std::time::Duration;

use crate::error::{Error, Result};

/// How the server heals a scene whose camera stopped fitting (see [`crate::heal`]).
#[derive(Debug, Clone, PartialEq)]
pub struct HealConfig {
    /// The `crossview` executable that trains and gates (the server's own).
    pub program: PathBuf,
    /// Where candidate models and their logs are written.
    pub dir: PathBuf,
    /// How long a camera must not fit before a retrain starts; what the retrain learns from
    /// is recorded meanwhile.
    pub after: Duration,
    /// Epochs each member of the model is fine-tuned for (`crossview train --epochs`): a fixed
    /// amount of work, so a busy machine makes a retrain slower, not worse.
    pub epochs: usize,
    /// Threads the training may use.
    pub threads: usize,
    /// CPU niceness of the retrain's child processes (19: the lowest priority; serving comes
    /// first).
    pub nice: i32,
    /// Stream recorded after the training data that the gate reads (at least).
    pub gate_after: Duration,
    /// Least time between the starts of two retrains of one scene.
    pub interval: Duration,
    /// A retrain (training and gate) still running after this long is stopped.
    pub timeout: Duration,
    /// Length of the stretches of recording kept as the reference of a scene whose cameras
    /// all fit.
    pub reference_every: Duration,
    /// How far below the scene's label-free key on the reference a retrained model's may be
    /// (`crossview model gate --tolerance`).
    pub tolerance: f64,
}

impl HealConfig {
    /// Defaults for the executable `program` writing into `dir` (chosen on the simulator,
    /// BENCHMARKS.md "Healing"): retrain after 5 minutes without fit, 150 epochs per member
    /// on one thread, a gate on at least 2 minutes of new stream against 5-minute reference
    /// stretches with a tolerance of 0.05 on the key, at most one retrain per scene every 15
    /// minutes, each stopped after 30 minutes.
    pub fn new(program: impl Into<PathBuf>, dir: impl Into<PathBuf>) -> Self {
        HealConfig {
            program: program.into(),
            dir: dir.into(),
            after: Duration::from_secs(300),
            epochs: 150,
            threads: 1,
            nice: 19,
            gate_after: Duration::from_secs(120),
            interval: Duration::from_secs(15 * 60),
            timeout: Duration::from_secs(30 * 60),
            reference_every: Duration::from_secs(5 * 60),
            tolerance: 0.05,
        }
    }

    /// Refuses settings that cannot heal.
    pub fn validate(&self) -> Result<()> {
        let bad = |flag: &str, why: &str| Err(Error::invalid(flag, why.to_string()));
        if self.after < Duration::from_secs(1) {
            return bad("--retrain-after", "must be at least 1s");
        }
        if !(1..=100_000).contains(&self.epochs) {
            return bad("--retrain-epochs", "must be within 1..=100000");
        }
        if !(1..=64).contains(&self.threads) {
            return bad("--retrain-threads", "must be within 1..=64");
        }
        if !(0..=19).contains(&self.nice) {
            return bad("--retrain-nice", "must be within 0..=19");
        }
        if self.gate_after < Duration::from_secs(1) {
            return bad("--retrain-gate-after", "must be at least 1s");
        }
        if self.reference_every < Duration::from_secs(1) {
            return bad("--retrain-reference-every", "must be at least 1s");
        }
        if !(0.0..=1.0).contains(&self.tolerance) {
            return bad("--retrain-tolerance", "must be within [0, 1]");
        }
        if self.timeout < Duration::from_secs(1) {
            return bad("--retrain-timeout", "must be at least 1s");
        }
        if self.program.as_os_str().is_empty() || self.dir.as_os_str().is_empty() {
            return bad(
                "--auto-retrain",
                "needs the crossview executable and a directory",
            );
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_heal_and_settings_that_cannot_are_refused_by_name() {
        let ok = HealConfig::new("/usr/bin/crossview", "/tmp/retrained");
        ok.validate().unwrap();
        type Spoil = fn(&mut HealConfig);
        let cases: [(&str, Spoil); 8] = [
            ("--retrain-nice", |c| c.nice = -1),
            ("--retrain-after", |c| c.after = Duration::ZERO),
            ("--retrain-epochs", |c| c.epochs = 0),
            ("--retrain-threads", |c| c.threads = 65),
            ("--retrain-gate-after", |c| c.gate_after = Duration::ZERO),
            ("--retrain-reference-every", |c| {
                c.reference_every = Duration::from_millis(10)
            }),
            ("--retrain-tolerance", |c| c.tolerance = f64::NAN),
            ("--auto-retrain", |c| c.dir = PathBuf::new()),
        ];
        for (flag, spoil) in cases {
            let mut c = ok.clone();
            spoil(&mut c);
            let e = c.validate().unwrap_err().to_string();
            assert!(e.contains(flag), "{flag}: {e}");
        }
    }
}

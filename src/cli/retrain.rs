//! `crossview serve`'s healing flags (`--auto-retrain` and its bounds): when a camera has not
//! fitted the model for a while, the server retrains on what it recorded and swaps the result
//! in (`crossview_serve::heal`).
use std::path::Path;
use std::time::Duration;

use anyhow::bail;
use clap::Args;

use crossview_api::duration::parse_duration;
use crossview_serve::HealConfig;

/// Healing options of `crossview serve`.
#[derive(Debug, Args)]
pub struct RetrainArgs {
    /// Heal a scene whose camera stopped fitting (it was bumped, re-aimed or zoomed): after
    /// `--retrain-after` the server fine-tunes the scene's model on what it recorded since
    /// (needs `--record`), in a child process at the lowest CPU priority, gates the result
    /// without labels on newer frames and swaps it in live (docs/serve.md, "Healing").
    #[arg(long, env = "CROSSVIEW_AUTO_RETRAIN")]
    pub auto_retrain: bool,
    /// How long a camera must not fit before its scene is retrained; the new view recorded
    /// meanwhile is what the retrain learns from.
    #[arg(long, env = "CROSSVIEW_RETRAIN_AFTER", default_value = "5m", value_parser = parse_duration)]
    pub retrain_after: Duration,
    /// Epochs each member of the model is fine-tuned for (a fixed amount of work: a busy
    /// machine makes a retrain slower, not worse).
    #[arg(long, env = "CROSSVIEW_RETRAIN_EPOCHS", default_value_t = HealConfig::new("", "").epochs)]
    pub retrain_epochs: usize,
    /// Threads a retrain may use (at the lowest CPU priority: serving comes first).
    #[arg(long, env = "CROSSVIEW_RETRAIN_THREADS", default_value_t = 1)]
    pub retrain_threads: usize,
    /// CPU niceness of a retrain (19: the lowest priority; serving comes first).
    #[arg(long, env = "CROSSVIEW_RETRAIN_NICE", default_value_t = 19)]
    pub retrain_nice: i32,
    /// Stream recorded after the training data that the gate reads, at least.
    #[arg(long, env = "CROSSVIEW_RETRAIN_GATE_AFTER", default_value = "2m", value_parser = parse_duration)]
    pub retrain_gate_after: Duration,
    /// Least time between two retrains of one scene.
    #[arg(long, env = "CROSSVIEW_RETRAIN_INTERVAL", default_value = "15m", value_parser = parse_duration)]
    pub retrain_interval: Duration,
    /// A retrain (training and gate) still running after this long is stopped.
    #[arg(long, env = "CROSSVIEW_RETRAIN_TIMEOUT", default_value = "30m", value_parser = parse_duration)]
    pub retrain_timeout: Duration,
    /// Length of the stretches of recording kept, while every camera fits, as the reference a
    /// retrained model must bring the scene back to.
    #[arg(long, env = "CROSSVIEW_RETRAIN_REFERENCE_EVERY", default_value = "5m", value_parser = parse_duration)]
    pub retrain_reference_every: Duration,
    /// How far below the scene's label-free key on the reference a retrained model's may be.
    #[arg(long, env = "CROSSVIEW_RETRAIN_TOLERANCE", default_value_t = HealConfig::new("", "").tolerance)]
    pub retrain_tolerance: f64,
    /// Where retrained models and their logs are written [default: `.retrained` under
    /// `--record`].
    #[arg(long, env = "CROSSVIEW_RETRAIN_DIR")]
    pub retrain_dir: Option<std::path::PathBuf>,
}

impl RetrainArgs {
    /// The healing settings, when `--auto-retrain` is on (`record`: the `--record` directory).
    pub fn to_config(&self, record: Option<&Path>) -> anyhow::Result<Option<HealConfig>> {
        if !self.auto_retrain {
            return Ok(None);
        }
        let Some(record) = record else {
            bail!("--auto-retrain needs --record: a retrain learns from what the server recorded");
        };
        let program = std::env::current_exe()?;
        let dir = self
            .retrain_dir
            .clone()
            .unwrap_or_else(|| record.join(".retrained"));
        let cfg = HealConfig {
            after: self.retrain_after,
            epochs: self.retrain_epochs,
            threads: self.retrain_threads,
            nice: self.retrain_nice,
            gate_after: self.retrain_gate_after,
            interval: self.retrain_interval,
            timeout: self.retrain_timeout,
            reference_every: self.retrain_reference_every,
            tolerance: self.retrain_tolerance,
            ..HealConfig::new(program, dir)
        };
        cfg.validate()?;
        Ok(Some(cfg))
    }
}

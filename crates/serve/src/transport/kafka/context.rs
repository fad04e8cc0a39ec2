//! librdkafka callbacks: rebalances (commit, drop what moves, epoch, readiness) and statistics
//! (lag of the owned partitions).
use std::sync::{Arc, Mutex};

use rdkafka::consumer::{BaseConsumer, CommitMode, Consumer, ConsumerContext, Rebalance};
use rdkafka::{ClientContext, Offset, Statistics, TopicPartitionList};

use crate::error::{Error, Result};

use super::offsets::Ownership;
use super::{lock, now_ms};
use crate::metrics::Metrics;
use crate::service::Service;

/// The consumer's context (see the module docs).
pub(super) struct Context {
    pub(super) topic: String,
    pub(super) offsets: Arc<Mutex<Ownership>>,
    pub(super) metrics: Metrics,
    pub(super) service: Arc<Service>,
}

impl ClientContext for Context {
    fn stats(&self, stats: Statistics) {
        let Some(t) = stats.topics.get(&self.topic) else {
            return;
        };
        let owned = lock(&self.offsets);
        for (p, part) in &t.partitions {
            if *p >= 0 && part.consumer_lag >= 0 && owned.owns(*p) {
                self.metrics.kafka_lag(&self.topic, *p, part.consumer_lag);
            }
        }
    }
}

impl ConsumerContext for Context {
    fn pre_rebalance(&self, consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        if let Rebalance::Revoke(list) = rebalance {
            self.revoke(consumer, list);
        }
    }

    fn post_rebalance(&self, _consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        match rebalance {
            Rebalance::Assign(list) => {
                let mut offsets = lock(&self.offsets);
                offsets.epoch = now_ms().max(offsets.epoch + 1);
                for e in list.elements() {
                    offsets.assign(e.partition());
                    self.metrics.kafka_assigned(e.topic(), e.partition(), true);
                }
                let parts: Vec<i32> = list.elements().iter().map(|e| e.partition()).collect();
                tracing::info!(?parts, epoch = offsets.epoch, "kafka: partitions assigned");
                // Joined (even with nothing assigned): ready.
                self.service.set_consumer_ready(true);
            }
            Rebalance::Revoke(_) => {}
            Rebalance::Error(e) => tracing::warn!(error = %e, "kafka: rebalance failed"),
        }
    }
}

impl Context {
    /// Partitions leave: commit what is done, then forget them, drop the pending frames of
    /// their scenes (never published here: the next owner re-reads them) and their lag.
    fn revoke(&self, consumer: &BaseConsumer<Self>, list: &TopicPartitionList) {
        let commits = lock(&self.offsets).take_commits();
        if !commits.is_empty() {
            match commit_list(&self.topic, &commits).and_then(|tpl| {
                consumer
                    .commit(&tpl, CommitMode::Sync)
                    .map_err(|e| Error::internal_from("kafka commit", e))
            }) {
                Ok(()) => {
                    for (p, o) in commits {
                        self.metrics.kafka_committed(&self.topic, p, o);
                    }
                }
                Err(e) => tracing::warn!(error = %e, "kafka: commit on revocation failed"),
            }
        }
        let mut dropped_frames = 0;
        for e in list.elements() {
            let (scenes, forgotten) = lock(&self.offsets).revoke(e.partition());
            dropped_frames += forgotten;
            for name in scenes {
                if let Some(scene) = self
                    .service
                    .scene_list()
                    .into_iter()
                    .find(|s| s.name() == name)
                {
                    scene.restart(None);
                }
            }
            self.metrics.kafka_assigned(e.topic(), e.partition(), false);
            self.metrics.kafka_lag_forget(e.topic(), e.partition());
        }
        self.metrics.kafka_revoked_frames(dropped_frames);
        let parts: Vec<i32> = list.elements().iter().map(|e| e.partition()).collect();
        tracing::info!(
            ?parts,
            dropped_frames,
            "kafka: partitions revoked; their pending frames are left to the next owner"
        );
    }
}

/// The commit request for `commits` (partition, next offset) of `topic`.
pub(super) fn commit_list(topic: &str, commits: &[(i32, i64)]) -> Result<TopicPartitionList> {
    let mut tpl = TopicPartitionList::new();
    for (p, o) in commits {
        tpl.add_partition_offset(topic, *p, Offset::Offset(*o))
            .map_err(|e| Error::internal_from("kafka: bad commit offset", e))?;
    }
    Ok(tpl)
}

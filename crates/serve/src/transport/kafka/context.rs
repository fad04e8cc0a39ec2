//! librdkafka callbacks: rebalances (commit, drop what moves, epoch, readiness) and statistics
//! (lag of the owned partitions, and their high watermarks: whether records wait unread).
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rdkafka::consumer::{BaseConsumer, CommitMode, Consumer, ConsumerContext, Rebalance};
use rdkafka::{ClientContext, Offset, Statistics, TopicPartitionList};

use crate::error::{Error, Result};

use super::offsets::Ownership;
use super::{lock, now_ms, wake};
use crate::metrics::Metrics;
use crate::service::Service;

/// The consumer's context (see the module docs).
pub(super) struct Context {
    pub(super) topic: String,
    pub(super) offsets: Arc<Mutex<Ownership>>,
    pub(super) metrics: Metrics,
    pub(super) service: Arc<Service>,
    pub(super) stats_clock: Mutex<StatsClock>,
    /// Per broker, the fetch requests sent as of the previous statistics.
    pub(super) fetches: Mutex<std::collections::HashMap<String, i64>>,
    /// Every broker is down (librdkafka said so): not ready until one is back and the group
    /// at rest.
    pub(super) brokers_down: std::sync::atomic::AtomicBool,
}

/// When librdkafka emitted a statistics report, on this process's clock: its `ts` is
/// librdkafka's own monotonic clock (µs), whose zero is unknown here. Every report is handled
/// at or after its emission, so the smallest (handled − `ts`) seen is the closest estimate of
/// that zero: a report handled late (a busy consumer) is dated when it was emitted, not
/// when it was read.
#[derive(Debug)]
pub(super) struct StatsClock {
    base: Instant,
    /// Smallest (handled − `ts`) so far, µs since `base`.
    offset: Option<i64>,
}

impl Default for StatsClock {
    fn default() -> Self {
        StatsClock {
            base: Instant::now(),
            offset: None,
        }
    }
}

impl StatsClock {
    /// The emission instant of a report stamped `ts`, handled now.
    fn emitted(&mut self, ts: i64) -> Instant {
        self.emitted_at(ts, Instant::now())
    }

    fn emitted_at(&mut self, ts: i64, handled: Instant) -> Instant {
        let since = handled.saturating_duration_since(self.base).as_micros() as i64;
        let offset = self.offset.map_or(since - ts, |o| o.min(since - ts));
        self.offset = Some(offset);
        let at = (ts + offset).clamp(0, since);
        self.base + Duration::from_micros(at as u64)
    }
}

impl ClientContext for Context {
    /// Global errors: every broker down turns readiness off (what was read and not produced
    /// stays uncommitted, and is read again); others are logged.
    fn error(&self, error: rdkafka::error::KafkaError, reason: &str) {
        use rdkafka::types::RDKafkaErrorCode;
        if error.rdkafka_error_code() == Some(RDKafkaErrorCode::AllBrokersDown) {
            if !self
                .brokers_down
                .swap(true, std::sync::atomic::Ordering::AcqRel)
            {
                tracing::warn!(%reason, "kafka: every broker is down; not ready until one is back");
            }
            self.service.set_consumer_ready(false);
        } else {
            tracing::warn!(error = %error, %reason, "kafka: client error");
        }
    }

    fn stats(&self, stats: Statistics) {
        self.broker_back(&stats);
        let Some(t) = stats.topics.get(&self.topic) else {
            return;
        };
        let at = lock(&self.stats_clock).emitted(stats.ts);
        let late = at.elapsed();
        if late > Duration::from_millis(50) {
            tracing::debug!(?late, "kafka: statistics handled late");
        }
        let mut moved = Vec::new();
        let wall = now_ms();
        // Caught up needs a group at rest (during a rebalance's rounds the fetchers of the
        // partitions kept stop) and fresh high watermarks: they come with fetch responses,
        // which stop too around a rebalance, a slow broker or a failover.
        let steady = stats.cgrp.as_ref().is_none_or(|g| g.join_state == "steady");
        let fresh = self.fetched_since_last(&stats);
        {
            let mut owned = lock(&self.offsets);
            for (p, part) in &t.partitions {
                if *p < 0 || !owned.owns(*p) {
                    continue;
                }
                if part.consumer_lag >= 0 {
                    self.metrics.kafka_lag(&self.topic, *p, part.consumer_lag);
                }
                let read = part.committed_offset.max(part.app_offset);
                // Nothing fetched and not yet handed over, the fetcher running.
                let fetching = steady
                    && fresh.contains(p)
                    && part.fetchq_cnt == 0
                    && part.fetch_state == "active";
                let high = if fetching { part.hi_offset } else { -1 };
                if let Some((ms, scenes)) = owned.report(*p, high, read, at) {
                    if ms > 0 {
                        self.metrics.kafka_stream_time(&self.topic, *p, ms, wall);
                    }
                    moved.extend(scenes);
                }
            }
        }
        wake(&self.service, &moved);
    }
}

impl ConsumerContext for Context {
    fn pre_rebalance(&self, consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        // Delivery is held while the rebalance lasts: stream time does not run on.
        lock(&self.offsets).hold_all();
        if let Rebalance::Revoke(list) = rebalance {
            self.revoke(consumer, list);
        }
    }

    fn post_rebalance(&self, _consumer: &BaseConsumer<Self>, rebalance: &Rebalance<'_>) {
        lock(&self.offsets).release_all(Instant::now());
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
    /// After every broker was down: ready again once one is up and the group at rest.
    fn broker_back(&self, stats: &Statistics) {
        use std::sync::atomic::Ordering;
        if !self.brokers_down.load(Ordering::Acquire) {
            return;
        }
        let up = stats.brokers.values().any(|b| b.state == "UP");
        let steady = stats
            .cgrp
            .as_ref()
            .is_some_and(|g| g.state == "up" && g.join_state == "steady");
        if up && steady && self.brokers_down.swap(false, Ordering::AcqRel) {
            tracing::info!("kafka: a broker is back and the group at rest; ready");
            self.service.set_consumer_ready(true);
        }
    }

    /// The input partitions whose broker answered a fetch since the previous statistics: its
    /// count of fetch requests sent grew by two or more (librdkafka keeps one fetch in flight
    /// per broker, so the first was answered). Their high watermarks are fresh.
    fn fetched_since_last(&self, stats: &Statistics) -> std::collections::HashSet<i32> {
        let mut fresh = std::collections::HashSet::new();
        let mut last = lock(&self.fetches);
        for b in stats.brokers.values() {
            let sent = b.req.get("Fetch").copied().unwrap_or(0);
            let before = last.insert(b.name.clone(), sent).unwrap_or(i64::MAX);
            if sent >= before.saturating_add(2) {
                fresh.extend(
                    b.toppars
                        .values()
                        .filter(|tp| tp.topic == self.topic)
                        .map(|tp| tp.partition),
                );
            }
        }
        fresh
    }

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
                if let Some(scene) = self.service.find_scene(&name) {
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

#[cfg(test)]
mod tests {
    use super::*;

    /// A report handled late is dated by the earlier reports' smallest delay.
    #[test]
    fn statistics_are_dated_when_emitted() {
        let mut c = StatsClock::default();
        let ms = Duration::from_millis;
        let base = c.base;
        // librdkafka's clock reads 5_000_000 µs when ours reads base + 100 ms (handled at once).
        assert_eq!(c.emitted_at(5_000_000, base + ms(100)), base + ms(100));
        // The next report, 100 ms later on its clock, handled 300 ms late.
        assert_eq!(c.emitted_at(5_100_000, base + ms(500)), base + ms(200));
        // One handled sooner than the first was: the estimate tightens.
        assert_eq!(c.emitted_at(5_200_000, base + ms(290)), base + ms(290));
        assert_eq!(c.emitted_at(5_100_000, base + ms(900)), base + ms(190));
    }
}
